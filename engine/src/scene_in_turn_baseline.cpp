// A scene's single rays walked in turn (scene_in_turn.h) at the x86-64 baseline: Isa::kScalar's,
// with the single-ray kernel trace.cpp compiles there.
#include <immintrin.h>

#include <cstddef>
#include <cstdint>

#include "kdrt/trace.h"
#include "packet.h"
#include "ray_prep.h"
#include "scene_in_turn.h"
#include "scene_in_turn_ops.h"
#include "scene_internal.h"

namespace kdrt::detail {

const SceneInTurnOps& scene_in_turn_ops_baseline() noexcept {
    static constexpr SceneInTurnOps kOps{&in_turn::intersect_in_turn, &in_turn::occluded_in_turn};
    return kOps;
}

}  // namespace kdrt::detail
