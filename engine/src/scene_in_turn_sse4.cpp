// A scene's single rays walked in turn (scene_in_turn.h) compiled for SSE4.
// Only the code after the pragma is compiled for that instruction set; see simd.h.
#include <immintrin.h>

#include <cstddef>
#include <cstdint>

#include "kdrt/trace.h"
#include "packet.h"
#include "ray_prep.h"
#include "scene_in_turn_ops.h"
#include "scene_internal.h"

#pragma GCC push_options
#pragma GCC target("sse4.2,popcnt")
#include "scene_in_turn.h"
#pragma GCC pop_options

namespace kdrt::detail {

const SceneInTurnOps& scene_in_turn_ops_sse4() noexcept {
    static constexpr SceneInTurnOps kOps{&in_turn::intersect_in_turn, &in_turn::occluded_in_turn};
    return kOps;
}

}  // namespace kdrt::detail
