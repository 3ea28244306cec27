#include "http/http_front.h"

#include <netdb.h>
#include <netinet/in.h>
#include <netinet/tcp.h>
#include <poll.h>
#include <sys/epoll.h>
#include <sys/eventfd.h>
#include <sys/resource.h>
#include <sys/socket.h>
#include <sys/uio.h>
#include <unistd.h>

#include <algorithm>
#include <atomic>
#include <cerrno>
#include <chrono>
#include <condition_variable>
#include <cstring>
#include <ctime>
#include <deque>
#include <limits>
#include <mutex>
#include <optional>
#include <string>
#include <thread>
#include <unordered_map>
#include <unordered_set>
#include <vector>

#include "http/request_body.h"
#include "http/request_head.h"
#include "kdrt/proto/problem.h"

namespace kdrt::server {
namespace {

using Clock = std::chrono::steady_clock;

/// Largest single recv() of the event loop.
constexpr size_t kLoopReadBytes = size_t{16} << 10;
/// Largest piece a worker hands to a ContentReader's receiver.
constexpr size_t kWorkerReadBytes = size_t{256} << 10;
/// Bodies up to this size are sent in one write with the head (copied after it).
constexpr size_t kCoalesceBytes = size_t{16} << 10;
/// Longest chunk-size or trailer line of a chunked body.
constexpr size_t kMaxChunkLineBytes = 4096;
/// How often the event loop looks for connections past a deadline.
constexpr auto kSweepInterval = std::chrono::milliseconds(50);
/// After an early reply the connection is read and dropped for up to this long before it is
/// closed, so the client sees the reply rather than a reset caused by its own unread bytes.
constexpr auto kLingerTime = std::chrono::seconds(1);
/// How long a worker that answered a request waits for the connection's next one before it
/// hands the connection back to the loop (next_request_here): a client's next request in a
/// sequence comes within it (the moving sensor's scan ~0.4 ms after its pose update's answer,
/// its next pose update 2-4 ms after the scan's in tests/bench/scene_latency.py; 2 ms missed
/// about one in five of those).
constexpr auto kNextRequestWait = std::chrono::nanoseconds(std::chrono::milliseconds(5));

/// The numeric host and port of a socket's peer (peer = true) or own end.
void socket_address(int fd, bool peer, std::string& host, int& port) {
    sockaddr_storage addr{};
    socklen_t len = sizeof addr;
    const int rc = peer ? ::getpeername(fd, reinterpret_cast<sockaddr*>(&addr), &len)
                        : ::getsockname(fd, reinterpret_cast<sockaddr*>(&addr), &len);
    char buffer[NI_MAXHOST];
    host.clear();
    port = 0;
    if (rc != 0 || ::getnameinfo(reinterpret_cast<const sockaddr*>(&addr), len, buffer,
                                 sizeof buffer, nullptr, 0, NI_NUMERICHOST) != 0)
        return;
    host = buffer;
    if (addr.ss_family == AF_INET)
        port = ntohs(reinterpret_cast<const sockaddr_in*>(&addr)->sin_port);
    else if (addr.ss_family == AF_INET6)
        port = ntohs(reinterpret_cast<const sockaddr_in6*>(&addr)->sin6_port);
}

/// Milliseconds from now to `t`, rounded up (0 once it has passed, at most `cap_ms`).
int millis_until(Clock::time_point t, int cap_ms) {
    const auto left = std::chrono::ceil<std::chrono::milliseconds>(t - Clock::now());
    return static_cast<int>(std::clamp<int64_t>(left.count(), 0, cap_ms));
}

/// One client connection. Owned by the event loop while parked (idle, or a request arriving),
/// by one worker while a request on it is answered; handed over under Impl::mutex.
struct Connection {
    enum class State { kIdle, kHead, kBody, kBusy, kLinger };

    explicit Connection(int socket) : fd(socket), idle_since(Clock::now()) {}

    int fd;
    State state = State::kIdle;
    std::vector<char> buffer;  ///< received, unconsumed bytes: buffer[begin, size)
    size_t begin = 0;
    HeadScan scan;           ///< the head still arriving
    size_t head_bytes = 0;   ///< length of the complete head (kBody)
    size_t body_wanted = 0;  ///< body bytes to receive before a thread is given (kBody)
    size_t reserved = 0;     ///< bytes taken from the prebuffer budget
    Clock::time_point idle_since, request_start, linger_until;
    bool fresh = true;  ///< no request received yet
    bool peer_closed = false;
    unsigned served = 0;
    std::string method;
    std::optional<RequestHead> head;  ///< parsed by the loop (kBody, kBusy)

    [[nodiscard]] size_t buffered() const noexcept { return buffer.size() - begin; }
    [[nodiscard]] const char* data() const noexcept { return buffer.data() + begin; }

    void consume(size_t n) noexcept {
        begin += n;
        if (begin == buffer.size()) {
            buffer.clear();
            begin = 0;
        }
    }

    /// Moves the unconsumed bytes to the front (before the buffer grows).
    void compact() {
        if (begin == 0) return;
        buffer.erase(buffer.begin(), buffer.begin() + static_cast<ptrdiff_t>(begin));
        begin = 0;
    }
};

/// A request being answered by a worker: the body's framing and what is left of it, reads and
/// writes bounded by the timeouts, the memory body and the resources kept until it is sent.
struct Exchange {
    Exchange(Connection& connection, const ConnectionLimits& limits, const RequestHead& head)
        : c(connection),
          read_timeout_ms(static_cast<int>(limits.read_timeout_s) * 1000),
          write_timeout_ms(static_cast<int>(limits.write_timeout_s) * 1000),
          deadline(connection.request_start + std::chrono::seconds(limits.request_timeout_s)),
          chunked(head.chunked),
          body_left(head.content_length.value_or(0)),
          body_done(!head.chunked && body_left == 0),
          continue_pending(head.expect_continue && !body_done) {}

