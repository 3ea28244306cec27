#include "image_helper.h"

#include <fcntl.h>
#include <spawn.h>
#include <sys/wait.h>
#include <unistd.h>

#include <cerrno>
#include <csignal>
#include <cstring>
#include <string>
#include <system_error>
#include <vector>

#include "bench_args.h"

extern char** environ;

namespace kdrt::bench {
namespace {

std::string os_reason(int err) { return std::generic_category().message(err); }

/// Closes a descriptor on every path out of a function.
class Fd {
public:
    explicit Fd(int fd = -1) noexcept : fd_(fd) {}
    Fd(const Fd&) = delete;
    Fd& operator=(const Fd&) = delete;
    ~Fd() { reset(); }
    [[nodiscard]] int get() const noexcept { return fd_; }
    void reset() noexcept {
        if (fd_ >= 0) ::close(fd_);
        fd_ = -1;
    }

private:
    int fd_;
};

/// Ignores SIGPIPE while alive, so a helper that exits early makes write() fail with EPIPE
/// instead of killing kdrt-bench.
class IgnoreSigpipe {
public:
    IgnoreSigpipe() noexcept { previous_ = std::signal(SIGPIPE, SIG_IGN); }
    ~IgnoreSigpipe() { std::signal(SIGPIPE, previous_); }
    IgnoreSigpipe(const IgnoreSigpipe&) = delete;
    IgnoreSigpipe& operator=(const IgnoreSigpipe&) = delete;

private:
    void (*previous_)(int);
};

}  // namespace

void write_image_with_helper(const std::filesystem::path& path, const Image& image) {
    std::error_code ec;
    const std::filesystem::path self = std::filesystem::read_symlink("/proc/self/exe", ec);
    if (ec) throw BenchError("cannot locate kdrt-bench itself to find kdrt-image: " + ec.message());
    const std::filesystem::path helper = self.parent_path() / "kdrt-image";
    if (::access(helper.c_str(), X_OK) != 0) {
        throw BenchError("cannot write " + path.string() + ": the helper " + helper.string() +
                         " is missing (build the kdrt-image target)");
    }

    int ends[2];
    if (::pipe2(ends, O_CLOEXEC) != 0)
        throw BenchError("cannot create a pipe: " + os_reason(errno));
    Fd read_end(ends[0]), write_end(ends[1]);

    posix_spawn_file_actions_t actions;
    posix_spawn_file_actions_init(&actions);
    posix_spawn_file_actions_adddup2(&actions, read_end.get(), STDIN_FILENO);
    std::vector<std::string> args = {helper.string(),
                                     "raw",
                                     std::to_string(image.width),
                                     std::to_string(image.height),
                                     std::to_string(image.channels),
                                     path.string()};
    std::vector<char*> argv;
    argv.reserve(args.size() + 1);
    for (std::string& a : args) argv.push_back(a.data());
    argv.push_back(nullptr);
    pid_t pid = 0;
    const int spawned = posix_spawn(&pid, helper.c_str(), &actions, nullptr, argv.data(), environ);
    posix_spawn_file_actions_destroy(&actions);
    if (spawned != 0)
        throw BenchError("cannot start " + helper.string() + ": " + os_reason(spawned));
    read_end.reset();

    std::string write_error;
    {
        const IgnoreSigpipe ignore;
        const auto* data = reinterpret_cast<const char*>(image.pixels.data());
        size_t left = image.pixels.size() * sizeof(float);
        while (left > 0) {
            const ssize_t n = ::write(write_end.get(), data, left);
            if (n < 0 && errno == EINTR) continue;
            if (n <= 0) {
                write_error = os_reason(errno);
                break;
            }
            data += n;
            left -= static_cast<size_t>(n);
        }
        write_end.reset();
    }
    int status = 0;
    while (::waitpid(pid, &status, 0) < 0) {
        if (errno != EINTR)
            throw BenchError("cannot wait for " + helper.string() + ": " + os_reason(errno));
    }
    if (!WIFEXITED(status) || WEXITSTATUS(status) != 0) {
        throw BenchError("kdrt-image could not write " + path.string() +
                         (WIFEXITED(status)
                              ? " (exit status " + std::to_string(WEXITSTATUS(status)) + ")"
                              : " (killed by a signal)"));
    }
    if (!write_error.empty())
        throw BenchError("cannot send the image to kdrt-image: " + write_error);
}

}  // namespace kdrt::bench
