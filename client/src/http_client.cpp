// kdrt::Client on cpp-httplib: connection pool, retries, chunked ray batches. The only library
// file that includes httplib.h; every body is encoded and decoded by kdrt::proto. Ray batches
// over plain http go through http_direct.h's connections instead (big reads and writes).

#include <httplib.h>
#include <netdb.h>
#include <sys/socket.h>
#include <sys/time.h>
#include <unistd.h>

#include <algorithm>
#include <atomic>
#include <cerrno>
#include <charconv>
#include <condition_variable>
#include <cstdlib>
#include <cstring>
#include <fstream>
#include <limits>
#include <mutex>
#include <stdexcept>
#include <thread>

#include "client_access.h"
#include "http_direct.h"
#include "kdrt/client/client.h"
#include "kdrt/proto/errors.h"
#include "kdrt/proto/file_io.h"
#include "kdrt/proto/multi_hit.h"
#include "kdrt/proto/problem.h"
#include "kdrt/proto/raw_image.h"
#include "kdrt/proto/ray_batch.h"

namespace kdrt {
namespace {

using Millis = std::chrono::milliseconds;

/// Bytes handed to httplib per content-provider call when a file is streamed.
constexpr size_t kUploadBlockBytes = size_t{1} << 20;

/// Largest answer read from a direct connection when it is not the batch's answer (a
/// problem+json refusal, a proxy's error page).
constexpr size_t kMaxErrorBodyBytes = size_t{1} << 20;

/// Largest image read from a direct connection: an 8192 x 8192 RGBA float EXR is 1 GiB before
/// compression.
constexpr uint64_t kMaxImageBodyBytes = uint64_t{4} << 30;

/// Percent-encodes one path segment (an id from the caller): only RFC 3986 unreserved
/// characters stay as they are, so "../x" or "a/b" cannot leave the route.
std::string escape_segment(std::string_view segment) {
    static constexpr char kHex[] = "0123456789ABCDEF";
    std::string out;
    for (const char c : segment) {
        const auto u = static_cast<unsigned char>(c);
        if ((u >= 'a' && u <= 'z') || (u >= 'A' && u <= 'Z') || (u >= '0' && u <= '9') ||
            u == '-' || u == '.' || u == '_' || u == '~') {
            out.push_back(c);
        } else {
            out.push_back('%');
            out.push_back(kHex[u >> 4]);
            out.push_back(kHex[u & 15]);
        }
    }
    return out;
}

std::span<const std::byte> as_bytes(const std::string& text) noexcept {
    return {reinterpret_cast<const std::byte*>(text.data()), text.size()};
}

std::string_view as_view(const std::vector<std::byte>& bytes) {
    return {reinterpret_cast<const char*>(bytes.data()), bytes.size()};
}

std::vector<std::byte> to_byte_vector(const std::string& text) {
    const auto bytes = as_bytes(text);
    return {bytes.begin(), bytes.end()};
}

/// 502 Bad Gateway, 504 Gateway Timeout: a proxy in front of replicas lost the request's replica
/// (docs/scale-out.md). Retried like a transport error, on idempotent requests only.
bool gateway_failure(int status) { return status == 502 || status == 504; }

/// Retry-After in delta-seconds form; nullopt for an HTTP-date or garbage (then the backoff
/// applies).
std::optional<uint32_t> parse_retry_after(const std::string& value) {
    uint32_t seconds = 0;
    const char* end = value.data() + value.size();
    const auto [ptr, ec] = std::from_chars(value.data(), end, seconds);
    if (ec != std::errc() || ptr != end) return std::nullopt;
    return seconds;
}

/// The httplib error a direct-transport failure stands for, so both transports retry the same
/// failures and describe them in the same words (kProtocol is not one: it is a bad answer).
httplib::Error as_httplib_error(detail::DirectFailure failure) noexcept {
    switch (failure) {
        case detail::DirectFailure::kConnect:
            return httplib::Error::Connection;
        case detail::DirectFailure::kConnectTimeout:
            return httplib::Error::ConnectionTimeout;
        case detail::DirectFailure::kWrite:
            return httplib::Error::Write;
        case detail::DirectFailure::kRead:
            return httplib::Error::Read;
        case detail::DirectFailure::kNone:
        case detail::DirectFailure::kProtocol:
            break;
    }
    return httplib::Error::Unknown;
}

/// True for httplib errors where the request never reached the server (always safe to resend).
bool failed_before_sending(httplib::Error error) noexcept {
    return error == httplib::Error::Connection || error == httplib::Error::ConnectionTimeout ||
           error == httplib::Error::BindIPAddress || error == httplib::Error::SSLConnection;
}

/// True for httplib errors of the transport (connection reset or timed out mid-exchange).
bool transport_failure(httplib::Error error) noexcept {
    return failed_before_sending(error) || error == httplib::Error::Read ||
           error == httplib::Error::Write;
}

/// What went wrong, in words: httplib's error names ("Connection", "Read") say little.
std::string describe(httplib::Error error) {
    switch (error) {
        case httplib::Error::Connection:
            return "could not connect";
        case httplib::Error::ConnectionTimeout:
            return "the connection timed out";
        case httplib::Error::Read:
            return "the connection closed or timed out while reading the answer";
        case httplib::Error::Write:
            return "the connection closed or timed out while sending the request";
        case httplib::Error::SSLConnection:
            return "the TLS handshake failed";
        case httplib::Error::SSLServerVerification:
            return "the server's TLS certificate was not accepted";
        default:
            break;
    }
    return httplib::to_string(error);
}

/// Why a TCP connection to host:port fails ("Connection refused", "Name or service not known"),
/// found by trying once more with a plain blocking connect: httplib reports only that it failed.
/// Empty when this attempt succeeds (the failure was transient).
std::string connect_failure_reason(const std::string& host, int port,
                                   std::chrono::milliseconds timeout) {
    addrinfo hints{};
    hints.ai_family = AF_UNSPEC;
    hints.ai_socktype = SOCK_STREAM;
    addrinfo* found = nullptr;
    const std::string service = std::to_string(port);
    if (const int rc = ::getaddrinfo(host.c_str(), service.c_str(), &hints, &found); rc != 0)
        return rc == EAI_SYSTEM ? std::strerror(errno) : ::gai_strerror(rc);
    std::string reason;
    for (const addrinfo* ai = found; ai; ai = ai->ai_next) {
        const int fd = ::socket(ai->ai_family, ai->ai_socktype | SOCK_CLOEXEC, ai->ai_protocol);
        if (fd < 0) {
            reason = std::strerror(errno);
            continue;
        }
        timeval tv{};
        tv.tv_sec = static_cast<time_t>(timeout.count() / 1000);
        tv.tv_usec = static_cast<suseconds_t>((timeout.count() % 1000) * 1000);
        ::setsockopt(fd, SOL_SOCKET, SO_SNDTIMEO, &tv, sizeof tv);  // bounds a blocking connect
        const bool connected = ::connect(fd, ai->ai_addr, ai->ai_addrlen) == 0;
        const int os_error = errno;
        ::close(fd);
        if (connected) {
            reason.clear();
            break;
        }
        reason = os_error == EINPROGRESS || os_error == EAGAIN ? std::strerror(ETIMEDOUT)
                                                               : std::strerror(os_error);
    }
    ::freeaddrinfo(found);
    return reason;
}

/// One HTTP exchange as the retry loop sends it (possibly several times).
struct Exchange {
    const char* method = "GET";
    std::string path;  ///< API path, base path included
    httplib::Headers headers;
    std::string_view body;   ///< in-memory body (POST), unless `stream` is set
    size_t stream_size = 0;  ///< streamed body size
    httplib::ContentProvider
        stream;  ///< streamed body (file uploads); re-invoked from 0 on a retry
    std::string content_type;
    /// May the request be sent again after the connection failed once it was (maybe) sent?
    /// False for requests that are not idempotent (async render submissions).
    bool resend_after_transport_error = true;
    /// Retry 503 answers (all routes but /readyz, which asks "ready now?").
    bool retry_unavailable = true;
};

}  // namespace

struct Client::Impl {
    Impl(ServerUrl server, ClientOptions opts) : url(std::move(server)), options(std::move(opts)) {
        if (options.token.empty()) {
            if (const char* env = std::getenv("KDRT_TOKEN")) options.token = env;
        }
        origin = url.to_string();
        origin.resize(origin.size() - url.base_path.size());
        direct = url.scheme == "http";
        if (direct) {
            const bool ipv6 = url.host.find(':') != std::string::npos;
            direct_target =
                detail::DirectTarget{.host = url.host,
                                     .port = url.port,
                                     .host_header = (ipv6 ? "[" + url.host + "]" : url.host) + ":" +
                                                    std::to_string(url.port),
                                     .token = options.token,
                                     .connect_timeout = options.connect_timeout,
                                     .io_timeout = options.io_timeout};
        }
    }