    Connection& c;
    int read_timeout_ms, write_timeout_ms;
    Clock::time_point deadline;
    bool chunked;
    uint64_t body_left;       ///< Content-Length bytes not yet read
    uint64_t chunk_left = 0;  ///< bytes of the current chunk not yet read
    bool body_done;
    bool body_failed = false;
    bool continue_pending;
    bool timed_out = false;
    bool write_failed = false;
    std::span<const std::byte> memory_body;
    std::shared_ptr<const void> memory_owner;
    std::vector<std::shared_ptr<void>> kept;

    /// Buffered bytes first, then one recv() after waiting for data up to the read timeout and
    /// the deadline. 0 when the peer closed, -1 on an error or a timeout.
    ptrdiff_t receive(char* out, size_t size) {
        if (size == 0) return 0;
        if (c.buffered() > 0) {
            const size_t n = std::min(size, c.buffered());
            std::memcpy(out, c.data(), n);
            c.consume(n);
            return static_cast<ptrdiff_t>(n);
        }
        for (;;) {
            const ssize_t n = ::recv(c.fd, out, size, MSG_DONTWAIT);
            if (n >= 0) return n;
            if (errno == EINTR) continue;
            if (errno != EAGAIN && errno != EWOULDBLOCK) return -1;
            const int until_deadline = millis_until(deadline, std::numeric_limits<int>::max());
            const bool deadline_first = until_deadline < read_timeout_ms;
            if (until_deadline == 0) {
                timed_out = true;
                return -1;
            }
            pollfd p{c.fd, POLLIN, 0};
            const int ready = ::poll(&p, 1, deadline_first ? until_deadline : read_timeout_ms);
            if (ready < 0 && errno == EINTR) continue;
            if (ready == 0 && deadline_first) timed_out = true;
            if (ready <= 0) return -1;
        }
    }

    /// Writes all of `parts`, waiting up to the write timeout for progress each time.
    bool send_all(std::vector<iovec> parts) {
        size_t first = 0;
        while (first < parts.size()) {
            if (parts[first].iov_len == 0) {
                ++first;
                continue;
            }
            msghdr message{};
            message.msg_iov = parts.data() + first;
            message.msg_iovlen = std::min<size_t>(parts.size() - first, 64);
            const ssize_t n = ::sendmsg(c.fd, &message, MSG_DONTWAIT | MSG_NOSIGNAL);
            if (n < 0) {
                if (errno == EINTR) continue;
                if (errno != EAGAIN && errno != EWOULDBLOCK) return false;
                pollfd p{c.fd, POLLOUT, 0};
                const int ready = ::poll(&p, 1, write_timeout_ms);
                if (ready < 0 && errno == EINTR) continue;
                if (ready <= 0 || (p.revents & (POLLERR | POLLHUP)) != 0) return false;
                continue;
            }
            auto left = static_cast<size_t>(n);
            while (left > 0 && first < parts.size()) {
                const size_t step = std::min(left, parts[first].iov_len);
                parts[first].iov_base = static_cast<char*>(parts[first].iov_base) + step;
                parts[first].iov_len -= step;
                left -= step;
                if (parts[first].iov_len == 0) ++first;
            }
        }
        return true;
    }

    /// Sends `100 Continue` the first time the body is asked for.
    bool send_continue() {
        if (!continue_pending) return true;
        continue_pending = false;
        static constexpr char kContinue[] = "HTTP/1.1 100 Continue\r\n\r\n";
        return send_all({iovec{const_cast<char*>(kContinue), sizeof kContinue - 1}});
    }

    /// One line of a chunked body's framing (without its line end), at most kMaxChunkLineBytes.
    bool read_line(std::string& line) {
        line.clear();
        for (;;) {
            const char* d = c.data();
            const size_t n = c.buffered();
            const char* nl = static_cast<const char*>(std::memchr(d, '\n', n));
            const size_t take = nl ? static_cast<size_t>(nl - d) + 1 : n;
            if (line.size() + take > kMaxChunkLineBytes) return false;
            line.append(d, take);
            c.consume(take);
            if (nl) {
                line.pop_back();
                if (!line.empty() && line.back() == '\r') line.pop_back();
                return true;
            }
            char piece[1024];
            const ptrdiff_t got = receive(piece, sizeof piece);
            if (got <= 0) return false;
            c.buffer.insert(c.buffer.end(), piece, piece + got);
        }
    }

    /// Reads the next chunk-size line (RFC 9112 7.1: hex digits, extensions ignored); at the
    /// last chunk, reads the trailer section too. False on a framing error.
    bool next_chunk() {
        std::string line;
        if (!read_line(line)) return false;
        const size_t end = std::min(line.find(';'), line.size());
        std::string_view digits = std::string_view(line).substr(0, end);
        while (!digits.empty() && (digits.back() == ' ' || digits.back() == '\t'))
            digits.remove_suffix(1);
        if (digits.empty() || digits.size() > 15) return false;
        uint64_t size = 0;
        for (char ch : digits) {
            const int v = std::isxdigit(static_cast<unsigned char>(ch))
                              ? (std::isdigit(static_cast<unsigned char>(ch))
                                     ? ch - '0'
                                     : (std::tolower(static_cast<unsigned char>(ch)) - 'a' + 10))
                              : -1;
            if (v < 0) return false;
            size = size * 16 + static_cast<uint64_t>(v);
        }
        if (size > 0) {
            chunk_left = size;
            return true;
        }
        for (size_t lines = 0; lines < 100; ++lines) {  // trailer fields are read and dropped
            if (!read_line(line)) return false;
            if (line.empty()) {
                body_done = true;
                return true;
            }
        }
        return false;
    }

