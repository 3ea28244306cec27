// Sensor scans: rays made from a pinhole camera or a spinning lidar, traced with the closest-hit
// batch tracer (pinhole) or intersect_all (lidar). Rays are built in double and rounded once, and
// every answer is written by index, so the result does not depend on the thread count.

#include "kdrt/scan.h"

#include <algorithm>
#include <array>
#include <cmath>
#include <numbers>
#include <numeric>
#include <string>

#include <emmintrin.h>
#include <tbb/blocked_range.h>
#include <tbb/parallel_for.h>

#include "kdrt/camera.h"
#include "kdrt/query.h"
#include "kdrt/trace.h"
#include "scan_internal.h"

namespace kdrt {
namespace {

std::string num(double v) {
    char buf[64];
    std::snprintf(buf, sizeof buf, "%.17g", v);
    return buf;
}

void require_range(float min_range, float max_range) {
    if (!(min_range >= 0.0f) || !std::isfinite(min_range))
        throw ScanError("min_range", "min_range " + num(min_range) + " must be finite and >= 0");
    if (!(max_range > min_range))
        throw ScanError("max_range", "max_range " + num(max_range) +
                                         " must be greater than min_range " + num(min_range));
}

/// The ray from the pose's origin along R * v / |v|.
Ray pose_ray(const Pose& pose, const double v[3], float min_range, float max_range,
             double* inv_len) noexcept {
    const double len = std::sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2]);
    const double* m = pose.m.data();
    double d[3];
    for (int r = 0; r < 3; ++r)
        d[r] = (m[4 * r] * v[0] + m[4 * r + 1] * v[1] + m[4 * r + 2] * v[2]) / len;
    if (inv_len) *inv_len = 1.0 / len;
    return Ray{
        static_cast<float>(m[3]), static_cast<float>(m[7]), static_cast<float>(m[11]), min_range,
        static_cast<float>(d[0]), static_cast<float>(d[1]), static_cast<float>(d[2]),  max_range};
}

constexpr size_t kRowBlock = 1;
constexpr double kDegToRad = std::numbers::pi / 180.0;

}  // namespace

void validate_pose(const Pose& pose, std::string_view field) {
    const std::string f(field);
    const double* m = pose.m.data();
    for (int k = 0; k < 16; ++k) {
        if (!std::isfinite(m[k]))
            throw ScanError(f, f + " entry [" + std::to_string(k / 4) + "][" +
                                   std::to_string(k % 4) + "] is NaN or infinite");
    }
    if (m[12] != 0.0 || m[13] != 0.0 || m[14] != 0.0 || m[15] != 1.0)
        throw ScanError(f, f + " last row is " + num(m[12]) + " " + num(m[13]) + " " + num(m[14]) +
                               " " + num(m[15]) + ", not 0 0 0 1: not a rigid transform");
    for (int a = 0; a < 3; ++a) {
        for (int b = 0; b < 3; ++b) {
            double s = 0.0;
            for (int r = 0; r < 3; ++r) s += m[4 * r + a] * m[4 * r + b];
            const double e = s - (a == b ? 1.0 : 0.0);
            if (!(std::fabs(e) <= kPoseTolerance))
                throw ScanError(f, f + " rotation is not orthonormal: (R^T R)[" +
                                       std::to_string(a) + "][" + std::to_string(b) +
                                       "] = " + num(s) + " (tolerance " + num(kPoseTolerance) +
                                       "): not a rigid transform");
        }
    }
    const double det = m[0] * (m[5] * m[10] - m[6] * m[9]) - m[1] * (m[4] * m[10] - m[6] * m[8]) +
                       m[2] * (m[4] * m[9] - m[5] * m[8]);
    if (!(std::fabs(det - 1.0) <= kPoseTolerance))
        throw ScanError(f, f + " rotation has determinant " + num(det) +
                               ", not +1: a reflection, not a rigid transform");
}

