#include "http/http_util.h"

#include <algorithm>
#include <charconv>
#include <memory>

#include "http/http_front.h"
#include "http/problems.h"
#include "kdrt/proto/text.h"

namespace kdrt::server {
namespace {

/// Responses up to this size are sent from a string in one write.
constexpr size_t kInlineResponseBytes = 64u << 10;

}  // namespace

bool is_chunked(const httplib::Request& req) {
    return req.get_header_value("Transfer-Encoding").find("chunked") != std::string::npos;
}

std::optional<uint64_t> declared_body_bytes(const httplib::Request& req) {
    if (is_chunked(req) || !req.has_header("Content-Length")) return std::nullopt;
    // The front admits only one Content-Length of decimal digits (request_head.cpp).
    const std::string value = req.get_header_value("Content-Length");
    uint64_t bytes = 0;
    const auto [end, ec] = std::from_chars(value.data(), value.data() + value.size(), bytes);
    if (ec != std::errc() || end != value.data() + value.size()) return std::nullopt;
    return bytes;
}

RequestContext& request_context() noexcept {
    thread_local RequestContext context;
    return context;
}

void reply_problem(const httplib::Request& req, httplib::Response& res, proto::Problem problem) {
    problem.instance = req.path;
    problem.request_id = request_context().request_id;
    res.status = problem.status();
    if (problem.retry_after) res.set_header("Retry-After", std::to_string(*problem.retry_after));
    if (problem.kind == proto::ProblemKind::kUnauthorized)
        res.set_header("WWW-Authenticate", "Bearer realm=\"kdrt\"");
    res.body = proto::encode_problem(problem);
    res.set_header("Content-Type", std::string(proto::kProblemMediaType));
}

bool has_media_type(const httplib::Request& req, httplib::Response& res, std::string_view type,
                    std::string_view route) {
    const std::string given = req.get_header_value("Content-Type");
    if (proto::media_type_essence(given) == type) return true;
    reply_problem(req, res,
                  make_problem(proto::ProblemKind::kUnsupportedMediaType,
                               std::string(route) + " expects Content-Type " + std::string(type) +
                                   ", not " + proto::quote_value(given)));
    return false;
}

std::function<std::optional<std::string>(std::string_view)> query_params(
    const httplib::Request& req) {
    return [&req](std::string_view name) -> std::optional<std::string> {
        const std::string key(name);
        if (!req.has_param(key)) return std::nullopt;
        return req.get_param_value(key);
    };
}

void reply_json(httplib::Response& res, int status, std::string json) {
    res.status = status;
    res.body = std::move(json);
    res.set_header("Content-Type", "application/json");
}

void reply_bytes(httplib::Response& res, std::vector<std::byte> bytes,
                 std::string_view content_type, VectorPool<std::byte>* pool) {
    if (bytes.size() <= kInlineResponseBytes) {
        res.status = 200;
        res.set_content(reinterpret_cast<const char*>(bytes.data()), bytes.size(),
                        std::string(content_type));
        return;
    }
    std::shared_ptr<std::vector<std::byte>> data(new std::vector<std::byte>(std::move(bytes)),
                                                 [pool](std::vector<std::byte>* v) {
                                                     if (pool) pool->give(std::move(*v));
                                                     delete v;
                                                 });
    const std::span<const std::byte> view(*data);
    reply_from_memory(res, view, std::move(data), content_type);
}

void reply_buffer(httplib::Response& res, PooledBuffer buffer, size_t size,
                  std::string_view content_type) {
    if (size <= kInlineResponseBytes) {
        res.status = 200;
        res.set_content(reinterpret_cast<const char*>(buffer.data()), size,
                        std::string(content_type));
        return;
    }
    auto data = std::make_shared<PooledBuffer>(std::move(buffer));
    const std::span<const std::byte> view(data->data(), size);
    reply_from_memory(res, view, std::move(data), content_type);
}

proto::Problem body_timeout_problem() {
    return make_problem(proto::ProblemKind::kRequestTimeout,
                        "the request body did not arrive within request_timeout_s");
}

std::unique_ptr<RequestBody> read_body(const httplib::Request& req, httplib::Response& res,
                                       const httplib::ContentReader& reader, uint64_t limit,
                                       uint64_t memory_bytes, const std::string& spool_dir,
                                       const std::string& what, std::vector<std::byte> buffer,
                                       const BodyProgress& progress) {
    const uint64_t declared = declared_body_bytes(req).value_or(0);
    if (declared > limit) {
        reply_problem(req, res, body_too_large_problem(limit, what));
        return nullptr;
    }
    auto body =
        std::make_unique<RequestBody>(limit, memory_bytes, spool_dir, declared, std::move(buffer));
    RequestContext& context = request_context();
    const bool has_body = declared > 0 || req.has_header("Transfer-Encoding");
    std::optional<proto::Problem> stopped;
    const bool read_ok = !has_body || reader([&](const char* data, size_t size) {
        context.bytes_in += size;
        if (!body->append(data, size)) return false;
        if (progress) stopped = progress(body->size());
        return !stopped;
    });
    if (stopped) {
        reply_problem(req, res, std::move(*stopped));
        return nullptr;
    }
    if (body->too_large()) {
        reply_problem(req, res, body_too_large_problem(limit, what));
        res.set_header("Connection", "close");
        return nullptr;
    }
    if (!read_ok && body->error().empty()) {
        // The connection broke, the request's deadline passed, or the chunked framing was
        // invalid.
        reply_problem(req, res,
                      request_deadline_passed()
                          ? body_timeout_problem()
                          : make_problem(proto::ProblemKind::kBadRequest,
                                         "the request body could not be read"));
        res.set_header("Connection", "close");
        return nullptr;
    }
    if (auto finished = body->finish(); !finished) {
        reply_problem(req, res,
                      make_problem(body->no_space() ? proto::ProblemKind::kInsufficientStorage
                                                    : proto::ProblemKind::kInternal,
                                   finished.error()));
        res.set_header("Connection", "close");
        return nullptr;
    }
    return body;
}

}  // namespace kdrt::server
