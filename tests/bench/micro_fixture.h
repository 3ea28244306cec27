#pragma once
// Shared state of the micro-benchmarks: the bunny's tree and a row of its camera rays.

#include <vector>

#include "kdrt/kdtree.h"
#include "kdrt/types.h"

namespace kdrt::bench {

struct MicroFixture {
    KdTree tree;
    std::vector<Ray> rays;    // 16 adjacent primary rays through the middle of the image
    uint32_t inner_node = 0;  // an inner node the rays cross
    uint32_t triangle = 0;    // a triangle the first ray hits
};

/// Built on first use (bunny00.off from the test data directory).
const MicroFixture& micro_fixture();

}  // namespace kdrt::bench
