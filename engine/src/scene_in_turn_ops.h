#pragma once
// Internal: a scene batch's single rays walked several at a time (scene_in_turn.h), compiled per
// ISA (scene_in_turn_*.cpp) with the mesh's single-ray walk of that ISA.

#include <cstddef>
#include <cstdint>

#include "kdrt/scene.h"
#include "kdrt/trace.h"

namespace kdrt::detail {

struct SceneData;

/// How many rays a scene batch walks in turn (the mesh batch walks kWalksInTurn, 12).
inline constexpr int kSceneWalksInTurn = 12;

/// The closest hits (hits) or occlusion (occluded) of rays[0, count) of a scene, each ray's
/// answer that of intersect(scene, ray) / occluded(scene, ray) bit for bit; the instances traced
/// are added to `visits`. On the calling thread.
struct SceneInTurnOps {
    void (*intersect)(const SceneData& s, const Ray* rays, size_t count, SceneHit* hits,
                      uint64_t& visits) noexcept;
    void (*occluded)(const SceneData& s, const Ray* rays, size_t count, uint8_t* occluded,
                     uint64_t& visits) noexcept;
};

const SceneInTurnOps& scene_in_turn_ops_baseline() noexcept;
const SceneInTurnOps& scene_in_turn_ops_sse4() noexcept;
const SceneInTurnOps& scene_in_turn_ops_avx2() noexcept;
const SceneInTurnOps& scene_in_turn_ops_avx512() noexcept;

/// The walks of `isa` (a supported one; Isa::kScalar: the x86-64 baseline's, as trace.cpp's
/// single-ray kernel).
inline const SceneInTurnOps& scene_in_turn_ops(Isa isa) noexcept {
    switch (isa) {
        case Isa::kAvx512:
            return scene_in_turn_ops_avx512();
        case Isa::kAvx2:
            return scene_in_turn_ops_avx2();
        case Isa::kSse4:
            return scene_in_turn_ops_sse4();
        default:
            return scene_in_turn_ops_baseline();
    }
}

}  // namespace kdrt::detail
