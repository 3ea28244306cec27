#pragma once
/// Distance queries on the wire: KDRP query points (request) and KDRD closest points (answer),
/// both the 16-byte batch header plus fixed records; the query parameters of
/// POST /v1/meshes/{id}/distance; and query points as text (XYZ / CSV lines). Byte layouts and
/// worked hex examples: proto/FORMATS.md.
///
/// Thread-safe, no shared state; decoders return a DecodeError naming the first problem and never
/// throw on bad input; encoders may throw std::bad_alloc or std::length_error (counts above u32).

#include <cstddef>
#include <cstdint>
#include <functional>
#include <limits>
#include <optional>
#include <span>
#include <string>
#include <string_view>
#include <vector>

#include "kdrt/distance_types.h"
#include "kdrt/proto/ray_batch_header.h"
#include "kdrt/proto/result.h"
#include "kdrt/types.h"

namespace kdrt::proto {

inline constexpr std::string_view kPointMagic = "KDRP";
inline constexpr std::string_view kDistanceMagic = "KDRD";
inline constexpr std::string_view kPointMediaType = "application/x-kdrt-points";
inline constexpr std::string_view kDistanceMediaType = "application/x-kdrt-distances";
/// KDRP record: f32 x, y, z.
inline constexpr size_t kPointRecordBytes = 12;
/// KDRD record: f32 distance, u32 prim, f32 u, f32 v, f32 px py pz, u8 feature, u8 side, u16 0.
inline constexpr size_t kDistanceRecordBytes = 32;
/// KDRD flag bit 0: the sides were asked for (signed=true). Without it every side is kUnknown.
inline constexpr uint16_t kDistanceFlagSigned = 0x0001;

[[nodiscard]] constexpr uint64_t kdrp_body_size(uint64_t points) noexcept {
    return kBatchHeaderBytes + kPointRecordBytes * points;
}
[[nodiscard]] constexpr uint64_t kdrd_body_size(uint64_t points) noexcept {
    return kBatchHeaderBytes + kDistanceRecordBytes * points;
}

/// Encodes a KDRP body (flags 0). Precondition: points.size() < 2^32.
[[nodiscard]] std::vector<std::byte> encode_points(std::span<const Vec3> points);
/// The first point of `points` with a NaN or infinite coordinate, worded as decode_points refuses
/// it ("point 17: field y is NaN"); nullopt when every coordinate is finite.
[[nodiscard]] std::optional<std::string> non_finite_point(std::span<const Vec3> points);
/// Decodes a KDRP body: the batch header's checks (magic, version 1, flags 0, reserved 0,
/// count <= limits.max_rays, the exact size), then, with limits.reject_non_finite, the first point
/// with a NaN or infinite coordinate as kNonFinitePoint ("point 17: field y is NaN").
[[nodiscard]] Result<std::vector<Vec3>, DecodeError> decode_points(std::span<const std::byte> body,
                                                                   const DecodeLimits& limits = {});

/// Encodes a KDRD body; `signed_query` sets flag bit 0.
[[nodiscard]] std::vector<std::byte> encode_distances(std::span<const ClosestPoint> answers,
                                                      bool signed_query);
struct Distances {
    bool signed_query = false;
    std::vector<ClosestPoint> points;
};
/// Decodes a KDRD body: the header's checks (only flag bit 0 known), then each record's feature
/// (0..7), side (0..2) and reserved bytes (0) as kBadRecord naming the point.
[[nodiscard]] Result<Distances, DecodeError> decode_distances(std::span<const std::byte> body,
                                                              const DecodeLimits& limits = {});

/// "face", "edge01", "edge12", "edge20", "vertex0", "vertex1", "vertex2", "none".
[[nodiscard]] std::string_view feature_name(Feature feature) noexcept;
/// "outside", "inside", "unknown".
[[nodiscard]] std::string_view side_name(Side side) noexcept;

/// Query parameter names of POST /v1/meshes/{id}/distance.
inline constexpr std::string_view kQueryMaxDistance = "max_distance";
inline constexpr std::string_view kQuerySigned = "signed";

/// The options of a distance request.
struct DistanceQuery {
    float max_distance = std::numeric_limits<float>::infinity();  ///< >= 0; +inf: no limit
    bool signed_query = false;
    friend bool operator==(const DistanceQuery&, const DistanceQuery&) = default;
};
/// Reads the query parameters of a distance request (`param(name)`: the value or nullopt).
/// max_distance is a decimal number >= 0 or "inf"; signed is true/false/1/0. The error names the
/// parameter, its value and what was expected.
[[nodiscard]] Result<DistanceQuery, std::string> parse_distance_query(
    const std::function<std::optional<std::string>(std::string_view)>& param);
/// The query string of `query` ("max_distance=0.5&signed=true"; max_distance left out when
/// infinite); parse_distance_query reads it back.
[[nodiscard]] std::string distance_query_string(const DistanceQuery& query);

/// Query points as text, one point a line: three numbers separated by spaces, tabs or commas
/// (XYZ or CSV); further numbers on a line are ignored (e.g. normals of an XYZ file); blank lines
/// and lines starting with '#' are skipped, and so is a first line that is not numeric (a CSV
/// header). The error names the line. Coordinates must be finite.
[[nodiscard]] Result<std::vector<Vec3>, std::string> parse_points_text(std::string_view text);

/// Closest points as CSV with a header line: x,y,z (the query point), distance, signed_distance
/// (empty unless the side is known), side, prim (empty when nothing was found), u, v, px, py, pz,
/// feature. Floats are printed as the shortest decimal that reads back to the same float. With
/// `geometry_ids` (a scene's answer: one per query point), a last column geometry_id (empty when
/// nothing was found).
[[nodiscard]] std::string distances_csv(std::span<const Vec3> queries,
                                        std::span<const ClosestPoint> answers,
                                        std::span<const uint32_t> geometry_ids = {});

}  // namespace kdrt::proto
