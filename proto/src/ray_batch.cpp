#include "kdrt/proto/ray_batch.h"

#include <algorithm>
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

/// Validates the 16 header bytes at `p` (everything but the body length).
Result<CheckedHeader, DecodeError> check_header_fields(const std::byte* p, const BatchKind& kind,
                                                       const DecodeLimits& limits) {
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
    return CheckedHeader{flags, count};
}

/// Validates the header and the exact body length; nothing is allocated.
Result<CheckedHeader, DecodeError> check_header(std::span<const std::byte> body,
                                                const BatchKind& kind, const DecodeLimits& limits) {
    if (body.size() < kBatchHeaderBytes) return Err{too_short(body.size())};
    auto header = check_header_fields(body.data(), kind, limits);
    if (!header) return header;
    if (body.size() != kBatchHeaderBytes + uint64_t{header->count} * kind.record_bytes)
        return Err{length_mismatch(kind, header->count, body.size())};
    return header;
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

/// The same test as first_bad_ray_field(ray) >= 0, branch-free on the bit patterns (the stream
/// decoder runs it on every ray as it arrives).
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
                                                    " is " + describe_non_finite(f[field]));
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
        for (size_t i = 0; i < batch.rays.size(); ++i)
            if (ray_refused(batch.rays[i])) return Err{non_finite_error(i, batch.rays[i])};
    }
    return batch;
}

RayStreamDecoder::RayStreamDecoder(DecodeLimits limits, Storage storage,
                                   std::optional<uint64_t> declared_bytes)
    : limits_(limits), storage_(std::move(storage)), declared_(declared_bytes) {}

bool RayStreamDecoder::fail(DecodeError error) {
    error_ = std::move(error);
    return false;
}

void RayStreamDecoder::check_new_rays(uint64_t end) {
    Ray* rays = reinterpret_cast<Ray*>(records_);
    if constexpr (!kHostLittleEndian) {
        for (uint64_t i = ready_; i < end; ++i) {
            Ray& r = rays[i];
            std::byte raw[kRayRecordBytes];
            std::memcpy(raw, &r, sizeof raw);
            float* f[8] = {&r.ox, &r.oy, &r.oz, &r.tmin, &r.dx, &r.dy, &r.dz, &r.tmax};
            for (int k = 0; k < 8; ++k) *f[k] = detail::load_le_f32(raw + 4 * k);
        }
    }
    if (limits_.reject_non_finite && !first_refused_) {
        for (uint64_t i = ready_; i < end; ++i) {
            if (!ray_refused(rays[i])) continue;
            first_refused_ = i;
            // With the size known to match, nothing that follows can change the verdict.
            if (declared_) fail(non_finite_error(i, rays[i]));
            break;
        }
    }
    ready_ = end;
}

bool RayStreamDecoder::feed(std::span<const std::byte> piece) {
    uint64_t pos = seen_;
    seen_ += piece.size();
    if (error_) return false;
    const std::byte* p = piece.data();
    size_t n = piece.size();
    if (!header_done_) {
        const size_t take = std::min<size_t>(n, kBatchHeaderBytes - pos);
        if (take > 0) std::memcpy(header_ + pos, p, take);
        pos += take;
        p += take;
        n -= take;
        if (pos < kBatchHeaderBytes) return true;
        auto header = check_header_fields(header_, kRays, limits_);
        if (!header) return fail(std::move(header).error());
        flags_ = header->flags;
        count_ = header->count;
        expected_ = kBatchHeaderBytes + uint64_t{count_} * kRayRecordBytes;
        header_done_ = true;
        if (declared_ && *declared_ != expected_)
            return fail(length_mismatch(kRays, count_, *declared_));
        const std::span<Ray> storage = storage_(count_, occlusion());
        if (storage.size() != count_)
            throw std::logic_error("RayStreamDecoder: storage for " +
                                   std::to_string(storage.size()) + " rays, the header says " +
                                   std::to_string(count_));
        records_ = reinterpret_cast<std::byte*>(storage.data());
    }
    if (n > 0 && pos < expected_) {
        const size_t take = static_cast<size_t>(std::min<uint64_t>(n, expected_ - pos));
        std::memcpy(records_ + (pos - kBatchHeaderBytes), p, take);
        pos += take;
        check_new_rays((pos - kBatchHeaderBytes) / kRayRecordBytes);
    }
    return !error_;
}

std::span<std::byte> RayStreamDecoder::next_window() const noexcept {
    if (!header_done_ || error_ || seen_ >= expected_) return {};
    return {records_ + (seen_ - kBatchHeaderBytes), static_cast<size_t>(expected_ - seen_)};
}

bool RayStreamDecoder::commit(size_t n) {
    if (n > next_window().size())
        throw std::logic_error("RayStreamDecoder::commit: " + std::to_string(n) +
                               " bytes, more than the window");
    seen_ += n;
    check_new_rays((seen_ - kBatchHeaderBytes) / kRayRecordBytes);
    return !error_;
}

Result<void, DecodeError> RayStreamDecoder::finish() {
    if (error_) return Err{*error_};
    if (!header_done_) return Err{too_short(seen_)};
    if (seen_ != expected_) return Err{length_mismatch(kRays, count_, seen_)};
    if (first_refused_) {
        const Ray* rays = reinterpret_cast<const Ray*>(records_);
        return Err{non_finite_error(*first_refused_, rays[*first_refused_])};
    }
    return {};
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

size_t write_answer_in_place(std::byte* out, AnswerKind kind, uint32_t count) noexcept {
    const BatchKind& batch = kind == AnswerKind::kHits ? kHits : kOcclusion;
    std::memcpy(out, batch.magic.data(), 4);
    detail::store_le16(out + 4, kBatchVersion);
    detail::store_le16(out + 6, 0);
    detail::store_le32(out + 8, count);
    detail::store_le32(out + 12, 0);
    std::byte* records = out + kBatchHeaderBytes;
    if (kind == AnswerKind::kOcclusion) {
        for (uint32_t i = 0; i < count; ++i)
            records[i] = std::byte{records[i] != std::byte{0} ? uint8_t{1} : uint8_t{0}};
    } else if constexpr (!kHostLittleEndian) {
        for (uint32_t i = 0; i < count; ++i) {
            Hit h;
            std::byte* dst = records + size_t{i} * kHitRecordBytes;
            std::memcpy(&h, dst, sizeof h);
            detail::store_le_f32(dst, h.t);
            detail::store_le32(dst + 4, h.prim);
            detail::store_le_f32(dst + 8, h.u);
            detail::store_le_f32(dst + 12, h.v);
        }
    }
    return kBatchHeaderBytes + size_t{count} * batch.record_bytes;
}

}  // namespace kdrt::proto