    ServerUrl url;
    ClientOptions options;
    std::string origin;  ///< scheme://host:port

    std::mutex pool_mutex;
    std::vector<std::unique_ptr<httplib::Client>> idle;  ///< keep-alive connections not in use
    /// Ray batches over plain http use http_direct.h's connections (https stays on httplib).
    bool direct = false;
    detail::DirectTarget direct_target;
    /// A direct connection and its reused buffers, pooled like the httplib connections.
    struct DirectSlot {
        explicit DirectSlot(const detail::DirectTarget& target) : connection(target) {}
        detail::DirectConnection connection;
        detail::DirectResponse response;
        std::vector<std::byte> body;
    };
    std::vector<std::unique_ptr<DirectSlot>> idle_direct;
    /// distance(): the points per request a refusal for size taught (0: options.chunk_rays).
    std::atomic<size_t> distance_chunk_limit{0};

    /// A pooled connection, returned to the pool when the lease ends.
    class Lease {
    public:
        explicit Lease(Impl& impl) : impl_(impl), client_(impl.acquire()) {}
        ~Lease() { impl_.release(std::move(client_)); }
        Lease(const Lease&) = delete;
        Lease& operator=(const Lease&) = delete;
        httplib::Client& operator*() const noexcept { return *client_; }

    private:
        Impl& impl_;
        std::unique_ptr<httplib::Client> client_;
    };

    std::unique_ptr<httplib::Client> acquire() {
        {
            std::lock_guard lock(pool_mutex);
            if (!idle.empty()) {
                auto client = std::move(idle.back());
                idle.pop_back();
                return client;
            }
        }
        auto client = std::make_unique<httplib::Client>(origin);
        client->set_keep_alive(true);
        client->set_tcp_nodelay(true);
        client->set_connection_timeout(options.connect_timeout);
        client->set_read_timeout(options.io_timeout);
        client->set_write_timeout(options.io_timeout);
        if (!options.token.empty()) client->set_bearer_token_auth(options.token);
        return client;
    }

    void release(std::unique_ptr<httplib::Client> client) {
        std::lock_guard lock(pool_mutex);
        // More idle connections than chunks in flight would only hold server threads.
        if (idle.size() < std::max(1u, options.connections)) idle.push_back(std::move(client));
    }

    std::unique_ptr<DirectSlot> acquire_direct() {
        {
            std::lock_guard lock(pool_mutex);
            if (!idle_direct.empty()) {
                auto slot = std::move(idle_direct.back());
                idle_direct.pop_back();
                return slot;
            }
        }
        return std::make_unique<DirectSlot>(direct_target);
    }

    void release_direct(std::unique_ptr<DirectSlot> slot) {
        std::lock_guard lock(pool_mutex);
        if (idle_direct.size() < std::max(1u, options.connections))
            idle_direct.push_back(std::move(slot));
    }

    [[nodiscard]] std::string api(std::string_view path) const {
        return url.base_path + std::string(path);
    }

    [[nodiscard]] Millis backoff(unsigned retry) const {
        const auto initial = std::max<int64_t>(1, options.backoff_initial.count());
        int64_t delay = initial;
        for (unsigned i = 0; i < retry && delay < options.backoff_max.count(); ++i) delay *= 2;
        return Millis(std::min<int64_t>(delay, options.backoff_max.count()));
    }

    /// `reason`: the OS's word for the failure when the transport knows it (the direct one);
    /// for a failed connect without one, a plain connect is tried once more to find it.
    [[nodiscard]] Error transport_error(const Exchange& ex, httplib::Error error, unsigned attempts,
                                        const std::string& reason = {}) const {
        const bool connect = failed_before_sending(error);
        std::string what = describe(error);
        if (!reason.empty()) {
            what += ": " + reason;
        } else if (error == httplib::Error::Connection) {
            const std::string found =
                connect_failure_reason(url.host, url.port, options.connect_timeout);
            if (!found.empty()) what += ": " + found;
        }
        Error e = make_client_error(
            ErrorKind::kConnection, connect ? "cannot connect" : "connection failed",
            url.to_string() + ": " + what + " (" + ex.method + " " + ex.path + ", " +
                std::to_string(attempts) + (attempts == 1 ? " attempt)" : " attempts)"));
        e.attempts = attempts;
        return e;
    }

