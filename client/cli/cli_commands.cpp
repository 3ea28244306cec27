// kdrt: the command table, `kdrt --help`, and dispatch to a command's run function.

#include "cli_commands.h"

#include <string>
#include <vector>

#include "cli_args.h"
#include "cli_command.h"
#include "cli_context.h"

namespace kdrt::cli {
namespace {

constexpr std::string_view kMainHelpHead =
    R"(usage: kdrt [--server URL] [--token TOKEN] COMMAND [ARGS...]

Command-line client of kdrt-server: upload meshes, trace ray files, render images.

Commands:
)";

/// The width of the command column of `kdrt --help` (synopses are narrower).
constexpr size_t kSynopsisWidth = 24;

constexpr std::string_view kHelpSynopsis = "help [COMMAND]";
constexpr std::string_view kHelpSummary = "this text, or a command's (also: kdrt COMMAND --help)";

constexpr std::string_view kMainHelpTail =
    R"(
Options of every command that talks to the server (before or after COMMAND):
  --server URL      server address; default $KDRT_SERVER, else http://127.0.0.1:8080
  --token TOKEN     bearer token; default $KDRT_TOKEN
  --timeout S       seconds one socket read or write may take (default 300)
  --retries N       retries on connection errors and 503 answers, with exponential backoff
                    (Retry-After honoured; never on other errors; default 4)
  --json            the report as JSON, one object per line (every command)
  -q, --quiet       no human-readable lines: progress and summaries (errors still print)
  -h, --help        help
  --version         print the version

-o FILE writes a command's data (rays, hits, images, scans, distances) to FILE; -o - writes it to
standard output. Progress and summaries always go to standard error; --json reports go to standard
output, or to standard error when -o - puts the data there.

A mesh ID may be shortened to a unique prefix of 4 or more hex digits.

Exit status: 0 success; 1 the server refused the request (its message is printed) or a render
failed; 2 usage error (bad arguments, or a file named on the command line cannot be read or
written); 3 cannot connect to the server; 130 interrupted while waiting for a render.
)";

constexpr const Command* kCommands[] = {
    &kUploadCommand, &kMeshesCommand, &kInfoCommand,     &kRmCommand,          &kRenderCommand,
    &kTraceCommand,  &kHitsCommand,   &kDistanceCommand, &kRaysCommand,        &kScanCommand,
    &kSceneCommand,  &kHealthCommand, &kMetricsCommand,  &kBenchRemoteCommand,
};

void append_command_line(std::string& out, std::string_view synopsis, std::string_view summary) {
    out += "  ";
    out += synopsis;
    out.append(kSynopsisWidth > synopsis.size() ? kSynopsisWidth - synopsis.size() : 1, ' ');
    out += summary;
    out += "\n";
}

bool is_global_value_option(std::string_view arg) {
    for (const OptionSpec& s : kGlobalOptions) {
        if (!s.takes_value) continue;
        const std::string flag = "--" + std::string(s.name);
        if (arg == flag || arg.rfind(flag + "=", 0) == 0) return true;
    }
    return false;
}

/// --json, --quiet, -q: accepted before the command too.
bool is_report_flag(std::string_view arg) {
    for (const OptionSpec& s : kReportOptions)
        if (arg == "--" + std::string(s.name) ||
            (s.short_name && arg.size() == 2 && arg[0] == '-' && arg[1] == s.short_name))
            return true;
    return false;
}

}  // namespace

std::span<const Command* const> commands() noexcept { return kCommands; }

const Command* find_command(std::string_view name) noexcept {
    for (const Command* c : kCommands)
        if (c->name == name) return c;
    return nullptr;
}

const std::string& main_help() {
    static const std::string text = [] {
        std::string out(kMainHelpHead);
        for (const Command* c : kCommands) append_command_line(out, c->synopsis, c->summary);
        append_command_line(out, kHelpSynopsis, kHelpSummary);
        out += kMainHelpTail;
        return out;
    }();
    return text;
}

