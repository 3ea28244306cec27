#include "server_process.h"

#include <arpa/inet.h>
#include <fcntl.h>
#include <gtest/gtest.h>
#include <netinet/in.h>
#include <sys/resource.h>
#include <sys/socket.h>
#include <sys/wait.h>
#include <unistd.h>

#include <csignal>
#include <cstdlib>
#include <cstring>
#include <fstream>
#include <sstream>
#include <thread>

extern char** environ;

namespace kdrt::test {
namespace fs = std::filesystem;

TempDir::TempDir() {
    const char* base = std::getenv("TMPDIR");
    std::string pattern = std::string(base && *base ? base : "/tmp") + "/kdrt-test-XXXXXX";
    if (!::mkdtemp(pattern.data())) throw std::runtime_error("mkdtemp failed");
    path_ = pattern;
}

TempDir::~TempDir() {
    std::error_code ec;
    fs::remove_all(path_, ec);
}

ServerProcess::ServerProcess(Options options) : options_(std::move(options)) {
    static int counter = 0;
    const std::string tag = std::to_string(::getpid()) + "-" + std::to_string(counter++);
    log_path_ = options_.cache_dir.parent_path() / ("server-" + tag + ".log");
    port_path_ = options_.cache_dir.parent_path() / ("server-" + tag + ".port");

    std::vector<std::string> args = {
        options_.binary.empty() ? std::string(KDRT_SERVER_BINARY) : options_.binary.string(),
        "--listen", "127.0.0.1:0", "--port-file", port_path_.string(), "--cache-dir",
        options_.cache_dir.string(), "--threads", "2", "--http-threads", "8",
        // Idle keep-alive connections hold up a stop for this long.
        "--keep-alive-timeout-s", "1"};
    args.insert(args.end(), options_.args.begin(), options_.args.end());
    std::vector<std::string> env;
    for (char** e = environ; *e; ++e)
        if (std::strncmp(*e, "KDRT_", 5) != 0 || std::strncmp(*e, "KDRT_TEST", 9) == 0)
            env.emplace_back(*e);
    env.insert(env.end(), options_.env.begin(), options_.env.end());

    std::vector<char*> argv, envp;
    for (auto& a : args) argv.push_back(a.data());
    argv.push_back(nullptr);
    for (auto& e : env) envp.push_back(e.data());
    envp.push_back(nullptr);

    const int log_fd = ::open(log_path_.c_str(), O_WRONLY | O_CREAT | O_TRUNC | O_CLOEXEC, 0644);
    pid_ = ::fork();
    if (pid_ == 0) {
        ::dup2(log_fd, 2);
        ::dup2(log_fd, 1);
        if (options_.file_size_limit > 0) {
            const rlimit limit{options_.file_size_limit, options_.file_size_limit};
            ::setrlimit(RLIMIT_FSIZE, &limit);
        }
        ::execve(argv[0], argv.data(), envp.data());
        ::_exit(127);
    }
    ::close(log_fd);

    const auto deadline = std::chrono::steady_clock::now() + std::chrono::seconds(60);
    while (std::chrono::steady_clock::now() < deadline) {
        std::ifstream in(port_path_);
        if (in >> port_) break;
        int status = 0;
        if (::waitpid(pid_, &status, WNOHANG) == pid_) {
            pid_ = -1;
            ADD_FAILURE() << "kdrt-server exited during start-up:\n" << log();
            return;
        }
        std::this_thread::sleep_for(std::chrono::milliseconds(10));
    }
    if (port_ == 0) {
        ADD_FAILURE() << "kdrt-server wrote no port file in 60 s:\n" << log();
        return;
    }
    if (!options_.wait_ready) return;
    auto cli = client();
    while (std::chrono::steady_clock::now() < deadline) {
        auto res = cli->Get("/readyz");
        if (res && res->status == 200) return;
        int status = 0;
        if (::waitpid(pid_, &status, WNOHANG) == pid_) {
            pid_ = -1;
            ADD_FAILURE() << "kdrt-server exited before it was ready:\n" << log();
            return;
        }
        std::this_thread::sleep_for(std::chrono::milliseconds(10));
    }
    ADD_FAILURE() << "kdrt-server not ready in 60 s:\n" << log();
}

ServerProcess::~ServerProcess() {
    if (pid_ > 0) {
        const int code = stop();
        EXPECT_EQ(code, 0) << "kdrt-server did not exit cleanly on SIGTERM:\n" << log();
    }
    std::error_code ec;
    fs::remove(log_path_, ec);
    fs::remove(port_path_, ec);
}

std::unique_ptr<httplib::Client> ServerProcess::client() const {
    auto cli = std::make_unique<httplib::Client>("127.0.0.1", port_);
    cli->set_keep_alive(true);
    cli->set_read_timeout(120, 0);
    cli->set_write_timeout(120, 0);
    cli->set_connection_timeout(5, 0);
    return cli;
}

int ServerProcess::stop(int signal, std::chrono::seconds timeout) {
    if (pid_ <= 0) return -1;
    ::kill(pid_, signal);
    const auto deadline = std::chrono::steady_clock::now() + timeout;
    int status = 0;
    while (std::chrono::steady_clock::now() < deadline) {
        if (::waitpid(pid_, &status, WNOHANG) == pid_) {
            pid_ = -1;
            return WIFEXITED(status) ? WEXITSTATUS(status) : -1;
        }
        std::this_thread::sleep_for(std::chrono::milliseconds(5));
    }
    ::kill(pid_, SIGKILL);
    ::waitpid(pid_, &status, 0);
    pid_ = -1;
    return -1;
}

std::string ServerProcess::log() const {
    std::ifstream in(log_path_);
    std::stringstream ss;
    ss << in.rdbuf();
    return ss.str();
}

std::optional<double> ServerProcess::metric(const std::string& series) const {
    auto res = client()->Get("/metrics");
    if (!res || res->status != 200) return std::nullopt;
    return find_metric(res->body, series);
}

std::optional<double> find_metric(const std::string& text, const std::string& series) {
    std::istringstream in(text);
    std::string line;
    while (std::getline(in, line)) {
        if (line.size() > series.size() && line.compare(0, series.size(), series) == 0 &&
            line[series.size()] == ' ')
            return std::strtod(line.c_str() + series.size() + 1, nullptr);
    }
    return std::nullopt;
}

int connect_loopback(int port) {
    const int fd = ::socket(AF_INET, SOCK_STREAM | SOCK_CLOEXEC, 0);
    sockaddr_in addr{};
    addr.sin_family = AF_INET;
    addr.sin_port = htons(static_cast<uint16_t>(port));
    addr.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
    if (::connect(fd, reinterpret_cast<sockaddr*>(&addr), sizeof addr) != 0) {
        ::close(fd);
        return -1;
    }
    return fd;
}

std::string raw_exchange(int port, const std::string& request, std::chrono::milliseconds timeout) {
    const int fd = connect_loopback(port);
    if (fd < 0) return {};
    timeval tv{};
    tv.tv_sec = static_cast<time_t>(timeout.count() / 1000);
    tv.tv_usec = static_cast<suseconds_t>((timeout.count() % 1000) * 1000);
    ::setsockopt(fd, SOL_SOCKET, SO_RCVTIMEO, &tv, sizeof tv);
    ::send(fd, request.data(), request.size(), MSG_NOSIGNAL);
    std::string out;
    char buf[4096];
    for (;;) {
        const ssize_t n = ::recv(fd, buf, sizeof buf, 0);
        if (n <= 0) break;
        out.append(buf, static_cast<size_t>(n));
    }
    ::close(fd);
    return out;
}

}  // namespace kdrt::test