    /// Sends `ex` on `cli`, retrying connection errors and 503 answers with exponential backoff
    /// (Retry-After honoured). A 2xx answer is returned; any other status becomes its Error.
    Result<httplib::Response> send(httplib::Client& cli, const Exchange& ex) {
        const unsigned attempts_allowed = options.max_retries + 1;
        for (unsigned attempt = 1;; ++attempt) {
            httplib::Result res = [&] {
                const std::string_view method = ex.method;
                if (method == "GET") return cli.Get(ex.path, ex.headers);
                if (method == "DELETE") return cli.Delete(ex.path, ex.headers);
                if (method == "PATCH")
                    return cli.Patch(ex.path, ex.headers, ex.body.data(), ex.body.size(),
                                     ex.content_type);
                if (ex.stream)
                    return cli.Post(ex.path, ex.headers, ex.stream_size, ex.stream,
                                    ex.content_type);
                return cli.Post(ex.path, ex.headers, ex.body.data(), ex.body.size(),
                                ex.content_type);
            }();
            if (!res) {
                const httplib::Error error = res.error();
                const bool retriable =
                    failed_before_sending(error) ||
                    (ex.resend_after_transport_error && transport_failure(error));
                if (!retriable || attempt >= attempts_allowed)
                    return proto::Err{transport_error(ex, error, attempt)};
                std::this_thread::sleep_for(backoff(attempt - 1));
                continue;
            }
            httplib::Response& response = res.value();
            if (response.status >= 200 && response.status < 300) return std::move(response);
            if (gateway_failure(response.status) && ex.resend_after_transport_error &&
                attempt < attempts_allowed) {
                std::this_thread::sleep_for(backoff(attempt - 1));
                continue;
            }
            if (response.status == 503 && ex.retry_unavailable && attempt < attempts_allowed) {
                Millis delay = backoff(attempt - 1);
                if (const auto after = parse_retry_after(response.get_header_value("Retry-After")))
                    delay = std::min<Millis>(std::chrono::seconds(*after), options.max_retry_after);
                std::this_thread::sleep_for(delay);
                continue;
            }
            Error e =
                error_from_response(response.status, response.get_header_value("Content-Type"),
                                    response.body, response.get_header_value("X-Request-Id"));
            e.attempts = attempt;
            return proto::Err{std::move(e)};
        }
    }

    /// send() on a direct connection (`body` is the request body), with the same retries and
    /// errors. Idempotent requests only. The answer is left in slot.response.
    Result<void> send_direct(DirectSlot& slot, const Exchange& ex, std::span<const std::byte> body,
                             size_t max_body) {
        const unsigned attempts_allowed = options.max_retries + 1;
        std::string reason;
        for (unsigned attempt = 1;; ++attempt) {
            const detail::DirectFailure failure = slot.connection.request(
                ex.method, ex.path, ex.content_type, body, max_body, slot.response, reason);
            if (failure == detail::DirectFailure::kProtocol)
                return proto::Err{bad_response(ex, reason)};
            if (failure != detail::DirectFailure::kNone) {
                const httplib::Error error = as_httplib_error(failure);
                const bool retriable =
                    failed_before_sending(error) ||
                    (ex.resend_after_transport_error && transport_failure(error));
                if (!retriable || attempt >= attempts_allowed)
                    return proto::Err{transport_error(ex, error, attempt, reason)};
                std::this_thread::sleep_for(backoff(attempt - 1));
                continue;
            }
            const detail::DirectResponse& response = slot.response;
            if (response.status >= 200 && response.status < 300) return {};
            if (gateway_failure(response.status) && ex.resend_after_transport_error &&
                attempt < attempts_allowed) {
                std::this_thread::sleep_for(backoff(attempt - 1));
                continue;
            }
            if (response.status == 503 && ex.retry_unavailable && attempt < attempts_allowed) {
                Millis delay = backoff(attempt - 1);
                if (const auto after = parse_retry_after(response.retry_after))
                    delay = std::min<Millis>(std::chrono::seconds(*after), options.max_retry_after);
                std::this_thread::sleep_for(delay);
                continue;
            }
            const auto answer = response.body();
            Error e = error_from_response(
                response.status, response.content_type,
                std::string_view(reinterpret_cast<const char*>(answer.data()), answer.size()),
                response.request_id);
            e.attempts = attempt;
            return proto::Err{std::move(e)};
        }
    }

    Result<httplib::Response> send(const Exchange& ex) {
        Lease lease(*this);
        return send(*lease, ex);
    }

    [[nodiscard]] Error bad_response(const Exchange& ex, const std::string& why) const {
        return make_client_error(
            ErrorKind::kProtocol, "bad response",
            std::string(ex.method) + " " + ex.path + " from " + url.to_string() + ": " + why);
    }

    /// POSTs `rays` to `path` as KDRR batches of options.chunk_rays, one after another, and hands
    /// each answer to take(ex, answer body, rays in the chunk), which returns an error or nothing.
    template <class Take>
    Result<void> post_ray_chunks(const std::string& path, std::span<const Ray> rays, Take take) {
        size_t first = 0;
        do {
            const size_t count = std::min(options.chunk_rays, rays.size() - first);
            const std::vector<std::byte> body =
                proto::encode_rays(rays.subspan(first, count), false);
            Exchange ex;
            ex.method = "POST";
            ex.path = path;
            ex.body = as_view(body);
            ex.content_type = std::string(proto::kRaysMediaType);
            auto res = send(ex);
            if (!res) return proto::Err{std::move(res).error()};
            if (auto failed = take(ex, as_bytes(res->body), count)) return proto::Err{*failed};
            first += count;
        } while (first < rays.size());
        return {};
    }

    template <class T, class Decode>
    Result<T> json_call(const Exchange& ex, Decode decode) {
        auto res = send(ex);
        if (!res) return proto::Err{std::move(res).error()};
        auto decoded = decode(res->body);
        if (!decoded) return proto::Err{bad_response(ex, decoded.error())};
        return std::move(*decoded);
    }

