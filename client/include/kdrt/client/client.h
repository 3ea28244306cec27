#pragma once
/// libkdrt-client: the kdrt HTTP API v1 (proto/openapi.yaml) from C++.
///
///   kdrt::Client client("http://127.0.0.1:8080");
///   auto mesh = client.upload("bunny.obj");
///   if (!mesh) { std::cerr << mesh.error().to_string() << "\n"; return 1; }
///   auto hits = client.intersect(mesh->id, rays);   // KDRR -> KDRH, chunked and in parallel
///
/// Every wire format comes from kdrt::proto (ray batches, JSON documents, problem details); the
/// library adds transport: keep-alive connections, timeouts, a bearer token, retries with
/// exponential backoff, and the splitting of large ray batches. Link target: kdrt::client
/// (CMake: find_package(kdrt) after installing). It never links OpenImageIO: images travel as
/// the encoded bytes the server produces, or as float pixels (render_split) that the caller
/// encodes.
///
/// Thread safety: a Client may be used from several threads at once; each call takes its own
/// connection(s) from a pool. Callbacks run on the calling thread.

#include <chrono>
#include <cstddef>
#include <cstdint>
#include <filesystem>
#include <functional>
#include <memory>
#include <optional>
#include <span>
#include <string>
#include <string_view>
#include <vector>

#include "kdrt/client/error.h"
#include "kdrt/client/server_url.h"
#include "kdrt/distance_types.h"
#include "kdrt/mesh_types.h"
#include "kdrt/proto/distance.h"
#include "kdrt/proto/json_api.h"
#include "kdrt/proto/mesh_io.h"
#include "kdrt/proto/multi_hit.h"
#include "kdrt/proto/raw_image.h"
#include "kdrt/proto/scan.h"
#include "kdrt/proto/scene.h"
#include "kdrt/types.h"

