// kdrt: the command-line client of kdrt-server. See `kdrt --help`; the commands are listed in
// client/cli/cli_command.h, each with its help text in the file that implements it.

#include <unistd.h>

#include <atomic>
#include <csignal>
#include <cstring>
#include <iostream>
#include <map>
#include <string>
#include <vector>

#include "cli_commands.h"

extern char** environ;

namespace {

std::atomic<bool> g_interrupted{false};
std::atomic<bool> g_waiting{false};

/// While a render is waited for, SIGINT only sets a flag (the job is then cancelled on the
/// server); at any other time it terminates the process as usual.
extern "C" void on_interrupt(int signal_number) {
    if (g_waiting.load()) {
        g_interrupted.store(true);
        return;
    }
    ::signal(signal_number, SIG_DFL);
    ::raise(signal_number);
}

}  // namespace

int main(int argc, char** argv) {
    static_assert(std::atomic<bool>::is_always_lock_free,
                  "the SIGINT handler stores to an atomic<bool>");
    std::vector<std::string> args(argv + 1, argv + argc);
    std::map<std::string, std::string> env;
    for (char** e = environ; *e; ++e) {
        const char* eq = std::strchr(*e, '=');
        if (eq && std::strncmp(*e, "KDRT_", 5) == 0)
            env.emplace(std::string(*e, static_cast<size_t>(eq - *e)), std::string(eq + 1));
    }
    struct sigaction action {};
    action.sa_handler = on_interrupt;
    sigemptyset(&action.sa_mask);
    ::sigaction(SIGINT, &action, nullptr);
    ::signal(SIGPIPE, SIG_IGN);

    const kdrt::cli::Console console{std::cout, std::cerr, ::isatty(STDERR_FILENO) == 1,
                                     &g_interrupted, &g_waiting};
    const int code = kdrt::cli::run(args, env, console);
    std::cout.flush();
    return code;
}
