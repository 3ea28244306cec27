// Header checks shared by every batch decoder, the non-finite ray test, and error names.

#include "kdrt/proto/ray_batch_header.h"

#include <array>
#include <cmath>
#include <cstring>
#include <string>

#include "byte_io.h"
#include "kdrt/proto/text.h"
#include "ray_batch_checks.h"

namespace kdrt::proto {
namespace detail {
namespace {

/// `v` as "0x" and `digits` lower-case hex digits.
std::string hex_literal(uint64_t v, int digits) { return "0x" + hex(v, digits); }

/// The 4 magic bytes as a C-style quoted string, non-printable bytes as \xNN.
std::string quoted_magic(const std::byte* p) {
    std::string s = "\"";
    for (int i = 0; i < 4; ++i) {
        const auto c = static_cast<unsigned char>(p[i]);
        if (c >= 0x20 && c < 0x7F && c != '"' && c != '\\') {
            s += static_cast<char>(c);
        } else {
            s += "\\x";
            s += hex(c, 2);
        }
    }
    return s + "\"";
}

std::string count_noun(uint64_t n, const BatchKind& kind) {
    return std::to_string(n) + " " + std::string(n == 1 ? kind.singular : kind.plural);
}

DecodeError make(DecodeErrorCode code, std::string detail) {
    return DecodeError{code, std::move(detail)};
}

constexpr std::array<const char*, 8> kRayFieldNames = {"ox", "oy", "oz", "tmin",
                                                       "dx", "dy", "dz", "tmax"};

/// First field of `ray` that reject_non_finite refuses, as an index into kRayFieldNames, or -1.
int first_bad_ray_field(const Ray& ray) noexcept {
    const float f[8] = {ray.ox, ray.oy, ray.oz, ray.tmin, ray.dx, ray.dy, ray.dz, ray.tmax};
    for (int i = 0; i < 8; ++i) {
        const bool is_range_bound = i == 3 || i == 7;  // tmin/tmax: only NaN is refused
        if (is_range_bound ? std::isnan(f[i]) : !std::isfinite(f[i])) return i;
    }
    return -1;
}

}  // namespace

DecodeError too_short(uint64_t size) {
    return make(DecodeErrorCode::kTooShort, "body has " + std::to_string(size) +
                                                " bytes, less than the " +
                                                std::to_string(kBatchHeaderBytes) + "-byte header");
}

DecodeError length_mismatch(const BatchKind& kind, uint32_t count, uint64_t size) {
    const uint64_t expected = kBatchHeaderBytes + uint64_t{count} * kind.record_bytes;
    return make(DecodeErrorCode::kLengthMismatch,
                "header says " + count_noun(count, kind) + " (" + std::to_string(expected) +
                    " bytes) but body has " + std::to_string(size) + " bytes");
}

Result<CheckedHeader, DecodeError> check_header_fields(const std::byte* p, const BatchKind& kind,
                                                       const DecodeLimits& limits) {
    if (std::memcmp(p, kind.magic.data(), 4) != 0) {
        return Err{make(
            DecodeErrorCode::kBadMagic,
            "bad magic " + quoted_magic(p) + ", expected \"" + std::string(kind.magic) + "\"")};
    }
    const uint16_t version = load_le16(p + 4);
    const uint16_t flags = load_le16(p + 6);
    const uint32_t count = load_le32(p + 8);
    const uint32_t reserved = load_le32(p + 12);
    if (version != kBatchVersion) {
        return Err{make(DecodeErrorCode::kBadVersion, "unsupported version " +
                                                          std::to_string(version) + ", expected " +
                                                          std::to_string(kBatchVersion))};
    }
    if ((flags & ~kind.known_flags) != 0) {
        std::string text = "unknown flag bits " + hex_literal(flags & ~kind.known_flags, 4) +
                           " in flags " + hex_literal(flags, 4) + " (";
        text += kind.known_flags != 0 ? "only bit 0, occlusion, is defined for "
                                      : "no flags are defined for ";
        text += std::string(kind.magic) + ")";
        return Err{make(DecodeErrorCode::kBadFlags, std::move(text))};
    }
    if (reserved != 0) {
        return Err{make(DecodeErrorCode::kBadReserved,
                        "reserved header field is " + hex_literal(reserved, 8) + ", expected 0")};
    }
    if (count > limits.max_rays) {
        return Err{make(DecodeErrorCode::kTooManyRays, "header says " + count_noun(count, kind) +
                                                           ", limit is " +
                                                           std::to_string(limits.max_rays))};
    }
    return CheckedHeader{flags, count};
}

Result<CheckedHeader, DecodeError> check_header(std::span<const std::byte> body,
                                                const BatchKind& kind, const DecodeLimits& limits) {
    if (body.size() < kBatchHeaderBytes) return Err{too_short(body.size())};
    auto header = check_header_fields(body.data(), kind, limits);
    if (!header) return header;
    if (body.size() != kBatchHeaderBytes + uint64_t{header->count} * kind.record_bytes)
        return Err{length_mismatch(kind, header->count, body.size())};
    return header;
}

bool ray_refused(const Ray& ray) noexcept {
    uint32_t b[8];
    std::memcpy(b, &ray, sizeof b);
    constexpr uint32_t kExp = 0x7f800000u;
    uint32_t bad = 0;
    for (int i : {0, 1, 2, 4, 5, 6}) bad |= static_cast<uint32_t>((b[i] & kExp) == kExp);
    for (int i : {3, 7}) bad |= static_cast<uint32_t>((b[i] & 0x7fffffffu) > kExp);
    return bad != 0;
}

DecodeError non_finite_error(uint64_t index, const Ray& r) {
    const int field = first_bad_ray_field(r);
    const float f[8] = {r.ox, r.oy, r.oz, r.tmin, r.dx, r.dy, r.dz, r.tmax};
    return make(DecodeErrorCode::kNonFiniteRay, "ray " + std::to_string(index) + ": field " +
                                                    kRayFieldNames[static_cast<size_t>(field)] +
                                                    " is " + non_finite_name(f[field]));
}

}  // namespace detail

std::string_view decode_error_code_name(DecodeErrorCode code) noexcept {
    switch (code) {
        case DecodeErrorCode::kTooShort:
            return "too_short";
        case DecodeErrorCode::kBadMagic:
            return "bad_magic";
        case DecodeErrorCode::kBadVersion:
            return "bad_version";
        case DecodeErrorCode::kBadReserved:
            return "bad_reserved";
        case DecodeErrorCode::kLengthMismatch:
            return "length_mismatch";
        case DecodeErrorCode::kTooManyRays:
            return "too_many_rays";
        case DecodeErrorCode::kBadFlags:
            return "bad_flags";
        case DecodeErrorCode::kBadOffsets:
            return "bad_offsets";
        case DecodeErrorCode::kNonFiniteRay:
            return "non_finite_ray";
        case DecodeErrorCode::kBadOcclusionValue:
            return "bad_occlusion_value";
        case DecodeErrorCode::kNonFinitePoint:
            return "non_finite_point";
        case DecodeErrorCode::kBadRecord:
            return "bad_record";
    }
    return "unknown";
}

std::string DecodeError::to_string() const {
    return std::string(decode_error_code_name(code)) + ": " + detail;
}

}  // namespace kdrt::proto
