#include "http/httplib_internals.h"

#include <netdb.h>
#include <netinet/in.h>
#include <poll.h>
#include <sys/epoll.h>
#include <sys/eventfd.h>
#include <sys/resource.h>
#include <sys/socket.h>
#include <unistd.h>

#include <algorithm>
#include <atomic>
#include <cerrno>
#include <charconv>
#include <chrono>
#include <condition_variable>
#include <cstring>
#include <deque>
#include <limits>
#include <mutex>
#include <optional>
#include <string>
#include <thread>
#include <unordered_map>
#include <unordered_set>
#include <vector>

#include "http/http_util.h"

namespace kdrt::server {
namespace {

using Clock = std::chrono::steady_clock;

/// Largest single recv() of the poll() loop.
constexpr size_t kLoopReadBytes = size_t{16} << 10;
/// How often the poll() loop looks for connections past a deadline.
constexpr auto kSweepInterval = std::chrono::milliseconds(50);
/// After an early reply the connection is read and dropped for up to this long before it is
/// closed, so the client sees the reply rather than a reset caused by its own unread bytes.
constexpr auto kLingerTime = std::chrono::seconds(1);

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

void socket_address(int fd, bool peer, std::string& host, int& port) {
    sockaddr_storage addr{};
    socklen_t len = sizeof addr;
    const int rc = peer ? ::getpeername(fd, reinterpret_cast<sockaddr*>(&addr), &len)
                        : ::getsockname(fd, reinterpret_cast<sockaddr*>(&addr), &len);
    if (rc != 0 || !numeric_address(addr, len, host, port)) {
        host.clear();
        port = 0;
    }
}

/// Milliseconds from now to `t`, rounded up (0 once it has passed, at most `cap_ms`).
int millis_until(Clock::time_point t, int cap_ms) {
    const auto left = std::chrono::ceil<std::chrono::milliseconds>(t - Clock::now());
    return static_cast<int>(std::clamp<int64_t>(left.count(), 0, cap_ms));
}

bool iequals(std::string_view a, std::string_view b) {
    return a.size() == b.size() && std::equal(a.begin(), a.end(), b.begin(), [](char x, char y) {
               return std::tolower(static_cast<unsigned char>(x)) ==
                      std::tolower(static_cast<unsigned char>(y));
           });
}

std::string_view trim(std::string_view s) {
    while (!s.empty() && (s.front() == ' ' || s.front() == '\t')) s.remove_prefix(1);
    while (!s.empty() && (s.back() == ' ' || s.back() == '\t' || s.back() == '\r'))
        s.remove_suffix(1);
    return s;
}

/// What the connection layer needs to know of a complete request head.
struct HeadInfo {
    std::string method;
    std::optional<uint64_t> content_length;  ///< when present and a plain decimal number
    bool transfer_encoding = false;
    bool expect_continue = false;
};

HeadInfo scan_head(std::string_view head) {
    HeadInfo info;
    size_t line_end = head.find('\n');
    const std::string_view request_line = head.substr(0, line_end);
    info.method = std::string(request_line.substr(0, std::min<size_t>(request_line.find(' '), 32)));
    while (line_end != std::string_view::npos && line_end + 1 < head.size()) {
        const size_t start = line_end + 1;
        line_end = head.find('\n', start);
        const std::string_view line = head.substr(start, line_end - start);
        const size_t colon = line.find(':');
        if (colon == std::string_view::npos) continue;
        const std::string_view name = line.substr(0, colon);
        const std::string_view value = trim(line.substr(colon + 1));
        if (iequals(name, "Content-Length")) {
            uint64_t n = 0;
            const auto [end, ec] = std::from_chars(value.data(), value.data() + value.size(), n);
            if (ec == std::errc() && end == value.data() + value.size() && !value.empty())
                info.content_length = n;
        } else if (iequals(name, "Transfer-Encoding")) {
            info.transfer_encoding = true;
        } else if (iequals(name, "Expect")) {
            info.expect_continue = iequals(value, "100-continue");
        }
    }
    return info;
}

const char* reason_phrase(int status) {
    switch (status) {
        case 400:
            return "Bad Request";
        case 408:
            return "Request Timeout";
        case 431:
            return "Request Header Fields Too Large";
        case 503:
            return "Service Unavailable";
        default:
            return "Error";
    }
}

/// One client connection. Owned by the poll() loop while parked (idle, or a request arriving),
/// by one worker while a request on it is answered; handed over under Reactor::mutex_.
struct Connection {
    enum class State { kIdle, kHead, kBody, kBusy, kLinger };