    /// Up to `size` body bytes into `out`: the count, 0 at the body's end, -1 on an error
    /// (connection, timeout, framing).
    ptrdiff_t read_body(char* out, size_t size) {
        if (body_done) return 0;
        if (body_failed || !send_continue()) {
            body_failed = true;
            return -1;
        }
        if (!chunked) {
            const ptrdiff_t n =
                receive(out, static_cast<size_t>(std::min<uint64_t>(size, body_left)));
            if (n <= 0) {
                body_failed = true;
                return -1;
            }
            body_left -= static_cast<uint64_t>(n);
            body_done = body_left == 0;
            return n;
        }
        if (chunk_left == 0 && (!next_chunk() || body_done)) {
            if (!body_done) body_failed = true;
            return body_done ? 0 : -1;
        }
        const ptrdiff_t n = receive(out, static_cast<size_t>(std::min<uint64_t>(size, chunk_left)));
        if (n <= 0) {
            body_failed = true;
            return -1;
        }
        chunk_left -= static_cast<uint64_t>(n);
        std::string line;
        if (chunk_left == 0 && (!read_line(line) || !line.empty())) {
            body_failed = true;
            return -1;
        }
        return n;
    }

    /// Reads the body through to its end, handing each piece to `take`.
    bool read_all(const std::function<bool(const char*, size_t)>& take) {
        thread_local std::vector<char> scratch(kWorkerReadBytes);
        for (;;) {
            const ptrdiff_t n = read_body(scratch.data(), scratch.size());
            if (n < 0) return false;
            if (n == 0) return true;
            if (!take(scratch.data(), static_cast<size_t>(n))) return false;
        }
    }
};

thread_local Connection* t_connection = nullptr;
thread_local Exchange* t_exchange = nullptr;

/// True when the response asks for its connection to be closed.
bool asks_close(const httplib::Response& res) {
    for (const auto& [name, value] : res.headers)
        if (iequals(name, "Connection") && iequals(value, "close")) return true;
    return false;
}

/// On every response, routed or refused by the front: each answer is data of the type it names
/// (JSON, problem details, images, binary batches, the viewer's files), which a browser must not
/// sniff into another (a script or a page).
constexpr std::string_view kNoSniffLine = "X-Content-Type-Options: nosniff\r\n";

/// Headers the front writes itself (framing, connection management, kNoSniffLine).
bool front_owned(std::string_view name) {
    return iequals(name, "Content-Length") || iequals(name, "Transfer-Encoding") ||
           iequals(name, "Connection") || iequals(name, "Keep-Alive") ||
           iequals(name, "X-Content-Type-Options");
}

}  // namespace

struct HttpFront::Impl {
    Impl(ConnectionLimits l, EarlyReply early, AnswerRequest a, ResponseSent s)
        : limits(l), early_reply(std::move(early)), answer(std::move(a)), sent(std::move(s)) {}

    ConnectionLimits limits;
    EarlyReply early_reply;
    AnswerRequest answer;
    ResponseSent sent;

    std::mutex mutex;
    /// A worker's place in `idle` (under `mutex`): listed while it waits for a request, or
    /// already as it hands its connection back (finish()); dispatch() and stop() take it off
    /// (listed = false) and wake it.
    struct Idle {
        std::condition_variable cv;
        bool listed = false;
    };
    /// The waiting workers, the most recently idle last. dispatch() wakes that one (LIFO): a
    /// client's next request goes to the thread that answered its last one, whose caches, malloc
    /// arena and per-thread scratch (a scene scan's, for one) are warm, instead of to the
    /// longest idle of `threads` in turn (a 64 x 2048 scene scan ran ~2 ms slower on a cold
    /// thread, tests/bench/README.md).
    std::vector<Idle*> idle;
    std::deque<Connection*> work;       ///< complete requests waiting for a worker
    std::vector<Connection*> incoming;  ///< connections back from a worker, for the loop
    std::unordered_map<Connection*, std::unique_ptr<Connection>> all;
    bool stopping = false;

    std::shared_ptr<ConnectionGauges> gauges = std::make_shared<ConnectionGauges>();
    std::atomic<size_t>& open = gauges->open;
    std::atomic<size_t> prebuffered{0};
    int listen_fd = -1;
    int epoll_fd = -1;
    int wake_fd = -1;
    std::vector<std::thread> workers;
    std::unordered_set<Connection*> parked;  ///< loop thread only
    int listen_tag = 0;                      ///< its address marks the listening socket's events

    ~Impl() {
        for (auto& [ptr, c] : all) ::close(c->fd);
        for (int fd : {listen_fd, epoll_fd, wake_fd})
            if (fd >= 0) ::close(fd);
    }

    void wake() const {
        const uint64_t one = 1;
        if (wake_fd >= 0) [[maybe_unused]]
            const ssize_t n = ::write(wake_fd, &one, sizeof one);
    }

    /// The open-file limit must fit max_connections sockets besides the store's files.
    void raise_file_limit() const {
        rlimit limit{};
        if (::getrlimit(RLIMIT_NOFILE, &limit) != 0) return;
        const rlim_t wanted = static_cast<rlim_t>(limits.max_connections) + 1024;
        if (limit.rlim_cur != RLIM_INFINITY && limit.rlim_cur < wanted) {
            limit.rlim_cur =
                limit.rlim_max == RLIM_INFINITY ? wanted : std::min(wanted, limit.rlim_max);
            ::setrlimit(RLIMIT_NOFILE, &limit);
        }
    }