    Result<MeshInfo> upload(Exchange ex) {
        ex.method = "POST";
        ex.path = api("/v1/meshes");
        return json_call<MeshInfo>(
            ex, [](const std::string& body) { return proto::decode_mesh_summary(body); });
    }

    /// Decodes one chunk's answer, checks the count and copies it into `out`.
    template <class T>
    Result<void> take_answer(const Exchange& ex, std::span<const std::byte> answer,
                             std::span<T> out) {
        const proto::DecodeLimits limits{.max_rays = static_cast<uint32_t>(out.size())};
        auto decoded = [&] {
            if constexpr (std::is_same_v<T, Hit>) {
                return proto::decode_hits(answer, limits);
            } else {
                return proto::decode_occlusion(answer, limits);
            }
        }();
        if (!decoded) return proto::Err{bad_response(ex, decoded.error().to_string())};
        if (decoded->size() != out.size())
            return proto::Err{bad_response(ex, std::to_string(decoded->size()) + " answers for " +
                                                   std::to_string(out.size()) + " rays")};
        std::copy(decoded->begin(), decoded->end(), out.begin());
        return {};
    }

    /// One chunk of a ray batch on a direct connection: the KDRR body encoded once and sent
    /// with the head in one write, the answer read with big reads into the slot's buffer.
    template <class T>
    Result<void> trace_chunk_direct(DirectSlot& slot, const std::string& path,
                                    std::span<const Ray> rays, bool occlusion, std::span<T> out) {
        slot.body = proto::encode_rays(rays, occlusion);
        Exchange ex;
        ex.method = "POST";
        ex.path = path;
        ex.content_type = std::string(proto::kRaysMediaType);
        // An answer of this batch has exactly this size; a problem+json refusal is small.
        const auto expected = static_cast<size_t>(proto::answer_body_size(
            occlusion ? proto::AnswerKind::kOcclusion : proto::AnswerKind::kHits, rays.size()));
        const size_t max_body = std::max(expected, kMaxErrorBodyBytes);
        auto sent = send_direct(slot, ex, slot.body, max_body);
        if (!sent) return proto::Err{std::move(sent).error()};
        return take_answer<T>(ex, slot.response.body(), out);
    }

    /// One chunk of a ray batch: POST, decode, check the count, copy into `out`.
    template <class T>
    Result<void> trace_chunk(httplib::Client& cli, const std::string& path,
                             std::span<const Ray> rays, bool occlusion, std::span<T> out) {
        const std::vector<std::byte> body = proto::encode_rays(rays, occlusion);
        Exchange ex;
        ex.method = "POST";
        ex.path = path;
        // Streamed from `body` (httplib copies an in-memory body into its request first).
        ex.stream_size = body.size();
        ex.stream = [&body](size_t offset, size_t length, httplib::DataSink& sink) {
            return sink.write(reinterpret_cast<const char*>(body.data()) + offset, length);
        };
        ex.content_type = std::string(proto::kRaysMediaType);
        auto res = send(cli, ex);
        if (!res) return proto::Err{std::move(res).error()};
        return take_answer<T>(ex, as_bytes(res->body), out);
    }

    /// A ray batch in chunks of options.chunk_rays, over up to options.connections connections.
    template <class T>
    Result<std::vector<T>> trace(std::string_view id, std::span<const Ray> rays, bool occlusion) {
        if (rays.size() > std::numeric_limits<uint32_t>::max())
            return proto::Err{
                make_client_error(ErrorKind::kInput, "too many rays",
                                  std::to_string(rays.size()) +
                                      " rays in one call; a batch holds at most 4294967295")};
        const std::string path = api("/v1/meshes/" + escape_segment(id) + "/intersect");
        // options.split parts at least, each with its own routing key (docs/scale-out.md).
        const size_t split = std::max<size_t>(options.split, 1);
        const size_t chunk =
            split > 1 ? std::clamp<size_t>((rays.size() + split - 1) / split, 1, options.chunk_rays)
                      : options.chunk_rays;
        const size_t chunks = rays.empty() ? 1 : (rays.size() - 1) / chunk + 1;
        const auto chunk_path = [&](size_t k) {
            if (split <= 1) return path;
            return path + "?route=" + escape_segment(id) + "." + std::to_string(k % split);
        };
        std::vector<T> out(rays.size());

        std::atomic<size_t> next{0};
        std::atomic<bool> failed{false};
        std::mutex error_mutex;
        std::optional<Error> error;
        size_t error_chunk = std::numeric_limits<size_t>::max();
        const auto worker = [&] {
            // One connection per worker: a direct one for plain http, else httplib's.
            std::unique_ptr<DirectSlot> slot = direct ? acquire_direct() : nullptr;
            std::optional<Lease> lease;
            if (!direct) lease.emplace(*this);
            struct ReleaseSlot {
                Impl& impl;
                std::unique_ptr<DirectSlot>& slot;
                ~ReleaseSlot() {
                    if (slot) impl.release_direct(std::move(slot));
                }
            } release_slot{*this, slot};
            while (!failed.load(std::memory_order_relaxed)) {
                const size_t k = next.fetch_add(1);
                if (k >= chunks) return;
                const size_t first = k * chunk;
                const size_t count = std::min(chunk, rays.size() - first);
                const auto part = rays.subspan(first, count);
                const auto into = std::span<T>(out).subspan(first, count);
                const std::string at = chunk_path(k);
                auto done = slot ? trace_chunk_direct<T>(*slot, at, part, occlusion, into)
                                 : trace_chunk<T>(**lease, at, part, occlusion, into);
                if (!done) {
                    std::lock_guard lock(error_mutex);
                    // Report the earliest failing chunk among those that failed (deterministic
                    // when every chunk fails the same way, e.g. an unknown id).
                    if (k < error_chunk) {
                        error_chunk = k;
                        error = std::move(done).error();
                    }
                    failed = true;
                    return;
                }
            }
        };
        const size_t threads = std::min<size_t>(options.connections, chunks);
        if (threads <= 1) {
            worker();
        } else {
            std::vector<std::jthread> pool;
            pool.reserve(threads - 1);
            for (size_t t = 1; t < threads; ++t) pool.emplace_back(worker);
            worker();
        }  // the jthreads join here
        if (error) return proto::Err{std::move(*error)};
        return out;
    }

