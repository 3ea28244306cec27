// GET /healthz, /readyz, /metrics.

#include "http/http_routes.h"
#include "http/http_util.h"
#include "http/problems.h"
#include "kdrt/proto/json_api.h"
#include "kdrt/proto/prometheus.h"

namespace kdrt::server {

void Routes::healthz(const httplib::Request&, httplib::Response& res) {
    const proto::JsonField fields[] = {{"status", std::string_view("ok")}};
    reply_json(res, 200, proto::encode_flat_object(fields));
}

void Routes::readyz(const httplib::Request& req, httplib::Response& res) {
    if (svc_.shutting_down) {
        proto::Problem p = not_ready_problem(true);
        p.retry_after.reset();  // a readiness probe is not asked to come back to a server leaving
        return reply_problem(req, res, std::move(p));
    }
    if (!svc_.ready) {
        auto p = make_problem(proto::ProblemKind::kNotReady,
                              "the mesh index is loading or meshes are preloading");
        p.retry_after = 1;
        return reply_problem(req, res, std::move(p));
    }
    const proto::JsonField fields[] = {{"status", std::string_view("ready")},
                                       {"meshes", static_cast<uint64_t>(svc_.cache.mesh_count())}};
    reply_json(res, 200, proto::encode_flat_object(fields));
}

void Routes::metrics(const httplib::Request&, httplib::Response& res) {
    res.status = 200;
    res.body = svc_.metrics.render();
    res.set_header("Content-Type", std::string(proto::kPrometheusMediaType));
}

}  // namespace kdrt::server
