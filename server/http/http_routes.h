#pragma once
/// The API v1 route handlers. Each is three steps: decode (proto), call (mesh cache / compute),
/// encode (proto). The route wrapper in http_server.cpp has already checked the bearer token,
/// readiness and admission when a handler runs. Included by http_*.cpp only.

#include <httplib.h>

#include <optional>

#include "kdrt/proto/json_api.h"
#include "kdrt/proto/multi_hit.h"
#include "service.h"

namespace kdrt::server {

/// Bytes of batch_memory_budget one ray of an intersect_all request holds (its rays and its
/// largest answer).
[[nodiscard]] uint64_t intersect_all_bytes_per_ray(const proto::MultiHitQuery& query) noexcept;

class Routes {
public:
    explicit Routes(Service& service) : svc_(service) {}

    // Streamed-body routes (the body is read, or discarded, by the handler).
    void upload_mesh(const httplib::Request& req, httplib::Response& res,
                     const httplib::ContentReader& reader);
    void intersect(const httplib::Request& req, httplib::Response& res,
                   const httplib::ContentReader& reader);
    void intersect_all(const httplib::Request& req, httplib::Response& res,
                       const httplib::ContentReader& reader);
    void render(const httplib::Request& req, httplib::Response& res,
                const httplib::ContentReader& reader);
    void distance(const httplib::Request& req, httplib::Response& res,
                  const httplib::ContentReader& reader);
    void scan(const httplib::Request& req, httplib::Response& res,
              const httplib::ContentReader& reader);

    void list_meshes(const httplib::Request& req, httplib::Response& res);
    void get_mesh(const httplib::Request& req, httplib::Response& res);
    void delete_mesh(const httplib::Request& req, httplib::Response& res);

    void get_job(const httplib::Request& req, httplib::Response& res);
    void delete_job(const httplib::Request& req, httplib::Response& res);
    void job_result(const httplib::Request& req, httplib::Response& res);

    void healthz(const httplib::Request& req, httplib::Response& res);
    void readyz(const httplib::Request& req, httplib::Response& res);
    void metrics(const httplib::Request& req, httplib::Response& res);

    /// The web viewer's files (web_assets.h): / is index.html, /ui/<name> the others.
    void web_file(const httplib::Request& req, httplib::Response& res);

private:
    /// The batch's memory from batch_memory_budget; on refusal (503, or 413 when it could
    /// never fit) replies and returns nullopt.
    std::optional<ByteBudget::Hold> take_batch_budget(const httplib::Request& req,
                                                      httplib::Response& res,
                                                      const httplib::ContentReader& reader,
                                                      bool binary);
    /// The tree of the mesh named by the path (req.matches[1]); on failure discards the body,
    /// replies (404 unknown mesh, ...) and returns nullptr.
    std::shared_ptr<const KdTree> acquire_tree(const httplib::Request& req, httplib::Response& res,
                                               const httplib::ContentReader& reader);
    /// `bytes` of batch_memory_budget, refused as take_batch_budget does.
    std::optional<ByteBudget::Hold> take_budget_bytes(const httplib::Request& req,
                                                      httplib::Response& res,
                                                      const httplib::ContentReader& reader,
                                                      uint64_t bytes);
    void intersect_binary(const httplib::Request& req, httplib::Response& res,
                          const httplib::ContentReader& reader, const KdTree& tree,
                          bool reject_invalid);
    void intersect_json(const httplib::Request& req, httplib::Response& res,
                        const httplib::ContentReader& reader, const KdTree& tree);

    /// The render request in the body; on failure the reply is set and nullopt returned.
    std::optional<proto::RenderRequest> read_render_request(const httplib::Request& req,
                                                            httplib::Response& res,
                                                            const httplib::ContentReader& reader);
    /// The request with its mesh's tree and validated settings; on failure as above.
    std::optional<RenderJob> make_render_job(const httplib::Request& req, httplib::Response& res,
                                             proto::RenderRequest request);
    void render_now(const httplib::Request& req, httplib::Response& res, const RenderJob& job);
    void submit_job(const httplib::Request& req, httplib::Response& res, RenderJob job);

    Service& svc_;
};

}  // namespace kdrt::server
