// kdrt rays, trace, hits: KDRR ray files, generated locally and traced remotely.

#include <cctype>
#include <sstream>
#include <vector>

#include "cli_command.h"
#include "cli_context.h"
#include "cli_output.h"
#include "cli_ray_sets.h"
#include "kdrt/proto/file_io.h"
#include "kdrt/proto/json_api.h"
#include "kdrt/proto/multi_hit.h"
#include "kdrt/proto/ray_batch.h"
#include "kdrt/query.h"

namespace kdrt::cli {
namespace {

constexpr std::string_view kRaysHelp =
    R"(usage: kdrt rays MESH -o FILE [--kind primary|shadow|diffuse|random] [--res N] [--seed N] [--json]
                 [--quiet]

Generates a deterministic KDRR ray set for a mesh file, locally (no server): the same bytes as
`kdrt-bench rays` on every machine. The mesh's kD-tree is built in this process.

  -o, --output FILE   the KDRR file (required; - for standard output)
  --kind K            primary: R x R camera rays of the default view (default)
                      shadow: from each primary hit towards a point light (occlusion query)
                      diffuse: from each primary hit, cosine-weighted
                      random: R x R rays with random origins in the bounds, random directions
  --res R             resolution (default 1024, at most 8192)
  --seed N            seed (default 1)
  --json              the summary as one JSON object (on stdout; stderr with -o -)
  -q, --quiet         no summary line
)";

constexpr OptionSpec kRaysOptions[] = {
    {"output", true, 'o'},
    {"kind", true},
    {"res", true},
    {"seed", true},
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
    if (auto failed = ctx.write_output(*output, bytes, "the rays")) return *failed;
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
    std::ostringstream human;
    human << "wrote " << set->rays.size() << " " << set->kind << " rays"
          << (set->occlusion ? " (occlusion query)" : "") << " to " << *output << " ("
          << bytes.size() << " bytes)";
    ctx.report(*output, human.str(), proto::encode_flat_object(fields));
    return kExitOk;
}

constexpr std::string_view kTraceHelp =
    R"(usage: kdrt trace ID RAYS.kdrr -o FILE [--connections N] [--chunk-rays N] [--split N]
                  [--json]

Traces every ray of a KDRR file (kdrt rays, kdrt-bench rays, proto/FORMATS.md) against a stored
mesh and writes the answers to FILE: KDRH closest hits, or KDRO occlusion bytes when the file's
occlusion flag is set. Large files go in chunks over several keep-alive connections in parallel.
Prints the ray count, time, Mrays/s and hits.

  -o, --output FILE    the KDRH / KDRO file (required; - for standard output)
  --connections N      chunks in flight at once (default 4)
  --chunk-rays N       rays per request (default 65536)
  --split N            at least N requests, each with its own routing key (?route=ID.K), so a
                       proxy in front of replicas spreads them (docs/scale-out.md)
  --json               the summary as one JSON object (on stdout; stderr with -o -)
  -q, --quiet          no summary line
)";

constexpr OptionSpec kTraceOptions[] = {
    {"output", true, 'o'},
    {"connections", true},
    {"chunk-rays", true},
    {"split", true},
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
    if (auto failed = ctx.write_output(*output, answer, "the answers")) return *failed;
    const double mrays = seconds > 0 ? static_cast<double>(set->rays.size()) / seconds / 1e6 : 0.0;
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
    std::ostringstream human;
    human << "traced " << set->rays.size() << " rays ("
          << (set->occlusion ? "occlusion" : "closest hits") << ") in " << fixed(seconds, 3)
          << " s, " << fixed(mrays, 2) << " Mrays/s over " << options->connections
          << (options->connections == 1 ? " connection: " : " connections: ") << hits
          << (set->occlusion ? " occluded" : " hits") << " -> " << *output;
    ctx.report(*output, human.str(), proto::encode_flat_object(fields));
    return kExitOk;
}

