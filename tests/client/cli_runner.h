#pragma once
// Runs the `kdrt` binary (KDRT_CLI_BINARY) as a child process for the CLI tests: arguments,
// extra environment, stdout and stderr captured (stderr optionally on a pseudo-terminal), a
// timeout, and an optional SIGINT once stderr shows a given text.

#include <chrono>
#include <string>
#include <vector>

namespace kdrt::test {

struct CliRun {
    int exit_code = -1;  ///< the exit status; 128 + N when killed by signal N; -1 on timeout
    std::string out;
    std::string err;
};

struct CliOptions {
    std::vector<std::string> env =
        {};                   ///< extra NAME=VALUE (KDRT_* of the test's environment are dropped)
    bool stderr_tty = false;  ///< stderr on a pseudo-terminal (progress bar)
    std::string interrupt_when = {};    ///< send SIGINT once stderr contains this text
    std::chrono::seconds timeout{120};  ///< then SIGKILL, exit_code -1
    std::string binary = {};            ///< the program to run; empty: KDRT_CLI_BINARY
};

/// Whether `text` (a captured stdout or stderr) contains `part`.
inline bool contains(const std::string& text, const std::string& part) {
    return text.find(part) != std::string::npos;
}

/// Runs `kdrt args...` and waits for it.
CliRun run_cli(const std::vector<std::string>& args, const CliOptions& options = {});

}  // namespace kdrt::test
