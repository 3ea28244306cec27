// POST /v1/meshes/{id}/intersect: KDRR -> KDRH/KDRO, or JSON -> JSON.

#include <algorithm>
#include <optional>
#include <span>

#include "http_routes.h"
#include "http_util.h"
#include "kdrt/proto/json_api.h"
#include "kdrt/proto/ray_batch.h"
#include "problems.h"

namespace kdrt::server {

using proto::ProblemKind;

namespace {

/// Batches this large are traced while their body is still arriving (StreamTrace); smaller
/// ones are decoded first and traced in one go.
constexpr uint32_t kStreamTraceRays = 2 * StreamTrace::kBlockRays;

/// A refused batch's remaining body is read and dropped up to this size (like discard_body), so
/// the keep-alive connection stays usable; beyond it the connection is closed.
constexpr uint64_t kDrainBytes = 64u << 20;

/// Bodies from this size on are read from the socket directly (see DirectBody in http_util.h),
/// in pieces of at most kDirectPieceBytes (so tracing starts on the first rays early).
constexpr uint64_t kDirectReadBytes = 256u << 10;
constexpr size_t kDirectPieceBytes = 1u << 20;

}  // namespace

void Routes::intersect(const httplib::Request& req, httplib::Response& res,
                       const httplib::ContentReader& reader) {
    const std::string type = proto::media_type_essence(req.get_header_value("Content-Type"));
    const bool binary = type == proto::kRaysMediaType;
    if (!binary && type != proto::kJsonMediaType) {
        discard_body(req, res, reader);
        return reply_problem(
            req, res,
            make_problem(ProblemKind::kUnsupportedMediaType,
                         "intersect " + std::string(proto::api_errors::kUnsupportedRayType) +
                             ", not \"" + req.get_header_value("Content-Type") + "\""));
    }
    const std::string id = req.matches[1];
    auto tree = svc_.cache.acquire(id);
    if (!tree) {
        discard_body(req, res, reader);
        return reply_problem(req, res,
                             tree.error().code == CacheError::Code::kUnknownMesh
                                 ? unknown_mesh_problem(id)
                                 : cache_problem(tree.error()));
    }
    if (binary) return intersect_binary(req, res, reader, **tree);
    intersect_json(req, res, reader, **tree);
}

void Routes::intersect_binary(const httplib::Request& req, httplib::Response& res,
                              const httplib::ContentReader& reader, const KdTree& tree) {
    // The body is decoded as it arrives, straight into a pooled ray buffer, and large batches are
    // traced block by block while the rest is still being received; the answer is written in
    // place into a pooled response buffer and streamed from it.
    const uint64_t limit =
        proto::kBatchHeaderBytes + uint64_t{proto::kRayRecordBytes} * svc_.config.max_rays;
    const std::string what = "a KDRR batch (16 + 32 x max_rays)";
    const bool chunked =
        req.get_header_value("Transfer-Encoding").find("chunked") != std::string::npos;
    std::optional<uint64_t> declared;
    if (!chunked && req.has_header("Content-Length"))
        declared = req.get_header_value<uint64_t>("Content-Length");
    if (declared && *declared > limit) {
        discard_body(req, res, reader);
        return reply_problem(req, res, body_too_large_problem(limit, what));
    }

    AlignedBuffer ray_buffer, answer_buffer;
    std::span<Ray> rays;
    std::optional<StreamTrace> tracer;  // destroyed (waits for its blocks) before the buffers
    const auto storage = [&](uint32_t count, bool occlusion) {
        ray_buffer = svc_.batch_buffers.take(size_t{count} * sizeof(Ray));
        answer_buffer = svc_.batch_buffers.take(proto::kBatchHeaderBytes +
                                                size_t{count} * (occlusion ? 1 : sizeof(Hit)));
        rays = std::span<Ray>(reinterpret_cast<Ray*>(ray_buffer.data()), count);
        if (count >= kStreamTraceRays) {
            std::byte* records = answer_buffer.data() + proto::kBatchHeaderBytes;
            if (occlusion)
                tracer.emplace(svc_.compute, tree, rays,
                               std::span<uint8_t>(reinterpret_cast<uint8_t*>(records), count));
            else
                tracer.emplace(svc_.compute, tree, rays,
                               std::span<Hit>(reinterpret_cast<Hit*>(records), count));
        }
        return rays;
    };
    proto::RayStreamDecoder decoder({.max_rays = svc_.config.max_rays, .reject_non_finite = true},
                                    storage, declared);

    RequestContext& context = request_context();
    uint64_t received = 0;
    bool too_large = false, refused = false;
    // Takes one piece of the body (already in `piece`, or already in the decoder's window when
    // `in_place`). False when reading should stop.
    const auto take_piece = [&](std::span<const std::byte> piece, bool in_place) {
        received += piece.size();
        context.bytes_in += piece.size();
        if (received > limit) {
            too_large = true;
            return false;
        }
        const bool ok = in_place ? decoder.commit(piece.size()) : decoder.feed(piece);
        if (!ok) {
            if (!refused && tracer) tracer->abandon();
            refused = true;
            // Drain what is left when it is small, so the connection stays usable.
            return declared && *declared <= kDrainBytes;
        }
        if (tracer) tracer->advance(decoder.rays_ready());
        return true;
    };
    const bool has_body = (declared && *declared > 0) || chunked;
    // Large bodies: the first piece through httplib, the rest straight from the socket.
    const std::optional<DirectBody> direct =
        declared && *declared >= kDirectReadBytes
            ? direct_body(req, static_cast<int>(svc_.config.read_timeout_s))
            : std::nullopt;
    bool go_direct = false;
    bool read_ok = !has_body || reader([&](const char* data, size_t size) {
        if (!take_piece(std::span(reinterpret_cast<const std::byte*>(data), size), false))
            return false;
        if (direct && received < *declared) {
            go_direct = true;
            return false;  // httplib's reader stops here; the route reads the rest
        }
        return true;
    });
    if (go_direct) {
        read_ok = true;
        std::vector<std::byte> scratch;
        while (read_ok && received < *declared) {
            const size_t left = static_cast<size_t>(*declared - received);
            const std::span<std::byte> window = decoder.next_window();
            ssize_t n = 0;
            if (!window.empty()) {
                n = receive_some(*direct, window.data(),
                                 std::min({window.size(), left, kDirectPieceBytes}));
                if (n > 0) read_ok = take_piece(window.first(static_cast<size_t>(n)), true);
            } else {
                // Header bytes, or the rest of a refused body being drained.
                scratch.resize(64u << 10);
                n = receive_some(*direct, scratch.data(), std::min(scratch.size(), left));
                if (n > 0)
                    read_ok = take_piece(std::span(scratch).first(static_cast<size_t>(n)), false);
            }
            if (n <= 0) read_ok = false;
        }
    }
    const auto give_back = [&] {
        tracer.reset();
        svc_.batch_buffers.give(std::move(ray_buffer));
        svc_.batch_buffers.give(std::move(answer_buffer));
    };
    if (too_large) {
        give_back();
        reply_problem(req, res, body_too_large_problem(limit, what));
        res.set_header("Connection", "close");
        return;
    }
    if (refused) {
        give_back();
        reply_problem(req, res, ray_batch_problem(*decoder.error()));
        if (!read_ok) res.set_header("Connection", "close");
        return;
    }
    if (!read_ok) {
        // The connection broke or the framing was invalid; httplib set 400 or 413.
        give_back();
        reply_problem(req, res,
                      res.status == 413 ? body_too_large_problem(limit, what)
                                        : make_problem(ProblemKind::kBadRequest,
                                                       "the request body could not be read"));
        res.set_header("Connection", "close");
        return;
    }
    if (auto verdict = decoder.finish(); !verdict) {
        give_back();
        return reply_problem(req, res, ray_batch_problem(verdict.error()));
    }

    const uint32_t count = decoder.count();
    const bool occlusion = decoder.occlusion();
    context.rays = count;
    svc_.metrics.add_rays(count, occlusion);
    std::byte* records = answer_buffer.data() + proto::kBatchHeaderBytes;
    if (tracer) {
        tracer->finish();
    } else if (occlusion) {
        svc_.compute.occluded(tree, rays,
                              std::span<uint8_t>(reinterpret_cast<uint8_t*>(records), count));
    } else {
        svc_.compute.intersect(tree, rays, std::span<Hit>(reinterpret_cast<Hit*>(records), count));
    }
    tracer.reset();
    svc_.batch_buffers.give(std::move(ray_buffer));

    size_t answer_bytes = 0;
    if (occlusion) {
        answer_bytes = proto::write_answer_in_place(answer_buffer.data(),
                                                    proto::AnswerKind::kOcclusion, count);
    } else {
        answer_bytes =
            proto::write_answer_in_place(answer_buffer.data(), proto::AnswerKind::kHits, count);
    }
    reply_buffer(res, std::move(answer_buffer), answer_bytes,
                 occlusion ? proto::kOcclusionMediaType : proto::kHitsMediaType,
                 &svc_.batch_buffers);
}

void Routes::intersect_json(const httplib::Request& req, httplib::Response& res,
                            const httplib::ContentReader& reader, const KdTree& tree) {
    auto body = read_body(req, res, reader, svc_.config.max_json_bytes, svc_.config.max_json_bytes,
                          svc_.store.tmp_dir().string(), "a JSON request (max_json_bytes)");
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
