// POST /v1/meshes/{id}/intersect: KDRR -> KDRH/KDRO, or JSON -> JSON.

#include <cstdint>
#include <memory>
#include <optional>
#include <span>
#include <utility>

#include "http/batch_ingest.h"
#include "http/http_front.h"
#include "http/http_routes.h"
#include "http/http_util.h"
#include "http/problems.h"
#include "kdrt/proto/json_api.h"
#include "kdrt/proto/ray_batch.h"
#include "kdrt/proto/text.h"

namespace kdrt::server {

using proto::ProblemKind;

namespace {

/// Bodies from this size on are read from the socket directly, past httplib (read_body_direct).
constexpr uint64_t kDirectReadBytes = 256u << 10;

/// How a KDRR body over the limit is named in the 413 detail.
constexpr const char* kBatchLimitWhat = "a KDRR batch (16 + 32 x max_rays)";

/// The problem a batch without an answer is reported as. `http_status`: what httplib set when
/// its reader failed (413 over its payload limit, else 400).
proto::Problem ingest_problem(const IngestFailure& failure, int http_status, uint64_t limit) {
    switch (failure.kind) {
        case IngestFailure::Kind::kTooLarge:
            return body_too_large_problem(limit, kBatchLimitWhat);
        case IngestFailure::Kind::kRefused:
            return ray_batch_problem(*failure.error);
        case IngestFailure::Kind::kUnreadable:
        case IngestFailure::Kind::kOverBudget:  // the route replies the budget's problem
            break;
    }
    // The connection broke, the request's deadline passed, or the framing was invalid.
    if (request_deadline_passed()) return body_timeout_problem();
    return http_status == 413
               ? body_too_large_problem(limit, kBatchLimitWhat)
               : make_problem(ProblemKind::kBadRequest, "the request body could not be read");
}

}  // namespace

void Routes::intersect(const httplib::Request& req, httplib::Response& res,
                       const httplib::ContentReader& reader) {
    const std::string type = proto::media_type_essence(req.get_header_value("Content-Type"));
    const bool binary = type == proto::kRaysMediaType;
    if (!binary && type != proto::kJsonMediaType) {
        return reply_problem(
            req, res,
            make_problem(ProblemKind::kUnsupportedMediaType,
                         "intersect " + std::string(proto::api_errors::kUnsupportedRayType) +
                             ", not " + proto::quote_value(req.get_header_value("Content-Type"))));
    }
    // ?invalid_rays=refuse (default): a ray with a NaN/Inf field makes the KDRR batch a 400
    // naming its index; =miss: such rays are answered as misses (as Embree and Open3D do).
    const std::string invalid = req.get_param_value("invalid_rays");
    if (!invalid.empty() && invalid != "refuse" && invalid != "miss") {
        return reply_problem(
            req, res,
            make_problem(ProblemKind::kBadRequest, "query parameter invalid_rays is " +
                                                       proto::quote_value(invalid) +
                                                       " (expected refuse or miss)"));
    }
    const std::shared_ptr<const KdTree> tree = acquire_tree(req, res);
    if (!tree) return;
    if (binary) return intersect_binary(req, res, reader, *tree, invalid != "miss");
    intersect_json(req, res, reader, *tree);
}

void Routes::intersect_binary(const httplib::Request& req, httplib::Response& res,
                              const httplib::ContentReader& reader, const KdTree& tree,
                              bool reject_invalid) {
    // The batch's memory (32 bytes a ray in, at most 16 out, and the header) is held from
    // before its body is read, or, chunked, from when its header says how many rays follow.
    const BatchBody spec{.limit = proto::kdrr_body_size(svc_.config.max_rays),
                         .what = kBatchLimitWhat,
                         .record_bytes = proto::kRayRecordBytes,
                         .memory_per_record = 48,
                         .memory_fixed = proto::kBatchHeaderBytes,
                         .advice = "; send fewer rays"};
    read_batch(req, res, spec, [&](const BodyProgress& grow) {
        std::optional<proto::Problem> refused;
        BatchIngest::Reserve reserve;
        if (grow) {
            reserve = [&](uint64_t body_bytes) {
                refused = grow(body_bytes);
                return !refused;
            };
        }
        BatchIngest ingest(svc_.compute, svc_.batch_buffers, tree, svc_.config.max_rays,
                           declared_body_bytes(req), reject_invalid, std::move(reserve));
        const bool read_ok = read_body_direct(
            req, reader, kDirectReadBytes,
            [&](std::span<const std::byte> piece) { return ingest.feed(piece); },
            [&](const SocketReceive& receive) { return ingest.receive_rest(receive); });
        request_context().bytes_in += ingest.received();
        auto answer = ingest.finish(read_ok);
        if (!answer) {
            reply_problem(req, res,
                          refused ? std::move(*refused)
                                  : ingest_problem(answer.error(), res.status, ingest.limit()));
            if (answer.error().close_connection) res.set_header("Connection", "close");
            return false;
        }
        request_context().rays = answer->count;
        svc_.metrics.add_rays(answer->count, answer->occlusion);
        reply_buffer(res, std::move(answer->body), answer->size,
                     answer->occlusion ? proto::kOcclusionMediaType : proto::kHitsMediaType);
        return true;
    });
}

void Routes::intersect_json(const httplib::Request& req, httplib::Response& res,
                            const httplib::ContentReader& reader, const KdTree& tree) {
    // The body, and up to max_json_rays rays and their answers (32 + 16 bytes each).
    auto body = read_batch(req, res, reader,
                           {.limit = svc_.config.max_json_bytes,
                            .what = "a JSON request (max_json_bytes)",
                            .header_bytes = 0,
                            .record_bytes = 1,
                            .memory_per_record = 1,
                            .memory_fixed = uint64_t{svc_.config.max_json_rays} * 48,
                            .records = "bytes of JSON rays",
                            .advice = "; send fewer rays"});
    if (!body) return;
    auto request = proto::decode_json_rays(as_text(body->bytes()), svc_.config.max_json_rays);
    body.reset();
    if (!request)
        return reply_problem(req, res, json_problem(request.error(), svc_.config.max_json_rays));
    request_context().rays = request->rays.size();
    svc_.metrics.add_rays(request->rays.size(), request->occlusion);
    if (request->occlusion) {
        std::vector<uint8_t> occluded(request->rays.size());
        svc_.compute.occluded(tree, request->rays, occluded);
        return reply_json(res, 200, proto::encode_json_occlusion(occluded));
    }
    std::vector<Hit> hits(request->rays.size());
    svc_.compute.intersect(tree, request->rays, hits);
    reply_json(res, 200, proto::encode_json_hits(hits));
}

}  // namespace kdrt::server
