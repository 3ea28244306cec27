#pragma once
/// The common part of the KDRR / KDRH / KDRO batch formats: the 16-byte header, record sizes,
/// body sizes, and the errors and limits every batch decoder shares. Byte layouts and worked hex
/// examples: proto/FORMATS.md.
///
/// Every batch is a 16-byte little-endian header followed by fixed-size records:
///
///   offset size field
///        0    4 magic     "KDRR" (rays), "KDRH" (hits) or "KDRO" (occlusion)
///        4    2 version   u16, 1
///        6    2 flags     u16; KDRR: bit 0 = occlusion query, other bits 0; KDRH/KDRO: 0
///        8    4 count     u32, number of records
///       12    4 reserved  u32, 0
///       16    . records   KDRR: 32 B (8 x f32 ox oy oz tmin dx dy dz tmax = kdrt::Ray)
///                         KDRH: 16 B (f32 t, u32 prim, f32 u, f32 v = kdrt::Hit)
///                         KDRO:  1 B (0 = not occluded, 1 = occluded)

#include <cstddef>
#include <cstdint>
#include <string>
#include <string_view>

#include "kdrt/types.h"

namespace kdrt::proto {

/// Size of the common batch header.
inline constexpr size_t kBatchHeaderBytes = 16;
/// Size of one record in each batch kind.
inline constexpr size_t kRayRecordBytes = 32;
inline constexpr size_t kHitRecordBytes = 16;
inline constexpr size_t kOcclusionRecordBytes = 1;
/// The only version this code reads and writes.
inline constexpr uint16_t kBatchVersion = 1;
/// KDRR flag bit 0: the rays are an occlusion (any-hit) query, answered with KDRO.
inline constexpr uint16_t kRayFlagOcclusion = 0x0001;
/// Every KDRR flag bit this version defines.
inline constexpr uint16_t kRayFlagsKnown = kRayFlagOcclusion;
/// Magics, 4 ASCII bytes at offset 0.
inline constexpr std::string_view kRayMagic = "KDRR";
inline constexpr std::string_view kHitMagic = "KDRH";
inline constexpr std::string_view kOcclusionMagic = "KDRO";

static_assert(sizeof(Ray) == kRayRecordBytes, "KDRR records are kdrt::Ray");
static_assert(sizeof(Hit) == kHitRecordBytes, "KDRH records are kdrt::Hit");

/// Size of a KDRR body of `count` rays: 16 + 32 x count (no overflow for any u32 count).
[[nodiscard]] constexpr uint64_t kdrr_body_size(uint64_t count) noexcept {
    return kBatchHeaderBytes + kRayRecordBytes * count;
}

/// Which answer a KDRR batch gets: closest hits (KDRH) or occlusion bytes (KDRO).
enum class AnswerKind { kHits, kOcclusion };

/// Size of one answer record: 16 (KDRH) or 1 (KDRO).
[[nodiscard]] constexpr size_t answer_record_size(AnswerKind kind) noexcept {
    return kind == AnswerKind::kHits ? kHitRecordBytes : kOcclusionRecordBytes;
}

/// Size of an answer body of `count` records: 16 + count x answer_record_size(kind).
[[nodiscard]] constexpr uint64_t answer_body_size(AnswerKind kind, uint64_t count) noexcept {
    return kBatchHeaderBytes + answer_record_size(kind) * count;
}

/// Why a batch was refused. Stable: the server maps these to HTTP statuses.
enum class DecodeErrorCode {
    kTooShort,           ///< fewer than 16 bytes: no complete header
    kBadMagic,           ///< bytes 0..3 are not the expected magic
    kBadVersion,         ///< version != 1
    kBadReserved,        ///< reserved field != 0
    kLengthMismatch,     ///< body size != 16 + count * record size (either direction)
    kTooManyRays,        ///< count > DecodeLimits::max_rays
    kBadFlags,           ///< a flag bit that this version does not define is set
    kNonFiniteRay,       ///< DecodeLimits::reject_non_finite and a ray has a NaN/Inf field
    kBadOcclusionValue,  ///< a KDRO byte other than 0 or 1
    kBadOffsets,         ///< KDRM: offsets not starting at 0, decreasing, or not ending at the
                         ///< hit count, or a ray's count below its kept hits
    kNonFinitePoint,     ///< KDRP with DecodeLimits::reject_non_finite: a NaN/Inf coordinate
    kBadRecord,          ///< KDRD: a record's feature, side or reserved bytes out of range
};

/// Stable snake_case name of a code ("too_short", "bad_magic", ...), e.g. for JSON error bodies.
[[nodiscard]] std::string_view decode_error_code_name(DecodeErrorCode code) noexcept;

/// A refused batch: the code plus a one-line, human-readable detail naming the offending field
/// and values, e.g. `bad magic "ABCD", expected "KDRR"`,
/// `header says 10 rays (336 bytes) but body has 300 bytes`, `ray 17: field dx is NaN`.
struct DecodeError {
    DecodeErrorCode code = DecodeErrorCode::kTooShort;
    std::string detail;

    /// "<code name>: <detail>".
    [[nodiscard]] std::string to_string() const;
};

/// Limits a decoder enforces before allocating anything.
struct DecodeLimits {
    /// Largest accepted record count (rays, hits or occlusion bytes). Larger -> kTooManyRays.
    uint32_t max_rays = 1u << 26;
    /// KDRR only. When false (default) rays are decoded as sent and the engine treats invalid ones
    /// as misses. When true, a ray is refused (kNonFiniteRay, detail names the first ray index and
    /// field among ox oy oz tmin dx dy dz tmax) if any origin or direction component is NaN or
    /// +-inf, or tmin or tmax is NaN. tmin/tmax = +-inf stay accepted: tmax = +inf is the usual
    /// unbounded ray and the engine traces it.
    bool reject_non_finite = false;
};

}  // namespace kdrt::proto
