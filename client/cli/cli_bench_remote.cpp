// kdrt bench-remote: how fast the server traces a batch over the network.

#include <algorithm>
#include <vector>

#include "cli_command.h"
#include "cli_context.h"
#include "cli_output.h"
#include "cli_ray_sets.h"
#include "kdrt/proto/json_api.h"

namespace kdrt::cli {
namespace {

constexpr std::string_view kBenchHelp =
    R"(usage: kdrt bench-remote ID [--kind primary|shadow|diffuse|random] [--res N] [--seed N]
                         [--mesh FILE | --rays FILE] [--connections N] [--chunk-rays N]
                         [--reps K] [--json]

Measures how fast the server traces a batch over the network: one untimed pass, then K timed
passes (default 3) of the whole batch through kdrt::Client (chunked, in parallel over
--connections keep-alive connections). Prints the median time and Mrays/s.

Rays:
  --rays FILE     a KDRR file (its flag picks closest hits or occlusion)
  --mesh FILE     the mesh file that was uploaded as ID (its id is checked): the --kind ray set
                  is generated from it exactly as `kdrt rays` does
  (neither)       --kind primary only: R x R camera rays of the default view of the bounds the
                  server reports (the server does not send triangles back, so the other kinds
                  need --mesh)
  --kind K        primary (default), shadow, diffuse or random
  --res R         resolution (default 1024, at most 8192)
  --seed N        seed (default 1)
  --connections N chunks in flight at once (default 4)
  --chunk-rays N  rays per request (default 65536)
  --reps K        timed passes, 1 .. 100 (default 3)
  --json          print one JSON object: mesh, kind, source, rays, occlusion, connections,
                  chunk_rays, reps, seconds (median), seconds_min, mrays_per_s, hits
)";

constexpr OptionSpec kBenchRemoteOptions[] = {
    {"kind", true}, {"res", true},         {"seed", true},       {"mesh", true},
    {"rays", true}, {"connections", true}, {"chunk-rays", true}, {"reps", true},
};

int run_bench_remote(Context& ctx) {
    if (ctx.args.positional.empty())
        return ctx.usage_error("missing ID (the mesh to trace against)");
    if (ctx.args.positional.size() > 1)
        return ctx.usage_error("unexpected argument \"" + ctx.args.positional[1] + "\"");
    if (ctx.args.has("mesh") && ctx.args.has("rays"))
        return ctx.usage_error("give --mesh or --rays, not both");
    auto ray_opts = ray_options(ctx);
    if (!ray_opts) return ray_opts.error();
    auto options = trace_client_options(ctx);
    if (!options) return options.error();
    unsigned reps = 3;
    if (auto text = ctx.args.value("reps")) {
        auto n = parse_uint(*text, 1, 100);
        if (!n) return ctx.usage_error("--reps: " + n.error());
        reps = static_cast<unsigned>(*n);
    }
    if (!ctx.args.has("mesh") && !ctx.args.has("rays") && ray_opts->kind != RayKind::kPrimary)
        return ctx.usage_error("--kind " + std::string(ray_kind_name(ray_opts->kind)) +
                               " needs the mesh's triangles: add --mesh FILE (the file uploaded as "
                               "ID) or --rays FILE");

    Client& client = ctx.connect(*options);
    auto id = ctx.resolve_mesh_id(ctx.args.positional[0]);
    if (!id) return id.error();
    proto::Result<RaySet, int> set = proto::Err{0};
    if (auto rays = ctx.args.value("rays")) {
        set = rays_from_file(ctx, *rays);
    } else if (auto mesh = ctx.args.value("mesh")) {
        set = rays_from_mesh_file(ctx, *mesh, *ray_opts, *id);
    } else {
        auto summary = client.mesh(*id);
        if (!summary) return ctx.fail(summary.error());
        set = primary_rays_from_bounds(ctx, summary->bounds, ray_opts->res);
    }
    if (!set) return set.error();

    // One untimed pass (connections, the server's tree in memory), then the timed ones.
    std::vector<double> times;
    uint64_t hits = 0;
    for (unsigned pass = 0; pass <= reps; ++pass) {
        const auto start = Clock::now();
        if (set->occlusion) {
            auto occluded = client.occluded(*id, set->rays);
            if (!occluded) return ctx.fail(occluded.error());
            hits = count_answers(*occluded);
        } else {
            auto found = client.intersect(*id, set->rays);
            if (!found) return ctx.fail(found.error());
            hits = count_answers(*found);
        }
        if (pass > 0) times.push_back(seconds_since(start));
    }
    std::sort(times.begin(), times.end());
    const double median = times[times.size() / 2];
    const double mrays = median > 0 ? static_cast<double>(set->rays.size()) / median / 1e6 : 0.0;
    if (ctx.json()) {
        const proto::JsonField fields[] = {{"command", std::string_view("bench-remote")},
                                           {"mesh", std::string_view(*id)},
                                           {"kind", std::string_view(set->kind)},
                                           {"source", std::string_view(set->source)},
                                           {"rays", uint64_t{set->rays.size()}},
                                           {"occlusion", set->occlusion},
                                           {"connections", uint64_t{options->connections}},
                                           {"chunk_rays", uint64_t{options->chunk_rays}},
                                           {"reps", uint64_t{reps}},
                                           {"seconds", median},
                                           {"seconds_min", times.front()},
                                           {"mrays_per_s", mrays},
                                           {"hits", hits}};
        ctx.console.out << proto::encode_flat_object(fields) << "\n";
    } else if (!ctx.quiet()) {
        ctx.console.out << set->kind << " rays (" << set->source << "): " << set->rays.size()
                        << " rays, " << options->connections
                        << (options->connections == 1 ? " connection" : " connections")
                        << ", chunks of " << options->chunk_rays << ": median " << fixed(median, 3)
                        << " s of " << reps << " (min " << fixed(times.front(), 3)
                        << " s) = " << fixed(mrays, 2) << " Mrays/s, " << hits
                        << (set->occlusion ? " occluded\n" : " hits\n");
    }
    return kExitOk;
}

}  // namespace

constinit const Command kBenchRemoteCommand{
    .name = "bench-remote",
    .synopsis = "bench-remote ID",
    .summary = "measure remote tracing speed in Mrays/s",
    .help = kBenchHelp,
    .options = kBenchRemoteOptions,
    .needs_server = true,
    .run = run_bench_remote,
};

}  // namespace kdrt::cli
