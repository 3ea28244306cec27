// Whole-body KDRR / KDRH / KDRO encoders and decoders, and the in-place answer encoding. Records
// are host structs in wire order (little-endian host, byte_io.h), so they are copied as arrays.

#include "kdrt/proto/ray_batch_codec.h"

#include <cstring>
#include <limits>
#include <stdexcept>
#include <string>

#include "byte_io.h"
#include "ray_batch_checks.h"

namespace kdrt::proto {
namespace {

using detail::BatchKind;

void write_header(std::byte* out, const BatchKind& kind, uint32_t count, uint16_t flags) noexcept {
    std::memcpy(out, kind.magic.data(), 4);
    detail::store_le16(out + 4, kBatchVersion);
    detail::store_le16(out + 6, flags);
    detail::store_le32(out + 8, count);
    detail::store_le32(out + 12, 0);
}

/// A vector of 16 + count * record_bytes bytes with the header filled in.
std::vector<std::byte> start_batch(const BatchKind& kind, size_t count, uint16_t flags) {
    if (count > std::numeric_limits<uint32_t>::max()) {
        throw std::length_error(std::string(kind.magic) + " batch of " + std::to_string(count) +
                                " records exceeds the u32 count field");
    }
    std::vector<std::byte> out(kBatchHeaderBytes + count * kind.record_bytes);
    write_header(out.data(), kind, static_cast<uint32_t>(count), flags);
    return out;
}

/// Occlusion records on the wire are 0 or 1, whatever nonzero value the engine wrote.
void normalise_occlusion(std::byte* records, size_t count) noexcept {
    for (size_t i = 0; i < count; ++i)
        records[i] = std::byte{records[i] != std::byte{0} ? uint8_t{1} : uint8_t{0}};
}

}  // namespace

Result<RayBatch, DecodeError> decode_rays(std::span<const std::byte> body,
                                          const DecodeLimits& limits) {
    auto header = detail::check_header(body, detail::kRays, limits);
    if (!header) return Err{std::move(header).error()};
    RayBatch batch;
    batch.flags = header->flags;
    batch.occlusion = (header->flags & kRayFlagOcclusion) != 0;
    batch.rays.resize(header->count);
    if (header->count != 0) {
        std::memcpy(batch.rays.data(), body.data() + kBatchHeaderBytes,
                    size_t{header->count} * kRayRecordBytes);
    }
    if (limits.reject_non_finite) {
        for (size_t i = 0; i < batch.rays.size(); ++i)
            if (detail::ray_refused(batch.rays[i]))
                return Err{detail::non_finite_error(i, batch.rays[i])};
    }
    return batch;
}

std::vector<std::byte> encode_rays(std::span<const Ray> rays, bool occlusion) {
    std::vector<std::byte> out =
        start_batch(detail::kRays, rays.size(), occlusion ? kRayFlagOcclusion : 0);
    if (!rays.empty()) std::memcpy(out.data() + kBatchHeaderBytes, rays.data(), rays.size_bytes());
    return out;
}

std::vector<std::byte> encode_hits(std::span<const Hit> hits) {
    std::vector<std::byte> out = start_batch(detail::kHits, hits.size(), 0);
    if (!hits.empty()) std::memcpy(out.data() + kBatchHeaderBytes, hits.data(), hits.size_bytes());
    return out;
}

Result<std::vector<Hit>, DecodeError> decode_hits(std::span<const std::byte> body,
                                                  const DecodeLimits& limits) {
    auto header = detail::check_header(body, detail::kHits, limits);
    if (!header) return Err{std::move(header).error()};
    std::vector<Hit> hits(header->count);
    if (header->count != 0) {
        std::memcpy(hits.data(), body.data() + kBatchHeaderBytes,
                    size_t{header->count} * kHitRecordBytes);
    }
    return hits;
}

std::vector<std::byte> encode_occlusion(std::span<const uint8_t> occluded) {
    std::vector<std::byte> out = start_batch(detail::kOcclusion, occluded.size(), 0);
    std::byte* dst = out.data() + kBatchHeaderBytes;
    if (!occluded.empty()) std::memcpy(dst, occluded.data(), occluded.size());
    normalise_occlusion(dst, occluded.size());
    return out;
}

Result<std::vector<uint8_t>, DecodeError> decode_occlusion(std::span<const std::byte> body,
                                                           const DecodeLimits& limits) {
    auto header = detail::check_header(body, detail::kOcclusion, limits);
    if (!header) return Err{std::move(header).error()};
    const std::byte* src = body.data() + kBatchHeaderBytes;
    std::vector<uint8_t> occluded(header->count);
    for (size_t i = 0; i < occluded.size(); ++i) {
        const auto v = static_cast<uint8_t>(src[i]);
        if (v > 1) {
            return Err{DecodeError{DecodeErrorCode::kBadOcclusionValue,
                                   "ray " + std::to_string(i) + ": occlusion value " +
                                       std::to_string(v) + ", expected 0 or 1"}};
        }
        occluded[i] = v;
    }
    return occluded;
}

std::span<Hit> answer_hit_records(std::byte* body, uint32_t count) noexcept {
    // Hit is an implicit-lifetime type: the caller's aligned storage holds the array.
    return {reinterpret_cast<Hit*>(body + kBatchHeaderBytes), count};
}

std::span<uint8_t> answer_occlusion_records(std::byte* body, uint32_t count) noexcept {
    return {reinterpret_cast<uint8_t*>(body + kBatchHeaderBytes), count};
}

size_t write_answer_in_place(std::byte* body, AnswerKind kind, uint32_t count) noexcept {
    const bool hits = kind == AnswerKind::kHits;
    write_header(body, hits ? detail::kHits : detail::kOcclusion, count, 0);
    if (!hits) normalise_occlusion(body + kBatchHeaderBytes, count);
    return static_cast<size_t>(answer_body_size(kind, count));
}

}  // namespace kdrt::proto
