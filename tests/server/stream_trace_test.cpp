// The server's side of the streamed KDRR path: StreamTrace gives Compute::intersect's /
// occluded's answers however the rays arrive.

#include <gtest/gtest.h>

#include <algorithm>
#include <cstring>
#include <span>
#include <vector>

#include "core/compute.h"
#include "kdrt/trace.h"
#include "test_util.h"

namespace kdrt::server {
namespace {

TEST(StreamTrace, AnswersEqualTheWholeBatchHoweverTheRaysArrive) {
    test::Rng rng(test::test_seed());
    SCOPED_TRACE(testing::Message() << "seed=" << test::test_seed());
    const Mesh mesh = test::random_soup(rng, 2000);
    const KdTree tree = build_kdtree(mesh);
    Compute compute(2);
    // More than two blocks (so some are traced while "arriving"), and a ragged tail.
    const size_t count = std::max<size_t>(test::scaled(3 * StreamTrace::kBlockRays + 1234), 3000);
    const std::vector<Ray> rays = test::rays_towards_unit_cube(count, 21);
    std::vector<Hit> want(count);
    std::vector<uint8_t> want_occluded(count);
    compute.intersect(tree, rays, want);
    compute.occluded(tree, rays, want_occluded);

    std::vector<Hit> hits(count);
    std::vector<uint8_t> occ(count);
    {
        StreamTrace trace(compute, tree, rays, std::span<Hit>(hits));
        StreamTrace trace_occ(compute, tree, rays, std::span<uint8_t>(occ));
        for (size_t ready = 0; ready < count;) {
            ready = std::min(count, ready + 1 + rng.below(40000));
            trace.advance(ready);
            trace_occ.advance(ready);
        }
        trace.finish();
        trace_occ.finish();
    }
    EXPECT_EQ(std::memcmp(hits.data(), want.data(), count * sizeof(Hit)), 0);
    EXPECT_EQ(occ, want_occluded);

    // Abandoned part-way (a refused batch): waits for what it started, traces nothing more.
    std::vector<Hit> partial(count);
    {
        StreamTrace trace(compute, tree, rays, std::span<Hit>(partial));
        trace.advance(count / 2);
        trace.abandon();
        trace.advance(count);  // ignored after abandon: nothing starts, nothing is left running
    }
}

}  // namespace
}  // namespace kdrt::server
