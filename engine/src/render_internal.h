#pragma once
// Internal: the renderer with its ray queries supplied by the caller, so tests can render with
// the brute-force oracle (brute_force_intersect / brute_force_occluded) instead of the tree.
// render() itself calls intersect_block / occluded_block directly (no indirect calls).

#include <cstdint>
#include <span>

#include "kdrt/render.h"
#include "kdrt/types.h"

namespace kdrt::detail {

/// Block queries with the contract of intersect_block / occluded_block, called once per block of
/// rays (per tile and sample, per AO sample, per bounce), never per ray. `context` is passed
/// through unchanged.
struct TraceFunctions {
    const void* context = nullptr;
    void (*intersect)(const void* context, std::span<const Ray> rays,
                      std::span<Hit> hits) noexcept = nullptr;
    void (*occluded)(const void* context, std::span<const Ray> rays,
                     std::span<uint8_t> occluded_out) noexcept = nullptr;
};

/// render() with `trace` answering every ray query. `tree` still supplies the triangles
/// (tree.tris) for shading and the bounds for the default camera and ray offsets; its nodes are
/// not used unless `trace` uses them.
[[nodiscard]] Image render_with(const KdTree& tree, const RenderSettings& settings,
                                const TraceFunctions& trace, const RenderControl& control = {},
                                RenderStats* stats = nullptr);

}  // namespace kdrt::detail
