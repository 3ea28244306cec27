// kdrt health, metrics: the server's state.

#include "cli_command.h"
#include "cli_context.h"

namespace kdrt::cli {
namespace {

constexpr std::string_view kHealthHelp = R"(usage: kdrt health

Asks the server whether it is alive (/healthz) and ready (/readyz). Prints "ok: URL is alive and
ready"; exit 1 with the server's reason when it is alive but not ready (starting, shutting down).
)";

int run_health(Context& ctx) {
    int code = kExitOk;
    if (!positional_count_ok(ctx, 0, 0, "", code)) return code;
    Client& client = ctx.connect(ctx.client_options());
    if (auto alive = client.health(); !alive) return ctx.fail(alive.error());
    if (auto ready = client.ready(); !ready) {
        ctx.console.out << client.url().to_string() << " is alive but not ready\n";
        return ctx.fail(ready.error());
    }
    ctx.console.out << "ok: " << client.url().to_string() << " is alive and ready\n";
    return kExitOk;
}

constexpr std::string_view kMetricsHelp = R"(usage: kdrt metrics

Prints the server's metrics in the Prometheus text format (GET /metrics).
)";

int run_metrics(Context& ctx) {
    int code = kExitOk;
    if (!positional_count_ok(ctx, 0, 0, "", code)) return code;
    auto text = ctx.connect(ctx.client_options()).metrics();
    if (!text) return ctx.fail(text.error());
    ctx.console.out << *text;
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