    /// Headers of an image answer that render_split reads.
    struct ImageHeaders {
        std::string replica;          ///< X-Kdrt-Replica
        std::string png_compression;  ///< X-Kdrt-Png-Compression
    };

    /// An exchange whose answer is an image (a synchronous render, a job's result): on a direct
    /// connection for plain http (big reads), else through httplib. `required_status`, when
    /// nonzero, is the only 2xx status accepted. `headers`, when set, receives ImageHeaders.
    Result<std::vector<std::byte>> image_call(const Exchange& ex, std::string_view body,
                                              int required_status,
                                              ImageHeaders* headers = nullptr) {
        const auto check = [&](int status) -> Result<void> {
            if (required_status != 0 && status != required_status)
                return proto::Err{bad_response(ex, "status " + std::to_string(status) +
                                                       " instead of " +
                                                       std::to_string(required_status))};
            return {};
        };
        if (!direct) {
            auto res = send(ex);
            if (!res) return proto::Err{std::move(res).error()};
            if (auto ok = check(res->status); !ok) return proto::Err{std::move(ok).error()};
            if (headers)
                *headers = {res->get_header_value("X-Kdrt-Replica"),
                            res->get_header_value("X-Kdrt-Png-Compression")};
            return to_byte_vector(res->body);
        }
        struct SlotLease {
            Impl& impl;
            std::unique_ptr<DirectSlot> slot;
            ~SlotLease() { impl.release_direct(std::move(slot)); }
        } lease{*this, acquire_direct()};
        const size_t max_body = static_cast<size_t>(
            std::min<uint64_t>(kMaxImageBodyBytes, std::numeric_limits<size_t>::max()));
        auto sent = send_direct(*lease.slot, ex, std::as_bytes(std::span(body)), max_body);
        if (!sent) return proto::Err{std::move(sent).error()};
        if (auto ok = check(lease.slot->response.status); !ok)
            return proto::Err{std::move(ok).error()};
        if (headers)
            *headers = {lease.slot->response.replica, lease.slot->response.png_compression};
        const auto answer = lease.slot->response.body();
        return std::vector<std::byte>(answer.begin(), answer.end());
    }