void validate(const PinholeSpec& spec) {
    const PinholeIntrinsics& k = spec.intrinsics;
    if (!(k.fx > 0.0) || !std::isfinite(k.fx))
        throw ScanError("intrinsics.fx", "intrinsics.fx " + num(k.fx) + " must be finite and > 0");
    if (!(k.fy > 0.0) || !std::isfinite(k.fy))
        throw ScanError("intrinsics.fy", "intrinsics.fy " + num(k.fy) + " must be finite and > 0");
    if (!std::isfinite(k.cx))
        throw ScanError("intrinsics.cx", "intrinsics.cx " + num(k.cx) + " must be finite");
    if (!std::isfinite(k.cy))
        throw ScanError("intrinsics.cy", "intrinsics.cy " + num(k.cy) + " must be finite");
    if (k.width == 0) throw ScanError("intrinsics.width", "intrinsics.width must be at least 1");
    if (k.height == 0) throw ScanError("intrinsics.height", "intrinsics.height must be at least 1");
    if (spec.kind != DepthKind::kDepth && spec.kind != DepthKind::kRange)
        throw ScanError("output", "output " + std::to_string(static_cast<uint32_t>(spec.kind)) +
                                      " is neither depth (0) nor range (1)");
    require_range(spec.min_range, spec.max_range);
    validate_pose(spec.pose);
}

void validate(const LidarSpec& spec) {
    if (spec.elevation_deg.empty())
        throw ScanError("elevation_deg",
                        "a lidar needs at least 1 channel (elevation_deg is empty)");
    for (size_t c = 0; c < spec.elevation_deg.size(); ++c) {
        const double e = spec.elevation_deg[c];
        if (!(e >= -90.0 && e <= 90.0))
            throw ScanError("elevation_deg[" + std::to_string(c) + "]",
                            "elevation_deg[" + std::to_string(c) + "] " + num(e) +
                                " is outside [-90, 90] degrees");
    }
    if (spec.azimuth_steps == 0)
        throw ScanError("azimuth_steps", "azimuth_steps must be at least 1");
    if (spec.returns == 0 || spec.returns > kMaxHitsPerRay)
        throw ScanError("returns", "returns " + std::to_string(spec.returns) + " is outside 1 .. " +
                                       std::to_string(kMaxHitsPerRay));
    require_range(spec.min_range, spec.max_range);
    validate_pose(spec.pose);
}

PinholeCamera pinhole_from_look_at(const CameraSpec& camera, uint32_t width, uint32_t height) {
    if (camera.projection != Projection::kPerspective)
        throw ScanError("camera.projection", "a scan camera must be perspective");
    const Camera checked(camera, width, height);  // throws CameraError naming the field
    // Camera's basis, in double (camera.cpp).
    const double eye[3] = {camera.eye.x, camera.eye.y, camera.eye.z};
    double fwd[3] = {double{camera.look_at.x} - eye[0], double{camera.look_at.y} - eye[1],
                     double{camera.look_at.z} - eye[2]};
    const double fl = std::sqrt(fwd[0] * fwd[0] + fwd[1] * fwd[1] + fwd[2] * fwd[2]);
    for (double& c : fwd) c /= fl;
    double up[3] = {camera.up.x, camera.up.y, camera.up.z};
    const double ul = std::sqrt(up[0] * up[0] + up[1] * up[1] + up[2] * up[2]);
    for (double& c : up) c /= ul;
    double right[3] = {fwd[1] * up[2] - fwd[2] * up[1], fwd[2] * up[0] - fwd[0] * up[2],
                       fwd[0] * up[1] - fwd[1] * up[0]};
    const double rl = std::sqrt(right[0] * right[0] + right[1] * right[1] + right[2] * right[2]);
    for (double& c : right) c /= rl;
    const double true_up[3] = {right[1] * fwd[2] - right[2] * fwd[1],
                               right[2] * fwd[0] - right[0] * fwd[2],
                               right[0] * fwd[1] - right[1] * fwd[0]};
    PinholeCamera out;
    for (int r = 0; r < 3; ++r) {
        out.pose.m[4 * r + 0] = right[r];
        out.pose.m[4 * r + 1] = -true_up[r];  // OpenCV: +y down
        out.pose.m[4 * r + 2] = fwd[r];
        out.pose.m[4 * r + 3] = eye[r];
    }
    const double half_h =
        std::tan(static_cast<double>(camera.fov_deg) * (std::numbers::pi / 360.0));
    out.intrinsics.fy = 0.5 * static_cast<double>(height) / half_h;
    out.intrinsics.fx = out.intrinsics.fy;
    out.intrinsics.cx = 0.5 * static_cast<double>(width);
    out.intrinsics.cy = 0.5 * static_cast<double>(height);
    out.intrinsics.width = width;
    out.intrinsics.height = height;
    return out;
}

