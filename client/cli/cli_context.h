#pragma once
/// What the subcommand implementations share (internal to the CLI): one run's context, and the
/// checks and messages every command uses.

#include <cstddef>
#include <optional>
#include <span>
#include <string>
#include <string_view>

#include "cli_args.h"
#include "cli_commands.h"
#include "cli_output.h"
#include "kdrt/client/client.h"

namespace kdrt::cli {

/// One subcommand's run: its parsed arguments, connection settings and (if it talks to the
/// server) the client.
struct Context {
    const Console& console;
    std::string_view command;  ///< "upload", ...
    ParsedArgs args;
    GlobalSettings settings;
    std::optional<Client> client;

    /// The client options the global settings ask for (token, timeout, retries).
    [[nodiscard]] ClientOptions client_options() const;
    /// Creates `client` with `options` (from client_options(), possibly adjusted).
    Client& connect(const ClientOptions& options);

    /// Prints "kdrt <command>: <message>" and a pointer to --help; returns kExitUsage.
    int usage_error(std::string_view message) const;
    /// Prints "kdrt <command>: [<subject>: ]<error>" (with a hint for connection errors) and
    /// returns its exit code: kServer/kProtocol/kJobFailed/kCancelled -> 1, kInput -> 2,
    /// kConnection -> 3.
    int fail(const Error& error, std::string_view subject = {}) const;
    /// The full mesh id for `arg`: a 64-digit id as is; a shorter hex prefix (4 or more digits)
    /// resolved against the stored meshes (ambiguous: usage error); anything else as is (the
    /// server then answers 404).
    [[nodiscard]] proto::Result<std::string, int> resolve_mesh_id(std::string_view arg);
    /// Loads the image module (kdrt/proto/image_module.h) for a command about to write an image: on
    /// failure prints "kdrt <command>: <why and what to install>" and returns kExitRefused.
    /// Commands call it before they start work on the server.
    [[nodiscard]] std::optional<int> need_image_module() const;

    /// --json was given: the report is JSON.
    [[nodiscard]] bool json() const { return args.has("json"); }
    /// --quiet was given: no human-readable lines.
    [[nodiscard]] bool quiet() const { return args.has("quiet"); }
    /// -o's value: "-" is standard output.
    [[nodiscard]] static bool is_stdout(std::string_view output) noexcept { return output == "-"; }
    /// The path whose extension tells the format of -o's file: "x.<--format>" when --format is
    /// given (needed with -o -, which has no extension), else `output` itself.
    [[nodiscard]] std::string format_path(const std::string& output) const;
    /// Writes the command's data to `output` (created or truncated; "-": standard output, as
    /// is). On failure prints "kdrt <command>: cannot write <what>: <why>" and returns its exit
    /// code (kExitUsage).
    [[nodiscard]] std::optional<int> write_output(const std::string& output,
                                                  std::span<const std::byte> bytes,
                                                  std::string_view what) const;
    /// The report of a command that wrote its data to `output`: with --json the line `json` on
    /// standard output (standard error when the data went there, -o -); otherwise the line
    /// `human` on standard error (never mixed into the data), unless --quiet.
    void report(std::string_view output, std::string_view human, std::string_view json) const;
};

/// Exit code of an Error kind (see Context::fail).
[[nodiscard]] int exit_code_for(const Error& error) noexcept;

/// Checks the positional count: at least `min`, at most `max`. Otherwise prints the usage error
/// ("missing <what>" or "unexpected argument"), sets `code` to its exit code and returns false.
[[nodiscard]] bool positional_count_ok(Context& ctx, size_t min, size_t max, std::string_view what,
                                       int& code);

}  // namespace kdrt::cli