    proto::Result<int, std::string> bind(const std::string& host, int port, int backlog) {
        addrinfo hints{};
        hints.ai_family = AF_UNSPEC;
        hints.ai_socktype = SOCK_STREAM;
        hints.ai_flags = AI_PASSIVE | AI_NUMERICSERV;
        addrinfo* found = nullptr;
        const std::string service = std::to_string(port);
        if (const int rc = ::getaddrinfo(host.c_str(), service.c_str(), &hints, &found); rc != 0)
            return proto::Err{std::string(::gai_strerror(rc))};
        int error = EADDRNOTAVAIL;
        for (addrinfo* a = found; a != nullptr; a = a->ai_next) {
            const int fd = ::socket(a->ai_family, a->ai_socktype | SOCK_CLOEXEC | SOCK_NONBLOCK,
                                    a->ai_protocol);
            if (fd < 0) {
                error = errno;
                continue;
            }
            // SO_REUSEADDR allows a restart while old connections are in TIME_WAIT (no
            // SO_REUSEPORT: a second server must not share the port).
            int yes = 1;
            ::setsockopt(fd, SOL_SOCKET, SO_REUSEADDR, &yes, sizeof yes);
            if (::bind(fd, a->ai_addr, a->ai_addrlen) == 0 && ::listen(fd, backlog) == 0) {
                listen_fd = fd;
                break;
            }
            error = errno;
            ::close(fd);
        }
        ::freeaddrinfo(found);
        if (listen_fd < 0) return proto::Err{std::string(std::strerror(error))};
        std::string bound_host;
        int bound_port = 0;
        socket_address(listen_fd, false, bound_host, bound_port);
        return bound_port;
    }

    bool serve() {
        {
            std::lock_guard lock(mutex);
            if (stopping || listen_fd < 0) return !stopping ? false : true;
            raise_file_limit();
            epoll_fd = ::epoll_create1(EPOLL_CLOEXEC);
            wake_fd = ::eventfd(0, EFD_CLOEXEC | EFD_NONBLOCK);
        }
        epoll_event ev{};
        ev.events = EPOLLIN;
        ev.data.ptr = nullptr;
        ::epoll_ctl(epoll_fd, EPOLL_CTL_ADD, wake_fd, &ev);
        ev.data.ptr = &listen_tag;
        ::epoll_ctl(epoll_fd, EPOLL_CTL_ADD, listen_fd, &ev);
        for (unsigned i = 0; i < std::max(1u, limits.threads); ++i)
            workers.emplace_back([this] { run_worker(); });
        const bool ok = run_loop();
        wake_idle_workers();
        for (std::thread& t : workers) t.join();
        workers.clear();
        std::lock_guard lock(mutex);
        for (auto& [ptr, c] : all) ::close(c->fd);
        open -= all.size();
        all.clear();
        incoming.clear();
        return ok;
    }

    void stop() {
        {
            std::lock_guard lock(mutex);
            stopping = true;
        }
        wake();
        wake_idle_workers();
    }

    void wake_idle_workers() {
        std::lock_guard lock(mutex);
        for (Idle* w : idle) {
            w->listed = false;
            w->cv.notify_one();
        }
        idle.clear();
        gauges->idle = 0;
    }

    /// Sends a complete early reply without blocking (best effort: a full socket buffer drops
    /// it).
    void send_early(int fd, int status, std::string_view method, const std::string& detail) const {
        const std::string body = early_reply ? early_reply(status, method, detail) : detail;
        std::string reply = "HTTP/1.1 " + std::to_string(status) + " " +
                            std::string(proto::http_reason_phrase(status)) +
                            "\r\nContent-Type: application/problem+json\r\nContent-Length: " +
                            std::to_string(body.size()) + "\r\nConnection: close\r\n" +
                            std::string(kNoSniffLine);
        if (status == 503) reply += "Retry-After: 1\r\n";
        reply += "\r\n" + body;
        [[maybe_unused]] const ssize_t n =
            ::send(fd, reply.data(), reply.size(), MSG_DONTWAIT | MSG_NOSIGNAL);
    }

    // ---- the event loop -------------------------------------------------------------------

    bool run_loop() {
        std::vector<epoll_event> events(256);
        auto last_sweep = Clock::now();
        bool ok = true;
        for (;;) {
            const int n = ::epoll_wait(epoll_fd, events.data(), static_cast<int>(events.size()),
                                       static_cast<int>(kSweepInterval.count()));
            std::vector<Connection*> arrived;
            {
                std::lock_guard lock(mutex);
                if (stopping) break;
                arrived.swap(incoming);
            }
            for (int i = 0; i < n; ++i) {
                void* tag = events[i].data.ptr;
                if (tag == nullptr) {
                    uint64_t count = 0;
                    [[maybe_unused]] const ssize_t r = ::read(wake_fd, &count, sizeof count);
                } else if (tag == &listen_tag) {
                    if (!accept_all()) ok = false;
                } else if (auto* c = static_cast<Connection*>(tag); parked.count(c) != 0) {
                    on_readable(*c);
                }
            }
            if (!ok) break;
            for (Connection* c : arrived) park(*c);
            if (Clock::now() - last_sweep >= kSweepInterval) {
                sweep();
                last_sweep = Clock::now();
            }
        }
        for (Connection* c : parked) release_budget(*c);
        parked.clear();
        {
            std::lock_guard lock(mutex);
            stopping = true;
        }
        return ok;
    }

