#pragma once
// Starts the real kdrt-server binary on an ephemeral loopback port with a temp cache directory,
// for the integration tests (the kdrt_test_server_process library). The binary's path comes from
// the KDRT_SERVER_BINARY definition of that library (tests/common/CMakeLists.txt).

#include <httplib.h>

#include <chrono>
#include <filesystem>
#include <memory>
#include <optional>
#include <string>
#include <vector>

namespace kdrt::test {

/// A fresh directory under $TMPDIR (or /tmp), removed on destruction.
class TempDir {
public:
    TempDir();
    ~TempDir();
    TempDir(const TempDir&) = delete;
    TempDir& operator=(const TempDir&) = delete;
    [[nodiscard]] const std::filesystem::path& path() const noexcept { return path_; }

private:
    std::filesystem::path path_;
};

class ServerProcess {
public:
    struct Options {
        std::filesystem::path cache_dir = {};  ///< required
        std::filesystem::path binary = {};     ///< the server (empty: KDRT_SERVER_BINARY)
        std::vector<std::string> args = {};    ///< extra flags
        std::vector<std::string> env = {};     ///< extra NAME=VALUE
        bool wait_ready = true;                ///< wait for /readyz 200
        uint64_t file_size_limit = 0;          ///< RLIMIT_FSIZE of the server (0 = inherited)
    };

    /// Starts the server and waits until it listens (and is ready, unless told otherwise).
    /// Fails the current test (ADD_FAILURE) and leaves port() == 0 if it does not come up.
    explicit ServerProcess(Options options);
    /// Stops the server with SIGTERM if it is still running.
    ~ServerProcess();
    ServerProcess(const ServerProcess&) = delete;
    ServerProcess& operator=(const ServerProcess&) = delete;

    [[nodiscard]] int port() const noexcept { return port_; }
    [[nodiscard]] bool running() const noexcept { return pid_ > 0; }
    /// The server's process id (for /proc/PID/status), or -1 once it has stopped.
    [[nodiscard]] int pid() const noexcept { return pid_; }

    /// A client for this server (keep-alive, generous timeouts).
    [[nodiscard]] std::unique_ptr<httplib::Client> client() const;

    /// Sends `signal` and waits (up to `timeout`) for the exit; returns the exit code, or -1 if
    /// it was killed by a signal or did not exit in time (then it is SIGKILLed).
    int stop(int signal = 15, std::chrono::seconds timeout = std::chrono::seconds(30));

    /// Everything the server wrote to stderr so far.
    [[nodiscard]] std::string log() const;

    /// The value of one Prometheus sample (`name` or `name{labels}` exactly as printed), or
    /// nullopt when absent.
    [[nodiscard]] std::optional<double> metric(const std::string& series) const;

private:
    Options options_;
    int pid_ = -1;
    int port_ = 0;
    std::filesystem::path log_path_;
    std::filesystem::path port_path_;
};

/// Sends raw bytes on a new loopback connection and returns everything received until the
/// server closes the connection or `timeout` passes.
std::string raw_exchange(int port, const std::string& request, std::chrono::milliseconds timeout);

/// A connected loopback socket (for holding a request open); -1 on failure. Close with ::close.
int connect_loopback(int port);

/// Parses a Prometheus exposition text for one series value.
std::optional<double> find_metric(const std::string& text, const std::string& series);

}  // namespace kdrt::test
