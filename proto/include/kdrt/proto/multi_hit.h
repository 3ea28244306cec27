#pragma once
/// Every-hit answers: KDRM (per-ray offsets, per-ray counts, then hit records in a layout chosen
/// per request) and the count-only KDRC. Byte layouts and worked hex examples: proto/FORMATS.md.
/// The request is an ordinary KDRR batch (flags 0) sent to /v1/meshes/{id}/intersect_all with the
/// options as query parameters (multi_hit_query_* below name them).
///
/// Thread-safe, no shared state; decoders return a DecodeError naming the first problem and never
/// throw on bad input; encoders may throw std::bad_alloc or std::length_error (counts above u32).

#include <cstddef>
#include <cstdint>
#include <functional>
#include <optional>
#include <span>
#include <string>
#include <string_view>
#include <vector>

#include "kdrt/proto/ray_batch_header.h"
#include "kdrt/proto/result.h"
#include "kdrt/types.h"

namespace kdrt::proto {

inline constexpr std::string_view kMultiHitMagic = "KDRM";
inline constexpr std::string_view kHitCountMagic = "KDRC";
inline constexpr std::string_view kMultiHitMediaType = "application/x-kdrt-multi-hits";
inline constexpr std::string_view kHitCountMediaType = "application/x-kdrt-hit-counts";
/// KDRM header size (KDRC uses the 16-byte batch header).
inline constexpr size_t kMultiHitHeaderBytes = 32;
inline constexpr size_t kHitCountRecordBytes = 4;

/// Which of a hit's base fields a KDRM record carries.
enum class HitFields : uint16_t {
    kFull = 0,   ///< t, prim, u, v (16 bytes: a KDRH record)
    kT = 1,      ///< t only (4 bytes)
    kTPrim = 2,  ///< t, prim (8 bytes)
};
/// "full", "t", "t_prim".
[[nodiscard]] std::string_view hit_fields_name(HitFields fields) noexcept;
[[nodiscard]] std::optional<HitFields> parse_hit_fields(std::string_view name) noexcept;

/// A KDRM record layout: the base fields, then optionally the normal, then optionally the point.
struct HitLayout {
    HitFields fields = HitFields::kFull;
    bool normal = false;  ///< + nx ny nz (f32): unit right-hand normal of the triangle's v0 v1 v2
    bool point = false;   ///< + px py pz (f32): (1-u-v) v0 + u v1 + v v2 in world space
    friend bool operator==(const HitLayout&, const HitLayout&) = default;
};

/// KDRM flag bits.
inline constexpr uint16_t kMultiHitFieldsMask = 0x0003;  ///< bits 0-1: HitFields
inline constexpr uint16_t kMultiHitFlagNormal = 0x0004;
inline constexpr uint16_t kMultiHitFlagPoint = 0x0008;
inline constexpr uint16_t kMultiHitFlagMerged = 0x0010;  ///< merge_coincident was applied
inline constexpr uint16_t kMultiHitFlagsKnown = 0x001F;

/// Bytes of one record in `layout`: 4, 8 or 16, plus 12 for the normal and 12 for the point.
[[nodiscard]] constexpr uint32_t hit_record_bytes(HitLayout layout) noexcept {
    const uint32_t base = layout.fields == HitFields::kT       ? 4u
                          : layout.fields == HitFields::kTPrim ? 8u
                                                               : 16u;
    return base + (layout.normal ? 12u : 0u) + (layout.point ? 12u : 0u);
}

/// Size of a KDRM body: 32 + 8 (rays + 1) + 4 rays + hits x record bytes.
[[nodiscard]] constexpr uint64_t kdrm_body_size(uint64_t rays, uint64_t hits,
                                                HitLayout layout) noexcept {
    return kMultiHitHeaderBytes + 8 * (rays + 1) + 4 * rays + hits * hit_record_bytes(layout);
}
/// Size of a KDRC body: 16 + 4 rays.
[[nodiscard]] constexpr uint64_t kdrc_body_size(uint64_t rays) noexcept {
    return kBatchHeaderBytes + kHitCountRecordBytes * rays;
}

/// One decoded KDRM record. Fields the layout leaves out read as a miss's (prim = kNoHit,
/// u = v = 0) and as zero vectors.
struct HitRecord {
    float t = 0.0f;
    uint32_t prim = kNoHit;
    float u = 0.0f;
    float v = 0.0f;
    Vec3 normal;
    Vec3 point;
};

/// A decoded KDRM answer: the kept hits of ray i are hits[offsets[i] .. offsets[i+1]) (nearest
/// first), counts[i] is the number of all its hits (>= the number kept).
struct MultiHits {
    HitLayout layout;
    bool merged = false;
    uint32_t max_hits = 0;
    std::vector<uint64_t> offsets;
    std::vector<uint32_t> counts;
    std::vector<HitRecord> hits;
};

/// What a KDRM encoder writes. `normals` / `points` have hits.size() entries when the layout
/// carries them (else they are ignored). offsets has counts.size() + 1 entries, from 0 to
/// hits.size(), nondecreasing.
struct MultiHitsView {
    HitLayout layout;
    bool merged = false;
    uint32_t max_hits = 0;
    std::span<const uint64_t> offsets;
    std::span<const uint32_t> counts;
    std::span<const Hit> hits;
    std::span<const Vec3> normals;
    std::span<const Vec3> points;
};

/// Encodes a KDRM body (kdrm_body_size bytes). Precondition: counts.size() < 2^32.
[[nodiscard]] std::vector<std::byte> encode_multi_hits(const MultiHitsView& answer);

/// Decodes a KDRM body. Checks, in order: size >= 32, magic, version 1, flags (known bits,
/// fields 0..2), record bytes matching the flags, reserved 0, rays <= limits.max_rays, the exact
/// size for the header's ray and hit counts, then offsets (0 first, nondecreasing, the hit count
/// last) and counts (each >= its kept hits) as kBadOffsets naming the ray.
[[nodiscard]] Result<MultiHits, DecodeError> decode_multi_hits(std::span<const std::byte> body,
                                                               const DecodeLimits& limits = {});

/// Encodes a KDRC body: the batch header (flags 0) and one u32 count per ray.
[[nodiscard]] std::vector<std::byte> encode_hit_counts(std::span<const uint32_t> counts);
/// Decodes a KDRC body (the batch header's checks, exact size).
[[nodiscard]] Result<std::vector<uint32_t>, DecodeError> decode_hit_counts(
    std::span<const std::byte> body, const DecodeLimits& limits = {});

/// The hit points of a KDRM answer as a binary little-endian PLY point cloud (proto/FORMATS.md):
/// one vertex per kept hit, properties float x y z, float t, uint ray, uint prim, and float
/// nx ny nz when the layout has normals. Precondition: answer.layout.point (else
/// std::invalid_argument).
[[nodiscard]] std::vector<std::byte> encode_hit_points_ply(const MultiHits& answer);

/// Query parameter names of POST /v1/meshes/{id}/intersect_all.
inline constexpr std::string_view kQueryMaxHits = "max_hits";
inline constexpr std::string_view kQueryMerge = "merge_coincident";
inline constexpr std::string_view kQueryCountOnly = "count_only";
inline constexpr std::string_view kQueryFields = "fields";
inline constexpr std::string_view kQueryNormal = "normal";
inline constexpr std::string_view kQueryPoint = "point";

/// max_hits when the request names none (or the server's limit, if lower).
inline constexpr uint32_t kDefaultMaxHits = 16;

/// The options of an intersect_all request.
struct MultiHitQuery {
    uint32_t max_hits = kDefaultMaxHits;
    bool merge_coincident = false;
    bool count_only = false;
    HitLayout layout;
    friend bool operator==(const MultiHitQuery&, const MultiHitQuery&) = default;
};

/// Reads the query parameters of an intersect_all request: `param(name)` gives a parameter's
/// value, or nullopt when absent. Booleans are true/false/1/0; max_hits is a decimal integer in
/// 1 .. max_hits_limit. The error names the parameter, its value and what was expected.
[[nodiscard]] Result<MultiHitQuery, std::string> parse_multi_hit_query(
    const std::function<std::optional<std::string>(std::string_view)>& param,
    uint32_t max_hits_limit);
/// The query string ("max_hits=16&merge_coincident=true...") of `query`, every parameter
/// spelled out; parse_multi_hit_query reads it back.
[[nodiscard]] std::string multi_hit_query_string(const MultiHitQuery& query);

}  // namespace kdrt::proto