constexpr std::string_view kHitsHelp =
    R"(usage: kdrt hits ID RAYS.kdrr --all -o FILE [--max-hits N] [--merge] [--count-only]
                 [--fields full|t|t_prim] [--normal] [--point] [--format ply]
                 [--json] [--quiet]

Every hit along each ray of a KDRR file (POST /v1/meshes/{id}/intersect_all): all triangles hit
within [tmin, tmax], each once, sorted by t, the nearest N kept per ray and the count of all
reported. FILE gets the KDRM answer (proto/FORMATS.md), or KDRC counts with --count-only, or,
when it ends in .ply, the hit points as a PLY point cloud (x y z t ray prim, and nx ny nz with
--normal) that any point-cloud viewer opens.

  --all               every hit (required: without it, use kdrt trace for closest hits)
  -o, --output FILE   the KDRM / KDRC / .ply file (required; - for standard output)
  --format ply        a .ply point cloud whatever FILE's extension (-o -); kdrm or kdrc:
                      the binary answer (the default)
  --max-hits N        hits kept per ray (default 16; the server caps it, max_hits_per_ray)
  --merge             report coincident hits at a shared edge or vertex once (crossing counts)
  --count-only        only the number of hits of each ray (KDRC)
  --fields F          record fields: full (t prim u v, default), t, t_prim
  --normal            add the unit geometric normal of each hit
  --point             add the world-space hit point (implied by a .ply FILE)
  --chunk-rays N      rays per request (default 65536)
  --json              the summary as one JSON object (on stdout; stderr with -o -)
  -q, --quiet         no summary line
)";

constexpr OptionSpec kHitsOptions[] = {
    {"all", false},        {"output", true, 'o'}, {"max-hits", true}, {"merge", false},
    {"count-only", false}, {"fields", true},      {"normal", false},  {"point", false},
    {"chunk-rays", true},  {"format", true},
};

bool ends_with_ply(std::string_view path) {
    if (path.size() < 4) return false;
    std::string tail(path.substr(path.size() - 4));
    for (char& c : tail) c = static_cast<char>(std::tolower(static_cast<unsigned char>(c)));
    return tail == ".ply";
}

int run_hits(Context& ctx) {
    if (!ctx.args.has("all"))
        return ctx.usage_error("kdrt hits needs --all (closest hits: kdrt trace)");
    if (ctx.args.positional.size() < 2)
        return ctx.usage_error("missing ID and RAYS (a mesh id and a KDRR file)");
    if (ctx.args.positional.size() > 2)
        return ctx.usage_error("unexpected argument \"" + ctx.args.positional[2] + "\"");
    const auto output = ctx.args.value("output");
    if (!output) return ctx.usage_error("missing -o FILE (the KDRM, KDRC or .ply file to write)");
    auto parsed = multi_hit_options(ctx);
    if (!parsed) return parsed.error();
    proto::MultiHitQuery query = *parsed;
    if (auto format = ctx.args.value("format");
        format && *format != "ply" && *format != "kdrm" && *format != "kdrc")
        return ctx.usage_error("--format: \"" + *format + "\" is not ply, kdrm or kdrc");
    const bool ply = ends_with_ply(ctx.format_path(*output));
    query.layout.point = query.layout.point || ply;
    if (ply && query.count_only)
        return ctx.usage_error("--count-only writes KDRC counts, not a .ply point cloud");
    auto options = trace_client_options(ctx);
    if (!options) return options.error();
    const std::string& rays_path = ctx.args.positional[1];
    auto set = rays_from_file(ctx, rays_path);
    if (!set) return set.error();
    if (set->occlusion)
        return ctx.usage_error(rays_path +
                               " is an occlusion ray set (flag bit 0); kdrt hits "
                               "takes closest-hit rays");
    Client& client = ctx.connect(*options);
    auto id = ctx.resolve_mesh_id(ctx.args.positional[0]);
    if (!id) return id.error();

    const auto start = Clock::now();
    std::vector<std::byte> answer;
    uint64_t total = 0, kept = 0;
    if (query.count_only) {
        auto counts = client.count_intersections(*id, set->rays, query.merge_coincident);
        if (!counts) return ctx.fail(counts.error());
        for (uint32_t c : *counts) total += c;
        answer = proto::encode_hit_counts(*counts);
    } else {
        auto all = client.intersect_all(*id, set->rays, query);
        if (!all) return ctx.fail(all.error());
        for (uint32_t c : all->counts) total += c;
        kept = all->hits.size();
        answer = ply ? proto::encode_hit_points_ply(*all) : multi_hits_bytes(*all);
    }
    const double seconds = seconds_since(start);
    if (auto failed = ctx.write_output(*output, answer, "the answers")) return *failed;
    const double mrays = seconds > 0 ? static_cast<double>(set->rays.size()) / seconds / 1e6 : 0.0;
    const proto::JsonField fields[] = {{"command", std::string_view("hits")},
                                       {"mesh", std::string_view(*id)},
                                       {"rays_file", std::string_view(rays_path)},
                                       {"rays", uint64_t{set->rays.size()}},
                                       {"max_hits", uint64_t{query.max_hits}},
                                       {"merge_coincident", query.merge_coincident},
                                       {"count_only", query.count_only},
                                       {"seconds", seconds},
                                       {"mrays_per_s", mrays},
                                       {"hits", total},
                                       {"kept", kept},
                                       {"out", std::string_view(*output)}};
    std::ostringstream human;
    human << "traced " << set->rays.size() << " rays (every hit) in " << fixed(seconds, 3) << " s, "
          << fixed(mrays, 2) << " Mrays/s: " << total << " hits";
    if (!query.count_only) human << ", " << kept << " kept";
    human << " -> " << *output;
    ctx.report(*output, human.str(), proto::encode_flat_object(fields));
    return kExitOk;
}

}  // namespace