Ray pinhole_ray(const PinholeSpec& spec, uint32_t i, uint32_t j, double* cos_axis) noexcept {
    const PinholeIntrinsics& k = spec.intrinsics;
    const double v[3] = {(static_cast<double>(i) + 0.5 - k.cx) / k.fx,
                         (static_cast<double>(j) + 0.5 - k.cy) / k.fy, 1.0};
    return pose_ray(spec.pose, v, spec.min_range, spec.max_range, cos_axis);  // v_z = 1
}

std::vector<double> lidar_elevations(double lower_deg, double upper_deg, uint32_t channels) {
    if (!(lower_deg >= -90.0 && upper_deg <= 90.0 && lower_deg <= upper_deg))
        throw ScanError("vertical_fov", "vertical_fov [" + num(lower_deg) + ", " + num(upper_deg) +
                                            "] must satisfy -90 <= lower <= upper <= 90 degrees");
    if (channels == 0) throw ScanError("channels", "channels must be at least 1");
    std::vector<double> out(channels);
    if (channels == 1) {
        out[0] = 0.5 * (lower_deg + upper_deg);
        return out;
    }
    for (uint32_t c = 0; c < channels; ++c)
        out[c] = upper_deg - (upper_deg - lower_deg) * static_cast<double>(c) /
                                 static_cast<double>(channels - 1);
    return out;
}

namespace {

/// Cosine and sine of channel `channel`'s elevation and of azimuth step `azimuth_index`.
std::array<double, 2> elevation_trig(const LidarSpec& spec, uint32_t channel) noexcept {
    const double e = spec.elevation_deg[channel] * kDegToRad;
    return {std::cos(e), std::sin(e)};
}

std::array<double, 2> azimuth_trig(const LidarSpec& spec, uint32_t azimuth_index) noexcept {
    const double a = 2.0 * std::numbers::pi * static_cast<double>(azimuth_index) /
                     static_cast<double>(spec.azimuth_steps);
    return {std::cos(a), std::sin(a)};
}

Ray lidar_ray(const LidarSpec& spec, const std::array<double, 2>& e,
              const std::array<double, 2>& a) noexcept {
    const double v[3] = {e[0] * a[0], e[0] * a[1], e[1]};
    return pose_ray(spec.pose, v, spec.min_range, spec.max_range, nullptr);
}

}  // namespace

Ray lidar_ray(const LidarSpec& spec, uint32_t channel, uint32_t azimuth_index) noexcept {
    return lidar_ray(spec, elevation_trig(spec, channel), azimuth_trig(spec, azimuth_index));
}