    /// Accepts every pending connection. False when the listening socket failed.
    bool accept_all() {
        for (;;) {
            const int fd = ::accept4(listen_fd, nullptr, nullptr, SOCK_NONBLOCK | SOCK_CLOEXEC);
            if (fd < 0) {
                if (errno == EINTR || errno == ECONNABORTED || errno == EPROTO) continue;
                if (errno == EAGAIN || errno == EWOULDBLOCK) return true;
                // Out of file descriptors or memory: try again on the next event.
                return errno == EMFILE || errno == ENFILE || errno == ENOBUFS || errno == ENOMEM;
            }
            if (open.load() >= limits.max_connections) {
                send_early(fd, 503, "",
                           "the server has " + std::to_string(limits.max_connections) +
                               " connections open (max_connections); retry later");
                ::close(fd);
                continue;
            }
            int yes = 1;
            ::setsockopt(fd, IPPROTO_TCP, TCP_NODELAY, &yes, sizeof yes);
            auto owned = std::make_unique<Connection>(fd);
            Connection* c = owned.get();
            {
                std::lock_guard lock(mutex);
                all.emplace(c, std::move(owned));
            }
            ++open;
            park(*c);
        }
    }

    /// Idle again, its head to be scanned anew from the buffered bytes.
    static void forget_head(Connection& c) {
        c.state = Connection::State::kIdle;
        c.scan = HeadScan{};
        c.head.reset();
    }

    /// A new connection, or one back from a worker: its next request may already be buffered.
    void park(Connection& c) {
        forget_head(c);
        c.idle_since = Clock::now();
        if (c.buffered() == 0) {
            c.buffer.clear();
            c.buffer.shrink_to_fit();
        }
        parked.insert(&c);
        epoll_event ev{};
        ev.events = EPOLLIN | EPOLLRDHUP;
        ev.data.ptr = &c;
        if (::epoll_ctl(epoll_fd, EPOLL_CTL_ADD, c.fd, &ev) != 0) return close(c);
        if (c.buffered() > 0) progress(c);
    }

    /// Removes a parked connection from the loop (before a worker gets it, or it closes).
    void unpark(Connection& c) {
        ::epoll_ctl(epoll_fd, EPOLL_CTL_DEL, c.fd, nullptr);
        parked.erase(&c);
        release_budget(c);
    }

    void release_budget(Connection& c) {
        prebuffered -= c.reserved;
        c.reserved = 0;
    }

    void close(Connection& c) {
        if (parked.count(&c) != 0) unpark(c);
        ::close(c.fd);
        std::lock_guard lock(mutex);
        all.erase(&c);
        --open;
    }

    /// Replies and closes, after reading and dropping what the client still sends for a while.
    void refuse(Connection& c, int status, const std::string& detail) {
        send_early(c.fd, status, c.method, detail);
        ::shutdown(c.fd, SHUT_WR);
        c.state = Connection::State::kLinger;
        c.linger_until = Clock::now() + kLingerTime;
        c.buffer.clear();
        c.buffer.shrink_to_fit();
        c.begin = 0;
        release_budget(c);
    }

    /// How many bytes the connection's buffer may hold in its state.
    [[nodiscard]] size_t read_limit(const Connection& c) const {
        if (c.state == Connection::State::kBody) return c.head_bytes + c.body_wanted;
        return limits.max_head_bytes + 1;
    }

    void on_readable(Connection& c) {
        if (c.state == Connection::State::kLinger) {
            char sink[4096];
            for (;;) {
                const ssize_t n = ::recv(c.fd, sink, sizeof sink, MSG_DONTWAIT);
                if (n == 0 || (n < 0 && errno != EINTR && errno != EAGAIN)) return close(c);
                if (n < 0) return;
            }
        }
        for (;;) {
            const size_t limit = read_limit(c);
            if (c.buffered() >= limit) break;
            const size_t room = std::min(kLoopReadBytes, limit - c.buffered());
            c.compact();
            const size_t old_size = c.buffer.size();
            c.buffer.resize(old_size + room);
            const ssize_t n = ::recv(c.fd, c.buffer.data() + old_size, room, MSG_DONTWAIT);
            c.buffer.resize(old_size + static_cast<size_t>(std::max<ssize_t>(n, 0)));
            if (n > 0) {
                if (c.state == Connection::State::kIdle) {
                    c.state = Connection::State::kHead;
                    c.request_start = Clock::now();
                }
                continue;
            }
            if (n == 0) {
                c.peer_closed = true;
                break;
            }
            if (errno == EINTR) continue;
            if (errno == EAGAIN || errno == EWOULDBLOCK) break;
            return close(c);  // connection reset
        }
        if (c.buffer.empty()) c.buffer.shrink_to_fit();
        progress(c);
        if (parked.count(&c) != 0 && c.peer_closed && c.state != Connection::State::kLinger)
            close(c);  // the peer left with an incomplete request (or none)
    }

    /// Looks at what has arrived: hands a complete request to a worker, refuses a bad head.
    void progress(Connection& c) {
        if (c.state == Connection::State::kIdle || c.state == Connection::State::kHead) {
            int status = 0;
            std::string detail;
            const HeadScanned scanned = scan_head(c, status, detail);
            if (scanned == HeadScanned::kRefused) return refuse(c, status, detail);
            if (scanned != HeadScanned::kComplete) return;
            c.body_wanted = 0;
            if (c.head->content_length && !c.head->expect_continue) {
                const size_t wanted = static_cast<size_t>(
                    std::min<uint64_t>(*c.head->content_length, limits.prebuffer_bytes));
                const size_t budget = std::max(kPrebufferBudgetBytes, limits.prebuffer_bytes);
                if (prebuffered.fetch_add(wanted) + wanted <= budget) {
                    c.reserved = wanted;
                    c.body_wanted = wanted;
                } else {
                    prebuffered -= wanted;  // over the budget: a worker receives the body
                }
            }
            c.state = Connection::State::kBody;
        }
        if (c.state == Connection::State::kBody && c.buffered() >= c.head_bytes + c.body_wanted)
            dispatch(c);
    }

