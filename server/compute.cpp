#include "compute.h"

#include <tbb/info.h>

#include "kdrt/trace.h"

namespace kdrt::server {
namespace {

unsigned resolve_threads(unsigned requested) {
    const int cores = tbb::info::default_concurrency();
    return requested == 0 ? static_cast<unsigned>(cores > 0 ? cores : 1) : requested;
}

}  // namespace

Compute::Compute(unsigned threads)
    : threads_(resolve_threads(threads)),
      // Caps oneTBB's worker pool at the arena size: nothing else in the process may add threads.
      control_(std::make_unique<tbb::global_control>(tbb::global_control::max_allowed_parallelism, threads_)),
      arena_(static_cast<int>(threads_)) {}

KdTree Compute::build(const Mesh& mesh) {
    return arena_.execute([&] { return build_kdtree(mesh, BuildOptions{}); });
}

void Compute::intersect(const KdTree& tree, std::span<const Ray> rays, std::span<Hit> hits) {
    if (rays.size() < kInlineRays) {
        intersect_block(tree, rays, hits);
        return;
    }
    arena_.execute([&] { kdrt::intersect(tree, rays, hits); });
}

void Compute::occluded(const KdTree& tree, std::span<const Ray> rays, std::span<uint8_t> occluded) {
    if (rays.size() < kInlineRays) {
        occluded_block(tree, rays, occluded);
        return;
    }
    arena_.execute([&] { kdrt::occluded(tree, rays, occluded); });
}

}  // namespace kdrt::server