namespace detail {

void pinhole_rays(const PinholeSpec& spec, std::vector<Ray>& rays, std::vector<double>& cosines) {
    const uint32_t w = spec.intrinsics.width, h = spec.intrinsics.height;
    const size_t n = static_cast<size_t>(w) * h;
    rays.resize(n);
    cosines.assign(spec.kind == DepthKind::kDepth ? n : 0, 0.0);
    tbb::parallel_for(tbb::blocked_range<uint32_t>(0, h, kRowBlock),
                      [&](const tbb::blocked_range<uint32_t>& rows) {
                          for (uint32_t j = rows.begin(); j != rows.end(); ++j) {
                              for (uint32_t i = 0; i < w; ++i) {
                                  const size_t p = static_cast<size_t>(j) * w + i;
                                  rays[p] = pinhole_ray(spec, i, j,
                                                        cosines.empty() ? nullptr : &cosines[p]);
                              }
                          }
                      });
}

std::vector<uint32_t> lidar_tile_order(uint32_t channels, uint32_t azimuth_steps) {
    std::vector<uint32_t> order(static_cast<size_t>(channels) * azimuth_steps);
    // A column of blocks (kBlockAzimuth steps, every channel) holds the same beams in both
    // orders: in parallel by column.
    const uint32_t columns = (azimuth_steps + kBlockAzimuth - 1) / kBlockAzimuth;
    tbb::parallel_for(uint32_t{0}, columns, [&](uint32_t column) {
        const uint32_t ba = column * kBlockAzimuth;
        const uint32_t ba_end = std::min(azimuth_steps, ba + kBlockAzimuth);
        uint32_t* out = order.data() + static_cast<size_t>(ba) * channels;
        for (uint32_t bc = 0; bc < channels; bc += kBlockChannels) {
            const uint32_t bc_end = std::min(channels, bc + kBlockChannels);
            for (uint32_t ta = ba; ta < ba_end; ta += kTileAzimuth) {
                const uint32_t ta_end = std::min(ba_end, ta + kTileAzimuth);
                for (uint32_t tc = bc; tc < bc_end; tc += kTileChannels) {
                    const uint32_t tc_end = std::min(bc_end, tc + kTileChannels);
                    for (uint32_t a = ta; a < ta_end; ++a)
                        for (uint32_t c = tc; c < tc_end; ++c) *out++ = a * channels + c;
                }
            }
        }
    });
    return order;
}

std::vector<Ray> lidar_rays(const LidarSpec& spec, std::span<const uint32_t> order) {
    const auto channels = static_cast<uint32_t>(spec.elevation_deg.size());
    std::vector<std::array<double, 2>> elevation(channels), azimuth(spec.azimuth_steps);
    for (uint32_t c = 0; c < channels; ++c) elevation[c] = elevation_trig(spec, c);
    for (uint32_t a = 0; a < spec.azimuth_steps; ++a) azimuth[a] = azimuth_trig(spec, a);
    std::vector<Ray> rays(order.size());
    // Two beams at a time in SSE2 doubles: pose_ray's operations in its order (no contraction:
    // -ffp-contract=off), each correctly rounded, so the same bits as lidar_ray; the square root
    // and the three divisions a beam are most of a ray's cost.
    const double* m = spec.pose.m.data();
    tbb::parallel_for(tbb::blocked_range<size_t>(0, order.size(), 4096), [&](const tbb::
                                                                                 blocked_range<
                                                                                     size_t>& r) {
        size_t k = r.begin();
        for (; k + 2 <= r.end(); k += 2) {
            const std::array<double, 2>& e0 = elevation[order[k] % channels];
            const std::array<double, 2>& e1 = elevation[order[k + 1] % channels];
            const std::array<double, 2>& a0 = azimuth[order[k] / channels];
            const std::array<double, 2>& a1 = azimuth[order[k + 1] / channels];
            const __m128d ce = _mm_set_pd(e1[0], e0[0]), se = _mm_set_pd(e1[1], e0[1]);
            const __m128d v[3] = {ce * _mm_set_pd(a1[0], a0[0]), ce * _mm_set_pd(a1[1], a0[1]), se};
            const __m128d len = _mm_sqrt_pd(v[0] * v[0] + v[1] * v[1] + v[2] * v[2]);
            __m128d d[3];
            for (int i = 0; i < 3; ++i)
                d[i] = (_mm_set1_pd(m[4 * i]) * v[0] + _mm_set1_pd(m[4 * i + 1]) * v[1] +
                        _mm_set1_pd(m[4 * i + 2]) * v[2]) /
                       len;
            for (int j = 0; j < 2; ++j)
                rays[k + j] = Ray{static_cast<float>(m[3]),    static_cast<float>(m[7]),
                                  static_cast<float>(m[11]),   spec.min_range,
                                  static_cast<float>(d[0][j]), static_cast<float>(d[1][j]),
                                  static_cast<float>(d[2][j]), spec.max_range};
        }
        for (; k != r.end(); ++k)
            rays[k] = lidar_ray(spec, elevation[order[k] % channels], azimuth[order[k] / channels]);
    });
    return rays;
}

std::vector<Ray> lidar_rays(const LidarSpec& spec) {
    std::vector<uint32_t> order(spec.elevation_deg.size() * size_t{spec.azimuth_steps});
    std::iota(order.begin(), order.end(), uint32_t{0});
    return lidar_rays(spec, order);
}

}  // namespace detail

