#include "http_util.h"

#include <arpa/inet.h>
#include <dirent.h>
#include <netdb.h>
#include <poll.h>
#include <sys/socket.h>
#include <sys/stat.h>
#include <unistd.h>

#include <cerrno>
#include <cstdlib>

#include "problems.h"

namespace kdrt::server {
namespace {

/// Bodies up to this size are read and dropped after an early error, so the connection stays
/// usable and clients that only read the reply after sending everything see it (64 MiB drain
/// in ~30 ms on loopback). Larger ones get `Connection: close` instead.
constexpr uint64_t kDrainLimit = 64u << 20;

/// Responses up to this size are sent from a string in one write.
constexpr size_t kInlineResponseBytes = 64u << 10;

/// The numeric host and port of a socket address, as httplib formats remote_addr/local_addr.
bool numeric_address(const sockaddr_storage& addr, socklen_t len, std::string& host, int& port) {
    char buffer[NI_MAXHOST];
    if (::getnameinfo(reinterpret_cast<const sockaddr*>(&addr), len, buffer, sizeof buffer, nullptr,
                      0, NI_NUMERICHOST) != 0)
        return false;
    host = buffer;
    if (addr.ss_family == AF_INET)
        port = ntohs(reinterpret_cast<const sockaddr_in*>(&addr)->sin_port);
    else if (addr.ss_family == AF_INET6)
        port = ntohs(reinterpret_cast<const sockaddr_in6*>(&addr)->sin6_port);
    else
        return false;
    return true;
}

/// True when `fd` is a connected TCP socket whose two ends are the request's.
bool is_connection_of(int fd, const httplib::Request& req) {
    sockaddr_storage addr{};
    socklen_t len = sizeof addr;
    std::string host;
    int port = 0;
    if (::getpeername(fd, reinterpret_cast<sockaddr*>(&addr), &len) != 0) return false;
    if (!numeric_address(addr, len, host, port) || port != req.remote_port ||
        host != req.remote_addr)
        return false;
    len = sizeof addr;
    if (::getsockname(fd, reinterpret_cast<sockaddr*>(&addr), &len) != 0) return false;
    return numeric_address(addr, len, host, port) && port == req.local_port &&
           host == req.local_addr;
}

/// The process's descriptor for the request's connection, or -1 (none, or more than one).
int find_connection_socket(const httplib::Request& req) {
    // httplib serves a connection on one thread from accept to close, so the socket found for
    // the previous request on this thread is checked first.
    thread_local int cached = -1;
    if (cached >= 0 && is_connection_of(cached, req)) return cached;
    DIR* dir = ::opendir("/proc/self/fd");
    if (!dir) return -1;
    int found = -1, matches = 0;
    while (const dirent* entry = ::readdir(dir)) {
        char* end = nullptr;
        const long fd = std::strtol(entry->d_name, &end, 10);
        if (*end != '\0' || end == entry->d_name || fd == ::dirfd(dir)) continue;
        struct stat st {};
        if (::fstat(static_cast<int>(fd), &st) != 0 || !S_ISSOCK(st.st_mode)) continue;
        if (is_connection_of(static_cast<int>(fd), req)) {
            found = static_cast<int>(fd);
            ++matches;
        }
    }
    ::closedir(dir);
    if (matches != 1) return -1;
    cached = found;
    return found;
}

}  // namespace

std::optional<DirectBody> direct_body(const httplib::Request& req, int read_timeout_s) {
    // The buffering this relies on was checked in cpp-httplib 0.11.4 (Debian 12's).
    if (std::string_view(CPPHTTPLIB_VERSION) != "0.11.4") return std::nullopt;
    if (!req.has_header("Content-Length") || req.has_header("Transfer-Encoding"))
        return std::nullopt;
    const std::string encoding = req.get_header_value("Content-Encoding");
    if (!encoding.empty() && encoding != "identity") return std::nullopt;
    if (req.remote_port <= 0 || req.local_port <= 0) return std::nullopt;
    const int fd = find_connection_socket(req);
    if (fd < 0) return std::nullopt;
    return DirectBody{fd, read_timeout_s};
}

ssize_t receive_some(const DirectBody& body, std::byte* out, size_t size) {
    for (;;) {
        const ssize_t n = ::recv(body.fd, out, size, MSG_DONTWAIT);
        if (n >= 0) return n;
        if (errno == EINTR) continue;
        if (errno != EAGAIN && errno != EWOULDBLOCK) return -1;
        pollfd p{body.fd, POLLIN, 0};
        const int ready = ::poll(&p, 1, body.timeout_s * 1000);
        if (ready < 0 && errno == EINTR) continue;
        if (ready <= 0) return -1;
    }
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

void reply_buffer(httplib::Response& res, AlignedBuffer buffer, size_t size,
                  std::string_view content_type, BufferPool* pool) {
    res.status = 200;
    if (size <= kInlineResponseBytes) {
        res.set_content(reinterpret_cast<const char*>(buffer.data()), size,
                        std::string(content_type));
        if (pool) pool->give(std::move(buffer));
        return;
    }
    std::shared_ptr<AlignedBuffer> data(new AlignedBuffer(std::move(buffer)),
                                        [pool](AlignedBuffer* b) {
                                            if (pool) pool->give(std::move(*b));
                                            delete b;
                                        });
    res.set_content_provider(size, std::string(content_type),
                             [data](size_t offset, size_t length, httplib::DataSink& sink) {
                                 return sink.write(
                                     reinterpret_cast<const char*>(data->data()) + offset, length);
                             });
}

void discard_body(const httplib::Request& req, httplib::Response& res,
                  const httplib::ContentReader& reader) {
    const bool chunked =
        req.get_header_value("Transfer-Encoding").find("chunked") != std::string::npos;
    const uint64_t length = req.get_header_value<uint64_t>("Content-Length");
    if (!chunked && length <= kDrainLimit) {
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
        // The connection broke or the framing was invalid; httplib set 400 or 413.
        reply_problem(req, res,
                      res.status == 413 ? body_too_large_problem(limit, what)
                                        : make_problem(proto::ProblemKind::kBadRequest,
                                                       "the request body could not be read"));
        res.set_header("Connection", "close");
        return nullptr;
    }
    if (auto finished = body->finish(); !finished) {
        reply_problem(req, res, make_problem(proto::ProblemKind::kInternal, finished.error()));
        res.set_header("Connection", "close");
        return nullptr;
    }
    return body;
}

}  // namespace kdrt::server
