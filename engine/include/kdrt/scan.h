#pragma once
/// Sensor scans whose rays are made here: a pinhole depth camera and a spinning lidar
/// (kdrt/scan_types.h has the frames and conventions).
///
/// Rays. Every ray starts at the pose's translation t (rounded to float) and has the unit
/// direction R * v / |v|, v the sensor-frame direction, computed in double and rounded to float
/// once per component. Hits are the closest-hit kernel's (pinhole) and intersect_all's (lidar),
/// with ray tmin = min_range and tmax = max_range, so range = the hit's t (units of the rounded
/// unit direction). Depth = range * (v_z / |v|), the cosine to the optical axis taken in double,
/// the product in double rounded to float. Normals are triangle_normal (kdrt/query.h): the unit
/// right-hand normal of the triangle's v0 v1 v2, as the every-hit answers give it, not turned
/// towards the camera. Lidar points are hit_point (kdrt/query.h): on the triangle to rounding.
///
/// Deterministic: the same spec gives the same answer bit for bit at any thread count.

#include <stdexcept>
#include <string>
#include <string_view>

#include "kdrt/camera_spec.h"
#include "kdrt/kdtree.h"
#include "kdrt/scan_types.h"

namespace kdrt {

/// A scan spec that cannot be scanned. field() names the offending field as the request JSON
/// spells it ("pose", "intrinsics.fx", "min_range", "elevation_deg[3]", ...); what() says why.
class ScanError : public std::invalid_argument {
public:
    ScanError(std::string field, const std::string& what)
        : std::invalid_argument(what), field_(std::move(field)) {}
    [[nodiscard]] const std::string& field() const noexcept { return field_; }

private:
    std::string field_;
};

/// Throws ScanError(field, ...) unless `pose` is rigid (scan_types.h).
void validate_pose(const Pose& pose, std::string_view field = "pose");

/// Throws ScanError naming the field unless every field of `spec` is in its documented range.
void validate(const PinholeSpec& spec);
void validate(const LidarSpec& spec);

/// The pinhole equivalent of the renderer's perspective look-at camera (kdrt/camera.h) for a
/// width x height image: the camera's basis (right, -up, forward) in double as the renderer
/// computes it, as the pose columns, t = eye; fx = fy = (height / 2) / tan(fov_deg / 2),
/// cx = width / 2, cy = height / 2. Its rays go through the renderer's pixels (not bit for bit: the
/// renderer rounds its basis to float first). Throws CameraError naming a bad field (as Camera
/// does) and ScanError("camera.projection") for an orthographic camera.
struct PinholeCamera {
    PinholeIntrinsics intrinsics;
    Pose pose;
};
[[nodiscard]] PinholeCamera pinhole_from_look_at(const CameraSpec& camera, uint32_t width,
                                                 uint32_t height);

/// The ray of pixel (i, j) (i < width, j < height) and the cosine of its angle to the optical axis
/// (v_z / |v|, in double). `spec` must be valid.
[[nodiscard]] Ray pinhole_ray(const PinholeSpec& spec, uint32_t i, uint32_t j,
                              double* cos_axis = nullptr) noexcept;

/// The elevations, in degrees, of `channels` evenly spaced channels from upper_deg (channel 0) down
/// to lower_deg (the last): upper - (upper - lower) * c / (channels - 1), in double; one channel
/// is at (lower + upper) / 2. Throws ScanError("vertical_fov" / "channels") unless
/// -90 <= lower <= upper <= 90 (finite) and channels >= 1.
[[nodiscard]] std::vector<double> lidar_elevations(double lower_deg, double upper_deg,
                                                   uint32_t channels);

/// The ray of a lidar beam. `spec` must be valid.
[[nodiscard]] Ray lidar_ray(const LidarSpec& spec, uint32_t channel,
                            uint32_t azimuth_index) noexcept;

/// The depth image of `spec` (validated first; throws ScanError). Parallel over the current
/// oneTBB arena. Throws std::bad_alloc.
[[nodiscard]] DepthImage scan_pinhole(const KdTree& tree, const PinholeSpec& spec);

/// The lidar returns of `spec` (validated first; throws ScanError): per beam the nearest
/// `returns` hits of intersect_all with merge_coincident (a beam through a shared edge or vertex
/// gives one return), in PointCloud order. Parallel over the current arena. Throws std::bad_alloc.
[[nodiscard]] PointCloud scan_lidar(const KdTree& tree, const LidarSpec& spec);

}  // namespace kdrt
