#include "cli_ray_sets.h"

#include <limits>

#include "kdrt/camera.h"
#include "kdrt/kdtree.h"
#include "kdrt/proto/file_io.h"
#include "kdrt/proto/mesh_id.h"
#include "kdrt/proto/ray_batch.h"

namespace kdrt::cli {
namespace {

/// Largest --res: 8192^2 rays are 2 GiB of KDRR.
constexpr uint64_t kMaxRes = 8192;
/// Largest --connections.
constexpr uint64_t kMaxConnections = 64;
/// Largest --chunk-rays: the server's default max_rays.
constexpr uint64_t kMaxChunkRays = uint64_t{1} << 24;

}  // namespace

double seconds_since(Clock::time_point start) {
    return std::chrono::duration<double>(Clock::now() - start).count();
}

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
    if (auto text = ctx.args.value("split")) {
        auto n = parse_uint(*text, 1, kMaxConnections);
        if (!n) return proto::Err{ctx.usage_error("--split: " + n.error())};
        options.split = static_cast<unsigned>(*n);
    }
    return options;
}

proto::Result<RaySet, int> rays_from_mesh_file(const Context& ctx, const std::string& path,
                                               const RayGenOptions& options,
                                               const std::string& expected_id) {
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

}  // namespace kdrt::cli
