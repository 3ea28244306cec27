#pragma once
/// `kdrt-bench scene instances --compare embree`: the same instanced scene through Embree's
/// instancing (one BLAS of the mesh, a top-level scene of RTC_GEOMETRY_TYPE_INSTANCE geometries
/// placed by the same 3x4 transforms), as a yardstick for kdrt's two-level scenes. Compiled only
/// when CMake found Embree (KDRT_HAVE_EMBREE); otherwise every call throws EmbreeError.

#include <cstdint>
#include <memory>
#include <span>
#include <string>
#include <vector>

#include "embree_compare.h"
#include "kdrt/mesh.h"
#include "kdrt/scene.h"
#include "kdrt/types.h"

namespace kdrt::bench {

/// One ray set through the Embree scene: the fastest of its query modes.
struct EmbreeSceneTiming {
    std::string best_mode;  ///< "intersect1", "intersect8", "intersect8_coherent" (occluded*)
    double best_mrays_per_s = 0;
    std::vector<std::pair<std::string, double>> modes;  ///< every mode's mrays/s
};

/// An Embree device with the instanced scene (RTC_BUILD_QUALITY_HIGH for the mesh, the top level
/// at Embree's default quality, as its instancing tutorials build it).
class EmbreeInstanceScene {
public:
    /// Builds the mesh's BLAS and the top level of `transforms.size()` instances. Throws
    /// EmbreeError.
    EmbreeInstanceScene(const Mesh& mesh, std::span<const Affine3x4> transforms);
    ~EmbreeInstanceScene();
    EmbreeInstanceScene(const EmbreeInstanceScene&) = delete;
    EmbreeInstanceScene& operator=(const EmbreeInstanceScene&) = delete;

    [[nodiscard]] double blas_build_ms() const noexcept;
    [[nodiscard]] double top_build_ms() const noexcept;
    /// Sets every instance's transform and commits the top level again; returns the wall ms.
    double set_transforms(std::span<const Affine3x4> transforms);
    /// Times `reps` passes of every query mode over the calling thread's oneTBB arena (after an
    /// untimed warm-up). The answers of the best mode go to `hits` (closest hit: geom = instID,
    /// prim = primID) or `occluded` (occlusion), each rays.size() long.
    EmbreeSceneTiming trace(std::span<const Ray> rays, bool occlusion, int reps,
                            std::span<SceneHit> hits, std::span<uint8_t> occluded);

private:
    struct Impl;
    std::unique_ptr<Impl> impl_;
};

#if !(defined(KDRT_HAVE_EMBREE) && KDRT_HAVE_EMBREE)
struct EmbreeInstanceScene::Impl {};
inline EmbreeInstanceScene::EmbreeInstanceScene(const Mesh&, std::span<const Affine3x4>) {
    throw EmbreeError("this kdrt-bench was built without Embree");
}
inline EmbreeInstanceScene::~EmbreeInstanceScene() = default;
inline double EmbreeInstanceScene::blas_build_ms() const noexcept { return 0; }
inline double EmbreeInstanceScene::top_build_ms() const noexcept { return 0; }
inline double EmbreeInstanceScene::set_transforms(std::span<const Affine3x4>) { return 0; }
inline EmbreeSceneTiming EmbreeInstanceScene::trace(std::span<const Ray>, bool, int,
                                                    std::span<SceneHit>, std::span<uint8_t>) {
    return {};
}
#endif

}  // namespace kdrt::bench
