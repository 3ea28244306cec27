// POST/GET/DELETE /v1/meshes...

#include "http/http_routes.h"
#include "http/http_util.h"
#include "http/problems.h"
#include "kdrt/proto/json_api.h"
#include "kdrt/proto/mesh_id.h"
#include "kdrt/proto/mesh_io.h"
#include "kdrt/proto/text.h"

namespace kdrt::server {
namespace {

using proto::ProblemKind;

/// The upload's format: ?format= when given, else the Content-Type.
proto::Result<proto::MeshFormat, proto::Problem> upload_format(const httplib::Request& req) {
    if (req.has_param("format")) {
        const std::string name = req.get_param_value("format");
        if (const auto format = proto::mesh_format_from_name(name)) return *format;
        return proto::Err{make_problem(ProblemKind::kUnsupportedMediaType,
                                       "unknown mesh format " + proto::quote_value(name) +
                                           " (expected obj, ply, off, stl or raw)")};
    }
    const std::string type = req.get_header_value("Content-Type");
    if (const auto format = proto::mesh_format_from_media_type(type)) return *format;
    return proto::Err{make_problem(ProblemKind::kUnsupportedMediaType,
                                   std::string(proto::api_errors::kUnsupportedMeshType) +
                                       " from Content-Type " + proto::quote_value(type) +
                                       ": use model/obj, model/stl, application/ply, "
                                       "application/x-off or application/x-kdrt-mesh, "
                                       "or ?format=obj|ply|off|stl|raw")};
}

/// 503 for an upload that finds max_builds building and max_queued waiting.
proto::Problem builds_busy_problem(const WorkGate& builds) {
    auto p = make_problem(
        ProblemKind::kOverCapacity,
        std::to_string(builds.running_limit()) + " uploads are being built (max_builds) and " +
            std::to_string(builds.queue_limit()) + " waiting (max_queued); retry later");
    p.retry_after = 1;
    p.limit = builds.running_limit();
    return p;
}

}  // namespace

void Routes::upload_mesh(const httplib::Request& req, httplib::Response& res,
                         const httplib::ContentReader& reader) {
    const auto format = upload_format(req);
    if (!format) return reply_problem(req, res, format.error());
    auto body =
        read_body(req, res, reader, svc_.config.max_upload_bytes, svc_.config.upload_memory_bytes,
                  svc_.store.tmp_dir().string(), "a mesh upload (max_upload_bytes)");
    if (!body) return;
    // Parsing and building take memory and every engine thread: at most max_builds at once,
    // max_queued waiting, the rest shed. (Taken once the body is in: a slow upload holds no
    // slot, and the body is spooled to disk beyond upload_memory_bytes.)
    auto slot = svc_.builds.enter(svc_.shutting_down);
    if (!slot) return reply_problem(req, res, builds_busy_problem(svc_.builds));
    proto::MeshLimits limits;
    limits.max_triangles = svc_.config.max_triangles;
    std::vector<std::string> warnings;
    limits.warnings = &warnings;
    auto mesh = proto::parse_mesh(body->bytes(), *format, limits);
    body.reset();  // the parsed mesh is the only copy from here on
    if (!mesh) return reply_problem(req, res, mesh_parse_problem(mesh.error()));
    if (mesh->triangle_count() == 0)
        return reply_problem(
            req, res,
            make_problem(ProblemKind::kInvalidMesh,
                         "the " + std::string(proto::mesh_format_name(*format)) + " mesh " +
                             std::string(proto::api_errors::kEmptyMesh)));
    auto added = svc_.cache.add(*mesh);
    if (!added) return reply_problem(req, res, cache_problem(added.error()));
    res.set_header("Location", "/v1/meshes/" + added->summary.id);
    added->summary.warnings = std::move(warnings);
    reply_json(res, added->created ? 201 : 200, proto::encode_mesh_summary(added->summary));
}

void Routes::list_meshes(const httplib::Request&, httplib::Response& res) {
    reply_json(res, 200, proto::encode_mesh_list(svc_.cache.list()));
}

void Routes::get_mesh(const httplib::Request& req, httplib::Response& res) {
    const std::string id = req.matches[1];
    const auto summary = svc_.cache.find(id);
    if (!summary) return reply_problem(req, res, unknown_mesh_problem(id));
    reply_json(res, 200, proto::encode_mesh_summary(*summary));
}

void Routes::delete_mesh(const httplib::Request& req, httplib::Response& res) {
    const std::string id = req.matches[1];
    // A mesh that the current revision of a scene uses stays: 409 naming the scenes.
    if (proto::is_mesh_id(id)) {
        const std::vector<std::string> users = svc_.scenes.mesh_users(id);
        if (!users.empty()) {
            std::string names;
            for (size_t i = 0; i < users.size() && i < 16; ++i)
                names += (i > 0 ? ", " : "") + users[i];
            if (users.size() > 16) names += ", ...";
            return reply_problem(
                req, res,
                make_problem(ProblemKind::kMeshInUse,
                             "mesh " + id + " is used by " + std::to_string(users.size()) +
                                 " scene(s): " + names +
                                 "; remove its instances from them (or delete them) first"));
        }
    }
    if (!svc_.cache.remove(id)) return reply_problem(req, res, unknown_mesh_problem(id));
    res.status = 204;
}

}  // namespace kdrt::server
