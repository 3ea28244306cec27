#pragma once
/// The API v1 route handlers. Each is three steps: decode (proto), call (mesh cache / compute),
/// encode (proto). The route wrapper in http_server.cpp has already checked the bearer token,
/// readiness and admission when a handler runs. Included by http_*.cpp only.

#include <httplib.h>

#include <cstdint>
#include <functional>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include "http/http_util.h"
#include "http/json_shape.h"
#include "http/request_body.h"
#include "kdrt/distance.h"
#include "kdrt/proto/json_api.h"
#include "kdrt/proto/multi_hit.h"
#include "kdrt/proto/problem.h"
#include "kdrt/proto/ray_batch_codec.h"
#include "kdrt/proto/scan.h"
#include "service.h"

namespace kdrt::server {

/// Bytes of batch_memory_budget one ray of an intersect_all request holds (its rays and its
/// largest answer).
[[nodiscard]] uint64_t intersect_all_bytes_per_ray(const proto::MultiHitQuery& query) noexcept;

/// Values a scan request may have besides its lidar elevations (it has a few dozen).
inline constexpr size_t kScanOtherValues = 256;
/// The shape of a scan request: 6 levels deep, one value a lidar channel given by
/// lidar.elevation_deg (up to max_sensor_beams) and kScanOtherValues others.
[[nodiscard]] constexpr JsonShapeLimits scan_json_shape(uint64_t max_sensor_beams) noexcept {
    return {.max_depth = 6, .max_values = static_cast<size_t>(max_sensor_beams) + kScanOtherValues};
}

/// Completes a scan request with the engine (a look-at camera as intrinsics and a pose, a
/// vertical field of view as elevations) and checks it (kdrt::validate); sets the rays it traces
/// and the batch_memory_budget bytes it needs. A problem naming the field in the request's
/// spelling when the sensor cannot scan (http_routes_scan.cpp; mesh and scene scans).
[[nodiscard]] std::optional<proto::Problem> complete_scan_request(proto::ScanRequest& request,
                                                                  uint64_t& rays, uint64_t& bytes);
/// A scan refused by batch_memory_budget: 413 if it could never fit, else 503.
[[nodiscard]] proto::Problem scan_budget_problem(const ByteBudget& budget, uint64_t bytes);

/// A batch body of fixed-size records (rays, points) after a header: its limits and the memory
/// it holds, memory_fixed + memory_per_record for each record the body has (or, while a chunked
/// body arrives, has begun).
struct BatchBody {
    uint64_t limit = 0;              ///< body bytes at most (413 beyond)
    std::string what;                ///< names the body in a 413 detail
    uint64_t header_bytes = 16;      ///< body bytes before the first record (KDRR, KDRP)
    uint64_t record_bytes = 32;      ///< body bytes of one record
    uint64_t memory_per_record = 0;  ///< batch_memory_budget bytes each record holds
    uint64_t memory_fixed = 64;      ///< held whatever the count
    std::string records = "rays";    ///< what a record is, for the 413 detail
    std::string advice;              ///< ends a memory 413, e.g. "; send fewer rays"
};

/// Reads a batch body its own way after Routes::read_batch admitted it (straight into a
/// decoder, say). `grow`, set for a chunked body only, must be called with a body size before
/// memory for that much body is taken (the batch's memory then grows to match, or grow returns
/// the problem to reply, and reading stops). Replies either way: true with an answer, false with
/// a problem.
using BatchReader = std::function<bool(const BodyProgress& grow)>;

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

