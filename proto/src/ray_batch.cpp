#include "kdrt/proto/ray_batch.h"

#include <array>
#include <cmath>
#include <cstring>
#include <limits>
#include <stdexcept>

#include "byte_io.h"

namespace kdrt::proto {
namespace {

using detail::kHostLittleEndian;

/// What distinguishes the three batch kinds.
struct BatchKind {
    std::string_view magic;
    size_t record_bytes;
    uint16_t known_flags;       // bits a decoder accepts
    std::string_view singular;  // record noun for details
    std::string_view plural;
};

constexpr BatchKind kRays{kRayMagic, kRayRecordBytes, kRayFlagsKnown, "ray", "rays"};
constexpr BatchKind kHits{kHitMagic, kHitRecordBytes, 0, "hit", "hits"};
constexpr BatchKind kOcclusion{kOcclusionMagic, kOcclusionRecordBytes, 0, "occlusion value",
                               "occlusion values"};

std::string hex(uint64_t v, int digits) {
    static constexpr char kDigits[] = "0123456789abcdef";
    std::string s = "0x";
    for (int i = digits - 1; i >= 0; --i) s += kDigits[(v >> (4 * i)) & 0xF];
    return s;
}

/// The 4 magic bytes as a C-style quoted string, non-printable bytes as \xNN.
std::string quoted_magic(const std::byte* p) {
    std::string s = "\"";
    for (int i = 0; i < 4; ++i) {
        const auto c = static_cast<unsigned char>(p[i]);
        if (c >= 0x20 && c < 0x7F && c != '"' && c != '\\') {
            s += static_cast<char>(c);
        } else {
            s += "\\x";
            s += hex(c, 2).substr(2);
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

struct CheckedHeader {
    uint16_t flags = 0;
    uint32_t count = 0;
};

/// Validates the header and the exact body length; nothing is allocated.
Result<CheckedHeader, DecodeError> check_header(std::span<const std::byte> body,
                                                const BatchKind& kind, const DecodeLimits& limits) {
    if (body.size() < kBatchHeaderBytes) {
        return Err{make(DecodeErrorCode::kTooShort,
                        "body has " + std::to_string(body.size()) + " bytes, less than the " +
                            std::to_string(kBatchHeaderBytes) + "-byte header")};
    }
    const std::byte* p = body.data();
    if (std::memcmp(p, kind.magic.data(), 4) != 0) {
        return Err{make(
            DecodeErrorCode::kBadMagic,
            "bad magic " + quoted_magic(p) + ", expected \"" + std::string(kind.magic) + "\"")};
    }
    const uint16_t version = detail::load_le16(p + 4);
    const uint16_t flags = detail::load_le16(p + 6);
    const uint32_t count = detail::load_le32(p + 8);
    const uint32_t reserved = detail::load_le32(p + 12);
    if (version != kBatchVersion) {
        return Err{make(DecodeErrorCode::kBadVersion, "unsupported version " +
                                                          std::to_string(version) + ", expected " +
                                                          std::to_string(kBatchVersion))};
    }
    if ((flags & ~kind.known_flags) != 0) {
        std::string detail = "unknown flag bits " + hex(flags & ~kind.known_flags, 4) +
                             " in flags " + hex(flags, 4) + " (";
        detail += kind.known_flags != 0 ? "only bit 0, occlusion, is defined for "
                                        : "no flags are defined for ";
        detail += std::string(kind.magic) + ")";
        return Err{make(DecodeErrorCode::kBadFlags, std::move(detail))};
    }
    if (reserved != 0) {
        return Err{make(DecodeErrorCode::kBadReserved,
                        "reserved header field is " + hex(reserved, 8) + ", expected 0")};
    }
    if (count > limits.max_rays) {
        return Err{make(DecodeErrorCode::kTooManyRays, "header says " + count_noun(count, kind) +
                                                           ", limit is " +
                                                           std::to_string(limits.max_rays))};
    }
    const uint64_t expected = kBatchHeaderBytes + uint64_t{count} * kind.record_bytes;
    if (body.size() != expected) {
        return Err{make(DecodeErrorCode::kLengthMismatch,
                        "header says " + count_noun(count, kind) + " (" + std::to_string(expected) +
                            " bytes) but body has " + std::to_string(body.size()) + " bytes")};
    }
    return CheckedHeader{flags, count};
}

/// A vector of 16 + count * record_bytes bytes with the header filled in.
std::vector<std::byte> start_batch(const BatchKind& kind, size_t count, uint16_t flags) {
    if (count > std::numeric_limits<uint32_t>::max()) {
        throw std::length_error(std::string(kind.magic) + " batch of " + std::to_string(count) +
                                " records exceeds the u32 count field");
    }
    std::vector<std::byte> out(kBatchHeaderBytes + count * kind.record_bytes);
    std::memcpy(out.data(), kind.magic.data(), 4);
    detail::store_le16(out.data() + 4, kBatchVersion);
    detail::store_le16(out.data() + 6, flags);
    detail::store_le32(out.data() + 8, static_cast<uint32_t>(count));
    detail::store_le32(out.data() + 12, 0);
    return out;
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

std::string describe_non_finite(float v) {
    if (std::isnan(v)) return "NaN";
    return v > 0 ? "+inf" : "-inf";
}

}  // namespace

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
        case DecodeErrorCode::kNonFiniteRay:
            return "non_finite_ray";
        case DecodeErrorCode::kBadOcclusionValue:
            return "bad_occlusion_value";
    }
    return "unknown";
}

std::string DecodeError::to_string() const {
    return std::string(decode_error_code_name(code)) + ": " + detail;
}

Result<RayBatch, DecodeError> decode_rays(std::span<const std::byte> body,
                                          const DecodeLimits& limits) {
    auto header = check_header(body, kRays, limits);
    if (!header) return Err{std::move(header).error()};
    RayBatch batch;
    batch.flags = header->flags;
    batch.occlusion = (header->flags & kRayFlagOcclusion) != 0;
    batch.rays.resize(header->count);
    const std::byte* src = body.data() + kBatchHeaderBytes;
    if constexpr (kHostLittleEndian) {
        // Ray is 8 packed floats in wire order: the body is the array.
        if (header->count != 0)
            std::memcpy(batch.rays.data(), src, size_t{header->count} * kRayRecordBytes);
    } else {
        for (Ray& r : batch.rays) {
            float* f[8] = {&r.ox, &r.oy, &r.oz, &r.tmin, &r.dx, &r.dy, &r.dz, &r.tmax};
            for (int i = 0; i < 8; ++i) *f[i] = detail::load_le_f32(src + 4 * i);
            src += kRayRecordBytes;
        }
    }
    if (limits.reject_non_finite) {
        for (size_t i = 0; i < batch.rays.size(); ++i) {
            const int field = first_bad_ray_field(batch.rays[i]);
            if (field < 0) continue;
            const Ray& r = batch.rays[i];
            const float f[8] = {r.ox, r.oy, r.oz, r.tmin, r.dx, r.dy, r.dz, r.tmax};
            return Err{make(DecodeErrorCode::kNonFiniteRay,
                            "ray " + std::to_string(i) + ": field " +
                                kRayFieldNames[static_cast<size_t>(field)] + " is " +
                                describe_non_finite(f[field]))};
        }
    }
    return batch;
}

std::vector<std::byte> encode_rays(std::span<const Ray> rays, bool occlusion) {
    std::vector<std::byte> out = start_batch(kRays, rays.size(), occlusion ? kRayFlagOcclusion : 0);
    std::byte* dst = out.data() + kBatchHeaderBytes;
    if constexpr (kHostLittleEndian) {
        if (!rays.empty()) std::memcpy(dst, rays.data(), rays.size_bytes());
    } else {
        for (const Ray& r : rays) {
            const float f[8] = {r.ox, r.oy, r.oz, r.tmin, r.dx, r.dy, r.dz, r.tmax};
            for (int i = 0; i < 8; ++i) detail::store_le_f32(dst + 4 * i, f[i]);
            dst += kRayRecordBytes;
        }
    }
    return out;
}

std::vector<std::byte> encode_hits(std::span<const Hit> hits) {
    std::vector<std::byte> out = start_batch(kHits, hits.size(), 0);
    std::byte* dst = out.data() + kBatchHeaderBytes;
    if constexpr (kHostLittleEndian) {
        if (!hits.empty()) std::memcpy(dst, hits.data(), hits.size_bytes());
    } else {
        for (const Hit& h : hits) {
            detail::store_le_f32(dst, h.t);
            detail::store_le32(dst + 4, h.prim);
            detail::store_le_f32(dst + 8, h.u);
            detail::store_le_f32(dst + 12, h.v);
            dst += kHitRecordBytes;
        }
    }
    return out;
}

Result<std::vector<Hit>, DecodeError> decode_hits(std::span<const std::byte> body,
                                                  const DecodeLimits& limits) {
    auto header = check_header(body, kHits, limits);
    if (!header) return Err{std::move(header).error()};
    std::vector<Hit> hits(header->count);
    const std::byte* src = body.data() + kBatchHeaderBytes;
    if constexpr (kHostLittleEndian) {
        if (header->count != 0)
            std::memcpy(hits.data(), src, size_t{header->count} * kHitRecordBytes);
    } else {
        for (Hit& h : hits) {
            h.t = detail::load_le_f32(src);
            h.prim = detail::load_le32(src + 4);
            h.u = detail::load_le_f32(src + 8);
            h.v = detail::load_le_f32(src + 12);
            src += kHitRecordBytes;
        }
    }
    return hits;
}

std::vector<std::byte> encode_occlusion(std::span<const uint8_t> occluded) {
    std::vector<std::byte> out = start_batch(kOcclusion, occluded.size(), 0);
    std::byte* dst = out.data() + kBatchHeaderBytes;
    for (size_t i = 0; i < occluded.size(); ++i)
        dst[i] = std::byte{occluded[i] != 0 ? uint8_t{1} : uint8_t{0}};
    return out;
}

Result<std::vector<uint8_t>, DecodeError> decode_occlusion(std::span<const std::byte> body,
                                                           const DecodeLimits& limits) {
    auto header = check_header(body, kOcclusion, limits);
    if (!header) return Err{std::move(header).error()};
    const std::byte* src = body.data() + kBatchHeaderBytes;
    std::vector<uint8_t> occluded(header->count);
    for (size_t i = 0; i < occluded.size(); ++i) {
        const auto v = static_cast<uint8_t>(src[i]);
        if (v > 1) {
            return Err{make(DecodeErrorCode::kBadOcclusionValue,
                            "ray " + std::to_string(i) + ": occlusion value " + std::to_string(v) +
                                ", expected 0 or 1")};
        }
        occluded[i] = v;
    }
    return occluded;
}

}  // namespace kdrt::proto
