#pragma once
/// The `kdrt` command-line tool: subcommands over kdrt::Client. main() only collects the
/// environment, the streams and the interrupt flag; everything else is here.

#include <atomic>
#include <map>
#include <ostream>
#include <span>
#include <string>

namespace kdrt::cli {

/// Where a run writes, and what it knows about the terminal.
struct Console {
    std::ostream& out;        ///< results (ids, tables, JSON lines)
    std::ostream& err;        ///< messages, progress
    bool err_is_tty = false;  ///< draw a progress bar instead of lines
    const std::atomic<bool>* interrupted =
        nullptr;                           ///< set on SIGINT while `waiting`: cancel the job
    std::atomic<bool>* waiting = nullptr;  ///< true while a render job is waited for
};

/// Runs `kdrt ARGS...` (argv without argv[0]). `env` holds the environment variables the tool
/// reads (KDRT_SERVER; the client library reads KDRT_TOKEN itself). Returns the exit code
/// (ExitCode in cli_args.h).
[[nodiscard]] int run(std::span<const std::string> args,
                      const std::map<std::string, std::string>& env, const Console& console);

}  // namespace kdrt::cli
