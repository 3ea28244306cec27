#include "cli_runner.h"

#include <fcntl.h>
#include <poll.h>
#include <sys/wait.h>
#include <unistd.h>

#include <csignal>
#include <cstdlib>
#include <cstring>
#include <stdexcept>

extern char** environ;

namespace kdrt::test {
namespace {

/// Reads what is available on `fd` into `out`; false at end of file (or an error such as EIO
/// from a pseudo-terminal whose other side closed).
bool drain(int fd, std::string& out) {
    char buf[65536];
    const ssize_t n = ::read(fd, buf, sizeof buf);
    if (n > 0) {
        out.append(buf, static_cast<size_t>(n));
        return true;
    }
    return n < 0 && (errno == EINTR || errno == EAGAIN);
}

}  // namespace

CliRun run_cli(const std::vector<std::string>& args, const CliOptions& options) {
    std::vector<std::string> argv_strings = {options.binary.empty() ? std::string(KDRT_CLI_BINARY)
                                                                    : options.binary};
    argv_strings.insert(argv_strings.end(), args.begin(), args.end());
    std::vector<std::string> env;
    for (char** e = environ; *e; ++e)
        if (std::strncmp(*e, "KDRT_", 5) != 0 || std::strncmp(*e, "KDRT_TEST", 9) == 0)
            env.emplace_back(*e);
    env.insert(env.end(), options.env.begin(), options.env.end());
    std::vector<char*> argv, envp;
    for (auto& a : argv_strings) argv.push_back(a.data());
    argv.push_back(nullptr);
    for (auto& e : env) envp.push_back(e.data());
    envp.push_back(nullptr);

    int out_pipe[2];
    int err_fds[2];  // [0] read side in the parent, [1] the child's stderr
    if (::pipe2(out_pipe, O_CLOEXEC) != 0) throw std::runtime_error("pipe failed");
    if (options.stderr_tty) {
        const int master = ::posix_openpt(O_RDWR | O_NOCTTY | O_CLOEXEC);
        if (master < 0 || ::grantpt(master) != 0 || ::unlockpt(master) != 0)
            throw std::runtime_error("no pty");
        const int slave = ::open(::ptsname(master), O_RDWR | O_NOCTTY | O_CLOEXEC);
        if (slave < 0) throw std::runtime_error("cannot open the pty");
        err_fds[0] = master;
        err_fds[1] = slave;
    } else if (::pipe2(err_fds, O_CLOEXEC) != 0) {
        throw std::runtime_error("pipe failed");
    }
    const int dev_null = ::open("/dev/null", O_RDONLY | O_CLOEXEC);

    const pid_t pid = ::fork();
    if (pid == 0) {
        ::dup2(dev_null, 0);
        ::dup2(out_pipe[1], 1);
        ::dup2(err_fds[1], 2);
        ::execve(argv[0], argv.data(), envp.data());
        ::_exit(127);
    }
    ::close(out_pipe[1]);
    ::close(err_fds[1]);
    ::close(dev_null);

    CliRun run;
    bool out_open = true, err_open = true, interrupted = false;
    const auto deadline = std::chrono::steady_clock::now() + options.timeout;
    while ((out_open || err_open) && std::chrono::steady_clock::now() < deadline) {
        pollfd fds[2] = {{out_open ? out_pipe[0] : -1, POLLIN, 0},
                         {err_open ? err_fds[0] : -1, POLLIN, 0}};
        if (::poll(fds, 2, 50) < 0 && errno != EINTR) break;
        if (fds[0].revents) out_open = drain(out_pipe[0], run.out);
        if (fds[1].revents) err_open = drain(err_fds[0], run.err);
        if (!interrupted && !options.interrupt_when.empty() &&
            run.err.find(options.interrupt_when) != std::string::npos) {
            ::kill(pid, SIGINT);
            interrupted = true;
        }
        // A pty's master never reports end of file while the child lives: stop once it exited.
        if (options.stderr_tty && !out_open) {
            int status = 0;
            if (::waitpid(pid, &status, WNOHANG) == pid) {
                // The child and its stderr are gone: read what is left until the pty reports EIO.
                while (drain(err_fds[0], run.err)) {
                }
                run.exit_code = WIFEXITED(status) ? WEXITSTATUS(status) : 128 + WTERMSIG(status);
                ::close(out_pipe[0]);
                ::close(err_fds[0]);
                return run;
            }
        }
    }
    ::close(out_pipe[0]);
    ::close(err_fds[0]);
    int status = 0;
    if (out_open || err_open) {  // timed out
        ::kill(pid, SIGKILL);
        ::waitpid(pid, &status, 0);
        run.exit_code = -1;
        return run;
    }
    ::waitpid(pid, &status, 0);
    run.exit_code = WIFEXITED(status) ? WEXITSTATUS(status) : 128 + WTERMSIG(status);
    return run;
}

}  // namespace kdrt::test
