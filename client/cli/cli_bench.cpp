// kdrt rays, trace and bench-remote: ray files and remote tracing speed.

#include <algorithm>
#include <chrono>
#include <limits>
#include <vector>

#include "cli_args.h"
#include "cli_context.h"
#include "cli_output.h"
#include "kdrt/camera.h"
#include "kdrt/kdtree.h"
#include "kdrt/proto/file_io.h"
#include "kdrt/proto/mesh_id.h"
#include "kdrt/proto/ray_batch.h"
#include "kdrt/raygen.h"

namespace kdrt::cli {
namespace {

using Clock = std::chrono::steady_clock;

/// Largest --res: 8192^2 rays are 2 GiB of KDRR.
constexpr uint64_t kMaxRes = 8192;
/// Largest --connections.
constexpr uint64_t kMaxConnections = 64;
/// Largest --chunk-rays: the server's default max_rays.
constexpr uint64_t kMaxChunkRays = uint64_t{1} << 24;

double seconds_since(Clock::time_point start) {
    return std::chrono::duration<double>(Clock::now() - start).count();
}

/// A ray set and where it came from.
struct RaySet {
    std::vector<Ray> rays;
    bool occlusion = false;
    std::string kind;    ///< primary, shadow, diffuse, random, or "file"
    std::string source;  ///< "mesh", "bounds" or "rays"
};

/// --kind, --res, --seed (defaults primary, 1024, 1). Returns an exit code on a usage error.
proto::Result<RayGenOptions, int> ray_options(const Context& ctx) {
    RayGenOptions options;
    if (auto kind = ctx.args.value("kind")) {
        auto parsed = parse_ray_kind(*kind);
        if (!parsed)
            return proto::Err{ctx.usage_error("--kind: \"" + *kind +
                                              "\" is not primary, shadow, diffuse or random")};
        options.kind = *parsed;
    }
    if (auto res = ctx.args.value("res")) {
        auto n = parse_uint(*res, 1, kMaxRes);
        if (!n) return proto::Err{ctx.usage_error("--res: " + n.error())};
        options.res = static_cast<uint32_t>(*n);
    }
    if (auto seed = ctx.args.value("seed")) {
        auto n = parse_uint(*seed, 0, std::numeric_limits<uint64_t>::max());
        if (!n) return proto::Err{ctx.usage_error("--seed: " + n.error())};
        options.seed = *n;
    }
    return options;
}

/// --connections and --chunk-rays on top of the global client options.
proto::Result<ClientOptions, int> trace_client_options(const Context& ctx) {
    ClientOptions options = ctx.client_options();
    if (auto text = ctx.args.value("connections")) {
        auto n = parse_uint(*text, 1, kMaxConnections);
        if (!n) return proto::Err{ctx.usage_error("--connections: " + n.error())};
        options.connections = static_cast<unsigned>(*n);
    }
    if (auto text = ctx.args.value("chunk-rays")) {
        auto n = parse_uint(*text, 1, kMaxChunkRays);
        if (!n) return proto::Err{ctx.usage_error("--chunk-rays: " + n.error())};
        options.chunk_rays = static_cast<size_t>(*n);
    }
    return options;
}

/// Loads a mesh file and generates `options` rays from its tree. With `expected_id`, the file's
/// mesh id must match it.
proto::Result<RaySet, int> rays_from_mesh_file(const Context& ctx, const std::string& path,
                                               const RayGenOptions& options,
                                               const std::string& expected_id = {}) {
    auto mesh = proto::load_mesh_file(path);
    if (!mesh)
        return proto::Err{ctx.fail(make_client_error(ErrorKind::kInput, "cannot read the mesh",
                                                     mesh.error().to_string()))};
    if (!expected_id.empty()) {
        const std::string id = proto::mesh_id(*mesh);
        if (id != expected_id)
            return proto::Err{ctx.usage_error("--mesh " + path + " is not mesh " + expected_id +
                                              " (its id is " + id +
                                              "); give the file that was uploaded")};
    }
    RaySet set;
    try {
        const KdTree tree = build_kdtree(*mesh);
        set.rays = generate_rays(tree, options);
    } catch (const MeshError& e) {
        return proto::Err{ctx.fail(
            make_client_error(ErrorKind::kInput, "cannot build the mesh", path + ": " + e.what()))};
    }
    set.occlusion = options.kind == RayKind::kShadow;
    set.kind = std::string(ray_kind_name(options.kind));
    set.source = "mesh";
    return set;
}

/// Reads a KDRR file.
proto::Result<RaySet, int> rays_from_file(const Context& ctx, const std::string& path) {
    auto bytes = proto::read_file_bytes(path);
    if (!bytes)
        return proto::Err{
            ctx.fail(make_client_error(ErrorKind::kInput, "cannot read the rays", bytes.error()))};
    auto batch = proto::decode_rays(*bytes, {.max_rays = std::numeric_limits<uint32_t>::max()});
    if (!batch)
        return proto::Err{ctx.fail(
            make_client_error(ErrorKind::kInput, "cannot read the rays",
                              path + " is not a KDRR ray batch: " + batch.error().to_string()))};
    RaySet set;
    set.rays = std::move(batch->rays);
    set.occlusion = batch->occlusion;
    set.kind = "file";
    set.source = "rays";
    return set;
}

/// res x res camera rays through the pixel centres of the default view of `bounds` (what
/// generate_rays' primary set does with the tree's padded bounds).
proto::Result<RaySet, int> primary_rays_from_bounds(const Context& ctx, const Aabb& bounds,
                                                    uint32_t res) {
    RaySet set;
    try {
        const Camera camera(default_camera(bounds, 1.0f), res, res);
        set.rays.resize(size_t{res} * res);
        for (uint32_t y = 0; y < res; ++y)
            for (uint32_t x = 0; x < res; ++x)
                set.rays[size_t{y} * res + x] =
                    camera.ray(static_cast<float>(x) + 0.5f, static_cast<float>(y) + 0.5f);
    } catch (const CameraError& e) {
        return proto::Err{
            ctx.fail(make_client_error(ErrorKind::kInput, "cannot place a camera", e.what()))};
    }
    set.kind = "primary";
    set.source = "bounds";
    return set;
}

template <class T>
uint64_t count_answers(const std::vector<T>& answers) {
    if constexpr (std::is_same_v<T, Hit>) {
        return static_cast<uint64_t>(
            std::count_if(answers.begin(), answers.end(), [](const Hit& h) { return h.is_hit(); }));
    } else {
        return static_cast<uint64_t>(std::count(answers.begin(), answers.end(), uint8_t{1}));
    }
}

}  // namespace

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
    if (ctx.args.has("json")) {
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
    } else {
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

}  // namespace kdrt::cli