    // Scenes (http_routes_scenes.cpp).
    void create_scene(const httplib::Request& req, httplib::Response& res,
                      const httplib::ContentReader& reader);
    void set_poses(const httplib::Request& req, httplib::Response& res,
                   const httplib::ContentReader& reader);
    void edit_instances(const httplib::Request& req, httplib::Response& res,
                        const httplib::ContentReader& reader);
    void scene_intersect(const httplib::Request& req, httplib::Response& res,
                         const httplib::ContentReader& reader);
    void scene_intersect_all(const httplib::Request& req, httplib::Response& res,
                             const httplib::ContentReader& reader);
    void scene_distance(const httplib::Request& req, httplib::Response& res,
                        const httplib::ContentReader& reader);
    void scene_scan(const httplib::Request& req, httplib::Response& res,
                    const httplib::ContentReader& reader);
    void list_scenes(const httplib::Request& req, httplib::Response& res);
    void get_scene(const httplib::Request& req, httplib::Response& res);
    void delete_scene(const httplib::Request& req, httplib::Response& res);

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
    /// The shared path of the batch routes: admission against batch_memory_budget, body
    /// reading and their problems. A body declared over `spec.limit` is 413 before it is read;
    /// the batch's memory is taken before reading for a declared size, or as the body arrives
    /// for a chunked one (so a small chunked batch is not refused for the largest one's
    /// memory), 413 when it could never fit the budget, 503 when it does not fit now. The
    /// memory is held until the answer has been sent. On refusal replies and returns nullptr.
    std::unique_ptr<RequestBody> read_batch(const httplib::Request& req, httplib::Response& res,
                                            const httplib::ContentReader& reader,
                                            const BatchBody& spec);
    /// read_batch with the body read by `read` (BatchReader) instead of into a RequestBody, on
    /// the same admission. Returns what `read` returns; false, replied, if it was not called.
    bool read_batch(const httplib::Request& req, httplib::Response& res, const BatchBody& spec,
                    const BatchReader& read);

    /// The tree of the mesh named by the path (req.matches[1]); on failure discards the body,
    /// replies (404 unknown mesh, ...) and returns nullptr.
    std::shared_ptr<const KdTree> acquire_tree(const httplib::Request& req, httplib::Response& res);
    void intersect_binary(const httplib::Request& req, httplib::Response& res,
                          const httplib::ContentReader& reader, const KdTree& tree,
                          bool reject_invalid);
    void intersect_json(const httplib::Request& req, httplib::Response& res,
                        const httplib::ContentReader& reader, const KdTree& tree);

    /// The scan request in the body (JSON, its shape and limits checked); on failure the reply
    /// is set and nullopt returned.
    std::optional<proto::ScanRequest> read_scan_request(const httplib::Request& req,
                                                        httplib::Response& res,
                                                        const httplib::ContentReader& reader);
    /// The render request in the body; on failure the reply is set and nullopt returned.
    std::optional<proto::RenderRequest> read_render_request(const httplib::Request& req,
                                                            httplib::Response& res,
                                                            const httplib::ContentReader& reader);
    /// The request with its mesh's tree and validated settings; on failure as above.
    std::optional<RenderJob> make_render_job(const httplib::Request& req, httplib::Response& res,
                                             proto::RenderRequest request);
    void render_now(const httplib::Request& req, httplib::Response& res, const RenderJob& job);
    void submit_job(const httplib::Request& req, httplib::Response& res, RenderJob job);

    /// A KDRP body read whole (max_distance_points, `memory_per_point` bytes of
    /// batch_memory_budget each) and decoded, NaN/Inf points refused naming the point; more
    /// points than max_distance_work refused before any search (every point costs at least 1).
    /// On refusal replies and returns nullopt (http_routes_distance.cpp; meshes and scenes).
    std::optional<std::vector<Vec3>> read_points(const httplib::Request& req,
                                                 httplib::Response& res,
                                                 const httplib::ContentReader& reader,
                                                 uint64_t memory_per_point);
    /// Runs `search`, a distance batch of `points` points under the request's DistanceControl
    /// (max_distance_work; cancelled when the client leaves), in the compute arena. True when it
    /// finished; otherwise replies (400 naming max_distance_work, or the cancellation, logged
    /// and the connection closed) and returns false.
    bool run_distance(const httplib::Request& req, httplib::Response& res, size_t points,
                      const std::function<DistanceStats(const DistanceControl&)>& search);

    /// The scene revision a query names (the path's id, ?revision=N or the current one); on
    /// failure discards the body, replies and returns nullptr.
    SceneCache::EntryPtr query_scene(const httplib::Request& req, httplib::Response& res,
                                     const httplib::ContentReader& reader);
    /// A KDRR body read whole within max_rays and `bytes_per_ray` of batch_memory_budget; on
    /// failure replies and returns nullopt.
    std::optional<proto::RayBatch> read_ray_body(const httplib::Request& req,
                                                 httplib::Response& res,
                                                 const httplib::ContentReader& reader,
                                                 uint64_t bytes_per_ray);

    Service& svc_;
};

}  // namespace kdrt::server
