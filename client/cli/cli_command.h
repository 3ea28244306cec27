#pragma once
/// The `kdrt` command table: one Command per subcommand, defined in the file that implements it
/// (its help text and options next to its code). Dispatch (cli_commands.cpp) and `kdrt --help`
/// read this table only. Internal to the CLI.

#include <span>
#include <string>
#include <string_view>

#include "cli_args.h"

namespace kdrt::cli {

struct Context;

/// One subcommand. All members point at static storage (literals, constant arrays), so a
/// Command is a constant and the table needs no initialisation order.
struct Command {
    std::string_view name;      ///< "upload": what follows `kdrt`
    std::string_view synopsis;  ///< its line in `kdrt --help`: "upload FILE..."
    std::string_view summary;   ///< what it does, after the synopsis in `kdrt --help`
    std::string_view help;      ///< `kdrt NAME --help` and `kdrt help NAME`
    std::span<const OptionSpec> options = {};  ///< its options besides kGlobalOptions
    bool needs_server = true;                  ///< reads --server, --token, --timeout, --retries
    int (*run)(Context&) = nullptr;            ///< runs it; returns the exit code (ExitCode)
    /// A family of commands (`kdrt scene create ...`): the argument after the name picks one of
    /// these, whose name is "<family> <subcommand>"; it takes its own options and this
    /// Command's. `help` then describes the family; `run` is not used.
    std::span<const Command* const> subcommands = {};
};

// The mesh commands (cli_meshes.cpp).
extern const Command kUploadCommand;
extern const Command kMeshesCommand;
extern const Command kInfoCommand;
extern const Command kRmCommand;
// Rendering (cli_render.cpp).
extern const Command kRenderCommand;
// Ray files: generate them locally, trace them remotely (cli_rays.cpp).
extern const Command kTraceCommand;
extern const Command kHitsCommand;
extern const Command kRaysCommand;
// Distance queries (cli_distance.cpp).
extern const Command kDistanceCommand;
// The server's state (cli_ops.cpp).
extern const Command kHealthCommand;
extern const Command kMetricsCommand;
// Sensor scans (cli_scan.cpp).
extern const Command kScanCommand;
// Scenes: kdrt scene create|get|list|rm|poses|trace|hits|distance|scan (cli_scene.cpp).
extern const Command kSceneCommand;
// Remote tracing speed (cli_bench_remote.cpp).
extern const Command kBenchRemoteCommand;

/// Every command, in the order `kdrt --help` lists them.
[[nodiscard]] std::span<const Command* const> commands() noexcept;

/// The command called `name`, or nullptr.
[[nodiscard]] const Command* find_command(std::string_view name) noexcept;

/// The `kdrt --help` text: usage, one line per command of commands(), the global options.
[[nodiscard]] const std::string& main_help();

}  // namespace kdrt::cli
