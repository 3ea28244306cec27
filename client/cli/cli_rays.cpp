// kdrt rays, trace: KDRR ray files, generated locally and traced remotely.

#include <vector>

#include "cli_command.h"
#include "cli_context.h"
#include "cli_output.h"
#include "cli_ray_sets.h"
#include "kdrt/proto/file_io.h"
#include "kdrt/proto/json_api.h"
#include "kdrt/proto/ray_batch.h"

namespace kdrt::cli {
namespace {

constexpr std::string_view kRaysHelp =
    R"(usage: kdrt rays MESH -o FILE [--kind primary|shadow|diffuse|random] [--res N] [--seed N] [--json]

Generates a deterministic KDRR ray set for a mesh file, locally (no server): the same bytes as
`kdrt-bench rays` on every machine. The mesh's kD-tree is built in this process.

  -o, --output FILE   the KDRR file (required)
  --kind K            primary: R x R camera rays of the default view (default)
                      shadow: from each primary hit towards a point light (occlusion query)
                      diffuse: from each primary hit, cosine-weighted
                      random: R x R rays with random origins in the bounds, random directions
  --res R             resolution (default 1024, at most 8192)
  --seed N            seed (default 1)
  --json              print the summary as one JSON object
)";

constexpr OptionSpec kRaysOptions[] = {
    {"output", true, 'o'}, {"kind", true}, {"res", true}, {"seed", true}, {"json", false},
};

int run_rays(Context& ctx) {
    if (ctx.args.positional.empty()) return ctx.usage_error("missing MESH (the mesh file)");
    if (ctx.args.positional.size() > 1)
        return ctx.usage_error("unexpected argument \"" + ctx.args.positional[1] + "\"");
    const auto output = ctx.args.value("output");
    if (!output) return ctx.usage_error("missing -o FILE (the KDRR file to write)");
    auto options = ray_options(ctx);
    if (!options) return options.error();
    const std::string& mesh_path = ctx.args.positional[0];
    const auto start = Clock::now();
    auto set = rays_from_mesh_file(ctx, mesh_path, *options);
    if (!set) return set.error();
    const double generate_ms = seconds_since(start) * 1e3;
    const std::vector<std::byte> bytes = proto::encode_rays(set->rays, set->occlusion);
    if (auto written = proto::write_file_bytes(*output, bytes); !written)
        return ctx.fail(
            make_client_error(ErrorKind::kInput, "cannot write the rays", written.error()));
    if (ctx.args.has("json")) {
        const proto::JsonField fields[] = {{"command", std::string_view("rays")},
                                           {"mesh", std::string_view(mesh_path)},
                                           {"kind", std::string_view(set->kind)},
                                           {"res", uint64_t{options->res}},
                                           {"seed", options->seed},
                                           {"rays", uint64_t{set->rays.size()}},
                                           {"occlusion", set->occlusion},
                                           {"out", std::string_view(*output)},
                                           {"bytes", uint64_t{bytes.size()}},
                                           {"generate_ms", generate_ms}};
        ctx.console.out << proto::encode_flat_object(fields) << "\n";
    } else {
        ctx.console.out << "wrote " << set->rays.size() << " " << set->kind << " rays"
                        << (set->occlusion ? " (occlusion query)" : "") << " to " << *output << " ("
                        << bytes.size() << " bytes)\n";
    }
    return kExitOk;
}

constexpr std::string_view kTraceHelp =
    R"(usage: kdrt trace ID RAYS.kdrr -o FILE [--connections N] [--chunk-rays N] [--split N]
                  [--json]

Traces every ray of a KDRR file (kdrt rays, kdrt-bench rays, proto/FORMATS.md) against a stored
mesh and writes the answers to FILE: KDRH closest hits, or KDRO occlusion bytes when the file's
occlusion flag is set. Large files go in chunks over several keep-alive connections in parallel.
Prints the ray count, time, Mrays/s and hits.

