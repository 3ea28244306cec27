// Scenes: POST /v1/scenes, GET /v1/scenes, GET/DELETE /v1/scenes/{id}, PATCH (or POST)
// /v1/scenes/{id}/poses, POST /v1/scenes/{id}/instances, and the queries under
// /v1/scenes/{id}/: intersect, intersect_all, distance, scan, render. Each is decode (proto) ->
// call (SceneCache, kdrt/scene.h) -> encode (proto, with the geometry-id plane).

#include <charconv>
#include <optional>
#include <string>
#include <unordered_map>

#include "http/http_front.h"
#include "http/http_routes.h"
#include "http/http_util.h"
#include "http/json_shape.h"
#include "http/problems.h"
#include "kdrt/proto/distance.h"
#include "kdrt/proto/multi_hit.h"
#include "kdrt/proto/ray_batch_codec.h"
#include "kdrt/proto/scan.h"
#include "kdrt/proto/scene.h"
#include "kdrt/proto/text.h"
#include "kdrt/scene.h"

namespace kdrt::server {

using proto::ProblemKind;

namespace {

constexpr const char* kRayBodyWhat = "a KDRR batch (16 + 32 x max_rays)";
/// batch_memory_budget per ray of a scene query: the ray, the engine's answer and its encoding
/// with the geometry id (32 + 20 + 20), rounded up.
constexpr uint64_t kSceneBytesPerRay = 96;
/// Per distance point: the point, the engine's answer and its encoding (12 + 40 + 36), rounded.
constexpr uint64_t kSceneBytesPerPoint = 96;

/// A scene document has at most 5 levels (document, instances, instance, transform, row) and
/// some 20 values per instance.
JsonShapeLimits scene_shape(uint32_t max_instances) {
    return {.max_depth = 6, .max_values = 64 + 24 * static_cast<size_t>(max_instances)};
}

proto::Problem field_problem(ProblemKind kind, std::string field, std::string detail) {
    proto::Problem p = make_problem(kind, std::move(detail));
    p.field = std::move(field);
    return p;
}

/// A decimal revision >= 1.
std::optional<uint64_t> parse_revision(std::string_view text) {
    uint64_t value = 0;
    const auto [end, ec] = std::from_chars(text.data(), text.data() + text.size(), value);
    if (ec != std::errc() || end != text.data() + text.size() || value == 0) return std::nullopt;
    return value;
}

/// If-Match: absent or "*" -> no condition; "N", W/"N" or N -> revision N; else a problem.
proto::Result<std::optional<uint64_t>, proto::Problem> if_match(const httplib::Request& req) {
    if (!req.has_header("If-Match")) return std::optional<uint64_t>{};
    // get_header_value returns a std::string: keep it alive for the view.
    const std::string header = req.get_header_value("If-Match");
    std::string_view v = header;
    while (!v.empty() && v.front() == ' ') v.remove_prefix(1);
    while (!v.empty() && v.back() == ' ') v.remove_suffix(1);
    if (v == "*") return std::optional<uint64_t>{};
    if (v.substr(0, 2) == "W/") v.remove_prefix(2);
    if (v.size() >= 2 && v.front() == '"' && v.back() == '"') v = v.substr(1, v.size() - 2);
    if (auto r = parse_revision(v)) return std::optional<uint64_t>{*r};
    return proto::Err{field_problem(
        ProblemKind::kBadRequest, "If-Match",
        "If-Match " + proto::in_quotes(header) +
            " is not a scene revision (the ETag of GET /v1/scenes/{id}, e.g. \"3\")")};
}

/// ?revision=N: absent -> the current revision.
proto::Result<std::optional<uint64_t>, proto::Problem> pinned_revision(
    const httplib::Request& req) {
    if (!req.has_param("revision")) return std::optional<uint64_t>{};
    const std::string v = req.get_param_value("revision");
    if (auto r = parse_revision(v)) return std::optional<uint64_t>{*r};
    return proto::Err{field_problem(ProblemKind::kBadRequest, "revision",
                                    "query parameter revision=" + proto::in_quotes(v) +
                                        " is not a revision (an integer >= 1)")};
}

void set_revision_headers(httplib::Response& res, uint64_t revision) {
    std::string etag(1, '"');
    etag += std::to_string(revision);
    etag += '"';
    res.set_header("ETag", etag);
    res.set_header("X-Kdrt-Scene-Revision", std::to_string(revision));
}

proto::SceneLimits scene_limits(const ServerConfig& c) {
    proto::SceneLimits limits;
    limits.max_instances = c.max_instances;
    return limits;
}

/// Splits the engine's scene hits into the mesh records and the geometry-id plane.
void split_hits(std::span<const SceneHit> in, std::vector<Hit>& hits,
                std::vector<uint32_t>& geoms) {
    hits.resize(in.size());
    geoms.resize(in.size());
    for (size_t i = 0; i < in.size(); ++i) {
        hits[i] = in[i].hit();
        geoms[i] = in[i].geom;
    }
}

/// A scene distance queries cannot run on (kdrt::check_distance_query): 400 naming the instance
/// and its field ("instances[4].transform").
proto::Problem distance_scene_problem(const SceneError& e) {
    proto::Problem p = make_problem(ProblemKind::kBadRequest, e.what());
    if (e.instance_index()) {
        p.index = e.instance_index();
        p.field = "instances[" + std::to_string(*e.instance_index()) + "]." + e.field();
    }
    return p;
}

}  // namespace

// ---- Documents ---------------------------------------------------------------------------------

void Routes::create_scene(const httplib::Request& req, httplib::Response& res,
                          const httplib::ContentReader& reader) {
    if (proto::media_type_essence(req.get_header_value("Content-Type")) != proto::kJsonMediaType) {
        return reply_problem(req, res,
                             make_problem(ProblemKind::kUnsupportedMediaType,
                                          "POST /v1/scenes expects Content-Type application/json"));
    }
    auto body = read_body(req, res, reader, svc_.config.max_json_bytes, svc_.config.max_json_bytes,
                          svc_.store.tmp_dir().string(), "a scene (max_json_bytes)");
    if (!body) return;
    const std::string_view text = as_text(body->bytes());
    if (auto shape = json_shape_error(text, scene_shape(svc_.config.max_instances)))
        return reply_problem(
            req, res,
            field_problem(ProblemKind::kBadRequest, shape->path, "scene: " + shape->detail));
    auto doc = proto::decode_scene_json(text, scene_limits(svc_.config));
    body.reset();
    if (!doc)
        return reply_problem(req, res,
                             scene_request_problem(doc.error(), svc_.config.max_instances));
    auto entry = svc_.scenes.create(std::move(doc->instances));
    if (!entry) return reply_problem(req, res, scene_problem(entry.error()));
    const proto::SceneDocument& d = (*entry)->doc;
    set_revision_headers(res, d.revision);
    res.set_header("Location", "/v1/scenes/" + d.id);
    reply_json(res, 201, proto::encode_scene_json(d));
}

void Routes::get_scene(const httplib::Request& req, httplib::Response& res) {
    auto revision = pinned_revision(req);
    if (!revision) return reply_problem(req, res, std::move(revision).error());
    auto entry = svc_.scenes.get(req.matches[1], *revision);
    if (!entry) return reply_problem(req, res, scene_problem(entry.error()));
    set_revision_headers(res, (*entry)->doc.revision);
    reply_json(res, 200, proto::encode_scene_json((*entry)->doc));
}

void Routes::list_scenes(const httplib::Request&, httplib::Response& res) {
    const auto entries = svc_.scenes.list();
    std::vector<proto::SceneListItem> items;
    items.reserve(entries.size());
    for (const auto& e : entries)
        items.push_back({e->doc.id, e->doc.revision, e->doc.instances.size()});
    reply_json(res, 200, proto::encode_scene_list(items));
}

void Routes::delete_scene(const httplib::Request& req, httplib::Response& res) {
    auto condition = if_match(req);
    if (!condition) return reply_problem(req, res, std::move(condition).error());
    const std::string id = req.matches[1];
    auto removed = svc_.scenes.remove(id, *condition);
    if (!removed) return reply_problem(req, res, scene_problem(removed.error()));
    if (!*removed)
        return reply_problem(req, res,
                             make_problem(ProblemKind::kUnknownScene, "no scene with id " + id));
    res.status = 204;
}

void Routes::set_poses(const httplib::Request& req, httplib::Response& res,
                       const httplib::ContentReader& reader) {
    const std::string type = proto::media_type_essence(req.get_header_value("Content-Type"));
    const bool binary = type == proto::kPoseBatchMediaType;
    if (!binary && type != proto::kJsonMediaType) {
        return reply_problem(req, res,
                             make_problem(ProblemKind::kUnsupportedMediaType,
                                          "poses expects Content-Type application/json or " +
                                              std::string(proto::kPoseBatchMediaType) + " (KDRX)"));
    }
    auto condition = if_match(req);
    if (!condition) {
        return reply_problem(req, res, std::move(condition).error());
    }
    const uint64_t limit = binary
                               ? proto::kBatchHeaderBytes +
                                     proto::kPoseRecordBytes * uint64_t{svc_.config.max_instances}
                               : svc_.config.max_json_bytes;
    auto body = read_body(
        req, res, reader, limit, limit, svc_.store.tmp_dir().string(),
        binary ? "a KDRX pose batch (16 + 52 x max_instances)" : "a pose update (max_json_bytes)");
    if (!body) return;
    std::vector<proto::PoseEntry> poses;
    if (binary) {
        auto decoded = proto::decode_pose_batch(body->bytes(), scene_limits(svc_.config));
        if (!decoded) {
            const bool too_many = decoded.error().code == proto::DecodeErrorCode::kTooManyRays;
            proto::Problem p =
                make_problem(too_many ? ProblemKind::kPayloadTooLarge : ProblemKind::kBadRequest,
                             "malformed KDRX pose batch: " + decoded.error().detail +
                                 (too_many ? " (max_instances)" : ""));
            p.code = std::string(proto::decode_error_code_name(decoded.error().code));
            if (too_many) p.limit = svc_.config.max_instances;
            return reply_problem(req, res, std::move(p));
        }
        poses = std::move(decoded).value();
    } else {
        const std::string_view text = as_text(body->bytes());
        if (auto shape = json_shape_error(text, scene_shape(svc_.config.max_instances)))
            return reply_problem(
                req, res,
                field_problem(ProblemKind::kBadRequest, shape->path, "poses: " + shape->detail));
        auto decoded = proto::decode_pose_json(text, scene_limits(svc_.config));
        if (!decoded)
            return reply_problem(req, res,
                                 scene_request_problem(decoded.error(), svc_.config.max_instances));
        poses = std::move(decoded).value();
    }
    body.reset();
    auto updated = svc_.scenes.set_poses(req.matches[1], *condition, poses);
    if (!updated) return reply_problem(req, res, scene_problem(updated.error()));
    set_revision_headers(res, updated->revision);
    reply_json(res, 200, proto::encode_scene_revision(*updated));
}

void Routes::edit_instances(const httplib::Request& req, httplib::Response& res,
                            const httplib::ContentReader& reader) {
    if (proto::media_type_essence(req.get_header_value("Content-Type")) != proto::kJsonMediaType) {
        return reply_problem(req, res,
                             make_problem(ProblemKind::kUnsupportedMediaType,
                                          "instances expects Content-Type application/json"));
    }
    auto condition = if_match(req);
    if (!condition) {
        return reply_problem(req, res, std::move(condition).error());
    }
    auto body = read_body(req, res, reader, svc_.config.max_json_bytes, svc_.config.max_json_bytes,
                          svc_.store.tmp_dir().string(), "an instance edit (max_json_bytes)");
    if (!body) return;
    const std::string_view text = as_text(body->bytes());
    if (auto shape = json_shape_error(text, scene_shape(svc_.config.max_instances)))
        return reply_problem(
            req, res,
            field_problem(ProblemKind::kBadRequest, shape->path, "edit: " + shape->detail));
    auto edit = proto::decode_instance_edit_json(text, scene_limits(svc_.config));
    body.reset();
    if (!edit)
        return reply_problem(req, res,
                             scene_request_problem(edit.error(), svc_.config.max_instances));
    auto entry = svc_.scenes.edit(req.matches[1], *condition, *edit);
    if (!entry) return reply_problem(req, res, scene_problem(entry.error()));
    set_revision_headers(res, (*entry)->doc.revision);
    reply_json(res, 200, proto::encode_scene_json((*entry)->doc));
}

// ---- Queries -----------------------------------------------------------------------------------

SceneCache::EntryPtr Routes::query_scene(
    const httplib::Request& req, httplib::Response& res,
    const httplib::ContentReader& /*reader: a refused body is left to the front*/) {
    auto revision = pinned_revision(req);
    if (!revision) {
        reply_problem(req, res, std::move(revision).error());
        return nullptr;
    }
    auto entry = svc_.scenes.get(req.matches[1], *revision);
    if (!entry) {
        reply_problem(req, res, scene_problem(entry.error()));
        return nullptr;
    }
    set_revision_headers(res, (*entry)->doc.revision);
    return std::move(entry).value();
}

std::optional<proto::RayBatch> Routes::read_ray_body(const httplib::Request& req,
                                                     httplib::Response& res,
                                                     const httplib::ContentReader& reader,
                                                     uint64_t bytes_per_ray) {
    const std::string invalid =
        req.has_param("invalid_rays") ? req.get_param_value("invalid_rays") : "refuse";
    if (invalid != "refuse" && invalid != "miss") {
        reply_problem(req, res,
                      field_problem(ProblemKind::kBadRequest, "invalid_rays",
                                    "invalid_rays=" + proto::quote_value(invalid) +
                                        " (expected refuse or miss)"));
        return std::nullopt;
    }
    auto body = read_batch(req, res, reader,
                           {.limit = proto::kdrr_body_size(svc_.config.max_rays),
                            .what = kRayBodyWhat,
                            .record_bytes = proto::kRayRecordBytes,
                            .memory_per_record = bytes_per_ray,
                            .records = "rays",
                            .advice = "; send fewer rays"});
    if (!body) return std::nullopt;
    auto batch = proto::decode_rays(
        body->bytes(), {.max_rays = svc_.config.max_rays, .reject_non_finite = invalid != "miss"});
    if (!batch) {
        reply_problem(req, res, ray_batch_problem(batch.error()));
        return std::nullopt;
    }
    request_context().rays = batch->rays.size();
    return std::move(batch).value();
}

void Routes::scene_intersect(const httplib::Request& req, httplib::Response& res,
                             const httplib::ContentReader& reader) {
    const SceneCache::EntryPtr entry = query_scene(req, res, reader);
    if (!entry) return;
    auto body = read_ray_body(req, res, reader, kSceneBytesPerRay);
    if (!body) return;
    const Scene& scene = entry->scene;
    const std::span<const Ray> rays = body->rays;
    svc_.metrics.add_rays(rays.size(), body->occlusion);
    if (body->occlusion) {
        std::vector<uint8_t> occluded_out(rays.size());
        svc_.compute.run([&] { kdrt::occluded(scene, rays, occluded_out); });
        reply_bytes(res, proto::encode_occlusion(occluded_out), proto::kOcclusionMediaType);
    } else {
        std::vector<SceneHit> scene_hits(rays.size());
        svc_.compute.run([&] { kdrt::intersect(scene, rays, scene_hits); });
        std::vector<Hit> hits;
        std::vector<uint32_t> geoms;
        split_hits(scene_hits, hits, geoms);
        std::vector<std::byte> answer = proto::encode_hits(hits);
        proto::append_geometry_ids(answer, geoms);
        reply_bytes(res, std::move(answer), proto::kHitsMediaType);
    }
}

void Routes::scene_intersect_all(const httplib::Request& req, httplib::Response& res,
                                 const httplib::ContentReader& reader) {
    auto query = proto::parse_multi_hit_query(query_params(req), svc_.config.max_hits_per_ray);
    if (!query) {
        return reply_problem(req, res, make_problem(ProblemKind::kBadRequest, query.error()));
    }
    const SceneCache::EntryPtr entry = query_scene(req, res, reader);
    if (!entry) return;
    auto body = read_ray_body(req, res, reader, intersect_all_bytes_per_ray(*query) + 8);
    if (!body) return;
    if (body->occlusion)
        return reply_problem(
            req, res,
            make_problem(ProblemKind::kBadRequest,
                         "intersect_all takes a KDRR batch without the occlusion flag (bit 0 of "
                         "flags); occlusion queries go to /intersect"));
    const Scene& scene = entry->scene;
    const std::span<const Ray> rays = body->rays;
    svc_.metrics.add_rays(rays.size(), false);
    const AllHitsOptions options{query->max_hits, query->merge_coincident};
    if (query->count_only) {
        std::vector<uint32_t> counts(rays.size());
        svc_.compute.run([&] { count_intersections(scene, rays, options, counts); });
        reply_bytes(res, proto::encode_hit_counts(counts), proto::kHitCountMediaType);
    } else {
        SceneAllHits all =
            svc_.compute.run([&] { return kdrt::intersect_all(scene, rays, options); });
        std::vector<Vec3> normals(query->layout.normal ? all.hits.size() : 0);
        std::vector<Vec3> points(query->layout.point ? all.hits.size() : 0);
        if (!normals.empty() || !points.empty())
            svc_.compute.run([&] { hit_attributes(scene, all.hits, normals, points); });
        std::vector<Hit> hits;
        std::vector<uint32_t> geoms;
        split_hits(all.hits, hits, geoms);
        proto::MultiHitsView view;
        view.layout = query->layout;
        view.merged = query->merge_coincident;
        view.max_hits = query->max_hits;
        view.offsets = all.offsets;
        view.counts = all.counts;
        view.hits = hits;
        view.normals = normals;
        view.points = points;
        std::vector<std::byte> answer = proto::encode_multi_hits(view);
        proto::append_geometry_ids(answer, geoms);
        reply_bytes(res, std::move(answer), proto::kMultiHitMediaType);
    }
}

void Routes::scene_distance(const httplib::Request& req, httplib::Response& res,
                            const httplib::ContentReader& reader) {
    if (!has_media_type(req, res, proto::kPointMediaType, "distance")) return;
    auto query = proto::parse_distance_query(query_params(req));
    if (!query) {
        return reply_problem(req, res, make_problem(ProblemKind::kBadRequest, query.error()));
    }
    const SceneCache::EntryPtr entry = query_scene(req, res, reader);
    if (!entry) return;
    // Distance needs similarity transforms (and, signed, every mesh's surface index): checked
    // before the body is read.
    Scene scene = entry->scene;
    try {
        check_distance_query(scene, false);
    } catch (const SceneError& e) {
        return reply_problem(req, res, distance_scene_problem(e));
    }
    const auto points = read_points(req, res, reader, kSceneBytesPerPoint);
    if (!points) return;
    std::vector<SceneClosestPoint> found(points->size());
    const DistanceOptions options{query->max_distance, query->signed_query};
    bool done = false;
    try {
        done = run_distance(req, res, points->size(), [&](const DistanceControl& control) {
            if (query->signed_query) {
                // Each distinct mesh's surface index, kept with its tree by the mesh cache.
                std::vector<SceneInstance> instances = scene.instances();
                std::unordered_map<const KdTree*, std::shared_ptr<const SurfaceIndex>> surfaces;
                for (size_t g = 0; g < instances.size(); ++g) {
                    auto& surface = surfaces[instances[g].tree.get()];
                    if (!surface)
                        surface = svc_.cache.surface_index(entry->doc.instances[g].mesh,
                                                           instances[g].tree);
                    instances[g].surface = surface;
                }
                scene = build_scene(std::move(instances), scene.options());
            }
            return closest_points(scene, *points, found, options, control);
        });
    } catch (const SceneError& e) {
        return reply_problem(req, res, distance_scene_problem(e));
    }
    if (!done) return;
    std::vector<ClosestPoint> answers(found.size());
    std::vector<uint32_t> geoms(found.size());
    for (size_t i = 0; i < found.size(); ++i) {
        answers[i] = found[i].closest;
        geoms[i] = found[i].geom;
    }
    std::vector<std::byte> answer = proto::encode_distances(answers, query->signed_query);
    proto::append_geometry_ids(answer, geoms);
    reply_bytes(res, std::move(answer), proto::kDistanceMediaType);
}

void Routes::scene_render(const httplib::Request& req, httplib::Response& res,
                          const httplib::ContentReader& reader) {
    auto request = read_render_request(req, res, reader, true);
    if (!request) return;
    auto job = make_render_job(req, res, std::move(*request), [&](RenderJob& out) {
        // The body is read already: no query_scene (it discards the body).
        auto revision = pinned_revision(req);
        if (!revision) {
            reply_problem(req, res, std::move(revision).error());
            return false;
        }
        auto entry = svc_.scenes.get(req.matches[1], *revision);
        if (!entry) {
            reply_problem(req, res, scene_problem(entry.error()));
            return false;
        }
        set_revision_headers(res, (*entry)->doc.revision);
        out.scene = (*entry)->scene;
        out.scene_id = (*entry)->doc.id;
        out.revision = (*entry)->doc.revision;
        return true;
    });
    if (!job) return;
    run_render(req, res, std::move(*job));
}

void Routes::scene_scan(const httplib::Request& req, httplib::Response& res,
                        const httplib::ContentReader& reader) {
    auto request = read_scan_request(req, res, reader);
    if (!request) return;
    const bool ranges = request->format == proto::ScanFormat::kRanges;
    if (request->format != proto::ScanFormat::kBinary && !ranges)
        return reply_problem(
            req, res,
            field_problem(ProblemKind::kBadRequest, "format",
                          "a scene scan answers \"format\": \"binary\" (KDRZ or KDRL) or, for a "
                          "lidar, \"ranges\" (KDRB), each with the geometry-id plane; " +
                              std::string(proto::scan_format_name(request->format)) +
                              " cannot carry geometry ids"));
    uint64_t rays = 0, bytes = 0;
    if (auto problem = complete_scan_request(*request, rays, bytes))
        return reply_problem(req, res, std::move(*problem));
    // The body is read already: no query_scene (it discards the body).
    auto revision = pinned_revision(req);
    if (!revision) return reply_problem(req, res, std::move(revision).error());
    auto entry = svc_.scenes.get(req.matches[1], *revision);
    if (!entry) return reply_problem(req, res, scene_problem(entry.error()));
    set_revision_headers(res, (*entry)->doc.revision);
    auto hold = svc_.batch_budget.try_take(bytes + 4 * rays);
    if (!hold) return reply_problem(req, res, scan_budget_problem(svc_.batch_budget, bytes));
    request_context().rays = rays;
    svc_.metrics.add_rays(rays, false);
    // A single-return lidar scan skips the every-hit windows its meshes' HitClearance rules
    // out: attached to the revision at its first such scan (built once per mesh tree).
    const SceneCache::EntryPtr scanned = request->lidar && request->lidar_spec.returns == 1
                                             ? svc_.scenes.scan_ready(*entry)
                                             : *entry;
    const Scene& scene = scanned->scene;
    if (request->lidar) {
        const ScenePointCloud cloud =
            svc_.compute.run([&] { return scan_lidar(scene, request->lidar_spec); });
        // Written once into a pooled buffer the answer is sent from: no zeroed allocation, no
        // page faults after warm-up and no copy for the plane (a 64 x 2048 scan is ~3 MB).
        // KDRB ("ranges", the compact record) or KDRL, as the request asked.
        const size_t points = cloud.cloud.points.size();
        const size_t size =
            (ranges ? proto::kdrb_body_size(points) : proto::kdrl_body_size(points)) +
            proto::geometry_id_plane_bytes(cloud.geom.size());
        PooledBuffer answer(svc_.batch_buffers, size);
        const std::span<std::byte> out(answer.data(), size);
        const size_t body = ranges ? proto::write_lidar_ranges(out, cloud.cloud)
                                   : proto::write_point_cloud(out, cloud.cloud);
        proto::write_geometry_ids(out, body, cloud.geom);
        reply_buffer(res, std::move(answer), size,
                     ranges ? proto::kLidarRangesMediaType : proto::kPointCloudMediaType);
    } else {
        const SceneDepthImage image =
            svc_.compute.run([&] { return scan_pinhole(scene, request->pinhole); });
        std::vector<std::byte> answer = proto::encode_depth_image(image.image);
        proto::append_geometry_ids(answer, image.geom);
        reply_bytes(res, std::move(answer), proto::kDepthImageMediaType);
    }
    keep_until_sent(std::make_shared<ByteBudget::Hold>(std::move(*hold)));
}

}  // namespace kdrt::server
