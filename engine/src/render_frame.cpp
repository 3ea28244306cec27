// The per-render set-up of the renderer: camera, region, tiles and ray offsets.

#include <cmath>

#include "render_frame.h"

namespace kdrt::detail {
namespace {

PixelRegion region_of(const RenderSettings& s) noexcept {
    return s.region ? *s.region : PixelRegion{0, 0, s.width, s.height};
}

Camera make_camera(const Aabb& bounds, const RenderSettings& s) {
    try {
        const CameraSpec spec =
            s.camera ? *s.camera
                     : default_camera(bounds, static_cast<float>(static_cast<double>(s.width) /
                                                                 static_cast<double>(s.height)));
        return Camera(spec, s.width, s.height);
    } catch (const CameraError& e) {
        throw RenderError(e.what());
    }
}

SampleGrid sample_grid(uint32_t spp) noexcept {
    auto columns = static_cast<uint32_t>(std::sqrt(static_cast<double>(spp)));
    while (columns * columns < spp) ++columns;
    while (columns > 1 && (columns - 1) * (columns - 1) >= spp) --columns;
    // NOLINTNEXTLINE(clang-analyzer-core.DivideZero): spp is validated >= 1, so columns >= 1
    return {columns, (spp + columns - 1) / columns};
}

}  // namespace

Frame make_frame(const KdTree* tree, const Scene* scene, const RenderSettings& s) {
    validate_render_settings(s);
    const Aabb& bounds = scene ? scene->bounds() : tree->bounds;
    const Aabb box = scene_box(bounds);
    const float diag = diagonal(box);
    const PixelRegion region = region_of(s);
    const uint32_t tile = s.tile_size;
    return Frame{
        .settings = s,
        .camera = make_camera(bounds, s),
        .region = region,
        .tree = tree,
        .scene = scene,
        .channels = s.alpha ? 4u : 3u,
        .tiles_x = (region.width + tile - 1) / tile,
        .tiles_y = (region.height + tile - 1) / tile,
        .grid = sample_grid(s.spp),
        .offset = surface_offset(box),  // the same offset the ray-set generator uses
        .ao_tmax = s.ao_distance * diag,
        .to_light =
            s.light.kind == LightKind::kDirectional ? normalized(s.light.direction) : Vec3{},
    };
}

}  // namespace kdrt::detail