  -o, --output FILE    the KDRH / KDRO file (required)
  --connections N      chunks in flight at once (default 4)
  --chunk-rays N       rays per request (default 65536)
  --split N            at least N requests, each with its own routing key (?route=ID.K), so a
                       proxy in front of replicas spreads them (docs/scale-out.md)
  --json               print the summary as one JSON object
)";

constexpr OptionSpec kTraceOptions[] = {
    {"output", true, 'o'}, {"connections", true}, {"chunk-rays", true},
    {"split", true},       {"json", false},
};

int run_trace(Context& ctx) {
    if (ctx.args.positional.size() < 2)
        return ctx.usage_error("missing ID and RAYS (a mesh id and a KDRR file)");
    if (ctx.args.positional.size() > 2)
        return ctx.usage_error("unexpected argument \"" + ctx.args.positional[2] + "\"");
    const auto output = ctx.args.value("output");
    if (!output) return ctx.usage_error("missing -o FILE (the KDRH/KDRO file to write)");
    auto options = trace_client_options(ctx);
    if (!options) return options.error();
    const std::string& rays_path = ctx.args.positional[1];
    auto set = rays_from_file(ctx, rays_path);
    if (!set) return set.error();
    Client& client = ctx.connect(*options);
    auto id = ctx.resolve_mesh_id(ctx.args.positional[0]);
    if (!id) return id.error();

    const auto start = Clock::now();
    std::vector<std::byte> answer;
    uint64_t hits = 0;
    if (set->occlusion) {
        auto occluded = client.occluded(*id, set->rays);
        if (!occluded) return ctx.fail(occluded.error());
        hits = count_answers(*occluded);
        answer = proto::encode_occlusion(*occluded);
    } else {
        auto found = client.intersect(*id, set->rays);
        if (!found) return ctx.fail(found.error());
        hits = count_answers(*found);
        answer = proto::encode_hits(*found);
    }
    const double seconds = seconds_since(start);
    if (auto written = proto::write_file_bytes(*output, answer); !written)
        return ctx.fail(
            make_client_error(ErrorKind::kInput, "cannot write the answers", written.error()));
    const double mrays = seconds > 0 ? static_cast<double>(set->rays.size()) / seconds / 1e6 : 0.0;
    if (ctx.args.has("json")) {
        const proto::JsonField fields[] = {{"command", std::string_view("trace")},
                                           {"mesh", std::string_view(*id)},
                                           {"rays_file", std::string_view(rays_path)},
                                           {"rays", uint64_t{set->rays.size()}},
                                           {"occlusion", set->occlusion},
                                           {"connections", uint64_t{options->connections}},
                                           {"chunk_rays", uint64_t{options->chunk_rays}},
                                           {"seconds", seconds},
                                           {"mrays_per_s", mrays},
                                           {"hits", hits},
                                           {"out", std::string_view(*output)}};
        ctx.console.out << proto::encode_flat_object(fields) << "\n";
    } else {
        ctx.console.out << "traced " << set->rays.size() << " rays ("
                        << (set->occlusion ? "occlusion" : "closest hits") << ") in "
                        << fixed(seconds, 3) << " s, " << fixed(mrays, 2) << " Mrays/s over "
                        << options->connections
                        << (options->connections == 1 ? " connection: " : " connections: ") << hits
                        << (set->occlusion ? " occluded" : " hits") << " -> " << *output << "\n";
    }
    return kExitOk;
}

}  // namespace

constinit const Command kTraceCommand{
    .name = "trace",
    .synopsis = "trace ID RAYS -o FILE",
    .summary = "trace a KDRR ray file; write the KDRH hits (KDRO for occlusion rays)",
    .help = kTraceHelp,
    .options = kTraceOptions,
    .needs_server = true,
    .run = run_trace,
};

constinit const Command kRaysCommand{
    .name = "rays",
    .synopsis = "rays MESH -o FILE",
    .summary = "generate a KDRR ray file locally (the ray sets of kdrt-bench rays)",
    .help = kRaysHelp,
    .options = kRaysOptions,
    .needs_server = false,
    .run = run_rays,
};

}  // namespace kdrt::cli
