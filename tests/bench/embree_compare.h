#pragma once
/// `kdrt-bench trace --compare embree`: the same mesh and rays through Embree (4 or 3, whichever
/// CMake found), as a yardstick.
/// Compiled only when CMake found Embree (KDRT_HAVE_EMBREE); otherwise kEmbreeAvailable is false
/// and kdrt-bench refuses --compare before calling anything here.

#include <cstdint>
#include <span>
#include <stdexcept>
#include <string>
#include <vector>

#include "kdrt/mesh.h"
#include "kdrt/proto/ray_batch.h"
#include "kdrt/types.h"

namespace kdrt::bench {

#if defined(KDRT_HAVE_EMBREE) && KDRT_HAVE_EMBREE
inline constexpr bool kEmbreeAvailable = true;
#else
inline constexpr bool kEmbreeAvailable = false;
#endif

/// An Embree device or scene call failed; what() carries Embree's error code and message.
class EmbreeError : public std::runtime_error {
public:
    using std::runtime_error::runtime_error;
};

struct EmbreeOptions {
    int reps = 5;  ///< timed passes per query mode (after one untimed warm-up pass)
};

/// Speed of one Embree query mode, e.g. "intersect8_coherent".
struct EmbreeModeTiming {
    std::string name;
    double mrays_per_s = 0;
    uint64_t differences = 0;  ///< answers that differ from kdrt's (see EmbreeReport)
    uint64_t ties = 0;         ///< of those, ties (see EmbreeReport)
    uint64_t kdrt_matches_oracle =
        0;  ///< of the rest, kdrt's answer is the oracle's (see EmbreeReport)
};

/// One Embree scene's results: the default scene flags, or RTC_SCENE_FLAG_ROBUST.
struct EmbreeSceneReport {
    double build_ms = 0;            ///< rtcCommitScene, RTC_BUILD_QUALITY_HIGH
    double bytes_per_triangle = 0;  ///< memory Embree holds after the build (memory monitor)
    std::string best_mode;          ///< the fastest of `modes`
    double best_mrays_per_s = 0;
    /// Rays whose answer differs from kdrt's in the best mode. Closest hit: the prim differs (a
    /// hit against a miss included), or both hit and t differs by more than 1e-4 relative (and
    /// more than 1e-7 of the scene's diagonal, in distance).
    /// Occlusion: the bit differs.
    uint64_t differences = 0;
    /// Of the differences (closest hit only), the ties: both hit at the same t (within the same
    /// 1e-4), and Embree's triangle shares a corner with kdrt's (the ray crosses their shared edge
    /// or vertex, and each test's rounding picks a side) or kdrt's own watertight test hits it at
    /// that t too. differences - ties are the answers the two tracers really disagree on (for
    /// occlusion every difference counts).
    uint64_t ties = 0;
    /// Of the differences that are not ties (closest hit only), the rays where kdrt's answer is
    /// bit for bit the brute-force oracle's (every triangle through kdrt's watertight test): there
    /// Embree is the one that differs, typically missing a triangle within a few ulps of its edge
    /// (its default test is not watertight) and reporting the one behind.
    uint64_t kdrt_matches_oracle = 0;
    std::vector<EmbreeModeTiming> modes;  ///< every mode measured, in a fixed order
};

/// Embree twice: with its default scene flags (its fastest triangle test, not watertight) and
/// with RTC_SCENE_FLAG_ROBUST (its watertight mode, as kdrt's test is). The goals are set
/// against whichever is faster (best()); the robust scene shows what the triangle test costs.
struct EmbreeReport {
    EmbreeSceneReport standard;  ///< RTC_SCENE_FLAG_NONE
    EmbreeSceneReport robust;    ///< RTC_SCENE_FLAG_ROBUST
    int version_major = 0;       ///< of the Embree library this kdrt-bench was built with

    /// The faster of the two scenes (the default one on a tie).
    [[nodiscard]] const EmbreeSceneReport& best() const noexcept {
        return robust.best_mrays_per_s > standard.best_mrays_per_s ? robust : standard;
    }
    /// "robust" if best() is the robust scene, else "default".
    [[nodiscard]] std::string best_flags() const {
        return &best() == &robust ? "robust" : "default";
    }
};

/// Builds two Embree scenes of `mesh` (default flags and RTC_SCENE_FLAG_ROBUST) and times `batch`
/// through each with rtcIntersect1/4/8/16, and rtcIntersect1M where the library has ray streams
/// (Embree 3 only) (or the rtcOccluded forms for an occlusion batch), each incoherent and
/// coherent, over the calling thread's oneTBB arena. `kd_hits` (closest hit) or `kd_occluded`
/// (occlusion) are kdrt's answers for the same rays. Widths the CPU or the Embree build lacks are
/// skipped. Throws EmbreeError.
[[nodiscard]] EmbreeReport compare_with_embree(const Mesh& mesh, const proto::RayBatch& batch,
                                               std::span<const Hit> kd_hits,
                                               std::span<const uint8_t> kd_occluded,
                                               const EmbreeOptions& options);

#if !(defined(KDRT_HAVE_EMBREE) && KDRT_HAVE_EMBREE)
// Without Embree the caller checks kEmbreeAvailable first; this keeps the call site free of #if.
inline EmbreeReport compare_with_embree(const Mesh&, const proto::RayBatch&, std::span<const Hit>,
                                        std::span<const uint8_t>, const EmbreeOptions&) {
    throw EmbreeError("this kdrt-bench was built without Embree");
}
#endif

}  // namespace kdrt::bench
