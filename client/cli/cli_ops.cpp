// kdrt health, metrics: the server's state.

#include <cmath>
#include <cstdlib>
#include <sstream>
#include <string>
#include <vector>

#include "cli_command.h"
#include "cli_context.h"
#include "kdrt/proto/json_api.h"

namespace kdrt::cli {
namespace {

constexpr std::string_view kHealthHelp = R"(usage: kdrt health [--json] [--quiet]

Asks the server whether it is alive (/healthz) and ready (/readyz). Prints "ok: URL is alive and
ready"; exit 1 with the server's reason when it is alive but not ready (starting, shutting down).

  --json        {"url": ..., "alive": true|false, "ready": true|false} on one line
  -q, --quiet   print nothing but errors: the exit status answers
)";

void health_line(const Context& ctx, const std::string& url, bool alive, bool ready) {
    if (ctx.json()) {
        const proto::JsonField fields[] = {
            {"url", std::string_view(url)}, {"alive", alive}, {"ready", ready}};
        ctx.console.out << proto::encode_flat_object(fields) << "\n";
    } else if (!ctx.quiet() && alive) {
        ctx.console.out << (ready ? "ok: " + url + " is alive and ready"
                                  : url + " is alive but not ready")
                        << "\n";
    }
}

int run_health(Context& ctx) {
    int code = kExitOk;
    if (!positional_count_ok(ctx, 0, 0, "", code)) return code;
    Client& client = ctx.connect(ctx.client_options());
    const std::string url = client.url().to_string();
    if (auto alive = client.health(); !alive) {
        health_line(ctx, url, false, false);
        return ctx.fail(alive.error());
    }
    if (auto ready = client.ready(); !ready) {
        health_line(ctx, url, true, false);
        return ctx.fail(ready.error());
    }
    health_line(ctx, url, true, true);
    return kExitOk;
}

constexpr std::string_view kMetricsHelp = R"(usage: kdrt metrics [--json]

Prints the server's metrics in the Prometheus text format (GET /metrics).

  --json   one JSON object per sample instead: {"name": ..., "labels": {...}, "value": ...};
           a value that JSON cannot hold (NaN, +Inf, -Inf) is that word as a string
)";

/// Appends `text` as a JSON string (quotes, backslash, control characters escaped).
void append_json_string(std::string& out, std::string_view text) {
    const proto::JsonField field[] = {{"", text}};
    const std::string object = proto::encode_flat_object(field);  // {"":"..."}
    out += std::string_view(object).substr(4, object.size() - 5);
}

/// One sample line of the Prometheus text format as a JSON object, or "" for a line that is not
/// a sample (comments, blank lines, anything malformed).
std::string sample_json(std::string_view line) {
    const size_t name_end = line.find_first_of("{ ");
    if (line.empty() || line[0] == '#' || name_end == 0 || name_end == std::string_view::npos)
        return {};
    std::string labels = "{";
    size_t i = name_end;
    if (line[i] == '{') {
        ++i;
        while (i < line.size() && line[i] != '}') {
            const size_t eq = line.find('=', i);
            if (eq == std::string_view::npos || eq + 1 >= line.size() || line[eq + 1] != '"')
                return {};
            std::string value;
            size_t j = eq + 2;
            for (; j < line.size() && line[j] != '"'; ++j) {
                if (line[j] == '\\' && j + 1 < line.size()) {
                    ++j;
                    value += line[j] == 'n' ? '\n' : line[j];
                } else {
                    value += line[j];
                }
            }
            if (j >= line.size()) return {};
            if (labels.size() > 1) labels += ",";
            append_json_string(labels, line.substr(i, eq - i));
            labels += ":";
            append_json_string(labels, value);
            i = j + 1;
            if (i < line.size() && line[i] == ',') ++i;
        }
        if (i >= line.size()) return {};
        ++i;
    }
    labels += "}";
    std::istringstream rest{std::string(line.substr(i))};
    std::string value_text;
    if (!(rest >> value_text)) return {};
    std::string out = "{\"name\":";
    append_json_string(out, line.substr(0, name_end));
    out += ",\"labels\":" + labels + ",\"value\":";
    char* end = nullptr;
    const double value = std::strtod(value_text.c_str(), &end);
    if (end == value_text.c_str() || *end != '\0') return {};
    if (std::isfinite(value)) {
        const proto::JsonField field[] = {{"v", value}};
        const std::string object = proto::encode_flat_object(field);  // {"v":...}
        out += std::string_view(object).substr(5, object.size() - 6);
    } else {
        append_json_string(out, std::isnan(value) ? "NaN" : value > 0 ? "+Inf" : "-Inf");
    }
    return out + "}";
}

int run_metrics(Context& ctx) {
    int code = kExitOk;
    if (!positional_count_ok(ctx, 0, 0, "", code)) return code;
    auto text = ctx.connect(ctx.client_options()).metrics();
    if (!text) return ctx.fail(text.error());
    if (!ctx.json()) {
        ctx.console.out << *text;
        return kExitOk;
    }
    std::istringstream lines(*text);
    for (std::string line; std::getline(lines, line);)
        if (std::string sample = sample_json(line); !sample.empty())
            ctx.console.out << sample << "\n";
    return kExitOk;
}

}  // namespace

constinit const Command kHealthCommand{
    .name = "health",
    .synopsis = "health",
    .summary = "check that the server is alive and ready",
    .help = kHealthHelp,
    .options = {},
    .needs_server = true,
    .run = run_health,
};

constinit const Command kMetricsCommand{
    .name = "metrics",
    .synopsis = "metrics",
    .summary = "print the server's Prometheus metrics",
    .help = kMetricsHelp,
    .options = {},
    .needs_server = true,
    .run = run_metrics,
};

}  // namespace kdrt::cli
