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
};

/// Exit code of an Error kind (see Context::fail).
[[nodiscard]] int exit_code_for(const Error& error) noexcept;

/// Checks the positional count: at least `min`, at most `max`. Otherwise prints the usage error
/// ("missing <what>" or "unexpected argument"), sets `code` to its exit code and returns false.
[[nodiscard]] bool positional_count_ok(Context& ctx, size_t min, size_t max, std::string_view what,
                                       int& code);

}  // namespace kdrt::cli
