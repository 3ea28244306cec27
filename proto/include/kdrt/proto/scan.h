#pragma once
/// Sensor scans on the wire (POST /v1/meshes/{id}/scan): the JSON request, the KDRZ depth image
/// and the KDRL point cloud answers, and point clouds as PLY. Byte layouts and worked hex examples:
/// proto/FORMATS.md. The EXR depth image is in kdrt/proto/scan_image.h (kdrt_proto_image).
///
/// Thread-safe, no shared state; decoders return an error naming the first problem and never
/// throw on bad input; encoders may throw std::bad_alloc or std::length_error.

#include <cstddef>
#include <cstdint>
#include <span>
#include <string>
#include <string_view>
#include <vector>

#include "kdrt/camera_spec.h"
#include "kdrt/proto/ray_batch_header.h"
#include "kdrt/proto/result.h"
#include "kdrt/scan_types.h"

namespace kdrt::proto {

inline constexpr std::string_view kDepthImageMagic = "KDRZ";
inline constexpr std::string_view kPointCloudMagic = "KDRL";
inline constexpr std::string_view kDepthImageMediaType = "application/x-kdrt-depth";
inline constexpr std::string_view kPointCloudMediaType = "application/x-kdrt-points-cloud";
inline constexpr std::string_view kPlyMediaType = "application/x-ply";
inline constexpr std::string_view kLidarRangesMagic = "KDRB";
inline constexpr std::string_view kLidarRangesMediaType = "application/x-kdrt-lidar-ranges";
inline constexpr std::string_view kScanRequestMediaType = "application/json";

/// KDRZ: 16-byte header (magic, u16 version 1, u16 flags, u32 width, u32 height), then planes of
/// width x height values each, row by row from the top: f32 depth, u32 prim, and with flag bit 1
/// f32 x 3 normals (interleaved x y z per pixel).
inline constexpr size_t kDepthImageHeaderBytes = 16;
inline constexpr uint16_t kDepthFlagRange = 0x0001;    ///< the depth plane holds ranges
inline constexpr uint16_t kDepthFlagNormals = 0x0002;  ///< a normal plane follows
/// KDRL: 32-byte header (magic, u16 version 1, u16 flags 0, u32 point count, u32 channels,
/// u32 azimuth_steps, u32 returns, u64 reserved 0), then 32-byte LidarPoint records.
inline constexpr size_t kPointCloudHeaderBytes = 32;
inline constexpr size_t kLidarPointBytes = 32;

/// KDRB: KDRL's 32-byte header (magic KDRB), then 12-byte records: f32 range, u32 beam
/// (azimuth_index x channels + channel), u32 prim. The return index is the record's place among
/// the records of its beam; the point is the beam's ray at the range (FORMATS.md, "KDRB").
inline constexpr size_t kLidarRangeBytes = 12;

[[nodiscard]] constexpr uint64_t kdrz_body_size(uint64_t pixels, bool normals) noexcept {
    return kDepthImageHeaderBytes + pixels * (normals ? 20 : 8);
}
[[nodiscard]] constexpr uint64_t kdrl_body_size(uint64_t points) noexcept {
    return kPointCloudHeaderBytes + kLidarPointBytes * points;
}

[[nodiscard]] constexpr uint64_t kdrb_body_size(uint64_t points) noexcept {
    return kPointCloudHeaderBytes + kLidarRangeBytes * points;
}

/// Encodes a KDRZ body. Precondition: depth and prim hold width * height entries, normals that
/// many or none.
[[nodiscard]] std::vector<std::byte> encode_depth_image(const DepthImage& image);
/// Decodes a KDRZ body: magic, version 1, known flags, width and height >= 1 with
/// width * height <= max_pixels (kTooManyRays), the exact size (kLengthMismatch), then per pixel
/// (kBadRecord naming it): a miss is depth +inf with prim 0xFFFFFFFF and normal 0 0 0, a hit a
/// finite depth >= 0 and a finite normal.
[[nodiscard]] Result<DepthImage, DecodeError> decode_depth_image(std::span<const std::byte> body,
                                                                 uint64_t max_pixels = 1ull << 28);

/// Encodes a KDRL body. Precondition: points.size() < 2^32.
[[nodiscard]] std::vector<std::byte> encode_point_cloud(const PointCloud& cloud);
/// Writes the same body into `out` (at least kdrl_body_size(points) bytes, e.g. a pooled
/// buffer the answer is sent from) and returns its size. Precondition: points.size() < 2^32.
size_t write_point_cloud(std::span<std::byte> out, const PointCloud& cloud);
/// Decodes a KDRL body: magic, version 1, flags 0, reserved 0, channels, azimuth_steps and returns
/// >= 1, count <= max_points (kTooManyRays), the exact size, then per point (kBadRecord naming
/// it): finite x y z, finite range >= 0, channel < channels, azimuth_index < azimuth_steps,
/// return_index < returns, prim != 0xFFFFFFFF, and the PointCloud order (beams in increasing
/// azimuth-major order, within a beam return indices 0, 1, 2, ...).
[[nodiscard]] Result<PointCloud, DecodeError> decode_point_cloud(std::span<const std::byte> body,
                                                                 uint32_t max_points = 1u << 26);

/// One KDRB record: a return's range, its beam (azimuth_index x channels + channel) and the
/// triangle hit.
struct LidarRange {
    float range = 0;
    uint32_t beam = 0;
    uint32_t prim = 0;
};
static_assert(sizeof(LidarRange) == kLidarRangeBytes);

/// A lidar scan's returns as KDRB carries them, in the PointCloud's order (beams azimuth-major;
/// within a beam nearest first, so the return index is the place in the beam's run).
struct LidarRanges {
    uint32_t channels = 0, azimuth_steps = 0, returns = 0;
    std::vector<LidarRange> points;
};

/// Encodes a KDRB body: the compact form of `cloud` (its x y z, channel, azimuth_index and
/// return_index are implied by the beam, the order and the sensor the client asked for).
/// Throws std::length_error when points.size() >= 2^32 or channels x azimuth_steps > 2^32.
[[nodiscard]] std::vector<std::byte> encode_lidar_ranges(const PointCloud& cloud);
/// Writes the same body into `out` (at least kdrb_body_size(points) bytes) and returns its size.
size_t write_lidar_ranges(std::span<std::byte> out, const PointCloud& cloud);
/// Decodes a KDRB body: magic, version 1, flags 0, reserved 0, channels, azimuth_steps and
/// returns >= 1 with channels x azimuth_steps <= 2^32, count <= max_points (kTooManyRays), the
/// exact size, then per record (kBadRecord naming it): finite range >= 0, beam < channels x
/// azimuth_steps, prim != 0xFFFFFFFF, beams in non-decreasing order and at most `returns`
/// records a beam.
[[nodiscard]] Result<LidarRanges, DecodeError> decode_lidar_ranges(std::span<const std::byte> body,
                                                                   uint32_t max_points = 1u << 26);

/// The cloud as a binary_little_endian PLY 1.0 file: one "vertex" element with properties
/// float x y z range, uint channel azimuth_index return_index prim (the KDRL record, byte for
/// byte), and comment lines naming the sensor's channels, azimuth_steps and returns. A scene's
/// cloud passes its geometry ids (one per point, the KDRL answer's plane): each vertex then has
/// a last property "uint geometry_id" (FORMATS.md, "Sensor scans").
/// Precondition: geometry_ids is empty or has cloud.points.size() entries.
[[nodiscard]] std::vector<std::byte> encode_point_cloud_ply(
    const PointCloud& cloud, std::span<const uint32_t> geometry_ids = {});

// ---- The request (kdrt_proto_json) ------------------------------------------------------------

/// Answer formats: KDRZ / KDRL, EXR (pinhole), PLY and KDRB (lidar).
enum class ScanFormat { kBinary, kExr, kPly, kRanges };
/// "binary", "exr", "ply", "ranges".
[[nodiscard]] std::string_view scan_format_name(ScanFormat format) noexcept;

/// POST /v1/meshes/{id}/scan. Exactly one of "pinhole" and "lidar":
///
///   {"pinhole": {"intrinsics": {"fx": 525, "fy": 525, "cx": 319.5, "cy": 239.5,
///                               "width": 640, "height": 480},
///                "pose": [[1,0,0,0],[0,1,0,0],[0,0,1,-2],[0,0,0,1]],
///                "output": "depth", "normals": false, "min_range": 0, "max_range": 100},
///    "format": "binary"}
///   {"pinhole": {"camera": {"eye": [0,0,3], "look_at": [0,0,0], "up": [0,1,0], "fov": 40},
///                "width": 640, "height": 480}}
///   {"lidar": {"vertical_fov": [-25, 15], "channels": 64, "azimuth_steps": 2048,
///              "min_range": 0.1, "max_range": 120, "returns": 2,
///              "pose": [[1,0,0,0],[0,1,0,0],[0,0,1,1.7],[0,0,0,1]]},
///    "format": "ply"}
///
/// pinhole: "intrinsics" and "pose" (camera-to-world, 4 rows of 4 numbers), or "camera" (the
/// renderer's look-at camera, perspective only, "fov" the vertical field of view in degrees,
/// default 40, "up" default [0,1,0]) with "width" and "height"; "output" "depth" (default) or
/// "range"; "normals" default false; "min_range" default 0; "max_range" default unlimited; format
/// "binary" (KDRZ, default) or "exr". lidar: "elevation_deg" (one per channel) or "vertical_fov"
/// [lower, upper] with "channels"; "azimuth_steps"; "returns" default 1; "min_range",
/// "max_range" as above; "pose" default the identity; format "binary" (KDRL, default), "ply" or
/// "ranges" (KDRB, the compact record).
struct ScanRequest {
    bool lidar = false;
    PinholeSpec pinhole;
    /// When set, the pinhole was given as a look-at camera (pinhole.intrinsics and pose were
    /// computed from it with kdrt::pinhole_from_look_at by the caller, see decode_scan_request).
    bool look_at = false;
    CameraSpec camera;
    uint32_t camera_width = 0, camera_height = 0;
    LidarSpec lidar_spec;
    /// When set, lidar_spec.elevation_deg came from vertical_fov and channels.
    bool vertical_fov = false;
    double fov_lower = 0, fov_upper = 0;
    uint32_t channels = 0;
    ScanFormat format = ScanFormat::kBinary;
};

/// The server's caps, checked while parsing (before any work).
struct ScanLimits {
    uint32_t max_width = 8192;       ///< max_image_width
    uint32_t max_height = 8192;      ///< max_image_height
    uint64_t max_beams = 1u << 21;   ///< max_sensor_beams: channels x azimuth_steps
    uint64_t max_points = 1u << 24;  ///< max_scan_points: pixels, or beams x returns
    uint32_t max_returns = 1024;     ///< max_hits_per_ray
};

/// A refused request: `field` names the member as the request spells it ("pinhole.pose",
/// "lidar.returns", "format"; empty for a syntax error), `detail` says what is wrong;
/// `over_limit` when a server limit (ScanLimits) was exceeded (HTTP 413).
struct ScanRequestError {
    std::string field;
    std::string detail;
    bool over_limit = false;
};

/// Parses a scan request with the strict JSON rules (unknown or duplicate members refused, every
/// number checked for type and range) and the limits. Geometric checks that need the engine
/// (kdrt::validate: a rigid pose, positive intrinsics, the range window; the look-at camera's
/// geometry) are left to the caller, which maps kdrt::ScanError's field with
/// scan_field_prefix. Fields of vertical_fov requests: elevation_deg is left empty and
/// fov_lower/fov_upper/channels are set; the caller fills it with kdrt::lidar_elevations.
[[nodiscard]] Result<ScanRequest, ScanRequestError> decode_scan_request(
    std::string_view text, const ScanLimits& limits = {});
/// The JSON decode_scan_request reads back to the same request.
[[nodiscard]] std::string encode_scan_request(const ScanRequest& request);
/// "pinhole." or "lidar.": what prefixes kdrt::ScanError::field() in the request's spelling.
[[nodiscard]] std::string_view scan_field_prefix(const ScanRequest& request) noexcept;

}  // namespace kdrt::proto
