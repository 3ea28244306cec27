// Client::distance: query points as KDRP chunks, KDRD answers joined in query order, the
// X-Kdrt-Surface header carried into the answer. Transport (retries, connections) is
// http_client.cpp's, through client_access.h.

#include <algorithm>
#include <limits>
#include <vector>

#include "client_access.h"
#include "kdrt/client/client.h"
#include "kdrt/proto/distance.h"

namespace kdrt {
namespace {

constexpr std::string_view kSurfaceHeader = "X-Kdrt-Surface";

}  // namespace

Result<DistanceAnswer> Client::distance(std::string_view id, std::span<const Vec3> points,
                                        const DistanceQuery& query) {
    if (points.size() > std::numeric_limits<uint32_t>::max())
        return proto::Err{make_client_error(
            ErrorKind::kInput, "too many points",
            std::to_string(points.size()) + " query points; at most 2^32 - 1 per call")};
    // Refused here, as the server would, but with the index in the whole call, not the chunk.
    if (auto bad = proto::non_finite_point(points)) {
        Error e = make_client_error(ErrorKind::kInput, "bad query point", std::move(*bad));
        e.code = "non_finite_point";
        return proto::Err{std::move(e)};
    }
    const std::string path = detail::ClientAccess::api_path(
        *this, "/v1/meshes/{id}/distance?" + proto::distance_query_string(query), id);
    std::atomic<size_t>& learned = detail::ClientAccess::distance_chunk_limit(*this);

    DistanceAnswer out;
    out.signed_query = query.signed_query;
    out.points.reserve(points.size());
    size_t first = 0;
    do {
        const size_t limit = learned.load(std::memory_order_relaxed);
        const size_t chunk = limit ? std::min(limit, options().chunk_rays) : options().chunk_rays;
        const size_t count = std::min(chunk, points.size() - first);
        const std::vector<std::byte> body = proto::encode_points(points.subspan(first, count));
        auto answer =
            detail::ClientAccess::post(*this, path, proto::kPointMediaType, body, kSurfaceHeader);
        if (!answer) {
            const Error& e = answer.error();
            if (e.kind == ErrorKind::kServer && e.status == 413 && count > 1) {
                // Never more than the server takes: send this chunk again in smaller ones.
                const size_t smaller = detail::smaller_point_chunk(e, count);
                size_t seen = learned.load(std::memory_order_relaxed);
                while ((seen == 0 || smaller < seen) &&
                       !learned.compare_exchange_weak(seen, smaller, std::memory_order_relaxed)) {
                }
                continue;
            }
            return proto::Err{std::move(answer).error()};
        }
        const std::span<const std::byte> bytes(
            reinterpret_cast<const std::byte*>(answer->body.data()), answer->body.size());
        auto part = proto::decode_distances(bytes, {.max_rays = static_cast<uint32_t>(count)});
        if (!part)
            return proto::Err{
                detail::ClientAccess::bad_response(*this, path, part.error().to_string())};
        if (part->points.size() != count || part->signed_query != query.signed_query)
            return proto::Err{detail::ClientAccess::bad_response(
                *this, path,
                "the answer holds " + std::to_string(part->points.size()) +
                    " points, for a batch of " + std::to_string(count))};
        if (first == 0) {
            out.surface = std::move(answer->header);
        } else if (answer->header != out.surface) {
            return proto::Err{detail::ClientAccess::bad_response(
                *this, path,
                "X-Kdrt-Surface changed between chunks: \"" + out.surface + "\", then \"" +
                    answer->header + "\"")};
        }
        out.points.insert(out.points.end(), part->points.begin(), part->points.end());
        first += count;
    } while (first < points.size());
    return out;
}

namespace detail {

size_t smaller_point_chunk(const Error& refusal, size_t count) {
    size_t allowed = 0;
    if (refusal.limit) {
        if (refusal.code == "too_many_rays")
            allowed = static_cast<size_t>(std::min<uint64_t>(*refusal.limit, SIZE_MAX));
        else if (*refusal.limit >= proto::kdrp_body_size(1))
            allowed = static_cast<size_t>(std::min<uint64_t>(
                (*refusal.limit - proto::kBatchHeaderBytes) / proto::kPointRecordBytes, SIZE_MAX));
    }
    if (allowed == 0 || allowed >= count) allowed = count / 2;
    return allowed;
}

}  // namespace detail
}  // namespace kdrt
