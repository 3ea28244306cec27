#pragma once
/// KDRR / KDRH / KDRO codecs for whole bodies: rays in, closest hits or occlusion bits out, and
/// the in-place encoding of an answer the engine wrote straight into its response buffer.
///
/// All functions are thread-safe (no shared state) and never throw on bad input; decoders return
/// a DecodeError naming the first problem. Encoders may throw std::bad_alloc only.

#include <cstddef>
#include <cstdint>
#include <span>
#include <vector>

#include "kdrt/proto/ray_batch_header.h"
#include "kdrt/proto/result.h"
#include "kdrt/types.h"

namespace kdrt::proto {

/// A decoded KDRR batch.
struct RayBatch {
    std::vector<Ray> rays;
    /// Flag bit 0: answer with occlusion bytes (KDRO) instead of closest hits (KDRH).
    bool occlusion = false;
    /// The raw flags field (only kRayFlagsKnown bits can be set in a decoded batch).
    uint16_t flags = 0;
};

/// Decodes a KDRR body. Checks, in order: size >= 16 (kTooShort), magic, version, flags (only
/// bit 0), reserved == 0, count <= limits.max_rays, size == 16 + 32 * count exactly, and, if
/// requested, finiteness. A count-0 batch is valid. Ray values are bit-exact copies of the wire.
[[nodiscard]] Result<RayBatch, DecodeError> decode_rays(std::span<const std::byte> body,
                                                        const DecodeLimits& limits = {});

/// Encodes rays as a KDRR body (flags = 1 if `occlusion`). Values are copied bit-exactly,
/// NaN payloads included. Precondition: rays.size() < 2^32 (else std::length_error).
[[nodiscard]] std::vector<std::byte> encode_rays(std::span<const Ray> rays, bool occlusion);

/// Encodes closest hits as a KDRH body (flags = 0), bit-exactly.
/// Precondition: hits.size() < 2^32 (else std::length_error).
[[nodiscard]] std::vector<std::byte> encode_hits(std::span<const Hit> hits);

/// Decodes a KDRH body: magic, version, flags == 0, reserved == 0, count <= limits.max_rays,
/// exact size. Hit values are not interpreted (any t/prim/u/v bit pattern is accepted).
[[nodiscard]] Result<std::vector<Hit>, DecodeError> decode_hits(std::span<const std::byte> body,
                                                                const DecodeLimits& limits = {});

/// Encodes occlusion answers as a KDRO body (flags = 0): one byte per ray, any nonzero input
/// byte is written as 1. Precondition: occluded.size() < 2^32 (else std::length_error).
[[nodiscard]] std::vector<std::byte> encode_occlusion(std::span<const uint8_t> occluded);

/// Decodes a KDRO body: magic, version, flags == 0, reserved == 0, count <= limits.max_rays,
/// exact size, every byte 0 or 1 (else kBadOcclusionValue naming the ray index and value).
[[nodiscard]] Result<std::vector<uint8_t>, DecodeError> decode_occlusion(
    std::span<const std::byte> body, const DecodeLimits& limits = {});

/// Answers encoded in place, for callers that trace straight into their response buffer: `body`
/// is caller storage of at least answer_body_size(kind, count) bytes whose record area (body +
/// 16) is aligned for kdrt::Hit (any 16-byte-aligned buffer is). The engine writes its answers
/// into the record view; write_answer_in_place then writes the header and puts the records in
/// their wire form.
///
/// The `count` KDRH records of `body`, as the engine's Hit array.
[[nodiscard]] std::span<Hit> answer_hit_records(std::byte* body, uint32_t count) noexcept;
/// The `count` KDRO records of `body`, one uint8_t per ray (any nonzero value means occluded).
[[nodiscard]] std::span<uint8_t> answer_occlusion_records(std::byte* body, uint32_t count) noexcept;

/// Writes the answer header into the first 16 bytes of `body` and turns its `count` records into
/// their wire form in place (any nonzero occlusion value becomes 1), giving the same bytes as
/// encode_hits / encode_occlusion of the records. Returns the body size,
/// answer_body_size(kind, count).
size_t write_answer_in_place(std::byte* body, AnswerKind kind, uint32_t count) noexcept;

}  // namespace kdrt::proto
