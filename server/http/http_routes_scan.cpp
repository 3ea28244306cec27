// POST /v1/meshes/{id}/scan: a JSON sensor description -> a KDRZ depth image (or EXR) for a
// pinhole camera, a KDRL point cloud (or PLY, or the compact KDRB ranges) for a lidar
// (kdrt/scan.h).

#include <optional>
#include <string>

#include "http/http_front.h"
#include "http/http_routes.h"
#include "http/http_util.h"
#include "http/json_shape.h"
#include "http/problems.h"
#include "kdrt/camera.h"
#include "kdrt/proto/image_module.h"
#include "kdrt/proto/json_api.h"
#include "kdrt/proto/problem.h"
#include "kdrt/proto/scan.h"
#include "kdrt/proto/text.h"
#include "kdrt/scan.h"

namespace kdrt::server {

using proto::ProblemKind;

namespace {

/// batch_memory_budget bytes per pixel: the ray and its cosine, the hit, the image planes with
/// normals, and the encoded answer (40 + 16 + 20 + 20, rounded up for EXR's buffers).
constexpr uint64_t kBytesPerPixel = 128;
/// Per beam: the ray, intersect_all's offsets and counts; per kept return: the engine's two
/// copies of the hit, the point and its encoded record.
constexpr uint64_t kBytesPerBeam = 64;
constexpr uint64_t kBytesPerReturn = 96;

proto::Problem field_problem(const std::string& field, const std::string& why) {
    return make_problem(ProblemKind::kBadRequest, proto::quote_value(field) + ": " + why);
}

/// A scan request past scan_json_shape: more lidar elevations than max_sensor_beams is 413
/// naming lidar.elevation_deg (as the decoder names a shorter list over it), anything else 400
/// naming where.
proto::Problem scan_shape_problem(const JsonShapeError& shape, uint64_t max_sensor_beams) {
    const JsonShapeLimits limits = scan_json_shape(max_sensor_beams);
    if (shape.path == "lidar.elevation_deg") {
        auto p = make_problem(
            ProblemKind::kPayloadTooLarge,
            "\"lidar.elevation_deg\" lists more channels than max_sensor_beams (" +
                std::to_string(max_sensor_beams) + ") allows (the request passed its limit of " +
                std::to_string(limits.max_values) + " values there)");
        p.field = shape.path;
        p.limit = max_sensor_beams;
        return p;
    }
    auto p = make_problem(ProblemKind::kBadRequest,
                          "scan request: " + shape.detail + " (a scan request has at most " +
                              std::to_string(limits.max_values) + " values (" +
                              std::to_string(kScanOtherValues) +
                              " and one a lidar channel up to max_sensor_beams), nested " +
                              std::to_string(limits.max_depth) + " deep)");
    p.field = shape.path;
    return p;
}

}  // namespace

/// Completes `request` with the engine (a look-at camera as intrinsics and a pose, a vertical
/// field of view as elevations) and checks it (kdrt::validate); sets the rays it traces and the
/// batch_memory_budget bytes it needs. A problem naming the field in the request's spelling when
/// the sensor cannot scan.
std::optional<proto::Problem> complete_scan_request(proto::ScanRequest& request, uint64_t& rays,
                                                    uint64_t& bytes) {
    const std::string prefix(proto::scan_field_prefix(request));
    try {
        if (request.lidar) {
            LidarSpec& spec = request.lidar_spec;
            if (request.vertical_fov)
                spec.elevation_deg =
                    lidar_elevations(request.fov_lower, request.fov_upper, request.channels);
            validate(spec);
            rays = uint64_t{spec.elevation_deg.size()} * spec.azimuth_steps;
            bytes = 64 + rays * (kBytesPerBeam + kBytesPerReturn * spec.returns);
        } else {
            if (request.look_at) {
                const PinholeCamera pin = pinhole_from_look_at(request.camera, request.camera_width,
                                                               request.camera_height);
                request.pinhole.intrinsics = pin.intrinsics;
                request.pinhole.pose = pin.pose;
            }
            validate(request.pinhole);
            rays = uint64_t{request.pinhole.intrinsics.width} * request.pinhole.intrinsics.height;
            bytes = 64 + rays * kBytesPerPixel;
        }
    } catch (const ScanError& e) {
        return field_problem(prefix + e.field(), e.what());
    } catch (const CameraError& e) {
        return field_problem("pinhole.camera", e.what());
    }
    return std::nullopt;
}

proto::Problem scan_budget_problem(const ByteBudget& budget, uint64_t bytes) {
    return budget_problem(budget, bytes, "this scan", "; scan fewer pixels or beams");
}

void Routes::scan(const httplib::Request& req, httplib::Response& res,
                  const httplib::ContentReader& reader) {
    auto request = read_scan_request(req, res, reader);
    if (!request) return;
    // The engine's checks (a rigid pose, the intrinsics, the range window, the look-at camera),
    // before any work.
    uint64_t rays = 0, bytes = 0;
    if (auto problem = complete_scan_request(*request, rays, bytes))
        return reply_problem(req, res, std::move(*problem));
    const std::shared_ptr<const KdTree> tree = acquire_tree(req, res);
    if (!tree) return;
    auto hold = svc_.batch_budget.try_take(bytes);
    if (!hold) return reply_problem(req, res, scan_budget_problem(svc_.batch_budget, bytes));
    keep_until_sent(std::make_shared<ByteBudget::Hold>(std::move(*hold)));
    request_context().rays = rays;
    svc_.metrics.add_rays(rays, false);
    if (request->lidar) {
        const PointCloud cloud =
            svc_.compute.run([&] { return scan_lidar(*tree, request->lidar_spec); });
        if (request->format == proto::ScanFormat::kPly)
            return reply_bytes(res, proto::encode_point_cloud_ply(cloud), proto::kPlyMediaType);
        if (request->format == proto::ScanFormat::kRanges)
            return reply_bytes(res, proto::encode_lidar_ranges(cloud),
                               proto::kLidarRangesMediaType);
        return reply_bytes(res, proto::encode_point_cloud(cloud), proto::kPointCloudMediaType);
    }
    // EXR needs the image module (kdrt/proto/image_module.h, loaded by the first request that
    // encodes one): without it the scan is refused before any work, naming what to install.
    const bool exr_answer = request->format == proto::ScanFormat::kExr;
    proto::Result<const proto::ImageModuleTable*, std::string> module = nullptr;
    if (exr_answer) module = proto::image_module();
    if (!module)
        return reply_problem(req, res, make_problem(ProblemKind::kInternal, module.error()));
    const DepthImage image =
        svc_.compute.run([&] { return scan_pinhole(*tree, request->pinhole); });
    if (!exr_answer)
        return reply_bytes(res, proto::encode_depth_image(image), proto::kDepthImageMediaType);
    auto exr = (*module)->encode_depth_exr(image, {});
    if (!exr) return reply_problem(req, res, make_problem(ProblemKind::kInternal, exr.error()));
    reply_bytes(res, std::move(*exr), "image/x-exr");
}

std::optional<proto::ScanRequest> Routes::read_scan_request(const httplib::Request& req,
                                                            httplib::Response& res,
                                                            const httplib::ContentReader& reader) {
    if (proto::media_type_essence(req.get_header_value("Content-Type")) != proto::kJsonMediaType) {
        reply_problem(req, res,
                      make_problem(ProblemKind::kUnsupportedMediaType,
                                   "scan " + std::string(proto::api_errors::kUnsupportedJsonType)));
        return std::nullopt;
    }
    auto body = read_body(req, res, reader, svc_.config.max_json_bytes, svc_.config.max_json_bytes,
                          svc_.store.tmp_dir().string(), "a JSON request (max_json_bytes)");
    if (!body) return std::nullopt;
    const std::string_view text = as_text(body->bytes());
    const ServerConfig& c = svc_.config;
    if (auto shape = json_shape_error(text, scan_json_shape(c.max_sensor_beams))) {
        reply_problem(req, res, scan_shape_problem(*shape, c.max_sensor_beams));
        return std::nullopt;
    }
    auto request =
        proto::decode_scan_request(text, {c.max_image_width, c.max_image_height, c.max_sensor_beams,
                                          c.max_scan_points, c.max_hits_per_ray});
    if (request) return std::move(request).value();
    const proto::ScanRequestError& e = request.error();
    auto p = make_problem(e.over_limit ? ProblemKind::kPayloadTooLarge : ProblemKind::kBadRequest,
                          e.detail);
    p.field = e.field;
    reply_problem(req, res, std::move(p));
    return std::nullopt;
}

}  // namespace kdrt::server
