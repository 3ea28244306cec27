// POST /v1/render (and what POST /v1/scenes/{id}/render shares with it: the request, its limits,
// sync or async), and the async job routes /v1/jobs/{id}[/result].

#include <algorithm>
#include <cctype>
#include <functional>
#include <optional>

#include "core/log.h"
#include "core/rendering.h"
#include "http/http_front.h"
#include "http/http_routes.h"
#include "http/http_util.h"
#include "http/json_shape.h"
#include "http/problems.h"
#include "kdrt/proto/image_format.h"
#include "kdrt/proto/image_module.h"
#include "kdrt/proto/json_api.h"
#include "kdrt/proto/raw_image.h"

namespace kdrt::server {
namespace {

using proto::ProblemKind;

/// True when the Prefer header (RFC 7240) asks for respond-async.
bool prefers_async(const httplib::Request& req) {
    // Every Prefer header (equal_range: the header map compares names without case).
    const auto [first, last] = req.headers.equal_range("Prefer");
    for (auto it = first; it != last; ++it) {
        std::string value = it->second;
        std::transform(value.begin(), value.end(), value.begin(),
                       [](unsigned char c) { return static_cast<char>(std::tolower(c)); });
        size_t start = 0;
        while (start <= value.size()) {
            const size_t comma = value.find(',', start);
            std::string token =
                value.substr(start, comma == std::string::npos ? std::string::npos : comma - start);
            token.erase(0, token.find_first_not_of(" \t"));
            token.erase(token.find_last_not_of(" \t") + 1);
            if (token == "respond-async") return true;
            if (comma == std::string::npos) break;
            start = comma + 1;
        }
    }
    return false;
}

/// What a render costs in rays, an upper bound (Russian roulette may end diffuse paths early).
struct RenderCost {
    uint64_t pixels = 0;
    uint64_t rays_per_sample = 1;
    uint64_t rays = 0;
};

RenderCost render_cost(const RenderSettings& s) {
    RenderCost cost;
    cost.pixels =
        s.region ? uint64_t{s.region->width} * s.region->height : uint64_t{s.width} * s.height;
    if (s.shading == Shading::kAo) cost.rays_per_sample = 1 + uint64_t{s.ao_samples};
    if (s.shading == Shading::kDiffuse) cost.rays_per_sample = 2 + 2 * uint64_t{s.bounces};
    cost.rays = cost.pixels * s.spp * cost.rays_per_sample;
    return cost;
}

/// Why a "format": "raw" render's KDRI answer (kdrt/proto/raw_image.h) would be larger than
/// `max_bytes` (max_raw_render_bytes), or nullopt when it fits or the format is another.
std::optional<proto::Problem> raw_answer_problem(const proto::RenderRequest& request,
                                                 proto::ImageFormat format, uint64_t max_bytes) {
    if (format != proto::ImageFormat::kRaw) return std::nullopt;
    const RenderSettings& s = request.settings;
    const PixelRegion r = s.region.value_or(PixelRegion{0, 0, s.width, s.height});
    const uint64_t channels = s.alpha ? 4 : 3;
    const uint64_t bytes = proto::kdri_body_size(r.width, r.height, channels);
    if (bytes <= max_bytes) return std::nullopt;
    auto p = make_problem(
        ProblemKind::kBadRequest,
        "raw render answer of " + std::to_string(bytes) + " bytes (" + std::to_string(r.width) +
            " x " + std::to_string(r.height) + (s.region ? " tile" : " frame") + " x " +
            std::to_string(channels) + " floats + a " +
            std::to_string(proto::kRawImageHeaderBytes) +
            "-byte header) exceeds max_raw_render_bytes " + std::to_string(max_bytes) +
            "; ask for smaller tiles (kdrt render --split N renders a frame as N bands)");
    p.limit = max_bytes;
    return p;
}

/// The shape a render request body may have before it is parsed (it has about 20 values).
constexpr JsonShapeLimits kRenderJsonShape{.max_depth = 8, .max_values = 256};

proto::Problem unknown_job_problem(const std::string& id) {
    return make_problem(
        ProblemKind::kUnknownJob,
        std::string(proto::api_errors::kUnknownJob) + " " + id +
            " (it never existed, expired after job_ttl_s, or was forgotten to keep finished "
            "images within job_result_bytes)");
}

/// A raw answer (sync or a job's result) names the zlib level this server encodes the render's
/// PNG with, so a client that stitches raw regions encodes the frame as the server would.
void name_png_level(httplib::Response& res, proto::ImageFormat format,
                    const proto::ImageEncodeOptions& encode) {
    if (format == proto::ImageFormat::kRaw)
        res.set_header("X-Kdrt-Png-Compression", std::to_string(encode.png_compression));
}

}  // namespace

void Routes::render(const httplib::Request& req, httplib::Response& res,
                    const httplib::ContentReader& reader) {
    auto request = read_render_request(req, res, reader, false);
    if (!request) return;
    const std::string mesh = request->mesh;
    auto job = make_render_job(req, res, std::move(*request), [&](RenderJob& out) {
        auto tree = svc_.cache.acquire(mesh);
        if (!tree) {
            reply_problem(req, res, mesh_lookup_problem(tree.error(), mesh));
            return false;
        }
        out.mesh = mesh;
        out.tree = std::move(*tree);
        return true;
    });
    if (!job) return;
    run_render(req, res, std::move(*job));
}

void Routes::run_render(const httplib::Request& req, httplib::Response& res, RenderJob job) {
    if (prefers_async(req)) return submit_job(req, res, std::move(job));
    // At most max_renders run at once and max_queued wait; the rest are shed now.
    auto slot = svc_.renders.enter(svc_.shutting_down);
    if (!slot) {
        auto p = make_problem(ProblemKind::kOverCapacity,
                              std::to_string(svc_.renders.running_limit()) +
                                  " renders are running (max_renders) and " +
                                  std::to_string(svc_.renders.queue_limit()) +
                                  " waiting (max_queued); retry later");
        p.retry_after = 1;
        p.limit = svc_.renders.running_limit();
        return reply_problem(req, res, std::move(p));
    }
    render_now(req, res, job);
}

std::optional<proto::RenderRequest> Routes::read_render_request(
    const httplib::Request& req, httplib::Response& res, const httplib::ContentReader& reader,
    bool scene) {
    if (proto::media_type_essence(req.get_header_value("Content-Type")) != proto::kJsonMediaType) {
        reply_problem(
            req, res,
            make_problem(ProblemKind::kUnsupportedMediaType,
                         "render " + std::string(proto::api_errors::kUnsupportedJsonType)));
        return std::nullopt;
    }
    auto body = read_body(req, res, reader, svc_.config.max_json_bytes, svc_.config.max_json_bytes,
                          svc_.store.tmp_dir().string(), "a JSON request (max_json_bytes)");
    if (!body) return std::nullopt;
    // A render request is a few dozen values, 3 levels deep; it is parsed into a DOM, so its
    // shape is bounded first (kRenderJsonShape).
    if (auto shape = json_shape_error(as_text(body->bytes()), kRenderJsonShape)) {
        reply_problem(req, res,
                      make_problem(ProblemKind::kBadRequest,
                                   "render request: " + shape->detail + " (a render request has " +
                                       std::to_string(kRenderJsonShape.max_values) +
                                       " values at most, nested " +
                                       std::to_string(kRenderJsonShape.max_depth) + " deep)"));
        return std::nullopt;
    }
    const proto::RenderLimits limits{svc_.config.max_image_width, svc_.config.max_image_height,
                                     svc_.config.max_spp};
    auto request = proto::decode_render_request(as_text(body->bytes()), limits, scene);
    if (!request) {
        reply_problem(req, res, make_problem(ProblemKind::kBadRequest, request.error().detail));
        return std::nullopt;
    }
    return std::move(*request);
}

std::optional<RenderJob> Routes::make_render_job(const httplib::Request& req,
                                                 httplib::Response& res,
                                                 proto::RenderRequest request,
                                                 const std::function<bool(RenderJob&)>& attach) {
    const proto::ImageFormat format = *proto::image_format_from_name(request.format);
    // Checked before the tree or scene is looked up or loaded: it depends on the request alone.
    if (auto p = raw_answer_problem(request, format, svc_.config.max_raw_render_bytes)) {
        reply_problem(req, res, std::move(*p));
        return std::nullopt;
    }
    // PNG, JPEG and EXR need the image module (kdrt/proto/image_module.h, loaded by the first
    // request that encodes one): without it the render is refused before any work (an async job
    // too), naming the paths tried and what to install.
    if (format != proto::ImageFormat::kRaw) {
        if (auto module = proto::image_module(); !module) {
            reply_problem(req, res, make_problem(ProblemKind::kInternal, module.error()));
            return std::nullopt;
        }
    }
    RenderJob job;
    if (!attach(job)) return std::nullopt;
    try {
        validate_render_settings(request.settings);
    } catch (const RenderError& e) {
        reply_problem(req, res, make_problem(ProblemKind::kBadRequest, e.what()));
        return std::nullopt;
    }
    const RenderCost cost = render_cost(request.settings);
    if (cost.rays > svc_.config.max_render_rays) {
        auto p = make_problem(ProblemKind::kBadRequest,
                              "render cost " + std::to_string(cost.rays) + " rays (" +
                                  std::to_string(cost.pixels) + " pixels x " +
                                  std::to_string(request.settings.spp) + " spp x " +
                                  std::to_string(cost.rays_per_sample) +
                                  " rays per sample) exceeds max_render_rays " +
                                  std::to_string(svc_.config.max_render_rays));
        p.limit = svc_.config.max_render_rays;
        reply_problem(req, res, std::move(p));
        return std::nullopt;
    }
    proto::ImageEncodeOptions encode;
    encode.png_compression =
        request.compression.value_or(static_cast<int>(svc_.config.png_compression));
    job.settings = request.settings;
    job.format = format;
    job.encode = encode;
    return job;
}

void Routes::render_now(const httplib::Request& req, httplib::Response& res, const RenderJob& job) {
    // A render whose client has gone is cancelled at its next tile (checked with each progress
    // report, about every 1/256 of the work).
    std::atomic<bool> cancel{false};
    RenderControl control;
    control.cancel = &cancel;
    control.progress = [gone = client_gone_check(), &cancel](double) {
        if (!cancel.load(std::memory_order_relaxed) && gone()) cancel = true;
    };
    proto::Result<RenderedImage, std::string> image = proto::Err{std::string()};
    try {
        image = render_and_encode(svc_.compute, job, control);
    } catch (const RenderCancelled&) {
        log_event(LogLevel::kInfo, "render cancelled: the client closed the connection",
                  {{"id", request_context().request_id}});
        res.set_header("Connection", "close");
        return reply_problem(req, res,
                             make_problem(ProblemKind::kBadRequest,
                                          "the client closed the connection; render cancelled"));
    }
    if (!image) return reply_problem(req, res, make_problem(ProblemKind::kInternal, image.error()));
    svc_.metrics.record_render(image->stats.rays, image->stats.seconds, std::nullopt);
    request_context().rays = image->stats.rays;
    res.set_header("X-Render-Ms", std::to_string(image->stats.seconds * 1e3));
    res.set_header("X-Encode-Ms", std::to_string(image->encode_ms));
    name_png_level(res, job.format, job.encode);
    reply_bytes(res, std::move(image->bytes), proto::image_media_type(job.format));
}

void Routes::submit_job(const httplib::Request& req, httplib::Response& res, RenderJob job) {
    auto status = svc_.jobs.submit(std::move(job));
    if (!status) {
        auto p = make_problem(ProblemKind::kOverCapacity, status.error() + "; retry later");
        p.retry_after = 1;
        p.limit = svc_.config.max_jobs;
        return reply_problem(req, res, std::move(p));
    }
    res.set_header("Location", "/v1/jobs/" + status->id);
    res.set_header("Preference-Applied", "respond-async");
    reply_json(res, 202, proto::encode_job_status(*status));
}

void Routes::get_job(const httplib::Request& req, httplib::Response& res) {
    const std::string id = req.matches[1];
    const auto status = svc_.jobs.status(id);
    if (!status) return reply_problem(req, res, unknown_job_problem(id));
    reply_json(res, 200, proto::encode_job_status(*status));
}

void Routes::delete_job(const httplib::Request& req, httplib::Response& res) {
    const std::string id = req.matches[1];
    proto::JobStatus status;
    switch (svc_.jobs.cancel(id, &status)) {
        case JobQueue::CancelOutcome::kUnknown:
            return reply_problem(req, res, unknown_job_problem(id));
        case JobQueue::CancelOutcome::kCancelling:
            return reply_json(res, 202, proto::encode_job_status(status));
        case JobQueue::CancelOutcome::kRemoved:
            res.status = 204;
            return;
    }
}

void Routes::job_result(const httplib::Request& req, httplib::Response& res) {
    const std::string id = req.matches[1];
    const auto out = svc_.jobs.output(id);
    if (!out) return reply_problem(req, res, unknown_job_problem(id));
    if (out->status.state != proto::JobState::kDone) {
        std::string detail =
            "job " + id + " is " + std::string(proto::job_state_name(out->status.state));
        if (out->status.state == proto::JobState::kRunning ||
            out->status.state == proto::JobState::kQueued)
            detail += " (progress " + std::to_string(out->status.progress) + ")";
        if (!out->status.error.empty()) detail += ": " + out->status.error;
        return reply_problem(
            req, res,
            make_problem(ProblemKind::kJobNotDone,
                         detail + " and " + std::string(proto::api_errors::kJobNotDone)));
    }
    // Sent from a string, not streamed: GET routes are not held back by the shutdown sequence.
    res.status = 200;
    name_png_level(res, out->format, out->encode);
    res.set_content(reinterpret_cast<const char*>(out->image->data()), out->image->size(),
                    std::string(proto::image_media_type(out->format)));
}

}  // namespace kdrt::server