    explicit Connection(int socket) : fd(socket), idle_since(Clock::now()) {}

    int fd;
    State state = State::kIdle;
    std::vector<char> buffer;  ///< received, unconsumed bytes: buffer[begin, size)
    size_t begin = 0;
    size_t scanned = 0;      ///< head bytes (from begin) already searched for the blank line
    size_t head_lines = 0;   ///< line ends seen in the head so far
    size_t head_bytes = 0;   ///< length of the complete head (kBody)
    size_t body_wanted = 0;  ///< body bytes to receive before a thread is given (kBody)
    size_t reserved = 0;     ///< bytes taken from the prebuffer budget
    Clock::time_point idle_since, request_start, linger_until;
    bool fresh = true;  ///< no request received yet
    bool peer_closed = false;
    bool timed_out = false;    ///< the request's deadline passed while a worker read its body
    bool close_after = false;  ///< the response asked for the connection to be closed
    unsigned served = 0;
    std::string method;

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

thread_local Connection* t_connection = nullptr;

/// The Stream httplib reads a request from and writes its response to: the bytes the poll()
/// loop already received first, then the socket, every read bounded by the read timeout and the
/// request's deadline.
class ConnectionStream final : public httplib::Stream {
public:
    ConnectionStream(Connection& c, const ConnectionLimits& limits)
        : c_(c),
          read_timeout_ms_(static_cast<int>(limits.read_timeout_s) * 1000),
          write_timeout_ms_(static_cast<int>(limits.write_timeout_s) * 1000),
          deadline_(c.request_start + std::chrono::seconds(limits.request_timeout_s)) {}

    bool is_readable() const override {
        if (c_.buffered() > 0) return true;
        pollfd p{c_.fd, POLLIN, 0};
        return ::poll(&p, 1,
                      std::min(read_timeout_ms_,
                               millis_until(deadline_, std::numeric_limits<int>::max()))) > 0;
    }

    bool is_writable() const override {
        pollfd p{c_.fd, POLLOUT, 0};
        return ::poll(&p, 1, write_timeout_ms_) > 0 && (p.revents & (POLLERR | POLLHUP)) == 0;
    }

    ssize_t read(char* ptr, size_t size) override { return receive(ptr, size); }

    /// Buffered bytes first, then one recv() after waiting for data up to the read timeout and
    /// the deadline.
    ssize_t receive(char* ptr, size_t size) {
        if (size == 0) return 0;
        if (c_.buffered() > 0) {
            const size_t n = std::min(size, c_.buffered());
            std::memcpy(ptr, c_.data(), n);
            c_.consume(n);
            return static_cast<ssize_t>(n);
        }
        for (;;) {
            const ssize_t n = ::recv(c_.fd, ptr, size, MSG_DONTWAIT);
            if (n >= 0) return n;
            if (errno == EINTR) continue;
            if (errno != EAGAIN && errno != EWOULDBLOCK) return -1;
            // Waits for the read timeout, or less when the deadline comes first (then a wait
            // without data is the deadline's).
            const int until_deadline = millis_until(deadline_, std::numeric_limits<int>::max());
            const bool deadline_first = until_deadline < read_timeout_ms_;
            if (until_deadline == 0) {
                c_.timed_out = true;
                return -1;
            }
            pollfd p{c_.fd, POLLIN, 0};
            const int ready = ::poll(&p, 1, deadline_first ? until_deadline : read_timeout_ms_);
            if (ready < 0 && errno == EINTR) continue;
            if (ready == 0 && deadline_first) c_.timed_out = true;
            if (ready <= 0) return -1;
        }
    }

    ssize_t write(const char* ptr, size_t size) override {
        for (;;) {
            const ssize_t n = ::send(c_.fd, ptr, size, MSG_DONTWAIT | MSG_NOSIGNAL);
            if (n >= 0) return n;
            if (errno == EINTR) continue;
            if (errno != EAGAIN && errno != EWOULDBLOCK) return -1;
            pollfd p{c_.fd, POLLOUT, 0};
            const int ready = ::poll(&p, 1, write_timeout_ms_);
            if (ready < 0 && errno == EINTR) continue;
            if (ready <= 0) return -1;
        }
    }