    enum class HeadScanned { kNone, kPartial, kRefused, kComplete };

    /// Looks for the request head in what has arrived (kIdle or kHead), for the loop and for a
    /// worker waiting for its connection's next request: kNone (nothing but empty lines),
    /// kPartial (not all of it yet), kRefused (`status` and `detail` say why), kComplete
    /// (`c.head` and `c.head_bytes` are set).
    HeadScanned scan_head(Connection& c, int& status, std::string& detail) const {
        // RFC 9112 2.2: empty lines before a request line are ignored.
        while (c.scan.scanned == 0 && c.buffered() > 0 && (*c.data() == '\r' || *c.data() == '\n'))
            c.consume(1);
        if (c.buffered() == 0) {
            c.state = Connection::State::kIdle;
            return HeadScanned::kNone;
        }
        if (c.state == Connection::State::kIdle) {
            c.state = Connection::State::kHead;
            c.request_start = Clock::now();
        }
        const std::string_view arrived(c.data(), c.buffered());
        const std::optional<size_t> end = find_head_end(arrived, c.scan);
        c.method = std::string(arrived.substr(0, std::min<size_t>(arrived.find(' '), 32)));
        if (!end) {
            status = 431;
            if (c.scan.lines > limits.max_headers + 1) {
                detail = too_many_headers();
                return HeadScanned::kRefused;
            }
            if (c.buffered() > limits.max_head_bytes) {
                detail = head_too_large();
                return HeadScanned::kRefused;
            }
            return HeadScanned::kPartial;
        }
        auto head = parse_request_head(arrived.substr(0, *end),
                                       {limits.max_head_bytes, limits.max_headers});
        if (!head) {
            status = head.error().status;
            detail = head.error().detail;
            return HeadScanned::kRefused;
        }
        c.head_bytes = *end;
        c.head = std::move(*head);
        return HeadScanned::kComplete;
    }

    [[nodiscard]] std::string head_too_large() const {
        return "the request head exceeds " + std::to_string(limits.max_head_bytes) +
               " bytes (max_request_head_bytes)";
    }
    [[nodiscard]] std::string too_many_headers() const {
        return "the request has more than " + std::to_string(limits.max_headers) +
               " header lines (max_request_headers)";
    }

    void dispatch(Connection& c) {
        unpark(c);
        c.state = Connection::State::kBusy;
        {
            std::lock_guard lock(mutex);
            work.push_back(&c);
            ++gauges->waiting;
            if (!idle.empty()) {  // the most recently idle worker (else the next one to finish)
                Idle* w = idle.back();
                idle.pop_back();
                gauges->idle = idle.size();
                w->listed = false;
                w->cv.notify_one();
            }
        }
    }

    /// Closes connections past their deadline: idle ones quietly, a late request with 408.
    void sweep() {
        const Clock::time_point now = Clock::now();
        std::vector<Connection*> expired;
        for (Connection* c : parked) {
            switch (c->state) {
                case Connection::State::kIdle: {
                    const auto wait = std::chrono::seconds(c->fresh ? limits.head_timeout_s
                                                                    : limits.keep_alive_timeout_s);
                    if (now >= c->idle_since + wait) expired.push_back(c);
                    break;
                }
                case Connection::State::kHead:
                    if (now >= c->request_start + std::chrono::seconds(limits.head_timeout_s))
                        expired.push_back(c);
                    break;
                case Connection::State::kBody:
                    if (now >= c->request_start + std::chrono::seconds(limits.request_timeout_s))
                        expired.push_back(c);
                    break;
                case Connection::State::kLinger:
                    if (now >= c->linger_until) expired.push_back(c);
                    break;
                case Connection::State::kBusy:
                    break;
            }
        }
        for (Connection* c : expired) {
            if (c->state == Connection::State::kHead)
                refuse(*c, 408,
                       "the request head did not arrive within " +
                           std::to_string(limits.head_timeout_s) + " s (request_head_timeout_s)");
            else if (c->state == Connection::State::kBody)
                refuse(*c, 408,
                       "the request body did not arrive within " +
                           std::to_string(limits.request_timeout_s) + " s (request_timeout_s)");
            else
                close(*c);
        }
    }

    // ---- workers --------------------------------------------------------------------------

    void run_worker() {
        Idle self;
        for (;;) {
            Connection* c = nullptr;
            bool stop_after = false;
            {
                std::unique_lock lock(mutex);
                while (!stopping && work.empty()) {
                    if (!self.listed) {
                        self.listed = true;
                        idle.push_back(&self);
                        gauges->idle = idle.size();
                    }
                    self.cv.wait(lock, [&] { return !self.listed; });
                }
                if (self.listed) {  // listed by finish() and not woken: off the list
                    idle.erase(std::find(idle.begin(), idle.end(), &self));
                    self.listed = false;
                    gauges->idle = idle.size();
                }
                if (work.empty()) return;
                c = work.front();
                work.pop_front();
                stop_after = stopping;
                --gauges->waiting;
                ++gauges->busy;
            }
            bool keep = serve_request(*c, stop_after);
            while (keep && next_request_here(*c, stop_after)) keep = serve_request(*c, stop_after);
            --gauges->busy;
            finish(*c, keep, self);
        }
    }

