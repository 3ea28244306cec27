#include "http/http_util.h"

#include <algorithm>
#include <memory>

#include "http/httplib_internals.h"
#include "http/problems.h"

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
    return req.get_header_value<uint64_t>("Content-Length");
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

void reply_json(httplib::Response& res, int status, std::string json) {
    res.status = status;
    res.body = std::move(json);
    res.set_header("Content-Type", "application/json");
}

void reply_bytes(httplib::Response& res, std::vector<std::byte> bytes,
                 std::string_view content_type, VectorPool<std::byte>* pool) {
    res.status = 200;
    if (bytes.size() <= kInlineResponseBytes) {
        res.set_content(reinterpret_cast<const char*>(bytes.data()), bytes.size(),
                        std::string(content_type));
        return;
    }
    std::shared_ptr<std::vector<std::byte>> data(new std::vector<std::byte>(std::move(bytes)),
                                                 [pool](std::vector<std::byte>* v) {
                                                     if (pool) pool->give(std::move(*v));
                                                     delete v;
                                                 });
    res.set_content_provider(data->size(), std::string(content_type),
                             [data](size_t offset, size_t length, httplib::DataSink& sink) {
                                 constexpr size_t kChunk = 4u << 20;
                                 return sink.write(
                                     reinterpret_cast<const char*>(data->data()) + offset,
                                     std::min(length, kChunk));
                             });
}

void reply_buffer(httplib::Response& res, PooledBuffer buffer, size_t size,
                  std::string_view content_type) {
    res.status = 200;
    if (size <= kInlineResponseBytes) {
        res.set_content(reinterpret_cast<const char*>(buffer.data()), size,
                        std::string(content_type));
        return;
    }
    auto data = std::make_shared<PooledBuffer>(std::move(buffer));
    res.set_content_provider(size, std::string(content_type),
                             [data](size_t offset, size_t length, httplib::DataSink& sink) {
                                 return sink.write(
                                     reinterpret_cast<const char*>(data->data()) + offset, length);
                             });
}

proto::Problem body_timeout_problem() {
    return make_problem(proto::ProblemKind::kRequestTimeout,
                        "the request body did not arrive within request_timeout_s");
}

void discard_body(const httplib::Request& req, httplib::Response& res,
                  const httplib::ContentReader& reader) {
    const uint64_t length = req.get_header_value<uint64_t>("Content-Length");
    if (!is_chunked(req) && length <= kDrainBodyBytes) {
        if (length > 0) reader([](const char*, size_t) { return true; });
        return;
    }
    res.set_header("Connection", "close");
}

std::unique_ptr<RequestBody> read_body(const httplib::Request& req, httplib::Response& res,
                                       const httplib::ContentReader& reader, uint64_t limit,
                                       uint64_t memory_bytes, const std::string& spool_dir,
                                       const std::string& what, std::vector<std::byte> buffer) {
    const uint64_t declared = req.get_header_value<uint64_t>("Content-Length");
    if (declared > limit) {
        discard_body(req, res, reader);
        reply_problem(req, res, body_too_large_problem(limit, what));
        return nullptr;
    }
    auto body =
        std::make_unique<RequestBody>(limit, memory_bytes, spool_dir, declared, std::move(buffer));
    RequestContext& context = request_context();
    const bool has_body = declared > 0 || req.has_header("Transfer-Encoding");
    const bool read_ok = !has_body || reader([&](const char* data, size_t size) {
        context.bytes_in += size;
        return body->append(data, size);
    });
    if (body->too_large()) {
        reply_problem(req, res, body_too_large_problem(limit, what));
        res.set_header("Connection", "close");
        return nullptr;
    }
    if (!read_ok && body->error().empty()) {
        // The connection broke, the request's deadline passed, or the framing was invalid
        // (httplib set 400 or 413).
        reply_problem(req, res,
                      request_deadline_passed() ? body_timeout_problem()
                      : res.status == 413       ? body_too_large_problem(limit, what)
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