    void get_remote_ip_and_port(std::string& ip, int& port) const override {
        socket_address(c_.fd, true, ip, port);
    }
    void get_local_ip_and_port(std::string& ip, int& port) const override {
        socket_address(c_.fd, false, ip, port);
    }
    socket_t socket() const override { return c_.fd; }

private:
    Connection& c_;
    int read_timeout_ms_, write_timeout_ms_;
    Clock::time_point deadline_;
};

thread_local ConnectionStream* t_stream = nullptr;

/// httplib's accept loop hands each accepted socket to a TaskQueue; this one runs the task at
/// once on the accept thread (the task is ConnectionServer::process_and_close_socket, which only
/// gives the socket to the poll() loop), and shutting it down stops the connection layer.
class HandOver final : public httplib::TaskQueue {
public:
    explicit HandOver(std::function<void()> on_shutdown) : on_shutdown_(std::move(on_shutdown)) {}
    void enqueue(std::function<void()> fn) override { fn(); }
    void shutdown() override { on_shutdown_(); }

private:
    std::function<void()> on_shutdown_;
};

}  // namespace

/// The epoll loop and the worker threads (see ConnectionServer).
struct ConnectionServer::Reactor {
    using Serve = std::function<bool(httplib::Stream&, bool last, bool& closed)>;

    explicit Reactor(Serve serve_request) : serve(std::move(serve_request)) {}
    ~Reactor() { stop(); }
    Reactor(const Reactor&) = delete;
    Reactor& operator=(const Reactor&) = delete;

    Serve serve;
    ConnectionLimits limits;
    EarlyReply early_reply;

    std::mutex mutex;
    std::condition_variable work_cv;
    std::deque<Connection*> work;       ///< complete requests waiting for a worker
    std::vector<Connection*> incoming;  ///< new or returned connections for the loop
    std::unordered_map<Connection*, std::unique_ptr<Connection>> all;
    bool stopping = false;
    bool running = false;

    std::shared_ptr<ConnectionGauges> gauges = std::make_shared<ConnectionGauges>();
    std::atomic<size_t>& open = gauges->open;
    std::atomic<size_t> prebuffered{0};
    int epoll_fd = -1;
    int wake_fd = -1;
    std::thread loop_thread;
    std::vector<std::thread> workers;

    void start() {
        std::lock_guard lock(mutex);
        if (running) return;
        raise_file_limit();
        epoll_fd = ::epoll_create1(EPOLL_CLOEXEC);
        wake_fd = ::eventfd(0, EFD_CLOEXEC | EFD_NONBLOCK);
        epoll_event ev{};
        ev.events = EPOLLIN;
        ev.data.ptr = nullptr;
        ::epoll_ctl(epoll_fd, EPOLL_CTL_ADD, wake_fd, &ev);
        stopping = false;
        running = true;
        loop_thread = std::thread([this] { run_loop(); });
        for (unsigned i = 0; i < std::max(1u, limits.threads); ++i)
            workers.emplace_back([this] { run_worker(); });
    }

    /// Parked connections are closed; requests being answered finish, then their connections
    /// close; complete requests still waiting for a worker are answered first.
    void stop() {
        {
            std::lock_guard lock(mutex);
            if (!running) return;
            stopping = true;
        }
        wake();
        work_cv.notify_all();
        loop_thread.join();
        for (std::thread& t : workers) t.join();
        workers.clear();
        std::lock_guard lock(mutex);
        for (auto& [ptr, c] : all) ::close(c->fd);
        open -= all.size();
        all.clear();
        incoming.clear();
        ::close(epoll_fd);
        ::close(wake_fd);
        running = false;
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

    void wake() const {
        const uint64_t one = 1;
        [[maybe_unused]] const ssize_t n = ::write(wake_fd, &one, sizeof one);
    }

    /// From the accept thread.
    void adopt(int fd) {
        if (open.load() >= limits.max_connections) {
            send_early(fd, 503, "",
                       "the server has " + std::to_string(limits.max_connections) +
                           " connections open (max_connections); retry later");
            ::close(fd);
            return;
        }
        auto owned = std::make_unique<Connection>(fd);
        Connection* c = owned.get();
        {
            std::lock_guard lock(mutex);
            if (stopping) {
                ::close(fd);
                return;
            }
            all.emplace(c, std::move(owned));
            incoming.push_back(c);
            ++open;
        }
        wake();
    }

    /// Sends a complete early reply without blocking (best effort: a full socket buffer drops
    /// it).
    void send_early(int fd, int status, std::string_view method, const std::string& detail) const {
        const std::string body = early_reply ? early_reply(status, method, detail) : detail;
        std::string reply = "HTTP/1.1 " + std::to_string(status) + " " + reason_phrase(status) +
                            "\r\nContent-Type: application/problem+json\r\nContent-Length: " +
                            std::to_string(body.size()) + "\r\nConnection: close\r\n";
        if (status == 503) reply += "Retry-After: 1\r\n";
        reply += "\r\n" + body;
        [[maybe_unused]] const ssize_t n =
            ::send(fd, reply.data(), reply.size(), MSG_DONTWAIT | MSG_NOSIGNAL);
    }

    // ---- the poll() loop ------------------------------------------------------------------

    std::unordered_set<Connection*> parked;  ///< loop thread only

    void run_loop() {
        std::vector<epoll_event> events(256);
        auto last_sweep = Clock::now();
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
                auto* c = static_cast<Connection*>(events[i].data.ptr);
                if (c == nullptr) {
                    uint64_t count = 0;
                    [[maybe_unused]] const ssize_t r = ::read(wake_fd, &count, sizeof count);
                    continue;
                }
                if (parked.count(c) != 0) on_readable(*c);
            }
            for (Connection* c : arrived) park(*c);
            if (Clock::now() - last_sweep >= kSweepInterval) {
                sweep();
                last_sweep = Clock::now();
            }
        }
        for (Connection* c : parked) release_budget(*c);
        parked.clear();
    }