int run(std::span<const std::string> args, const std::map<std::string, std::string>& env,
        const Console& console) {
    // The command is the first argument that is neither a global option nor its value.
    size_t command_index = args.size();
    for (size_t i = 0; i < args.size(); ++i) {
        const std::string& arg = args[i];
        if (arg == "--help" || arg == "-h") {
            console.out << main_help();
            return kExitOk;
        }
        if (arg == "--version") {
            console.out << "kdrt " << KDRT_VERSION << "\n";
            return kExitOk;
        }
        if (is_global_value_option(arg)) {
            if (arg.find('=') == std::string::npos) ++i;
            continue;
        }
        if (is_report_flag(arg)) continue;
        if (arg.size() > 1 && arg[0] == '-') {
            console.err << "kdrt: unknown option \"" << arg << "\" before the command\n"
                        << "run 'kdrt --help' for usage\n";
            return kExitUsage;
        }
        command_index = i;
        break;
    }
    if (command_index == args.size()) {
        console.err << "kdrt: missing command\n\n" << main_help();
        return kExitUsage;
    }
    const std::string& name = args[command_index];
    if (name == "help") {
        if (command_index + 1 >= args.size()) {
            console.out << main_help();
            return kExitOk;
        }
        const Command* spec = find_command(args[command_index + 1]);
        if (!spec) {
            console.err << "kdrt help: unknown command \"" << args[command_index + 1] << "\"\n"
                        << "run 'kdrt --help' for the list of commands\n";
            return kExitUsage;
        }
        console.out << spec->help;
        return kExitOk;
    }
    const Command* spec = find_command(name);
    if (!spec) {
        console.err << "kdrt: unknown command \"" << name << "\"\n"
                    << "run 'kdrt --help' for the list of commands\n";
        return kExitUsage;
    }
    size_t skip = 1;  // the command's name, and a family's subcommand
    const Command* family = nullptr;
    if (!spec->subcommands.empty()) {
        const std::string sub =
            command_index + 1 < args.size() ? args[command_index + 1] : std::string();
        if (sub == "--help" || sub == "-h") {
            console.out << spec->help;
            return kExitOk;
        }
        const Command* found = nullptr;
        for (const Command* c : spec->subcommands)
            if (c->name.size() > name.size() && c->name.substr(name.size() + 1) == sub) found = c;
        if (found == nullptr) {
            console.err << "kdrt " << name << ": "
                        << (sub.empty() ? "missing subcommand"
                                        : "unknown subcommand \"" + sub + "\"")
                        << "\n\n"
                        << spec->help;
            return kExitUsage;
        }
        family = spec;
        spec = found;
        skip = 2;
    }
    std::vector<std::string> rest(args.begin(),
                                  args.begin() + static_cast<std::ptrdiff_t>(command_index));
    rest.insert(rest.end(), args.begin() + static_cast<std::ptrdiff_t>(command_index + skip),
                args.end());
    std::vector<OptionSpec> options(spec->options.begin(), spec->options.end());
    if (family != nullptr)
        options.insert(options.end(), family->options.begin(), family->options.end());
    options.insert(options.end(), std::begin(kGlobalOptions), std::end(kGlobalOptions));
    options.insert(options.end(), std::begin(kReportOptions), std::end(kReportOptions));

    Context ctx{console, spec->name, {}, {}, std::nullopt};
    auto parsed = parse_args(rest, options, "kdrt " + std::string(spec->name));
    if (!parsed) {
        console.err << "kdrt " << spec->name << ": " << parsed.error() << "\n";
        return kExitUsage;
    }
    ctx.args = std::move(*parsed);
    if (ctx.args.has("help")) {
        console.out << spec->help;
        return kExitOk;
    }
    if (spec->needs_server) {
        auto settings = global_settings(ctx.args, env);
        if (!settings) return ctx.usage_error(settings.error());
        ctx.settings = std::move(*settings);
    }
    return spec->run(ctx);
}

}  // namespace kdrt::cli