DepthImage scan_pinhole(const KdTree& tree, const PinholeSpec& spec) {
    validate(spec);
    const uint32_t w = spec.intrinsics.width, h = spec.intrinsics.height;
    const size_t n = static_cast<size_t>(w) * h;
    DepthImage image;
    image.width = w;
    image.height = h;
    image.kind = spec.kind;
    std::vector<Ray> rays;
    std::vector<double> cosines;
    detail::pinhole_rays(spec, rays, cosines);
    std::vector<Hit> hits(n);
    intersect(tree, rays, hits);
    image.depth.resize(n);
    image.prim.resize(n);
    if (spec.normals) image.normals.resize(n);
    tbb::parallel_for(tbb::blocked_range<size_t>(0, n, 4096),
                      [&](const tbb::blocked_range<size_t>& r) {
                          for (size_t p = r.begin(); p != r.end(); ++p) {
                              const Hit& hit = hits[p];
                              if (!hit.is_hit()) {
                                  image.depth[p] = std::numeric_limits<float>::infinity();
                                  image.prim[p] = kNoHit;
                                  if (spec.normals) image.normals[p] = Vec3{};
                                  continue;
                              }
                              image.depth[p] = detail::pinhole_depth(hit.t, cosines, p);
                              image.prim[p] = hit.prim;
                              if (spec.normals)
                                  image.normals[p] = triangle_normal(tree.triangle(hit.prim));
                          }
                      });
    return image;
}

namespace detail {

PointCloud scan_lidar(const KdTree& tree, const LidarSpec& spec, std::optional<Isa> isa) {
    validate(spec);
    const uint32_t channels = static_cast<uint32_t>(spec.elevation_deg.size());
    // The beams in tiles, as the scene scan traces them (scan_internal.h): a packet's eight beams
    // at one elevation, side by side, rather than eight channels of one azimuth (the answers are
    // per beam, so they do not depend on the order).
    const std::vector<uint32_t> order = lidar_tile_order(channels, spec.azimuth_steps);
    const std::vector<Ray> rays = lidar_rays(spec, order);
    AllHitsOptions options;
    options.max_hits = spec.returns;
    options.merge_coincident = true;
    options.isa = isa;
    const AllHits all = intersect_all(tree, rays, options);
    PointCloud cloud;
    cloud.channels = channels;
    cloud.azimuth_steps = spec.azimuth_steps;
    cloud.returns = spec.returns;
    lidar_points(
        std::span<const uint32_t>(order), std::span<const uint64_t>(all.offsets),
        std::span<const Hit>(all.hits), channels,
        [&](const Hit& hit) { return hit_point(tree.triangle(hit.prim), hit); },
        [](uint64_t, const Hit&) {}, cloud);
    return cloud;
}

}  // namespace detail

PointCloud scan_lidar(const KdTree& tree, const LidarSpec& spec) {
    return detail::scan_lidar(tree, spec, std::nullopt);
}

}  // namespace kdrt