    /// The render's mesh id rides along as ?route= (ignored by the server): a proxy in front of
    /// replicas hashes it, so the render runs where the mesh's tree is hot (docs/scale-out.md).
    /// `route_suffix` (".<k>" for region k of a split render) is appended to the mesh id.
    [[nodiscard]] Exchange render_exchange(const RenderRequest& request,
                                           std::string_view route_suffix = {}) const {
        Exchange ex;
        ex.method = "POST";
        ex.path =
            api("/v1/render?route=" + escape_segment(request.mesh) + escape_segment(route_suffix));
        ex.content_type = std::string(proto::kJsonMediaType);
        return ex;
    }
};

Client::Client(std::string_view url, ClientOptions options) {
    auto parsed = parse_server_url(url);
    if (!parsed) throw std::invalid_argument(parsed.error());
    if (options.chunk_rays == 0)
        throw std::invalid_argument("ClientOptions::chunk_rays must be at least 1");
    if (options.connections == 0)
        throw std::invalid_argument("ClientOptions::connections must be at least 1");
    impl_ = std::make_unique<Impl>(std::move(*parsed), std::move(options));
}

Client::~Client() = default;
Client::Client(Client&&) noexcept = default;
Client& Client::operator=(Client&&) noexcept = default;

const ServerUrl& Client::url() const noexcept { return impl_->url; }
const ClientOptions& Client::options() const noexcept { return impl_->options; }

Result<MeshInfo> Client::upload(const std::filesystem::path& file,
                                std::optional<proto::MeshFormat> format) {
    if (!format) format = proto::mesh_format_from_path(file);
    if (!format)
        return proto::Err{make_client_error(
            ErrorKind::kInput, "cannot upload",
            std::string(proto::errors::kUnknownExtension) + " of \"" + file.string() +
                "\" from its extension (expected .obj, .ply, .off, .stl, .raw or .kdrtmesh)")};
    std::error_code ec;
    if (std::filesystem::is_directory(file, ec))
        return proto::Err{make_client_error(ErrorKind::kInput, "cannot upload",
                                            "\"" + file.string() + "\" is a directory")};
    if (std::filesystem::exists(file, ec) && !std::filesystem::is_regular_file(file, ec)) {
        // A pipe or device (/dev/stdin): no size to stream against, so read it whole.
        auto bytes = proto::read_file_bytes(file);
        if (!bytes)
            return proto::Err{make_client_error(ErrorKind::kInput, "cannot upload", bytes.error())};
        return upload(*bytes, *format);
    }
    auto stream = std::make_shared<std::ifstream>(file, std::ios::binary);
    if (!*stream)
        return proto::Err{make_client_error(
            ErrorKind::kInput, "cannot upload",
            "cannot open \"" + file.string() + "\" for reading: " + std::strerror(errno))};
    const auto size = std::filesystem::file_size(file, ec);
    if (ec)
        return proto::Err{make_client_error(
            ErrorKind::kInput, "cannot upload",
            "cannot read the size of \"" + file.string() + "\": " + ec.message())};
    auto read_failed = std::make_shared<bool>(false);
    Exchange ex;
    ex.content_type = std::string(proto::mesh_media_type(*format));
    ex.stream_size = static_cast<size_t>(size);
    ex.stream = [stream, read_failed, block = std::vector<char>()](
                    size_t offset, size_t length, httplib::DataSink& sink) mutable {
        block.resize(std::min(length, kUploadBlockBytes));
        stream->clear();
        stream->seekg(static_cast<std::streamoff>(offset));
        stream->read(block.data(), static_cast<std::streamsize>(block.size()));
        if (stream->gcount() != static_cast<std::streamsize>(block.size())) {
            *read_failed = true;  // the file shrank or failed while it was sent
            return false;
        }
        return sink.write(block.data(), block.size());
    };
    auto result = impl_->upload(std::move(ex));
    if (!result && *read_failed)
        return proto::Err{
            make_client_error(ErrorKind::kInput, "cannot upload",
                              "reading \"" + file.string() + "\" failed while it was sent")};
    return result;
}

Result<MeshInfo> Client::upload(const Mesh& mesh) {
    std::vector<std::byte> bytes;
    try {
        bytes = proto::write_mesh(mesh, proto::MeshFormat::kRaw);
    } catch (const std::invalid_argument& e) {
        return proto::Err{make_client_error(ErrorKind::kInput, "cannot upload",
                                            std::string("malformed mesh: ") + e.what())};
    }
    return upload(bytes, proto::MeshFormat::kRaw);
}

Result<MeshInfo> Client::upload(std::span<const std::byte> bytes, proto::MeshFormat format) {
    Exchange ex;
    ex.body = {reinterpret_cast<const char*>(bytes.data()), bytes.size()};
    ex.content_type = std::string(proto::mesh_media_type(format));
    return impl_->upload(std::move(ex));
}

Result<std::vector<MeshInfo>> Client::meshes() {
    Exchange ex;
    ex.path = impl_->api("/v1/meshes");
    return impl_->json_call<std::vector<MeshInfo>>(
        ex, [](const std::string& b) { return proto::decode_mesh_list(b); });
}

Result<MeshInfo> Client::mesh(std::string_view id) {
    Exchange ex;
    ex.path = impl_->api("/v1/meshes/" + escape_segment(id));
    return impl_->json_call<MeshInfo>(
        ex, [](const std::string& b) { return proto::decode_mesh_summary(b); });
}

Result<void> Client::remove(std::string_view id) {
    Exchange ex;
    ex.method = "DELETE";
    ex.path = impl_->api("/v1/meshes/" + escape_segment(id));
    auto res = impl_->send(ex);
    if (!res) return proto::Err{std::move(res).error()};
    return {};
}

Result<std::vector<Hit>> Client::intersect(std::string_view id, std::span<const Ray> rays) {
    return impl_->trace<Hit>(id, rays, false);
}

Result<std::vector<uint8_t>> Client::occluded(std::string_view id, std::span<const Ray> rays) {
    return impl_->trace<uint8_t>(id, rays, true);
}

Result<proto::MultiHits> Client::intersect_all(std::string_view id, std::span<const Ray> rays,
                                               const proto::MultiHitQuery& query) {
    proto::MultiHitQuery q = query;
    q.count_only = false;
    const std::string path = impl_->api("/v1/meshes/" + escape_segment(id) + "/intersect_all?" +
                                        proto::multi_hit_query_string(q));
    proto::MultiHits all;
    all.layout = q.layout;
    all.merged = q.merge_coincident;
    all.max_hits = q.max_hits;
    all.offsets.push_back(0);
    auto sent = impl_->post_ray_chunks(
        path, rays,
        [&](const Exchange& ex, std::span<const std::byte> answer,
            size_t count) -> std::optional<Error> {
            auto part = proto::decode_multi_hits(
                answer, {.max_rays = std::numeric_limits<uint32_t>::max()});
            if (!part) return impl_->bad_response(ex, part.error().to_string());
            if (part->counts.size() != count || part->layout != q.layout)
                return impl_->bad_response(ex, "the answer is for another batch");
            const uint64_t base = all.offsets.back();
            for (size_t i = 1; i < part->offsets.size(); ++i)
                all.offsets.push_back(base + part->offsets[i]);
            all.counts.insert(all.counts.end(), part->counts.begin(), part->counts.end());
            all.hits.insert(all.hits.end(), part->hits.begin(), part->hits.end());
            return std::nullopt;
        });
    if (!sent) return proto::Err{std::move(sent).error()};
    return all;
}

Result<std::vector<uint32_t>> Client::count_intersections(std::string_view id,
                                                          std::span<const Ray> rays,
                                                          bool merge_coincident) {
    proto::MultiHitQuery q;
    q.count_only = true;
    q.merge_coincident = merge_coincident;
    q.max_hits = 1;
    const std::string path = impl_->api("/v1/meshes/" + escape_segment(id) + "/intersect_all?" +
                                        proto::multi_hit_query_string(q));
    std::vector<uint32_t> counts;
    auto sent = impl_->post_ray_chunks(
        path, rays,
        [&](const Exchange& ex, std::span<const std::byte> answer,
            size_t count) -> std::optional<Error> {
            auto part = proto::decode_hit_counts(
                answer, {.max_rays = std::numeric_limits<uint32_t>::max()});
            if (!part) return impl_->bad_response(ex, part.error().to_string());
            if (part->size() != count)
                return impl_->bad_response(ex, "the answer is for another batch");
            counts.insert(counts.end(), part->begin(), part->end());
            return std::nullopt;
        });
    if (!sent) return proto::Err{std::move(sent).error()};
    return counts;
}

Result<std::vector<std::byte>> Client::scan(std::string_view id,
                                            const proto::ScanRequest& request) {
    // The mesh id rides along as ?route= like a render's, for a proxy that hashes it.
    Exchange ex;
    ex.method = "POST";
    ex.path = impl_->api("/v1/meshes/" + escape_segment(id) + "/scan?route=" + escape_segment(id));
    ex.content_type = std::string(proto::kJsonMediaType);
    const std::string body = proto::encode_scan_request(request);
    ex.body = body;
    return impl_->image_call(ex, body, 200);
}

Result<std::vector<std::byte>> Client::render(const RenderRequest& request) {
    Exchange ex = impl_->render_exchange(request);
    const std::string body = proto::encode_render_request(request);
    ex.body = body;
    return impl_->image_call(ex, body, 200);
}

Result<StitchedFrame> Client::render_split(const RenderRequest& request, unsigned parts,
                                           const RegionProgress& progress) {
    const RenderSettings& s = request.settings;
    const PixelRegion whole = s.region.value_or(PixelRegion{0, 0, s.width, s.height});
    if (parts == 0 || parts > whole.height)
        return proto::Err{
            make_client_error(ErrorKind::kInput, "cannot split the render",
                              std::to_string(parts) + " parts of a " + std::to_string(whole.width) +
                                  " x " + std::to_string(whole.height) +
                                  (s.region ? " tile" : " frame") + ": a render splits into 1 .. " +
                                  std::to_string(whole.height) + " parts (bands of whole rows)")};
    const std::vector<PixelRegion> bands = split_rows(whole, parts);
    std::vector<proto::RawImage> images(parts);
    StitchedFrame frame;
    frame.replicas.resize(parts);
    std::vector<std::string> levels(parts);

    std::mutex mutex;
    std::condition_variable changed;
    unsigned done = 0, finished_workers = 0;
    size_t next = 0;
    bool stop = false;
    std::optional<Error> error;
    size_t error_part = parts;
    const auto fail = [&](size_t k, Error e) {  // under `mutex`
        if (k < error_part) {
            error_part = k;
            error = std::move(e);
        }
        stop = true;
    };
    const auto worker = [&] {
        for (;;) {
            size_t k = 0;
            {
                std::lock_guard lock(mutex);
                if (stop || next == parts) break;
                k = next++;
            }
            RenderRequest band = request;
            band.format = std::string(proto::kRawImageFormatName);
            band.compression.reset();  // PNG only; the caller encodes
            band.settings.region = bands[k];
            // Built piecewise: GCC 12 reports a false -Wrestrict for "." + std::to_string(k).
            std::string key;
            if (parts > 1) {
                key = ".";
                key += std::to_string(k);
            }
            Exchange ex = impl_->render_exchange(band, key);
            const std::string body = proto::encode_render_request(band);
            ex.body = body;
            Impl::ImageHeaders headers;
            auto answer = impl_->image_call(ex, body, 200, &headers);
            std::optional<Error> problem;
            if (!answer) {
                problem = std::move(answer).error();
            } else if (auto raw = proto::decode_raw_image(*answer); !raw) {
                problem = impl_->bad_response(ex, raw.error());
            } else if (!(raw->region == bands[k]) || raw->frame_width != s.width ||
                       raw->frame_height != s.height) {
                problem = impl_->bad_response(
                    ex, "the answer holds another region of the frame than the one asked for");
            } else {
                images[k] = std::move(*raw);
            }
            std::lock_guard lock(mutex);
            if (problem) {
                fail(k, std::move(*problem));
            } else {
                frame.replicas[k] = std::move(headers.replica);
                levels[k] = std::move(headers.png_compression);
                ++done;
            }
            changed.notify_all();
        }
        std::lock_guard lock(mutex);
        ++finished_workers;
        changed.notify_all();
    };
    const unsigned threads = std::min(impl_->options.connections, parts);
    {
        std::vector<std::jthread> pool;
        pool.reserve(threads);
        for (unsigned t = 0; t < threads; ++t) pool.emplace_back(worker);
        // This thread reports progress (the callback runs on the caller's thread).
        std::unique_lock lock(mutex);
        unsigned reported = 0;
        while (finished_workers < threads) {
            changed.wait(lock, [&] { return finished_workers == threads || done != reported; });
            if (done != reported && !stop && progress) {
                reported = done;
                lock.unlock();
                const bool go_on = progress(reported, parts);
                lock.lock();
                if (!go_on && !stop) {
                    stop = true;
                    if (!error)
                        error = make_client_error(ErrorKind::kCancelled, "cancelled",
                                                  "split render of mesh " + request.mesh +
                                                      " stopped after " + std::to_string(reported) +
                                                      " of " + std::to_string(parts) + " regions");
                }
            }
            reported = done;
        }
    }  // the jthreads join here
    if (error) return proto::Err{std::move(*error)};
    auto image = stitch_regions(whole, images);
    if (!image)
        return proto::Err{
            make_client_error(ErrorKind::kProtocol, "bad response",
                              "split render of mesh " + request.mesh + ": " + image.error())};
    frame.image = std::move(*image);
    if (request.compression) {
        frame.png_compression = *request.compression;
    } else {
        int level = 0;
        const std::string& text = levels.front();
        const auto [end, ec] = std::from_chars(text.data(), text.data() + text.size(), level);
        if (!text.empty() && ec == std::errc() && end == text.data() + text.size())
            frame.png_compression = level;
    }
    return frame;
}

Result<Job> Client::submit(const RenderRequest& request) {
    Exchange ex = impl_->render_exchange(request);
    const std::string body = proto::encode_render_request(request);
    ex.body = body;
    ex.headers.emplace("Prefer", "respond-async");
    ex.resend_after_transport_error = false;
    auto res = impl_->send(ex);
    if (!res) return proto::Err{std::move(res).error()};
    if (res->status != 202)
        return proto::Err{
            impl_->bad_response(ex, "status " + std::to_string(res->status) +
                                        " instead of 202 (the server did not queue a job)")};
    auto job = proto::decode_job_status(res->body);
    if (!job) return proto::Err{impl_->bad_response(ex, job.error())};
    return std::move(*job);
}

Result<Job> Client::job(std::string_view id) {
    Exchange ex;
    ex.path = impl_->api("/v1/jobs/" + escape_segment(id));
    return impl_->json_call<Job>(ex,
                                 [](const std::string& b) { return proto::decode_job_status(b); });
}

Result<std::vector<std::byte>> Client::wait(const Job& submitted,
                                            const ProgressCallback& progress) {
    for (;;) {
        auto status = job(submitted.id);
        if (!status) return proto::Err{std::move(status).error()};
        if (progress && !progress(*status)) {
            (void)cancel(*status);
            return proto::Err{
                make_client_error(ErrorKind::kCancelled, "cancelled",
                                  "job " + submitted.id + " cancelled while waiting for it")};
        }
        switch (status->state) {
            case proto::JobState::kDone:
                return result(*status);
            case proto::JobState::kFailed:
                return proto::Err{make_client_error(ErrorKind::kJobFailed, "render failed",
                                                    "job " + submitted.id + ": " + status->error)};
            case proto::JobState::kCancelled:
                return proto::Err{make_client_error(ErrorKind::kCancelled, "cancelled",
                                                    "job " + submitted.id + " was cancelled")};
            case proto::JobState::kQueued:
            case proto::JobState::kRunning:
                break;
        }
        std::this_thread::sleep_for(impl_->options.poll_interval);
    }
}

Result<std::vector<std::byte>> Client::result(const Job& job) {
    Exchange ex;
    ex.path = impl_->api("/v1/jobs/" + escape_segment(job.id) + "/result");
    return impl_->image_call(ex, {}, 0);
}

Result<void> Client::cancel(const Job& job) {
    Exchange ex;
    ex.method = "DELETE";
    ex.path = impl_->api("/v1/jobs/" + escape_segment(job.id));
    auto res = impl_->send(ex);
    if (!res) return proto::Err{std::move(res).error()};
    return {};
}

Result<void> Client::health() {
    Exchange ex;
    ex.path = impl_->api("/healthz");
    auto res = impl_->send(ex);
    if (!res) return proto::Err{std::move(res).error()};
    return {};
}

Result<void> Client::ready() {
    Exchange ex;
    ex.path = impl_->api("/readyz");
    ex.retry_unavailable = false;
    auto res = impl_->send(ex);
    if (!res) return proto::Err{std::move(res).error()};
    return {};
}

Result<std::string> Client::metrics() {
    Exchange ex;
    ex.path = impl_->api("/metrics");
    auto res = impl_->send(ex);
    if (!res) return proto::Err{std::move(res).error()};
    return std::move(res->body);
}

namespace detail {

std::string ClientAccess::api_path(const Client& client, std::string_view path,
                                   std::string_view id) {
    std::string out(path);
    if (const size_t at = out.find("{id}"); at != std::string::npos)
        out.replace(at, 4, escape_segment(id));
    return client.impl_->api(out);
}

Result<PostAnswer> ClientAccess::post(Client& client, const std::string& path,
                                      std::string_view content_type,
                                      std::span<const std::byte> body,
                                      std::string_view answer_header) {
    return request(client, {.method = "POST",
                            .path = path,
                            .content_type = content_type,
                            .body = body,
                            .answer_header = answer_header});
}

Result<PostAnswer> ClientAccess::request(Client& client, const ApiRequest& request) {
    static constexpr std::string_view kMethods[] = {"GET", "DELETE", "POST", "PATCH"};
    Exchange ex;
    for (const std::string_view m : kMethods)
        if (m == request.method) ex.method = m.data();  // literals: NUL-terminated
    ex.path = request.path;
    for (const auto& [name, value] : request.headers) ex.headers.emplace(name, value);
    ex.body =
        std::string_view(reinterpret_cast<const char*>(request.body.data()), request.body.size());
    ex.content_type = std::string(request.content_type);
    ex.resend_after_transport_error = request.idempotent;
    auto res = client.impl_->send(ex);
    if (!res) return proto::Err{std::move(res).error()};
    PostAnswer answer;
    answer.body = std::move(res->body);
    if (!request.answer_header.empty())
        answer.header = res->get_header_value(std::string(request.answer_header));
    return answer;
}

std::atomic<size_t>& ClientAccess::distance_chunk_limit(Client& client) {
    return client.impl_->distance_chunk_limit;
}

Error ClientAccess::bad_response(const Client& client, const std::string& path,
                                 const std::string& why) {
    Exchange ex;
    ex.method = "POST";
    ex.path = path;
    return client.impl_->bad_response(ex, why);
}

}  // namespace detail

std::vector<PixelRegion> split_rows(const PixelRegion& region, unsigned parts) {
    if (parts == 0 || parts > region.height)
        throw std::invalid_argument("split_rows: " + std::to_string(parts) + " parts of " +
                                    std::to_string(region.height) + " rows");
    std::vector<PixelRegion> bands;
    bands.reserve(parts);
    for (unsigned k = 0; k < parts; ++k) {
        const auto row = [&](uint64_t i) {
            return region.y + static_cast<uint32_t>(uint64_t{region.height} * i / parts);
        };
        bands.push_back(PixelRegion{region.x, row(k), region.width, row(k + 1) - row(k)});
    }
    return bands;
}

proto::Result<Image, std::string> stitch_regions(const PixelRegion& within,
                                                 std::span<const proto::RawImage> parts) {
    if (parts.empty()) return proto::Err{std::string("no regions to stitch")};
    if (within.width == 0 || within.height == 0)
        return proto::Err{std::string("the stitched rectangle is empty")};
    const proto::RawImage& first = parts.front();
    Image out;
    out.width = within.width;
    out.height = within.height;
    out.channels = first.image.channels;
    out.pixels.resize(size_t{within.width} * within.height * out.channels);
    std::vector<uint8_t> covered(size_t{within.width} * within.height, 0);
    for (size_t k = 0; k < parts.size(); ++k) {
        const proto::RawImage& part = parts[k];
        const PixelRegion& r = part.region;
        const std::string name = "region " + std::to_string(k) + " (" + std::to_string(r.width) +
                                 " x " + std::to_string(r.height) + " at " + std::to_string(r.x) +
                                 ", " + std::to_string(r.y) + ")";
        if (part.frame_width != first.frame_width || part.frame_height != first.frame_height)
            return proto::Err{name + " belongs to a " + std::to_string(part.frame_width) + " x " +
                              std::to_string(part.frame_height) + " frame, region 0 to a " +
                              std::to_string(first.frame_width) + " x " +
                              std::to_string(first.frame_height) + " one"};
        if (part.image.channels != out.channels)
            return proto::Err{name + " has " + std::to_string(part.image.channels) +
                              " channels, region 0 " + std::to_string(out.channels)};
        if (part.image.width != r.width || part.image.height != r.height ||
            part.image.pixels.size() != size_t{r.width} * r.height * out.channels)
            return proto::Err{name + " holds an image of another size"};
        if (r.x < within.x || r.y < within.y ||
            uint64_t{r.x} + r.width > uint64_t{within.x} + within.width ||
            uint64_t{r.y} + r.height > uint64_t{within.y} + within.height)
            return proto::Err{name + " lies outside the " + std::to_string(within.width) + " x " +
                              std::to_string(within.height) + " rectangle at " +
                              std::to_string(within.x) + ", " + std::to_string(within.y)};
        const size_t row_floats = size_t{r.width} * out.channels;
        for (uint32_t row = 0; row < r.height; ++row) {
            const size_t y = r.y - within.y + row, x = r.x - within.x;
            uint8_t* mark = &covered[y * within.width + x];
            if (std::any_of(mark, mark + r.width, [](uint8_t m) { return m != 0; }))
                return proto::Err{name + " overlaps another region at row " +
                                  std::to_string(r.y + row)};
            std::fill(mark, mark + r.width, uint8_t{1});
            std::copy_n(&part.image.pixels[row * row_floats], row_floats,
                        &out.pixels[(y * within.width + x) * out.channels]);
        }
    }
    if (const auto gap = std::find(covered.begin(), covered.end(), uint8_t{0});
        gap != covered.end()) {
        const size_t at = static_cast<size_t>(gap - covered.begin());
        return proto::Err{"no region covers pixel (" +
                          std::to_string(within.x + at % within.width) + ", " +
                          std::to_string(within.y + at / within.width) + ")"};
    }
    return out;
}

}  // namespace kdrt