    /// A new connection, or one back from a worker: its next request may already be buffered.
    void park(Connection& c) {
        c.state = Connection::State::kIdle;
        c.idle_since = Clock::now();
        c.scanned = 0;
        c.head_lines = 0;
        c.timed_out = false;
        c.close_after = false;
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
            // RFC 9112 2.2: empty lines before a request line are ignored.
            while (c.scanned == 0 && c.buffered() > 0 && (*c.data() == '\r' || *c.data() == '\n'))
                c.consume(1);
            if (c.buffered() == 0) {
                c.state = Connection::State::kIdle;
                return;
            }
            if (c.state == Connection::State::kIdle) {
                c.state = Connection::State::kHead;
                c.request_start = Clock::now();
            }
            const std::optional<size_t> head = find_head_end(c);
            if (!head) {
                if (c.head_lines > limits.max_headers + 1)
                    return refuse(c, 431, too_many_headers());
                if (c.buffered() > limits.max_head_bytes) return refuse(c, 431, head_too_large());
                return;
            }
            if (*head > limits.max_head_bytes) return refuse(c, 431, head_too_large());
            if (c.head_lines > limits.max_headers + 1) return refuse(c, 431, too_many_headers());
            const HeadInfo info = scan_head(std::string_view(c.data(), *head));
            c.method = info.method;
            c.head_bytes = *head;
            c.body_wanted = 0;
            if (info.content_length && !info.transfer_encoding && !info.expect_continue) {
                const size_t wanted = static_cast<size_t>(
                    std::min<uint64_t>(*info.content_length, limits.prebuffer_bytes));
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

    /// The length of the head (through its blank line) when it is complete. Counts line ends.
    std::optional<size_t> find_head_end(Connection& c) const {
        const char* d = c.data();
        const size_t size = c.buffered();
        for (size_t i = c.scanned; i < size; ++i) {
            if (d[i] != '\n') continue;
            ++c.head_lines;
            if (i + 1 < size && d[i + 1] == '\n') return i + 2;
            if (i + 2 < size && d[i + 1] == '\r' && d[i + 2] == '\n') return i + 3;
            if (i + 2 >= size) {  // the blank line may still be arriving: look here again
                c.scanned = i;
                --c.head_lines;
                return std::nullopt;
            }
        }
        c.scanned = size;
        return std::nullopt;
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
        }
        work_cv.notify_one();
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
        for (;;) {
            Connection* c = nullptr;
            bool stop_after = false;
            {
                std::unique_lock lock(mutex);
                work_cv.wait(lock, [&] { return stopping || !work.empty(); });
                if (work.empty()) return;
                c = work.front();
                work.pop_front();
                stop_after = stopping;
                --gauges->waiting;
                ++gauges->busy;
            }
            answer(*c, stop_after);
            --gauges->busy;
        }
    }

    void answer(Connection& c, bool stopping_now) {
        c.fresh = false;
        const bool last =
            stopping_now || c.peer_closed || c.served + 1 >= limits.keep_alive_max_requests;
        bool closed = false;
        bool ok = false;
        {
            ConnectionStream stream(c, limits);
            t_connection = &c;
            t_stream = &stream;
            try {
                ok = serve(stream, last, closed);
            } catch (...) {
                ok = false;
            }
            t_stream = nullptr;
            t_connection = nullptr;
        }
        ++c.served;
        bool keep = ok && !closed && !last && !c.close_after && !c.timed_out;
        {
            std::lock_guard lock(mutex);
            if (keep && !stopping) {
                incoming.push_back(&c);
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
};

ConnectionServer::ConnectionServer()
    : reactor_(std::make_unique<Reactor>([this](httplib::Stream& s, bool last, bool& closed) {
          return serve_one(s, last, closed);
      })) {
    new_task_queue = [this] {
        reactor_->start();
        return new HandOver([this] { reactor_->stop(); });
    };
}

ConnectionServer::~ConnectionServer() { reactor_->stop(); }

void ConnectionServer::set_connection_limits(const ConnectionLimits& limits,
                                             EarlyReply early_reply) {
    reactor_->limits = limits;
    reactor_->early_reply = std::move(early_reply);
}

bool ConnectionServer::set_listen_backlog(int backlog) {
    const socket_t sock = svr_sock_;
    return sock != INVALID_SOCKET && ::listen(sock, backlog) == 0;
}

size_t ConnectionServer::open_connections() const noexcept { return reactor_->open.load(); }

std::shared_ptr<const ConnectionGauges> ConnectionServer::gauges() const noexcept {
    return reactor_->gauges;
}

bool ConnectionServer::process_and_close_socket(socket_t sock) {
    reactor_->adopt(sock);
    return true;
}

bool ConnectionServer::serve_one(httplib::Stream& stream, bool last, bool& closed) {
    // Range requests are ignored on every route: the whole body is sent (200).
    static const std::function<void(httplib::Request&)> ignore_ranges = [](httplib::Request& req) {
        req.ranges.clear();
    };
    return process_request(stream, last, closed, ignore_ranges);
}

bool request_deadline_passed() noexcept {
    return t_connection != nullptr && t_connection->timed_out;
}

std::function<bool()> client_gone_check() {
    const int fd = t_connection != nullptr ? t_connection->fd : -1;
    return [fd] {
        if (fd < 0) return false;
        pollfd p{fd, POLLRDHUP, 0};
        return ::poll(&p, 1, 0) > 0 && (p.revents & (POLLRDHUP | POLLHUP | POLLERR)) != 0;
    };
}

void note_response_sent(const httplib::Response& res) noexcept {
    if (t_connection == nullptr) return;
    const auto it = res.headers.find("Connection");
    if (it != res.headers.end() && iequals(it->second, "close")) t_connection->close_after = true;
}

uint64_t response_body_bytes(const httplib::Response& res) noexcept {
    return res.content_length_ ? res.content_length_ : res.body.size();
}

bool response_has_content(const httplib::Response& res) noexcept {
    return !res.body.empty() || res.content_length_ > 0;
}

void keep_until_sent(httplib::Response& res, std::shared_ptr<void> resource) {
    if (!res.content_provider_) return;
    auto previous = std::move(res.content_provider_resource_releaser_);
    res.content_provider_resource_releaser_ = [resource = std::move(resource),
                                               previous](bool success) {
        if (previous) previous(success);
    };
}

bool read_body_direct(const httplib::Request& req, const httplib::ContentReader& reader,
                      uint64_t direct_bytes,
                      const std::function<bool(std::span<const std::byte>)>& take,
                      const std::function<bool(const SocketReceive&)>& take_rest) {
    const std::optional<uint64_t> declared = declared_body_bytes(req);
    const bool chunked = is_chunked(req);
    if (!(declared && *declared > 0) && !chunked) return true;  // no body to read
    const std::string encoding = req.get_header_value("Content-Encoding");
    ConnectionStream* const stream = t_stream;
    const bool direct = stream != nullptr && declared && *declared >= direct_bytes &&
                        !req.has_header("Transfer-Encoding") &&
                        (encoding.empty() || encoding == "identity");
    uint64_t received = 0;
    bool go_direct = false;
    const bool read_ok = reader([&](const char* data, size_t size) {
        received += size;
        if (!take(std::span(reinterpret_cast<const std::byte*>(data), size))) return false;
        if (direct && received < *declared) {
            go_direct = true;
            return false;  // httplib's reader stops here; take_rest receives the rest
        }
        return true;
    });
    if (!go_direct) return read_ok;
    return take_rest([stream](std::byte* out, size_t size) {
        return static_cast<ptrdiff_t>(stream->receive(reinterpret_cast<char*>(out), size));
    });
}

}  // namespace kdrt::server