namespace kdrt {

namespace detail {
struct ClientAccess;
}

/// What the server reports about a stored mesh: id, triangles, vertices, bounds, build statistics.
using MeshInfo = proto::MeshSummary;
/// An async render job's state and progress (GET /v1/jobs/{id}).
using Job = proto::JobStatus;
/// A render: mesh id, RenderSettings (camera, size, spp, shading, seed, tile) and image format.
using RenderRequest = proto::RenderRequest;

/// A frame rendered as regions and stitched (Client::render_split).
struct StitchedFrame {
    /// The frame's (or the request's tile's) linear float pixels: bit for bit what one server
    /// renders for the whole request before it encodes the image.
    Image image;
    /// The PNG zlib level the server encodes this render with: the request's `compression`, else
    /// the server's png_compression (its X-Kdrt-Png-Compression answer header); nullopt when
    /// the server does not say. Encoding `image` with proto::encode_image, this level and
    /// proto::render_transfer(shading) gives the bytes the server answers for the unsplit render.
    std::optional<int> png_compression;
    /// The X-Kdrt-Replica header of each region's answer, in region order ("" when none).
    std::vector<std::string> replicas;
};

/// Called by Client::render_split on its calling thread after each region arrives, with the
/// regions done and the regions in all. Return false to stop: no further region is asked for,
/// and render_split returns ErrorKind::kCancelled once those in flight have answered.
using RegionProgress = std::function<bool(unsigned done, unsigned parts)>;

/// The `parts` bands of rows render_split cuts `region` into, top to bottom: band k is rows
/// region.y + floor(k h / parts) .. region.y + floor((k + 1) h / parts) - 1 at the region's
/// full width (h = region.height). Precondition: 1 <= parts <= region.height.
[[nodiscard]] std::vector<PixelRegion> split_rows(const PixelRegion& region, unsigned parts);

/// Places `parts` (regions of one frame, each decoded from a KDRI answer) into an image of
/// `within` (a rectangle of that frame). Errors name the part: a part outside `within`, parts
/// of different frames or channel counts, two parts covering one pixel, or a pixel no part covers.
[[nodiscard]] proto::Result<Image, std::string> stitch_regions(
    const PixelRegion& within, std::span<const proto::RawImage> parts);

/// The options of a distance query: max_distance (>= 0, +inf: no limit) and signed_query.
using DistanceQuery = proto::DistanceQuery;

/// The answer of Client::distance.
struct DistanceAnswer {
    /// One closest point per query point, in query order: the server's KDRD records decoded
    /// (proto::decode_distances). A point with nothing within max_distance: found() is false.
    std::vector<ClosestPoint> points;
    /// The query asked for sides (DistanceQuery::signed_query). Without it every side is kUnknown.
    bool signed_query = false;
    /// The server's X-Kdrt-Surface header: "closed", or "not closed: B boundary edges, N
    /// non-manifold edges, M misoriented edges" (sides are then kUnknown and signed distances NaN).
    std::string surface;
    /// surface == "closed": the mesh is closed and consistently oriented, so sides are decided.
    [[nodiscard]] bool closed() const noexcept { return surface == "closed"; }
};

/// A scene revision as the server keeps it: id, revision (from 1) and the instances (mesh id,
/// transform, name), each instance's geometry id its index.
using SceneDocument = proto::SceneDocument;
/// One scene of Client::scenes, and the answer of a pose update: id, revision, instance count.
using SceneRevision = proto::SceneListItem;

/// Closest hits of a scene: the mesh records (prim, u, v of the instance's mesh; t of the world
/// ray) and each ray's geometry id (kNoHit for a miss), from one revision (`revision`).
struct SceneHits {
    std::vector<Hit> hits;
    std::vector<uint32_t> geometry_ids;
    uint64_t revision = 0;
};
/// Occlusion of a scene's rays (1 = something is hit within [tmin, tmax]), from one revision
/// (`revision`: KDRO has no geometry-id plane, so the revision is all it adds to the mesh form).
struct SceneOcclusion {
    std::vector<uint8_t> occluded;
    uint64_t revision = 0;
};
/// The number of hits of each of a scene's rays, from one revision.
struct SceneHitCounts {
    std::vector<uint32_t> counts;
    uint64_t revision = 0;
};
/// Every hit of a scene's rays: the mesh form (normals and points in world space) and the
/// geometry id of each hit record (geometry_ids[k] belongs to all.hits[k]).
struct SceneMultiHits {
    proto::MultiHits all;
    std::vector<uint32_t> geometry_ids;
    uint64_t revision = 0;
};
/// Closest points of a scene (distance and point in world space; prim, u, v, feature of the
/// instance's mesh) and each point's geometry id (kNoHit: nothing found).
struct SceneDistanceAnswer {
    std::vector<ClosestPoint> points;
    std::vector<uint32_t> geometry_ids;
    bool signed_query = false;
    uint64_t revision = 0;
};
/// A scene scan: the server's answer as it came (KDRZ, KDRL or KDRB with the geometry-id plane,
/// proto/FORMATS.md "Scenes"), decoded: the depth image (pinhole), the point cloud (lidar, KDRL)
/// or its compact form (lidar, KDRB: asked for with "format" ranges), and the geometry id of each
/// pixel or point.
struct SceneScan {
    std::vector<std::byte> body;
    std::optional<DepthImage> depth;
    std::optional<PointCloud> cloud;
    std::optional<proto::LidarRanges> ranges;
    std::vector<uint32_t> geometry_ids;
    uint64_t revision = 0;
};

/// Called by Client::wait after every poll with the job's latest status. Return false to stop
/// waiting: wait() then cancels the job and returns ErrorKind::kCancelled.
using ProgressCallback = std::function<bool(const Job& job)>;

/// Transport settings. Every member has a working default.
struct ClientOptions {
    /// Bearer token sent on every request. Empty: the KDRT_TOKEN environment variable (read by
    /// the constructor), or none.
    std::string token;
    /// Longest wait for a TCP (and TLS) connection to be set up.
    std::chrono::milliseconds connect_timeout{5'000};
    /// Per socket read and write (not per request): a render or a batch may take longer in total.
    std::chrono::milliseconds io_timeout{300'000};
    /// Retries after the first attempt, on connection errors and on 503; idempotent requests
    /// (all but submit) also on 502 and 504, a proxy's answer when the replica behind it failed.
    unsigned max_retries = 4;
    /// Delay before retry k (0-based): min(backoff_initial * 2^k, backoff_max), unless a 503
    /// carries Retry-After (seconds), which is honoured up to max_retry_after.
    std::chrono::milliseconds backoff_initial{100};
    std::chrono::milliseconds backoff_max{5'000};
    std::chrono::milliseconds max_retry_after{60'000};
    /// intersect/occluded: rays per request (1 .. the server's max_rays, default 2^24). A batch of
    /// more rays is split into chunks of this many. 2^16 rays (2 MiB out, 1 MiB back) keeps the
    /// buffers cache-sized and the connections pipelined; much larger chunks measured slower on
    /// loopback (page faults of fresh multi-MiB buffers on both sides).
    size_t chunk_rays = size_t{1} << 16;
    /// intersect/occluded: chunks in flight at once, each on its own keep-alive connection.
    unsigned connections = 4;
    /// intersect/occluded: split every batch into at least this many chunks, chunk k carrying
    /// the routing key "?route=<id>.<k mod split>" so a proxy that hashes it (nginx with
    /// docker/nginx/, docs/scale-out.md) spreads one big batch over the replicas. The answers
    /// are put back in ray order: the result equals the unsplit one. 0 or 1: no split, no key.
    /// intersect_scene/occluded_scene split the same way ("<scene id>.<k mod split>"): the first
    /// chunk answers from the scene's current revision and the others pin it (?revision=), then
    /// go up to `connections` at once, so every replica answers from the same revision.
    unsigned split = 0;
    /// wait(): time between two polls of the job.
    std::chrono::milliseconds poll_interval{100};
};

class Client {
public:
    /// A client of the server at `url` (see parse_server_url). Connects lazily, on the first call.
    /// Throws std::invalid_argument naming the problem when `url` is malformed, or when
    /// options.chunk_rays or options.connections is 0.
    explicit Client(std::string_view url, ClientOptions options = {});
    ~Client();
    Client(Client&&) noexcept;
    Client& operator=(Client&&) noexcept;
    Client(const Client&) = delete;
    Client& operator=(const Client&) = delete;

    [[nodiscard]] const ServerUrl& url() const noexcept;
    [[nodiscard]] const ClientOptions& options() const noexcept;

    // ---- Meshes (POST/GET/DELETE /v1/meshes...) ---------------------------------------------

    /// Uploads a mesh file, streamed from disk (a pipe or device such as /dev/stdin is read whole
    /// first). The format comes from `format`, else from the extension (.obj .ply .off .stl .raw
    /// .kdrtmesh; another one is a kInput error, as is an unreadable file). The server parses it:
    /// a bad file is a kServer 422 error whose detail (and `line` / `byte_offset`) says where.
    /// Uploading the same triangles again returns the stored summary without a rebuild.
    [[nodiscard]] Result<MeshInfo> upload(const std::filesystem::path& file,
                                          std::optional<proto::MeshFormat> format = std::nullopt);
    /// Uploads an in-memory mesh (sent in the raw format, exactly its arrays).
    [[nodiscard]] Result<MeshInfo> upload(const Mesh& mesh);
    /// Uploads the bytes of a mesh file in `format`.
    [[nodiscard]] Result<MeshInfo> upload(std::span<const std::byte> bytes,
                                          proto::MeshFormat format);
    /// Every stored mesh, sorted by id.
    [[nodiscard]] Result<std::vector<MeshInfo>> meshes();
    /// One stored mesh (404 kServer error when unknown).
    [[nodiscard]] Result<MeshInfo> mesh(std::string_view id);
    /// Deletes a stored mesh (404 kServer error when unknown).
    [[nodiscard]] Result<void> remove(std::string_view id);

    // ---- Rays (POST /v1/meshes/{id}/intersect, binary KDRR) --------------------------------

    /// Closest hit of every ray, in ray order (a miss: t = +inf, prim = kNoHit). Batches larger
    /// than options.chunk_rays go as several requests over up to options.connections keep-alive
    /// connections in parallel; the answers are put back in order. The server refuses rays with a
    /// NaN/Inf origin or direction component (400). An empty span still asks the server (so an
    /// unknown id is reported). More than 2^32 - 1 rays is a kInput error. On any chunk's error
    /// the call stops sending and returns that error.
    [[nodiscard]] Result<std::vector<Hit>> intersect(std::string_view id,
                                                     std::span<const Ray> rays);
    /// Occlusion of every ray (1 = something is hit within [tmin, tmax]), chunked the same way.
    [[nodiscard]] Result<std::vector<uint8_t>> occluded(std::string_view id,
                                                        std::span<const Ray> rays);

    // ---- Every hit along a ray (POST /v1/meshes/{id}/intersect_all, KDRR -> KDRM / KDRC) -----

    /// Every hit of every ray (the nearest query.max_hits of each, and the count of all), in
    /// the record layout query.layout asks for (proto/FORMATS.md). query.count_only is ignored
    /// (see count_intersections). Batches larger than options.chunk_rays go as several requests,
    /// one after another, and are joined into one answer. Errors as for intersect (a bad option
    /// is a kServer 400 naming it).
    [[nodiscard]] Result<proto::MultiHits> intersect_all(std::string_view id,
                                                         std::span<const Ray> rays,
                                                         const proto::MultiHitQuery& query);
    /// The number of hits of every ray (KDRC), merged as `merge_coincident` says.
    [[nodiscard]] Result<std::vector<uint32_t>> count_intersections(std::string_view id,
                                                                    std::span<const Ray> rays,
                                                                    bool merge_coincident);

    // ---- Sensor scans (POST /v1/meshes/{id}/scan; client/src/scan.cpp) ------------------------

    /// The answer to a scan request as the server encodes it (request.format: KDRZ or EXR for a
    /// pinhole, KDRL or PLY for a lidar), checked to be a 200 answer only. Errors as for render
    /// (a bad field is a kServer 400 naming it, a limit a 413).
    [[nodiscard]] Result<std::vector<std::byte>> scan(std::string_view id,
                                                      const proto::ScanRequest& request);
    /// A pinhole scan, asked for as KDRZ (request.format is ignored) and decoded.
    [[nodiscard]] Result<DepthImage> scan_pinhole(std::string_view id, proto::ScanRequest request);
    /// A lidar scan, asked for as KDRL (request.format is ignored) and decoded.
    [[nodiscard]] Result<PointCloud> scan_lidar(std::string_view id, proto::ScanRequest request);
    /// A lidar scan, asked for as KDRB (the compact record: range, beam, prim; request.format is
    /// ignored) and decoded. Points are the beams' rays at the ranges (proto/FORMATS.md, "KDRB").
    [[nodiscard]] Result<proto::LidarRanges> scan_lidar_ranges(std::string_view id,
                                                               proto::ScanRequest request);

    // ---- Distance queries (POST /v1/meshes/{id}/distance, KDRP -> KDRD) -----------------------

    /// The closest point on the mesh to every query point (within query.max_distance), its
    /// distance, triangle, barycentrics and feature, and with query.signed_query its side. Points
    /// go options.chunk_rays at a time, one request after another, joined in query order (the
    /// answer equals one unsplit request's). A chunk the server refuses as too large (413: more
    /// than its max_distance_points, or than its batch_memory_budget could ever hold) is sent
    /// again in smaller chunks (the size its `limit` allows, else half), and later calls on this
    /// Client start from that size, so no number of points is refused for its size. A point with
    /// a NaN or infinite coordinate is a kInput error naming it ("point 17: field y is NaN")
    /// before anything is sent; more than 2^32 - 1 points too. An empty span still asks the
    /// server (so an unknown id is reported). Other errors as for intersect (a bad max_distance is
    /// a kServer 400 naming it).
    [[nodiscard]] Result<DistanceAnswer> distance(std::string_view id, std::span<const Vec3> points,
                                                  const DistanceQuery& query = {});

    // ---- Scenes (/v1/scenes...; client/src/scene.cpp) -----------------------------------------
    //
    // A scene places stored meshes by affine transforms (proto/FORMATS.md, "Scenes"). Every
    // change makes a new revision; `if_revision` makes a change conditional (If-Match: a kServer
    // 412 error when the scene has moved on). A query answers from the current revision, or from
    // `revision` (one of the newest the server keeps); a query sent as several requests (more
    // rays or points than options.chunk_rays) pins the revision the first request answered from,
    // so the whole answer is of one revision. Refusals name the instance: Error::index and
    // Error::field ("instances[3].transform").

    /// Creates a scene of `instances` (geometry ids in this order). Not resent after a lost
    /// connection once sent (it could create a second scene).
    [[nodiscard]] Result<SceneDocument> create_scene(
        std::span<const proto::SceneInstanceSpec> instances);
    /// A scene's current revision, or `revision`.
    [[nodiscard]] Result<SceneDocument> scene(std::string_view id,
                                              std::optional<uint64_t> revision = std::nullopt);
    /// Every scene (id, current revision, instance count), sorted by id.
    [[nodiscard]] Result<std::vector<SceneRevision>> scenes();
    /// Deletes a scene (every revision).
    [[nodiscard]] Result<void> remove_scene(std::string_view id,
                                            std::optional<uint64_t> if_revision = std::nullopt);
    /// Moves instances (by geometry id or by name; later entries for one instance win): one new
    /// revision. Sent as KDRX (52 bytes a pose) when every entry names a geometry id, else as
    /// JSON. Entries are checked here first (a kInput error naming the entry for a NaN or
    /// infinite transform entry, or for none or both of geometry id and name).
    [[nodiscard]] Result<SceneRevision> set_poses(
        std::string_view id, std::span<const proto::PoseEntry> poses,
        std::optional<uint64_t> if_revision = std::nullopt);
    /// Removes and adds instances (proto::InstanceEdit): one new revision. Not resent after a
    /// lost connection once sent.
    [[nodiscard]] Result<SceneDocument> edit_scene(
        std::string_view id, const proto::InstanceEdit& edit,
        std::optional<uint64_t> if_revision = std::nullopt);

    /// Closest hit of every ray over the scene, chunked as intersect() (one chunk after another,
    /// each pinning the first one's revision; with options.split > 1, the chunks after the first
    /// in parallel, each with its routing key).
    [[nodiscard]] Result<SceneHits> intersect_scene(
        std::string_view id, std::span<const Ray> rays,
        std::optional<uint64_t> revision = std::nullopt);
    /// Occlusion of every ray (1 = something is hit within [tmin, tmax]), chunked as
    /// intersect_scene, and the revision that answered.
    [[nodiscard]] Result<SceneOcclusion> occluded_scene(
        std::string_view id, std::span<const Ray> rays,
        std::optional<uint64_t> revision = std::nullopt);
    /// Every hit along every ray over the scene (as intersect_all; query.count_only ignored).
    [[nodiscard]] Result<SceneMultiHits> intersect_all_scene(
        std::string_view id, std::span<const Ray> rays, const proto::MultiHitQuery& query,
        std::optional<uint64_t> revision = std::nullopt);
    /// The number of hits of every ray over the scene, and the revision that answered.
    [[nodiscard]] Result<SceneHitCounts> count_scene_intersections(
        std::string_view id, std::span<const Ray> rays, bool merge_coincident,
        std::optional<uint64_t> revision = std::nullopt);
    /// Closest points of the scene (as distance(): points checked here first, chunks smaller
    /// after a 413). Every instance needs a similarity transform (a kServer 400 naming
    /// instances[i].transform otherwise).
    [[nodiscard]] Result<SceneDistanceAnswer> scene_distance(
        std::string_view id, std::span<const Vec3> points, const DistanceQuery& query = {},
        std::optional<uint64_t> revision = std::nullopt);
    /// A sensor scan of the scene (request.format must be binary, or ranges for a lidar: the
    /// server answers scenes in KDRZ / KDRL / KDRB with geometry ids only).
    [[nodiscard]] Result<SceneScan> scan_scene(std::string_view id,
                                               const proto::ScanRequest& request,
                                               std::optional<uint64_t> revision = std::nullopt);

    // ---- Renders (POST /v1/render, /v1/jobs/{id}...) -----------------------------------------

    /// Renders synchronously and returns the encoded image (request.format: png, jpg/jpeg, exr).
    [[nodiscard]] Result<std::vector<std::byte>> render(const RenderRequest& request);
    /// Renders request's frame (its tile, when settings.region is set) as `parts` bands of rows
    /// (split_rows), each a synchronous render with "format": "raw" (KDRI, the float pixels) and
    /// the routing key "?route=<mesh>.<k>", so a proxy that hashes it (docs/scale-out.md) spreads
    /// them over the replicas; up to options.connections run at once, and the bands are stitched
    /// (stitch_regions). request.format is not used (the caller encodes the image); its
    /// compression is carried into the answer. Bands are retried like render(). `parts` must be
    /// in 1 .. the rows of the frame or tile, else a kInput error.
    [[nodiscard]] Result<StitchedFrame> render_split(const RenderRequest& request, unsigned parts,
                                                     const RegionProgress& progress = {});
    /// Queues the render as an async job (Prefer: respond-async). Not retried after a lost
    /// connection once the request was sent (it could queue a second job); retried on 503.
    [[nodiscard]] Result<Job> submit(const RenderRequest& request);
    /// The job's current status.
    [[nodiscard]] Result<Job> job(std::string_view id);
    /// Polls the `submitted` job every options.poll_interval until it finishes, calling
    /// `progress` (if set) after every poll, then returns its image. A failed job is a kJobFailed
    /// error, a cancelled one kCancelled. The job stays on the server (until cancel() or its time
    /// to live).
    [[nodiscard]] Result<std::vector<std::byte>> wait(const Job& submitted,
                                                      const ProgressCallback& progress = {});
    /// The image of a finished job (409 kServer error while it is not done).
    [[nodiscard]] Result<std::vector<std::byte>> result(const Job& job);
    /// Cancels a queued or running job (it stops before its next tile), or forgets a finished one.
    [[nodiscard]] Result<void> cancel(const Job& job);

    // ---- Operations -------------------------------------------------------------------------

    /// GET /healthz: success when the process answers.
    [[nodiscard]] Result<void> health();
    /// GET /readyz: success when the server is ready; a 503 (starting, shutting down) is a
    /// kServer error carrying the server's reason. Not retried on 503: it asks "now?".
    [[nodiscard]] Result<void> ready();
    /// GET /metrics: the Prometheus text exposition.
    [[nodiscard]] Result<std::string> metrics();

private:
    friend struct detail::ClientAccess;
    struct Impl;
    std::unique_ptr<Impl> impl_;
};

}  // namespace kdrt