proto::Result<proto::MultiHitQuery, int> multi_hit_options(const Context& ctx) {
    proto::MultiHitQuery query;
    if (auto text = ctx.args.value("max-hits")) {
        auto n = parse_uint(*text, 1, kMaxHitsPerRay);
        if (!n) return proto::Err{ctx.usage_error("--max-hits: " + n.error())};
        query.max_hits = static_cast<uint32_t>(*n);
    }
    if (auto text = ctx.args.value("fields")) {
        auto f = proto::parse_hit_fields(*text);
        if (!f)
            return proto::Err{
                ctx.usage_error("--fields: \"" + *text + "\" is not full, t or t_prim")};
        query.layout.fields = *f;
    }
    query.merge_coincident = ctx.args.has("merge");
    query.count_only = ctx.args.has("count-only");
    query.layout.normal = ctx.args.has("normal");
    query.layout.point = ctx.args.has("point");
    return query;
}

std::vector<std::byte> multi_hits_bytes(const proto::MultiHits& all) {
    // Re-encoded from the decoded records: the same bytes the server sent per chunk.
    std::vector<Hit> hits(all.hits.size());
    std::vector<Vec3> normals, points;
    for (size_t i = 0; i < hits.size(); ++i) {
        const proto::HitRecord& r = all.hits[i];
        hits[i] = Hit{r.t, r.prim, r.u, r.v};
        if (all.layout.normal) normals.push_back(r.normal);
        if (all.layout.point) points.push_back(r.point);
    }
    proto::MultiHitsView view;
    view.layout = all.layout;
    view.merged = all.merged;
    view.max_hits = all.max_hits;
    view.offsets = all.offsets;
    view.counts = all.counts;
    view.hits = hits;
    view.normals = normals;
    view.points = points;
    return proto::encode_multi_hits(view);
}

constinit const Command kHitsCommand{
    .name = "hits",
    .synopsis = "hits ID RAYS --all -o FILE",
    .summary = "every hit along each ray of a KDRR file (KDRM, KDRC counts, or a .ply of points)",
    .help = kHitsHelp,
    .options = kHitsOptions,
    .needs_server = true,
    .run = run_hits,
};

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
