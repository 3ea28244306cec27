#pragma once
/// Command-line parsing for `kdrt`: options of the form --name VALUE, --name=VALUE, -o VALUE and
/// boolean --flag, positionals, `--` to end the options; and the value parsers the subcommands
/// share (sizes, vectors, counts). Errors are one-line messages for the usage error (exit 2).

#include <cstdint>
#include <map>
#include <optional>
#include <span>
#include <string>
#include <string_view>
#include <vector>

#include "kdrt/proto/result.h"
#include "kdrt/render.h"
#include "kdrt/types.h"

namespace kdrt::cli {

/// Process exit codes of `kdrt` (documented in `kdrt --help`).
enum ExitCode : int {
    kExitOk = 0,           ///< success
    kExitRefused = 1,      ///< the server said no (message printed), or a render job failed
    kExitUsage = 2,        ///< bad command line, or a file named on it cannot be read or written
    kExitUnreachable = 3,  ///< cannot connect to the server (or the connection failed)
    kExitInterrupted =
        130,  ///< interrupted (SIGINT) while waiting for a render; the job is cancelled
};

template <class T>
using ParseResult = proto::Result<T, std::string>;

/// One option a subcommand accepts.
struct OptionSpec {
    std::string_view name;     ///< long name without dashes: "size" for --size
    bool takes_value = false;  ///< --size 1024x768 (true) or --json (false)
    char short_name = 0;       ///< e.g. 'o' for -o; 0 = none
};

/// The options and positionals of one subcommand.
struct ParsedArgs {
    std::vector<std::string> positional;
    std::map<std::string, std::string, std::less<>>
        values;                      ///< by long name; the last one given wins
    std::vector<std::string> flags;  ///< boolean options given, by long name

    [[nodiscard]] bool has(std::string_view name) const;  ///< a flag or a value option was given
    [[nodiscard]] std::optional<std::string> value(std::string_view name) const;
};

/// Splits `args` by `specs`. Errors: an unknown option, a missing value, a value given to a flag.
/// `command` names the subcommand in messages ("kdrt upload").
[[nodiscard]] ParseResult<ParsedArgs> parse_args(std::span<const std::string> args,
                                                 std::span<const OptionSpec> specs,
                                                 std::string_view command);

/// Options every subcommand that talks to a server accepts, wherever they appear.
inline constexpr OptionSpec kGlobalOptions[] = {
    {"server", true}, {"token", true}, {"timeout", true}, {"retries", true}, {"help", false, 'h'},
};

/// Options of every command: how it reports (cli_context.h, Context::report).
///   --json       the report as JSON (one object per line)
///   -q, --quiet  no human-readable lines (progress, summaries); errors are still printed
inline constexpr OptionSpec kReportOptions[] = {{"json", false}, {"quiet", false, 'q'}};

/// Connection settings from the global options and the environment (KDRT_SERVER, KDRT_TOKEN).
struct GlobalSettings {
    std::string server;               ///< --server, else KDRT_SERVER, else kDefaultServerUrl
    std::string token;                ///< --token, else KDRT_TOKEN (read by the client), else none
    std::optional<double> timeout_s;  ///< --timeout: per socket read/write, seconds
    std::optional<unsigned> retries;  ///< --retries
};

[[nodiscard]] ParseResult<GlobalSettings> global_settings(
    const ParsedArgs& args, const std::map<std::string, std::string>& env);

/// "1024x768" -> {1024, 768}; each 1 .. kMaxImageSize.
[[nodiscard]] ParseResult<std::pair<uint32_t, uint32_t>> parse_size(std::string_view text);
/// "x,y,z" -> finite floats.
[[nodiscard]] ParseResult<Vec3> parse_vec3(std::string_view text);
/// "x,y,w,h" -> a pixel region (w, h >= 1).
[[nodiscard]] ParseResult<PixelRegion> parse_region(std::string_view text);
/// A decimal integer in [min, max].
[[nodiscard]] ParseResult<uint64_t> parse_uint(std::string_view text, uint64_t min, uint64_t max);
/// A finite decimal number.
[[nodiscard]] ParseResult<double> parse_number(std::string_view text);

/// The API's image format name for an output file: .png -> "png", .jpg/.jpeg -> "jpg",
/// .exr -> "exr" (case-insensitive); nullopt for anything else.
[[nodiscard]] std::optional<std::string> image_format_for_path(std::string_view path);

}  // namespace kdrt::cli