    /// After an answer, waits up to kNextRequestWait for the connection's next request on this
    /// thread (while another worker is free for the other connections) and takes it when its
    /// whole head has arrived: a client's request sent right after its last answer wakes this
    /// thread, not the loop, which would then wake a worker. Anything else (nothing within the
    /// wait, pipelined bytes, a partial or refused head, the peer gone) goes back to the loop,
    /// which scans it again. True: the request's head is in `c.head`, to be served here.
    bool next_request_here(Connection& c, bool& stop_after) {
        if (c.buffered() > 0 || c.peer_closed) return false;
        {
            std::lock_guard lock(mutex);
            if (stopping || idle.empty()) return false;
            stop_after = stopping;
        }
        const Clock::time_point until = Clock::now() + kNextRequestWait;
        // Waits for more bytes until `until`; false: none came, or the peer is gone.
        auto wait_for_bytes = [&] {
            pollfd p{c.fd, POLLIN | POLLRDHUP, 0};
            const auto left = std::max(until - Clock::now(), Clock::duration::zero());
            const auto ns = std::chrono::duration_cast<std::chrono::nanoseconds>(left).count();
            const timespec wait{static_cast<time_t>(ns / 1'000'000'000),
                                static_cast<long>(ns % 1'000'000'000)};
            int ready = 0;
            --gauges->busy;  // waiting for a request is not answering one
            do {
                ready = ::ppoll(&p, 1, &wait, nullptr);
            } while (ready < 0 && errno == EINTR);
            ++gauges->busy;
            return ready > 0 && (p.revents & (POLLRDHUP | POLLHUP | POLLERR)) == 0;
        };
        // Reads what has arrived, up to `limit` bytes buffered in all.
        auto read_arrived = [&](size_t limit) {
            while (c.buffered() < limit) {
                const size_t room = std::min(kLoopReadBytes, limit - c.buffered());
                const size_t old_size = c.buffer.size();
                c.buffer.resize(old_size + room);
                const ssize_t n = ::recv(c.fd, c.buffer.data() + old_size, room, MSG_DONTWAIT);
                c.buffer.resize(old_size + static_cast<size_t>(std::max<ssize_t>(n, 0)));
                if (n > 0) continue;
                if (n < 0 && errno == EINTR) continue;
                break;  // all that has arrived (or the peer closed: the loop sees it)
            }
        };
        if (!wait_for_bytes()) return false;
        forget_head(c);
        read_arrived(limits.max_head_bytes + 1);
        int status = 0;
        std::string detail;
        if (scan_head(c, status, detail) != HeadScanned::kComplete) return false;
        // The body's part the loop would buffer before giving the request to a thread must be
        // here too (within the same wait): a worker never waits on a slow body that the loop
        // would have held. Else the connection goes back to the loop, its head scanned anew.
        const size_t wanted = c.head->content_length && !c.head->expect_continue
                                  ? static_cast<size_t>(std::min<uint64_t>(*c.head->content_length,
                                                                           limits.prebuffer_bytes))
                                  : 0;
        const size_t whole = c.head_bytes + wanted;
        read_arrived(whole);
        while (c.buffered() < whole && wait_for_bytes()) read_arrived(whole);
        if (c.buffered() < whole) {
            forget_head(c);
            return false;
        }
        c.body_wanted = 0;
        c.state = Connection::State::kBusy;
        ++gauges->taken_after_answer;
        return true;
    }

    /// Back to the loop, or closed. A connection going back to the loop lists `self` (its
    /// worker) as idle first, so that its next request, which the loop may dispatch before the
    /// worker is back waiting, goes to this thread.
    void finish(Connection& c, bool keep, Idle& self) {
        {
            std::lock_guard lock(mutex);
            if (keep && !stopping) {
                incoming.push_back(&c);
                if (!self.listed) {
                    self.listed = true;
                    idle.push_back(&self);
                    gauges->idle = idle.size();
                }
            } else {
                keep = false;
            }
        }
        if (keep) return wake();
        ::shutdown(c.fd, SHUT_RDWR);
        ::close(c.fd);
        std::lock_guard lock(mutex);
        all.erase(&c);
        --open;
    }

    /// Answers the request whose head (and small body) the loop received. True when the
    /// connection stays open for the next request.
    bool serve_request(Connection& c, bool stopping_now) {
        c.fresh = false;
        const RequestHead head = std::move(*c.head);
        c.head.reset();
        c.consume(c.head_bytes);
        ++c.served;
        httplib::Request req;
        req.method = head.method;
        req.target = head.target;
        req.path = head.path;
        req.version = head.version;
        for (const auto& [name, value] : head.headers) req.headers.emplace(name, value);
        for (const auto& [name, value] : head.query) req.params.emplace(name, value);
        socket_address(c.fd, true, req.remote_addr, req.remote_port);
        socket_address(c.fd, false, req.local_addr, req.local_port);
        httplib::Response res;
        Exchange exchange(c, limits, head);
        const httplib::ContentReader reader(
            [&exchange](httplib::ContentReceiver receiver) {
                return exchange.read_all(
                    [&](const char* data, size_t size) { return receiver(data, size); });
            },
            [](auto&&...) { return false; });  // multipart bodies are not taken
        t_connection = &c;
        t_exchange = &exchange;
        bool failed = false;
        try {
            answer(req, res, reader);
        } catch (...) {
            failed = true;
        }
        if (failed || res.status < 100) {
            res = httplib::Response();
            res.status = 500;
            res.set_header("Connection", "close");
        }
        // A reply held in res.body needs nothing kept: budgets and slots go back before it is
        // written, as soon as the route is done (a memory body keeps them until it is sent).
        if (!exchange.memory_owner || !res.body.empty()) exchange.kept.clear();
        const bool body_read = exchange.body_done || drain(exchange);
        const bool keep = !stopping_now && head.keep_alive && !c.peer_closed && body_read &&
                          !exchange.timed_out && !asks_close(res) &&
                          c.served < limits.keep_alive_max_requests;
        const bool written = write_response(exchange, req, res, keep);
        sent(req, res);
        t_exchange = nullptr;
        t_connection = nullptr;
        return keep && written;
    }

    /// A body the route left unread: read and dropped when it is small and its size known, so
    /// the connection stays usable. False when it is not (the connection is then closed).
    static bool drain(Exchange& exchange) {
        if (exchange.continue_pending || exchange.chunked || exchange.body_failed ||
            exchange.body_left > kDrainBodyBytes)
            return false;
        return exchange.read_all([](const char*, size_t) { return true; });
    }

    bool write_response(Exchange& exchange, const httplib::Request& req,
                        const httplib::Response& res, bool keep) {
        // A body set after a memory body (an error reply replacing it) wins.
        const bool memory = exchange.memory_owner != nullptr && res.body.empty();
        const size_t body_size = memory ? exchange.memory_body.size() : res.body.size();
        std::string head = "HTTP/1.1 " + std::to_string(res.status) + " " +
                           std::string(proto::http_reason_phrase(res.status)) + "\r\n";
        for (const auto& [name, value] : res.headers)
            if (!front_owned(name)) head += name + ": " + value + "\r\n";
        head += kNoSniffLine;
        const bool no_body = res.status == 204 || res.status == 304 || res.status < 200;
        if (!no_body) head += "Content-Length: " + std::to_string(body_size) + "\r\n";
        if (!keep)
            head += "Connection: close\r\n";
        else if (req.version == "HTTP/1.0")
            head += "Connection: keep-alive\r\n";
        head += "\r\n";
        const bool send_body = !no_body && req.method != "HEAD" && body_size > 0;
        const char* body =
            memory ? reinterpret_cast<const char*>(exchange.memory_body.data()) : res.body.data();
        if (send_body && body_size <= kCoalesceBytes) {
            head.append(body, body_size);
            return exchange.send_all({iovec{head.data(), head.size()}});
        }
        std::vector<iovec> parts{iovec{head.data(), head.size()}};
        if (send_body) parts.push_back(iovec{const_cast<char*>(body), body_size});
        return exchange.send_all(std::move(parts));
    }
};

HttpFront::HttpFront(ConnectionLimits limits, EarlyReply early_reply, AnswerRequest answer,
                     ResponseSent sent)
    : impl_(std::make_unique<Impl>(limits, std::move(early_reply), std::move(answer),
                                   std::move(sent))) {}

HttpFront::~HttpFront() = default;

proto::Result<int, std::string> HttpFront::bind(const std::string& host, int port, int backlog) {
    return impl_->bind(host, port, backlog);
}

bool HttpFront::serve() { return impl_->serve(); }

void HttpFront::stop() { impl_->stop(); }

std::shared_ptr<const ConnectionGauges> HttpFront::gauges() const noexcept { return impl_->gauges; }

bool request_deadline_passed() noexcept { return t_exchange != nullptr && t_exchange->timed_out; }

std::function<bool()> client_gone_check() {
    const int fd = t_connection != nullptr ? t_connection->fd : -1;
    return [fd] {
        if (fd < 0) return false;
        pollfd p{fd, POLLRDHUP, 0};
        return ::poll(&p, 1, 0) > 0 && (p.revents & (POLLRDHUP | POLLHUP | POLLERR)) != 0;
    };
}

void reply_from_memory(httplib::Response& res, std::span<const std::byte> bytes,
                       std::shared_ptr<const void> owner, std::string_view content_type) {
    res.status = 200;
    res.body.clear();
    res.set_header("Content-Type", std::string(content_type));
    if (t_exchange == nullptr) {
        res.body.assign(reinterpret_cast<const char*>(bytes.data()), bytes.size());
        return;
    }
    t_exchange->memory_body = bytes;
    t_exchange->memory_owner = owner ? std::move(owner) : std::make_shared<int>(0);
}

uint64_t response_body_bytes(const httplib::Response& res) noexcept {
    if (t_exchange != nullptr && t_exchange->memory_owner && res.body.empty())
        return t_exchange->memory_body.size();
    return res.body.size();
}

void keep_until_sent(std::shared_ptr<void> resource) {
    if (t_exchange != nullptr) t_exchange->kept.push_back(std::move(resource));
}

bool read_body_direct(const httplib::Request& req, const httplib::ContentReader& reader,
                      uint64_t direct_bytes,
                      const std::function<bool(std::span<const std::byte>)>& take,
                      const std::function<bool(const SocketReceive&)>& take_rest) {
    Exchange* const exchange = t_exchange;
    const bool direct = exchange != nullptr && !exchange->chunked && !exchange->body_done &&
                        exchange->body_left >= direct_bytes;
    if (!direct)
        return reader([&](const char* data, size_t size) {
            return take(std::span(reinterpret_cast<const std::byte*>(data), size));
        });
    (void)req;
    if (!exchange->send_continue()) return false;
    // What the loop already received goes to `take`; the rest straight into the caller's
    // storage.
    const size_t buffered =
        static_cast<size_t>(std::min<uint64_t>(exchange->c.buffered(), exchange->body_left));
    if (buffered > 0) {
        const std::span piece(reinterpret_cast<const std::byte*>(exchange->c.data()), buffered);
        const bool ok = take(piece);
        exchange->c.consume(buffered);
        exchange->body_left -= buffered;
        exchange->body_done = exchange->body_left == 0;
        if (!ok) return false;
    }
    return take_rest([exchange](std::byte* out, size_t size) -> ptrdiff_t {
        return exchange->read_body(reinterpret_cast<char*>(out), size);
    });
}

}  // namespace kdrt::server
