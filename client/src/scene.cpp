// Client's scene calls: the documents (create, get, list, delete, poses, instance edits) as
// proto's scene JSON and KDRX, and the queries, whose answers are the mesh formats with the
// geometry-id plane (proto::split_geometry_ids). A query of several requests pins the revision
// the first one answered from. Transport (retries, connections) is http_client.cpp's, through
// client_access.h.

#include <algorithm>
#include <atomic>
#include <cctype>
#include <charconv>
#include <cmath>
#include <limits>
#include <mutex>
#include <optional>
#include <string>
#include <thread>
#include <utility>
#include <vector>

#include "client_access.h"
#include "kdrt/client/client.h"
#include "kdrt/proto/distance.h"
#include "kdrt/proto/json_api.h"
#include "kdrt/proto/multi_hit.h"
#include "kdrt/proto/ray_batch_codec.h"
#include "kdrt/proto/scan.h"
#include "kdrt/proto/scene.h"

namespace kdrt {
namespace {

using detail::ApiRequest;
using detail::ClientAccess;

constexpr std::string_view kRevisionHeader = "X-Kdrt-Scene-Revision";
constexpr uint32_t kNoLimit = std::numeric_limits<uint32_t>::max();

std::span<const std::byte> as_bytes(std::string_view text) noexcept {
    return {reinterpret_cast<const std::byte*>(text.data()), text.size()};
}

/// `path` with "revision=N" added to its query string.
std::string with_revision(std::string path, std::optional<uint64_t> revision) {
    if (!revision) return path;
    path += path.find('?') == std::string::npos ? '?' : '&';
    return path + "revision=" + std::to_string(*revision);
}

/// `path` with the routing key of chunk `k` of a query split `split` ways added:
/// "route=<id>.<k mod split>", as the mesh calls send it (ClientOptions::split), for a proxy
/// that hashes it (docs/scale-out.md). The server ignores it.
std::string with_route(std::string path, std::string_view id, size_t k, size_t split) {
    path += path.find('?') == std::string::npos ? '?' : '&';
    path += "route=";
    static constexpr char kHex[] = "0123456789ABCDEF";
    for (const char c : id) {
        const auto u = static_cast<unsigned char>(c);
        if (std::isalnum(u) != 0 || c == '-' || c == '_' || c == '~') {
            path += c;
        } else {
            path += '%';
            path += kHex[u >> 4];
            path += kHex[u & 0xF];
        }
    }
    return path + "." + std::to_string(k % split);
}

/// The If-Match header of a conditional change.
std::vector<std::pair<std::string, std::string>> if_match(std::optional<uint64_t> revision) {
    if (!revision) return {};
    return {{"If-Match", "\"" + std::to_string(*revision) + "\""}};
}

/// The revision an answer came from (its X-Kdrt-Scene-Revision header).
std::optional<uint64_t> revision_of(const detail::PostAnswer& answer) {
    uint64_t value = 0;
    const std::string& h = answer.header;
    const auto [end, ec] = std::from_chars(h.data(), h.data() + h.size(), value);
    if (ec != std::errc() || end != h.data() + h.size() || value == 0) return std::nullopt;
    return value;
}

/// A transform entry that is not finite, worded as the server words it.
std::optional<std::string> bad_pose(std::span<const proto::PoseEntry> poses) {
    for (size_t i = 0; i < poses.size(); ++i) {
        const proto::PoseEntry& p = poses[i];
        const std::string where = "poses[" + std::to_string(i) + "]";
        if (p.geometry_id.has_value() == !p.name.empty())
            return where + " needs exactly one of geometry_id and name";
        for (size_t k = 0; k < 12; ++k) {
            if (!std::isfinite(p.transform.m[k]))
                return where + ".transform[" + std::to_string(k / 4) + "][" +
                       std::to_string(k % 4) + "] is not finite";
        }
    }
    return std::nullopt;
}

/// How query_chunks sends a query.
struct ChunkedQuery {
    std::string path = {};
    std::string_view content_type = {};
    size_t total = 0;  ///< records (rays, points)
    size_t chunk = 0;  ///< records per request at most
    std::optional<uint64_t> revision = {};
    /// The answers carry a geometry-id plane (not KDRO, KDRC).
    bool plane = true;
    /// Non-null: a chunk refused as too large (413) is sent again in smaller ones, as distance()
    /// does, and the size is remembered here.
    std::atomic<size_t>* learned = nullptr;
    /// > 1 (ClientOptions::split, closest hits and occlusion only, as for a mesh): at least this
    /// many chunks, chunk k with the routing key "<route_id>.<k mod split>"; the chunks after
    /// the first go over up to `connections` connections at once.
    size_t split = 0;
    std::string_view route_id = {};
    size_t connections = 1;
};

/// Checks one chunk's answer to `target` (its revision is `pin` when set) and hands it to take().
template <class Take>
std::optional<Error> take_chunk(Client& client, const ChunkedQuery& q, const std::string& target,
                                const detail::PostAnswer& answer, Take& take, size_t count) {
    std::optional<std::string> failed;
    if (q.plane) {
        auto split = proto::split_geometry_ids(as_bytes(answer.body), {.max_rays = kNoLimit});
        if (!split) return ClientAccess::bad_response(client, target, split.error().to_string());
        failed = take(std::span<const std::byte>(split->mesh_body),
                      std::span<const uint32_t>(split->geometry_ids), count);
    } else {
        failed = take(as_bytes(answer.body), std::span<const uint32_t>(), count);
    }
    if (failed) return ClientAccess::bad_response(client, target, *failed);
    return std::nullopt;
}

/// query_chunks with q.split > 1. The first chunk answers from the current revision (or the one
/// asked for); every other chunk pins that revision, so whichever replica a routing key hashes to
/// answers from the same one (a replica reads a revision it never saw from the shared store).
template <class Encode, class Take>
Result<uint64_t> split_chunks(Client& client, const ChunkedQuery& q, Encode& encode, Take& take) {
    const size_t split = q.split;
    const size_t chunk = std::clamp<size_t>((q.total + split - 1) / split, 1, q.chunk);
    const size_t chunks = q.total == 0 ? 1 : (q.total - 1) / chunk + 1;
    std::vector<std::string> targets(chunks);
    std::vector<detail::PostAnswer> answers(chunks);
    const auto count_of = [&](size_t k) { return std::min(chunk, q.total - k * chunk); };
    const auto send = [&](size_t k, std::optional<uint64_t> pin) -> std::optional<Error> {
        const std::vector<std::byte> body = encode(k * chunk, count_of(k));
        targets[k] = with_revision(with_route(q.path, q.route_id, k, split), pin);
        auto answer = ClientAccess::request(client, {.method = "POST",
                                                     .path = targets[k],
                                                     .content_type = q.content_type,
                                                     .body = body,
                                                     .answer_header = kRevisionHeader});
        if (!answer) return std::move(answer).error();
        const auto answered = revision_of(*answer);
        if (!answered || (pin && *answered != *pin))
            return ClientAccess::bad_response(client, targets[k],
                                              "the answer's X-Kdrt-Scene-Revision \"" +
                                                  answer->header +
                                                  "\" is not the revision asked for");
        answers[k] = std::move(*answer);
        return std::nullopt;
    };
    if (auto failed = send(0, q.revision)) return proto::Err{std::move(*failed)};
    const uint64_t revision = *revision_of(answers[0]);

    std::atomic<size_t> next{1};
    std::atomic<bool> stop{false};
    std::mutex error_mutex;
    std::optional<Error> error;
    size_t error_chunk = std::numeric_limits<size_t>::max();
    const auto worker = [&] {
        while (!stop.load(std::memory_order_relaxed)) {
            const size_t k = next.fetch_add(1);
            if (k >= chunks) return;
            if (auto failed = send(k, revision)) {
                std::lock_guard lock(error_mutex);
                // The earliest failing chunk's error, as the mesh calls report it.
                if (k < error_chunk) {
                    error_chunk = k;
                    error = std::move(*failed);
                }
                stop = true;
                return;
            }
        }
    };
    const size_t threads = std::clamp<size_t>(q.connections, 1, std::max<size_t>(chunks - 1, 1));
    {
        std::vector<std::jthread> pool;
        for (size_t t = 1; t < threads; ++t) pool.emplace_back(worker);
        worker();
    }  // the jthreads join here
    if (error) return proto::Err{std::move(*error)};
    for (size_t k = 0; k < chunks; ++k)
        if (auto failed = take_chunk(client, q, targets[k], answers[k], take, count_of(k)))
            return proto::Err{std::move(*failed)};
    return revision;
}

/// Sends a query in chunks (encode(first, count) makes a body; take(mesh body, geometry ids,
/// count) consumes its answer, returning what is wrong with it or nothing). Every chunk after the
/// first pins the revision the first answered from. Returns that revision.
template <class Encode, class Take>
Result<uint64_t> query_chunks(Client& client, ChunkedQuery q, Encode encode, Take take) {
    if (q.split > 1) return split_chunks(client, q, encode, take);
    const std::string& path = q.path;
    const size_t total = q.total, chunk = q.chunk;
    std::optional<uint64_t>& revision = q.revision;
    std::atomic<size_t>* learned = q.learned;
    size_t first = 0;
    do {
        size_t size = chunk;
        if (learned != nullptr) {
            const size_t limit = learned->load(std::memory_order_relaxed);
            if (limit != 0) size = std::min(size, limit);
        }
        const size_t count = std::min(size, total - first);
        const std::vector<std::byte> body = encode(first, count);
        const std::string target = with_revision(path, revision);
        auto answer = ClientAccess::request(client, {.method = "POST",
                                                     .path = target,
                                                     .content_type = q.content_type,
                                                     .body = body,
                                                     .answer_header = kRevisionHeader});
        if (!answer) {
            const Error& e = answer.error();
            if (learned != nullptr && e.kind == ErrorKind::kServer && e.status == 413 &&
                count > 1) {
                const size_t smaller = detail::smaller_point_chunk(e, count);
                size_t seen = learned->load(std::memory_order_relaxed);
                while ((seen == 0 || smaller < seen) &&
                       !learned->compare_exchange_weak(seen, smaller, std::memory_order_relaxed)) {
                }
                continue;
            }
            return proto::Err{std::move(answer).error()};
        }
        const auto answered = revision_of(*answer);
        if (!answered || (revision && *answered != *revision))
            return proto::Err{ClientAccess::bad_response(client, target,
                                                         "the answer's X-Kdrt-Scene-Revision \"" +
                                                             answer->header +
                                                             "\" is not the revision asked for")};
        revision = answered;
        if (auto failed = take_chunk(client, q, target, *answer, take, count))
            return proto::Err{std::move(*failed)};
        first += count;
    } while (first < total);
    return *revision;
}

/// query_chunks for a ray batch (KDRR, occlusion flag `occlusion`) sent to `path`. With a
/// `split_id` (closest hits and occlusion), split as ClientOptions::split says.
template <class Take>
Result<uint64_t> ray_chunks(Client& client, std::string path, std::span<const Ray> rays,
                            bool occlusion, std::optional<uint64_t> revision, bool plane, Take take,
                            std::string_view split_id = {}) {
    return query_chunks(
        client,
        {.path = std::move(path),
         .content_type = proto::kRaysMediaType,
         .total = rays.size(),
         .chunk = client.options().chunk_rays,
         .revision = revision,
         .plane = plane,
         .split = split_id.empty() ? 0 : client.options().split,
         .route_id = split_id,
         .connections = client.options().connections},
        [&](size_t first, size_t count) {
            return proto::encode_rays(rays.subspan(first, count), occlusion);
        },
        take);
}

/// A take() for answers without a plane, one record per ray (KDRO, KDRC): decoded by `decode`
/// and appended to `out`.
template <class T, class Decode>
auto append_records(std::vector<T>& out, Decode decode) {
    return [&out, decode](std::span<const std::byte> body, std::span<const uint32_t>,
                          size_t count) -> std::optional<std::string> {
        auto part = decode(body);
        if (!part) return part.error().to_string();
        if (part->size() != count) return "the answer is for another batch";
        out.insert(out.end(), part->begin(), part->end());
        return std::nullopt;
    };
}

/// A too large count is a kInput error before anything is sent.
std::optional<Error> too_many(size_t count, std::string_view what) {
    if (count <= std::numeric_limits<uint32_t>::max()) return std::nullopt;
    return make_client_error(
        ErrorKind::kInput, "too many " + std::string(what),
        std::to_string(count) + " " + std::string(what) + "; at most 2^32 - 1 per call");
}

}  // namespace

// ---- Documents ---------------------------------------------------------------------------------

Result<SceneDocument> Client::create_scene(std::span<const proto::SceneInstanceSpec> instances) {
    const std::string body = proto::encode_scene_request(instances);
    const std::string path = ClientAccess::api_path(*this, "/v1/scenes", "");
    auto answer = ClientAccess::request(*this, {.method = "POST",
                                                .path = path,
                                                .content_type = proto::kSceneMediaType,
                                                .body = as_bytes(body),
                                                .idempotent = false});
    if (!answer) return proto::Err{std::move(answer).error()};
    auto created = proto::decode_scene_json(answer->body, {.max_instances = kNoLimit}, true);
    if (!created)
        return proto::Err{ClientAccess::bad_response(*this, path, created.error().detail)};
    return std::move(*created);
}

Result<SceneDocument> Client::scene(std::string_view id, std::optional<uint64_t> revision) {
    const std::string path =
        with_revision(ClientAccess::api_path(*this, "/v1/scenes/{id}", id), revision);
    auto answer = ClientAccess::request(*this, {.method = "GET", .path = path});
    if (!answer) return proto::Err{std::move(answer).error()};
    auto doc = proto::decode_scene_json(answer->body, {.max_instances = kNoLimit}, true);
    if (!doc) return proto::Err{ClientAccess::bad_response(*this, path, doc.error().detail)};
    return std::move(*doc);
}

Result<std::vector<SceneRevision>> Client::scenes() {
    const std::string path = ClientAccess::api_path(*this, "/v1/scenes", "");
    auto answer = ClientAccess::request(*this, {.method = "GET", .path = path});
    if (!answer) return proto::Err{std::move(answer).error()};
    auto list = proto::decode_scene_list(answer->body);
    if (!list) return proto::Err{ClientAccess::bad_response(*this, path, list.error())};
    return std::move(*list);
}

Result<void> Client::remove_scene(std::string_view id, std::optional<uint64_t> if_revision) {
    auto answer =
        ClientAccess::request(*this, {.method = "DELETE",
                                      .path = ClientAccess::api_path(*this, "/v1/scenes/{id}", id),
                                      .headers = if_match(if_revision)});
    if (!answer) return proto::Err{std::move(answer).error()};
    return {};
}

Result<SceneRevision> Client::set_poses(std::string_view id,
                                        std::span<const proto::PoseEntry> poses,
                                        std::optional<uint64_t> if_revision) {
    if (auto error = too_many(poses.size(), "poses")) return proto::Err{std::move(*error)};
    if (auto bad = bad_pose(poses))
        return proto::Err{make_client_error(ErrorKind::kInput, "bad pose", std::move(*bad))};
    const bool by_id = std::all_of(poses.begin(), poses.end(), [](const proto::PoseEntry& p) {
        return p.geometry_id.has_value();
    });
    std::vector<std::byte> binary;
    std::string text;
    if (by_id && !poses.empty()) {
        binary = proto::encode_pose_batch(poses);
    } else {
        text = proto::encode_pose_json(poses);
    }
    const std::string path = ClientAccess::api_path(*this, "/v1/scenes/{id}/poses", id);
    auto answer = ClientAccess::request(
        *this, {.method = "PATCH",
                .path = path,
                .headers = if_match(if_revision),
                .content_type = binary.empty() ? proto::kJsonMediaType : proto::kPoseBatchMediaType,
                .body = binary.empty() ? as_bytes(text) : std::span<const std::byte>(binary)});
    if (!answer) return proto::Err{std::move(answer).error()};
    auto revision = proto::decode_scene_revision(answer->body);
    if (!revision) return proto::Err{ClientAccess::bad_response(*this, path, revision.error())};
    return std::move(*revision);
}

Result<SceneDocument> Client::edit_scene(std::string_view id, const proto::InstanceEdit& edit,
                                         std::optional<uint64_t> if_revision) {
    const std::string body = proto::encode_instance_edit_json(edit);
    const std::string path = ClientAccess::api_path(*this, "/v1/scenes/{id}/instances", id);
    auto answer = ClientAccess::request(*this, {.method = "POST",
                                                .path = path,
                                                .headers = if_match(if_revision),
                                                .content_type = proto::kJsonMediaType,
                                                .body = as_bytes(body),
                                                .idempotent = false});
    if (!answer) return proto::Err{std::move(answer).error()};
    auto doc = proto::decode_scene_json(answer->body, {.max_instances = kNoLimit}, true);
    if (!doc) return proto::Err{ClientAccess::bad_response(*this, path, doc.error().detail)};
    return std::move(*doc);
}

// ---- Queries -----------------------------------------------------------------------------------

Result<SceneHits> Client::intersect_scene(std::string_view id, std::span<const Ray> rays,
                                          std::optional<uint64_t> revision) {
    if (auto error = too_many(rays.size(), "rays")) return proto::Err{std::move(*error)};
    SceneHits out;
    out.hits.reserve(rays.size());
    out.geometry_ids.reserve(rays.size());
    auto answered = ray_chunks(
        *this, ClientAccess::api_path(*this, "/v1/scenes/{id}/intersect", id), rays, false,
        revision, true,
        [&](std::span<const std::byte> body, std::span<const uint32_t> geoms,
            size_t count) -> std::optional<std::string> {
            auto hits = proto::decode_hits(body, {.max_rays = kNoLimit});
            if (!hits) return hits.error().to_string();
            if (hits->size() != count || geoms.size() != count)
                return "the answer is for another batch";
            out.hits.insert(out.hits.end(), hits->begin(), hits->end());
            out.geometry_ids.insert(out.geometry_ids.end(), geoms.begin(), geoms.end());
            return std::nullopt;
        },
        id);
    if (!answered) return proto::Err{std::move(answered).error()};
    out.revision = *answered;
    return out;
}

Result<SceneOcclusion> Client::occluded_scene(std::string_view id, std::span<const Ray> rays,
                                              std::optional<uint64_t> revision) {
    if (auto error = too_many(rays.size(), "rays")) return proto::Err{std::move(*error)};
    SceneOcclusion result;
    std::vector<uint8_t>& out = result.occluded;
    out.reserve(rays.size());
    auto answered =
        ray_chunks(*this, ClientAccess::api_path(*this, "/v1/scenes/{id}/intersect", id), rays,
                   true, revision, false,
                   append_records(out,
                                  [](std::span<const std::byte> body) {
                                      return proto::decode_occlusion(body, {.max_rays = kNoLimit});
                                  }),
                   id);
    if (!answered) return proto::Err{std::move(answered).error()};
    result.revision = *answered;
    return result;
}

Result<SceneMultiHits> Client::intersect_all_scene(std::string_view id, std::span<const Ray> rays,
                                                   const proto::MultiHitQuery& query,
                                                   std::optional<uint64_t> revision) {
    if (auto error = too_many(rays.size(), "rays")) return proto::Err{std::move(*error)};
    proto::MultiHitQuery q = query;
    q.count_only = false;
    SceneMultiHits out;
    out.all.layout = q.layout;
    out.all.merged = q.merge_coincident;
    out.all.max_hits = q.max_hits;
    out.all.offsets.push_back(0);
    auto answered = ray_chunks(
        *this,
        ClientAccess::api_path(
            *this, "/v1/scenes/{id}/intersect_all?" + proto::multi_hit_query_string(q), id),
        rays, false, revision, true,
        [&](std::span<const std::byte> body, std::span<const uint32_t> geoms,
            size_t count) -> std::optional<std::string> {
            auto part = proto::decode_multi_hits(body, {.max_rays = kNoLimit});
            if (!part) return part.error().to_string();
            if (part->counts.size() != count || part->layout != q.layout ||
                geoms.size() != part->hits.size())
                return "the answer is for another batch";
            const uint64_t base = out.all.offsets.back();
            for (size_t i = 1; i < part->offsets.size(); ++i)
                out.all.offsets.push_back(base + part->offsets[i]);
            out.all.counts.insert(out.all.counts.end(), part->counts.begin(), part->counts.end());
            out.all.hits.insert(out.all.hits.end(), part->hits.begin(), part->hits.end());
            out.geometry_ids.insert(out.geometry_ids.end(), geoms.begin(), geoms.end());
            return std::nullopt;
        });
    if (!answered) return proto::Err{std::move(answered).error()};
    out.revision = *answered;
    return out;
}

Result<SceneHitCounts> Client::count_scene_intersections(std::string_view id,
                                                         std::span<const Ray> rays,
                                                         bool merge_coincident,
                                                         std::optional<uint64_t> revision) {
    if (auto error = too_many(rays.size(), "rays")) return proto::Err{std::move(*error)};
    proto::MultiHitQuery q;
    q.count_only = true;
    q.merge_coincident = merge_coincident;
    q.max_hits = 1;
    SceneHitCounts result;
    std::vector<uint32_t>& counts = result.counts;
    counts.reserve(rays.size());
    auto answered = ray_chunks(
        *this,
        ClientAccess::api_path(
            *this, "/v1/scenes/{id}/intersect_all?" + proto::multi_hit_query_string(q), id),
        rays, false, revision, false, append_records(counts, [](std::span<const std::byte> body) {
            return proto::decode_hit_counts(body, {.max_rays = kNoLimit});
        }));
    if (!answered) return proto::Err{std::move(answered).error()};
    result.revision = *answered;
    return result;
}

Result<SceneDistanceAnswer> Client::scene_distance(std::string_view id,
                                                   std::span<const Vec3> points,
                                                   const DistanceQuery& query,
                                                   std::optional<uint64_t> revision) {
    if (auto error = too_many(points.size(), "points")) return proto::Err{std::move(*error)};
    if (auto bad = proto::non_finite_point(points)) {
        Error e = make_client_error(ErrorKind::kInput, "bad query point", std::move(*bad));
        e.code = "non_finite_point";
        return proto::Err{std::move(e)};
    }
    SceneDistanceAnswer out;
    out.signed_query = query.signed_query;
    out.points.reserve(points.size());
    auto answered = query_chunks(
        *this,
        {.path = ClientAccess::api_path(
             *this, "/v1/scenes/{id}/distance?" + proto::distance_query_string(query), id),
         .content_type = proto::kPointMediaType,
         .total = points.size(),
         .chunk = options().chunk_rays,
         .revision = revision,
         .learned = &ClientAccess::distance_chunk_limit(*this)},
        [&](size_t first, size_t count) {
            return proto::encode_points(points.subspan(first, count));
        },
        [&](std::span<const std::byte> body, std::span<const uint32_t> geoms,
            size_t count) -> std::optional<std::string> {
            auto part = proto::decode_distances(body, {.max_rays = kNoLimit});
            if (!part) return part.error().to_string();
            if (part->points.size() != count || geoms.size() != count ||
                part->signed_query != query.signed_query)
                return "the answer is for another batch";
            out.points.insert(out.points.end(), part->points.begin(), part->points.end());
            out.geometry_ids.insert(out.geometry_ids.end(), geoms.begin(), geoms.end());
            return std::nullopt;
        });
    if (!answered) return proto::Err{std::move(answered).error()};
    out.revision = *answered;
    return out;
}

Result<SceneScan> Client::scan_scene(std::string_view id, const proto::ScanRequest& request,
                                     std::optional<uint64_t> revision) {
    const bool ranges = request.lidar && request.format == proto::ScanFormat::kRanges;
    if (request.format != proto::ScanFormat::kBinary && !ranges)
        return proto::Err{make_client_error(
            ErrorKind::kInput, "bad scan format",
            "a scene scan answers \"format\": \"binary\" (KDRZ or KDRL) or, for a lidar, "
            "\"ranges\" (KDRB), with geometry ids; not " +
                std::string(proto::scan_format_name(request.format)))};
    const std::string body = proto::encode_scan_request(request);
    const std::string path =
        with_revision(ClientAccess::api_path(*this, "/v1/scenes/{id}/scan", id), revision);
    auto answer = ClientAccess::request(*this, {.method = "POST",
                                                .path = path,
                                                .content_type = proto::kJsonMediaType,
                                                .body = as_bytes(body),
                                                .answer_header = kRevisionHeader});
    if (!answer) return proto::Err{std::move(answer).error()};
    SceneScan out;
    const auto answered = revision_of(*answer);
    if (!answered)
        return proto::Err{ClientAccess::bad_response(*this, path, "no X-Kdrt-Scene-Revision")};
    out.revision = *answered;
    const auto bytes = as_bytes(answer->body);
    out.body.assign(bytes.begin(), bytes.end());
    auto split = proto::split_geometry_ids(out.body, {.max_rays = kNoLimit});
    if (!split)
        return proto::Err{ClientAccess::bad_response(*this, path, split.error().to_string())};
    if (ranges) {
        auto decoded = proto::decode_lidar_ranges(split->mesh_body, kNoLimit);
        if (!decoded)
            return proto::Err{ClientAccess::bad_response(*this, path, decoded.error().to_string())};
        out.ranges = std::move(*decoded);
    } else if (request.lidar) {
        auto cloud = proto::decode_point_cloud(split->mesh_body, kNoLimit);
        if (!cloud)
            return proto::Err{ClientAccess::bad_response(*this, path, cloud.error().to_string())};
        out.cloud = std::move(*cloud);
    } else {
        auto image =
            proto::decode_depth_image(split->mesh_body, std::numeric_limits<uint64_t>::max());
        if (!image)
            return proto::Err{ClientAccess::bad_response(*this, path, image.error().to_string())};
        out.depth = std::move(*image);
    }
    out.geometry_ids = std::move(split->geometry_ids);
    return out;
}

}  // namespace kdrt
