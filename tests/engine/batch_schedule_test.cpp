// The batch scheduler under the packet kernels (engine/src/batch_schedule.h), without a kernel:
// its sort keys, which blocks it sorts, and that it hands every valid ray to exactly one octant
// run and answers the rest, so the kernels' answers land in input order.

#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <limits>
#include <vector>

#include "batch_schedule.h"
#include "kdrt/camera.h"
#include "kdrt/kdtree.h"
#include "test_util.h"

namespace kdrt::test {
namespace {

using detail::block_is_incoherent;
using detail::collect_valid;
using detail::image_row;
using detail::kBlockRays;
using detail::kCoherentRun;
using detail::kOctantShift;
using detail::morton3;
using detail::octant;
using detail::packet_pays;
using detail::quantize;
using detail::schedule_rays;
using detail::sort_by_origin_and_direction;
using detail::spread3;
using detail::trace_origin_sorted_block;
using detail::trace_patch_block;
using detail::TraceCounters;

constexpr float kInf = std::numeric_limits<float>::infinity();
constexpr float kNaN = std::numeric_limits<float>::quiet_NaN();

/// A tree the scheduler accepts: it only reads the bounds (an empty root answers every ray).
KdTree tree_with_bounds() {
    KdTree tree;
    tree.bounds = Aabb{{-1.0f, -1.0f, -1.0f}, {1.0f, 1.0f, 1.0f}};
    return tree;
}

Ray ray(Vec3 o, Vec3 d) { return Ray{o.x, o.y, o.z, 0.0f, d.x, d.y, d.z, kInf}; }

/// Random origins in the unit cube and directions on the sphere: incoherent.
std::vector<Ray> random_rays(Rng& rng, size_t count) {
    std::vector<Ray> rays;
    for (size_t i = 0; i < count; ++i)
        rays.push_back(ray(rng.in_box(Aabb{{0, 0, 0}, {1, 1, 1}}), rng.on_sphere()));
    return rays;
}

/// A pinhole camera's rays: one origin, so the block keeps its order.
std::vector<Ray> camera_rays(uint32_t res) {
    const Camera camera(default_camera(Aabb{{0, 0, 0}, {1, 1, 1}}), res, res);
    std::vector<Ray> rays;
    for (uint32_t y = 0; y < res; ++y)
        for (uint32_t x = 0; x < res; ++x)
            rays.push_back(camera.ray(static_cast<float>(x) + 0.5f, static_cast<float>(y) + 0.5f));
    return rays;
}

/// Every kind of ray the engine answers without tracing.
std::vector<Ray> invalid_rays() {
    return {
        ray({kNaN, 0, 0}, {1, 0, 0}),      ray({0, 0, 0}, {0, kInf, 0}),
        ray({0, 0, 0}, {0, 0, 0}),         Ray{0, 0, 0, 2.0f, 1, 0, 0, 1.0f},  // tmin > tmax
        Ray{0, 0, 0, kNaN, 1, 0, 0, kInf},                                     // NaN tmin
        Ray{0, 0, 0, 0.0f, 1, 0, 0, kNaN},                                     // NaN tmax
    };
}

bool is_miss(const Hit& h) { return h.t == kInf && h.prim == kNoHit && h.u == 0.0f && h.v == 0.0f; }

/// Stands in for the kernel: checks each run and answers ray `i` with prim = i, so the test can
/// see where every answer landed.
struct RecordingRun {
    const std::vector<Ray>& rays;
    std::vector<Hit>& hits;
    std::vector<uint8_t>& occluded;
    std::vector<int>& times_traced;
    std::vector<std::vector<uint32_t>>& runs;  ///< global indices of each run, in run order

    void operator()(const Ray* block, size_t base, const uint16_t* order, int count) const {
        std::vector<uint32_t> run;
        for (int i = 0; i < count; ++i) {
            const size_t at = base + order[i];
            ASSERT_LT(at, rays.size());
            // The run's rays are the caller's rays: the block pointer and base agree.
            ASSERT_EQ(0, std::memcmp(&block[order[i]], &rays[at], sizeof(Ray))) << "ray " << at;
            ASSERT_EQ(octant(rays[at]), octant(rays[base + order[0]])) << "a run mixes octants";
            ++times_traced[at];
            hits[at] = Hit{1.0f, static_cast<uint32_t>(at), 0.0f, 0.0f};
            occluded[at] = 1;
            run.push_back(static_cast<uint32_t>(at));
        }
        runs.push_back(std::move(run));
    }
};

struct Scheduled {
    std::vector<Hit> hits;
    std::vector<uint8_t> occluded;
    std::vector<int> times_traced;
    std::vector<std::vector<uint32_t>> runs;
    TraceCounters counters;
};

template <bool AnyHit>
Scheduled schedule(const KdTree& tree, const std::vector<Ray>& rays) {
    Scheduled s;
    s.hits.assign(rays.size(), Hit{2.0f, 7, 0.5f, 0.5f});  // neither a miss nor a run's answer
    s.occluded.assign(rays.size(), 7);
    s.times_traced.assign(rays.size(), 0);
    const RecordingRun run{rays, s.hits, s.occluded, s.times_traced, s.runs};
    schedule_rays<AnyHit>(tree, rays.data(), rays.size(), AnyHit ? nullptr : s.hits.data(),
                          AnyHit ? s.occluded.data() : nullptr, s.counters, run);
    return s;
}

TEST(BatchSchedule, OctantIsTheSignBitsOfTheDirection) {
    EXPECT_EQ(octant(ray({}, {1, 1, 1})), 0u);
    EXPECT_EQ(octant(ray({}, {-1, 1, 1})), 1u);
    EXPECT_EQ(octant(ray({}, {1, -1, 1})), 2u);
    EXPECT_EQ(octant(ray({}, {1, 1, -1})), 4u);
    EXPECT_EQ(octant(ray({}, {-1, -1, -1})), 7u);
    // -0 is negative: the reciprocal is -inf, so the ray walks the axis downwards.
    EXPECT_EQ(octant(ray({}, {-0.0f, 0.0f, 1})), 1u);
}

TEST(BatchSchedule, OctantOrInvalidAgreesWithRayIsValidOnEverySpecialValue) {
    // Each of the ray's eight fields takes every special value while the others stay those of a
    // valid ray; then random rays whose every field is drawn from the same values.
    const float specials[] = {0.0f,
                              -0.0f,
                              1.0f,
                              -2.5f,
                              std::numeric_limits<float>::denorm_min(),
                              -std::numeric_limits<float>::denorm_min(),
                              std::numeric_limits<float>::min(),
                              std::numeric_limits<float>::max(),
                              -std::numeric_limits<float>::max(),
                              kInf,
                              -kInf,
                              kNaN,
                              -kNaN};
    const auto check = [](const Ray& r, const char* what) {
        const int got = detail::octant_or_invalid(r);
        const int want = detail::ray_is_valid(r) ? static_cast<int>(octant(r)) : -1;
        float f[8];
        std::memcpy(f, &r, sizeof f);
        EXPECT_EQ(got, want) << what << ": " << f[0] << " " << f[1] << " " << f[2] << " " << f[3]
                             << " " << f[4] << " " << f[5] << " " << f[6] << " " << f[7];
    };
    const Ray base{0.5f, -0.5f, 0.25f, 0.0f, 0.3f, -0.4f, 0.5f, 10.0f};
    int invalid = 0;
    for (int field = 0; field < 8; ++field) {
        for (const float x : specials) {
            Ray r = base;
            float f[8];
            std::memcpy(f, &r, sizeof f);
            f[field] = x;
            std::memcpy(&r, f, sizeof f);
            check(r, "one field");
            invalid += detail::octant_or_invalid(r) < 0 ? 1 : 0;
        }
    }
    EXPECT_GT(invalid, 20) << "the special values make invalid rays of every kind";
    Rng rng(test_seed());
    for (int i = 0; i < 20000; ++i) {
        float f[8];
        for (float& x : f) x = specials[rng.next() % (sizeof specials / sizeof specials[0])];
        Ray r;
        std::memcpy(&r, f, sizeof f);
        check(r, "random fields");
    }
    // All three direction components zero (of either sign): invalid; one non-zero: valid.
    check(ray({}, {-0.0f, 0.0f, -0.0f}), "zero direction");
    check(ray({}, {-0.0f, std::numeric_limits<float>::denorm_min(), -0.0f}), "tiny direction");
}

TEST(BatchSchedule, MortonCodesInterleaveFourBitsPerAxis) {
    EXPECT_EQ(spread3(0xFu), 0x249u);
    EXPECT_EQ(spread3(0x1Fu), 0x249u) << "bits above the fourth are dropped";
    EXPECT_EQ(morton3(1, 0, 0), 1u);
    EXPECT_EQ(morton3(0, 1, 0), 2u);
    EXPECT_EQ(morton3(0, 0, 1), 4u);
    EXPECT_EQ(morton3(2, 0, 0), 8u);
    EXPECT_EQ(morton3(15, 15, 15), 0xFFFu);
    // Origin codes (12 bits from kOriginShift) and direction codes (6 bits) sit below the octant.
    EXPECT_LE(detail::kOriginShift + 12, kOctantShift);
    EXPECT_LE(morton3(3, 3, 3), (1u << detail::kOriginShift) - 1);
    EXPECT_EQ(detail::kKeyBits, kOctantShift + 3);
}

TEST(BatchSchedule, QuantizeClampsToTheLevels) {
    EXPECT_EQ(quantize(0.0, 16), 0u);
    EXPECT_EQ(quantize(-0.5, 16), 0u);
    EXPECT_EQ(quantize(std::nan(""), 16), 0u);
    EXPECT_EQ(quantize(0.5, 16), 8u);
    EXPECT_EQ(quantize(0.99, 4), 3u);
    EXPECT_EQ(quantize(1.0, 16), 15u) << "v = 1 lands in the top level";
    EXPECT_EQ(quantize(7.0, 4), 3u);
}

TEST(BatchSchedule, PacketsPayFromHalfTheLanes) {
    for (int width : {4, 8, 16}) {
        for (int lanes = 1; lanes <= width; ++lanes) {
            EXPECT_EQ(packet_pays(lanes, width), lanes >= 2 && 2 * lanes >= width)
                << lanes << " of " << width;
        }
    }
    EXPECT_FALSE(packet_pays(1, 1));
}

TEST(BatchSchedule, OnlyBlocksWithSpreadOriginsAndDirectionsAreSorted) {
    Rng rng(test_seed());
    float lo[3], hi[3];
    const std::vector<Ray> random = random_rays(rng, kBlockRays);
    EXPECT_TRUE(block_is_incoherent(random.data(), static_cast<int>(random.size()), lo, hi));
    for (int a = 0; a < 3; ++a) {
        EXPECT_GE(lo[a], 0.0f);
        EXPECT_LE(hi[a], 1.0f);
        EXPECT_LT(lo[a], hi[a]);
    }

    // One origin (a pinhole camera): kept in image order, however the directions spread.
    const std::vector<Ray> camera = camera_rays(64);
    EXPECT_FALSE(block_is_incoherent(camera.data(), static_cast<int>(camera.size()), lo, hi));

    // One direction (an orthographic view, shadow rays towards a far light): kept too.
    std::vector<Ray> parallel;
    for (size_t i = 0; i < kBlockRays; ++i)
        parallel.push_back(ray(rng.in_box(Aabb{{0, 0, 0}, {1, 1, 1}}), {0.1f, -1.0f, 0.2f}));
    EXPECT_FALSE(block_is_incoherent(parallel.data(), static_cast<int>(parallel.size()), lo, hi));

    // Invalid rays in the sample are skipped; a block of nothing else is not sorted.
    std::vector<Ray> invalid;
    while (invalid.size() < kBlockRays) {
        for (const Ray& r : invalid_rays()) invalid.push_back(r);
    }
    EXPECT_FALSE(block_is_incoherent(invalid.data(), static_cast<int>(kBlockRays), lo, hi));
}

TEST(BatchSchedule, SortOrdersByOctantThenOriginThenDirectionStably) {
    const uint64_t seed = test_seed();
    SCOPED_TRACE(testing::Message() << "seed=" << seed);
    Rng rng(seed);
    std::vector<Ray> block = random_rays(rng, kBlockRays);
    for (size_t i = 0; i < block.size(); i += 97) block[i] = invalid_rays()[i % 6];
    // Duplicates, so equal keys occur and stability is visible.
    for (size_t i = 1; i < block.size(); i += 13) block[i] = block[i - 1];
    const int n = static_cast<int>(block.size());

    const KdTree tree = tree_with_bounds();
    std::vector<Hit> hits(block.size(), Hit{2.0f, 7, 0.0f, 0.0f});
    TraceCounters counters;
    std::vector<uint32_t> key(kBlockRays), key_tmp(kBlockRays);
    std::vector<uint16_t> index(kBlockRays), index_tmp(kBlockRays);
    const int valid = collect_valid<false>(tree, block.data(), 0, n, hits.data(), nullptr, counters,
                                           key.data(), index.data());
    int invalid = 0;
    for (int i = 0; i < n; ++i) {
        if (!detail::ray_is_valid(block[i])) {
            ++invalid;
            EXPECT_TRUE(is_miss(hits[i])) << "invalid ray " << i << " is answered as a miss";
        }
    }
    EXPECT_EQ(valid + invalid, n);
    EXPECT_EQ(counters.invalid_rays, static_cast<uint64_t>(invalid));
    for (int j = 0; j < valid; ++j) EXPECT_EQ(key[j], octant(block[index[j]]) << kOctantShift);

    float lo[3], hi[3];
    ASSERT_TRUE(block_is_incoherent(block.data(), n, lo, hi));
    const bool in_tmp = sort_by_origin_and_direction(
        block.data(), valid, lo, hi, key.data(), index.data(), key_tmp.data(), index_tmp.data());
    const std::vector<uint32_t>& sorted_key = in_tmp ? key_tmp : key;
    const std::vector<uint16_t>& sorted = in_tmp ? index_tmp : index;

    std::vector<int> seen(block.size(), 0);
    for (int j = 0; j < valid; ++j) {
        ASSERT_LT(sorted[j], block.size());
        ++seen[sorted[j]];
        EXPECT_LT(sorted_key[j], 1u << detail::kKeyBits);
        EXPECT_EQ(sorted_key[j] >> kOctantShift, octant(block[sorted[j]])) << "position " << j;
        if (j == 0) continue;
        EXPECT_LE(sorted_key[j - 1], sorted_key[j]) << "position " << j;
        if (sorted_key[j - 1] == sorted_key[j]) {
            EXPECT_LT(sorted[j - 1], sorted[j]) << "equal keys keep the input order";
        }
    }
    for (size_t i = 0; i < block.size(); ++i) {
        EXPECT_EQ(seen[i], detail::ray_is_valid(block[i]) ? 1 : 0) << "ray " << i;
    }
    // The duplicated rays have equal keys.
    for (size_t i = 1; i < block.size(); i += 13) {
        if (!detail::ray_is_valid(block[i])) continue;
        const auto at = [&](size_t r) {
            return sorted_key[static_cast<size_t>(
                std::find(sorted.begin(), sorted.begin() + valid, r) - sorted.begin())];
        };
        EXPECT_EQ(at(i), at(i - 1)) << "ray " << i;
    }
}

/// Incoherent blocks, coherent blocks, a tail and invalid rays, with block boundaries crossed.
std::vector<Ray> mixed_batch(uint64_t seed) {
    Rng rng(seed);
    std::vector<Ray> rays = random_rays(rng, kBlockRays + 1000);
    const std::vector<Ray> camera = camera_rays(64);
    rays.insert(rays.end(), camera.begin(), camera.end());
    const std::vector<Ray> more = random_rays(rng, 777);
    rays.insert(rays.end(), more.begin(), more.end());
    for (size_t i = 5; i < rays.size(); i += 61) rays[i] = invalid_rays()[i % 6];
    return rays;
}

template <bool AnyHit>
void expect_every_valid_ray_traced_once_in_place(const std::vector<Ray>& rays) {
    const Scheduled s = schedule<AnyHit>(tree_with_bounds(), rays);
    uint64_t invalid = 0;
    for (size_t i = 0; i < rays.size(); ++i) {
        if (detail::ray_is_valid(rays[i])) {
            ASSERT_EQ(s.times_traced[i], 1) << "ray " << i;
            if constexpr (AnyHit) {
                EXPECT_EQ(s.occluded[i], 1) << "ray " << i;
            } else {
                EXPECT_EQ(s.hits[i].prim, i) << "ray " << i << " got another ray's answer";
            }
        } else {
            ++invalid;
            ASSERT_EQ(s.times_traced[i], 0) << "ray " << i;
            if constexpr (AnyHit) {
                EXPECT_EQ(s.occluded[i], 0) << "ray " << i;
            } else {
                EXPECT_TRUE(is_miss(s.hits[i])) << "ray " << i;
            }
        }
    }
    EXPECT_EQ(s.counters.invalid_rays, invalid);
    EXPECT_EQ(s.counters.packets + s.counters.packet_rays + s.counters.single_rays, 0u)
        << "the scheduler counts no traced rays: the kernel does";
}

TEST(BatchSchedule, EveryValidRayIsInExactlyOneRunAndAnswersLandInInputOrder) {
    const uint64_t seed = test_seed();
    SCOPED_TRACE(testing::Message() << "seed=" << seed);
    const std::vector<Ray> rays = mixed_batch(seed);
    expect_every_valid_ray_traced_once_in_place<false>(rays);
    expect_every_valid_ray_traced_once_in_place<true>(rays);
}

TEST(BatchSchedule, IncoherentBlocksAreSortedWholeCoherentOnesRunInInputOrder) {
    const uint64_t seed = test_seed();
    SCOPED_TRACE(testing::Message() << "seed=" << seed);
    Rng rng(seed);
    // Block 0: random rays (sorted). Block 1: camera rays (kept in order, runs of kCoherentRun).
    std::vector<Ray> rays = random_rays(rng, kBlockRays);
    const std::vector<Ray> camera = camera_rays(64);
    ASSERT_EQ(camera.size(), kBlockRays);
    rays.insert(rays.end(), camera.begin(), camera.end());
    const Scheduled s = schedule<false>(tree_with_bounds(), rays);
    EXPECT_EQ(s.counters.sorted_rays, kBlockRays) << "only the random block is sorted";

    std::vector<uint32_t> octants_of_block0;
    for (const std::vector<uint32_t>& run : s.runs) {
        if (run.empty()) continue;
        if (run.front() < kBlockRays) {
            // A sorted block: one run per octant, in increasing octant order.
            for (uint32_t i : run) ASSERT_LT(i, kBlockRays) << "a run crosses blocks";
            octants_of_block0.push_back(octant(rays[run.front()]));
            continue;
        }
        // A coherent block: runs of at most kCoherentRun rays within one aligned window, in
        // input order.
        ASSERT_LE(run.size(), static_cast<size_t>(kCoherentRun));
        const uint32_t window = (run.front() - kBlockRays) / kCoherentRun;
        for (size_t j = 0; j < run.size(); ++j) {
            EXPECT_EQ((run[j] - kBlockRays) / kCoherentRun, window);
            if (j > 0) {
                EXPECT_LT(run[j - 1], run[j]) << "a coherent run keeps the input order";
            }
        }
    }
    EXPECT_TRUE(std::is_sorted(octants_of_block0.begin(), octants_of_block0.end()));
    EXPECT_EQ(std::adjacent_find(octants_of_block0.begin(), octants_of_block0.end()),
              octants_of_block0.end())
        << "one run per octant";
    EXPECT_EQ(octants_of_block0.size(), 8u) << "random directions cover every octant";
}

/// Mean over aligned groups of 16 consecutive rays of `order` (grid indices i + 64 j) of the
/// group's extent in i plus its extent in j: 15 for rows of the grid, 6 for 4x4 patches.
double mean_group_span(const std::vector<uint32_t>& order) {
    double sum = 0;
    size_t groups = 0;
    for (size_t g = 0; g + 16 <= order.size(); g += 16) {
        uint32_t i_lo = 64, i_hi = 0, j_lo = 64, j_hi = 0;
        for (size_t k = g; k < g + 16; ++k) {
            const uint32_t i = order[k] % 64, j = order[k] / 64;
            i_lo = std::min(i_lo, i), i_hi = std::max(i_hi, i);
            j_lo = std::min(j_lo, j), j_hi = std::max(j_hi, j);
        }
        sum += (i_hi - i_lo) + (j_hi - j_lo);
        ++groups;
    }
    return groups > 0 ? sum / static_cast<double>(groups) : 0.0;
}

TEST(BatchSchedule, CoherentAnyHitBlocksAreSortedIntoPatchesAcrossTheirWay) {
    // Shadow rays of a 64 x 60 image of a tilted plane towards one far light (z dominant), in
    // image order: the origins' x and y are the plane across the rays' way. Then 256 rays of
    // another octant and invalid ones, answered in place all the same; one of them starts at
    // (1, 1), so the origins span exactly 1 in x and y: the grid's steps are whole sort levels
    // and its 4 x 4 patches whole Morton cells.
    const uint64_t seed = test_seed();
    SCOPED_TRACE(testing::Message() << "seed=" << seed);
    Rng rng(seed);
    std::vector<Ray> rays;
    for (uint32_t j = 0; j < 60; ++j)
        for (uint32_t i = 0; i < 64; ++i) {
            const float x = static_cast<float>(i) / 64.0f, y = static_cast<float>(j) / 64.0f;
            rays.push_back(ray({x, y, 0.3f * x + rng.uniform() * 1e-3f}, {0.1f, 0.2f, 1.0f}));
        }
    for (uint32_t k = 0; k < 256; ++k) {
        const Vec3 o{rng.uniform(), rng.uniform(0.25f, 1.0f), 0.0f};  // within both blocks
        rays.push_back(k % 2 == 0 ? ray(o, {-0.1f, 0.2f, 1.0f}) : invalid_rays()[k % 6]);
    }
    rays[64 * 60] = ray({1.0f, 1.0f, 0.3f}, {-0.1f, 0.2f, 1.0f});
    ASSERT_EQ(rays.size(), kBlockRays);
    for (const size_t base : {size_t{0}, size_t{64 * 16}}) {  // a whole block; its last part
        SCOPED_TRACE(testing::Message() << "base=" << base);
        const int n = static_cast<int>(rays.size() - base);
        Scheduled s;
        s.occluded.assign(rays.size(), 7);
        s.hits.assign(rays.size(), Hit{});
        s.times_traced.assign(rays.size(), 0);
        const RecordingRun run{rays, s.hits, s.occluded, s.times_traced, s.runs};
        trace_origin_sorted_block<true>(tree_with_bounds(), rays.data() + base, base, n, nullptr,
                                        s.occluded.data(), s.counters, run);
        uint64_t invalid = 0;
        for (size_t i = base; i < rays.size(); ++i) {
            const bool valid = detail::ray_is_valid(rays[i]);
            invalid += valid ? 0 : 1;
            ASSERT_EQ(s.times_traced[i], valid ? 1 : 0) << "ray " << i;
            EXPECT_EQ(s.occluded[i], valid ? 1 : 0) << "ray " << i;
        }
        for (size_t i = 0; i < base; ++i) ASSERT_EQ(s.occluded[i], 7) << "outside the block";
        EXPECT_EQ(s.counters.invalid_rays, invalid);
        ASSERT_EQ(s.runs.size(), 2u) << "one run per octant";
        ASSERT_EQ(s.runs[0].size(), 64 * 60 - base) << "octant 0 first: the image's rays";
        EXPECT_EQ(octant(rays[s.runs[1].front()]), 1u);
        // The image's packets of 16 are its 4 x 4 patches, not strips of a row.
        std::vector<uint32_t> input_order = s.runs[0];
        std::sort(input_order.begin(), input_order.end());
        EXPECT_EQ(mean_group_span(input_order), 15.0);
        EXPECT_EQ(mean_group_span(s.runs[0]), 6.0);
    }
}

/// An image of width x height rays from one point, in image order, all of octant 0.
std::vector<Ray> octant0_image(int width, int height) {
    std::vector<Ray> rays;
    for (int y = 0; y < height; ++y)
        for (int x = 0; x < width; ++x)
            rays.push_back(ray({0, 0, -5}, {1.0f + 0.01f * static_cast<float>(x),
                                            1.0f + 0.01f * static_cast<float>(y), 1.0f}));
    return rays;
}

TEST(BatchSchedule, AnImagesRowsAreFoundFromItsDirections) {
    for (const uint32_t res : {4u, 16u, 64u}) {  // square camera images, 2 to 64 rows a block
        const std::vector<Ray> rays = camera_rays(res);
        const int n = static_cast<int>(std::min<size_t>(rays.size(), kBlockRays));
        SCOPED_TRACE(testing::Message() << "res=" << res);
        EXPECT_EQ(image_row(rays.data(), n, 0), static_cast<int>(res));
        EXPECT_EQ(image_row(rays.data(), n, static_cast<int>(res) - 1), static_cast<int>(res));
        EXPECT_EQ(image_row(rays.data(), n, static_cast<int>(res) + 1), static_cast<int>(res));
        EXPECT_EQ(image_row(rays.data() + 3, n - 3, 0), static_cast<int>(res)) << "mid-row";
        EXPECT_EQ(image_row(rays.data(), 2 * static_cast<int>(res) - 1, 0), 0) << "under 2 rows";
        EXPECT_EQ(image_row(rays.data(), 2 * static_cast<int>(res), 0), static_cast<int>(res));
    }
    for (const int width : {3, 17, 100, 1024, 2048}) {  // wide images: whole blocks
        const std::vector<Ray> rays =
            octant0_image(width, static_cast<int>(kBlockRays) / width + 2);
        SCOPED_TRACE(testing::Message() << "width=" << width);
        EXPECT_EQ(image_row(rays.data(), static_cast<int>(kBlockRays), 0), width);
        EXPECT_EQ(image_row(rays.data() + width - 1, static_cast<int>(kBlockRays), 0), width)
            << "from a row's last ray";
    }
    std::vector<Ray> sprinkled = camera_rays(64);
    const std::vector<Ray> bad = invalid_rays();
    for (size_t i = 0; i < sprinkled.size(); i += 37) sprinkled[i] = bad[i % bad.size()];
    EXPECT_EQ(image_row(sprinkled.data(), static_cast<int>(sprinkled.size()), 0), 64);
    // No rows: random rays, rays from many points one way, one ray repeated, too few rays.
    Rng rng(test_seed());
    const std::vector<Ray> random = random_rays(rng, kBlockRays);
    EXPECT_EQ(image_row(random.data(), static_cast<int>(random.size()), 64), 0);
    std::vector<Ray> parallel = camera_rays(64);
    for (size_t i = 0; i < parallel.size(); ++i) {
        parallel[i].ox = static_cast<float>(i % 64);
        parallel[i].oy = static_cast<float>(i / 64);
        parallel[i].dx = 0.1f, parallel[i].dy = 0.2f, parallel[i].dz = 1.0f;
    }
    EXPECT_EQ(image_row(parallel.data(), static_cast<int>(parallel.size()), 64), 0);
    const std::vector<Ray> same(kBlockRays, ray({0, 0, 0}, {1, 2, 3}));
    EXPECT_EQ(image_row(same.data(), static_cast<int>(same.size()), 0), 0);
    EXPECT_EQ(image_row(same.data(), 3, 0), 0);
    const std::vector<Ray> only_bad(100, bad[0]);
    EXPECT_EQ(image_row(only_bad.data(), static_cast<int>(only_bad.size()), 10), 0);
}

/// Traces block `rays` (whose first ray is the image's ray `first`) in patches of packets of W,
/// checking that every valid ray is traced once and the invalid ones answered as misses in
/// place, and returns the runs (indices into the image).
template <int W>
std::vector<std::vector<uint32_t>> patch_runs(const std::vector<Ray>& rays, int row) {
    Scheduled s;
    s.hits.assign(rays.size(), Hit{2.0f, 7, 0.5f, 0.5f});
    s.occluded.assign(rays.size(), 7);
    s.times_traced.assign(rays.size(), 0);
    const RecordingRun run{rays, s.hits, s.occluded, s.times_traced, s.runs};
    trace_patch_block<W, false>(rays.data(), 0, static_cast<int>(rays.size()), row, s.hits.data(),
                                nullptr, s.counters, run);
    uint64_t invalid = 0;
    for (size_t i = 0; i < rays.size(); ++i) {
        const bool valid = detail::ray_is_valid(rays[i]);
        invalid += valid ? 0 : 1;
        EXPECT_EQ(s.times_traced[i], valid ? 1 : 0) << "ray " << i;
        if (valid)
            EXPECT_EQ(s.hits[i].prim, i) << "ray " << i;
        else
            EXPECT_TRUE(is_miss(s.hits[i])) << "ray " << i;
    }
    EXPECT_EQ(s.counters.invalid_rays, invalid);
    std::vector<std::vector<uint32_t>> runs;
    for (auto& r : s.runs) {
        EXPECT_LE(r.size(), static_cast<size_t>(kCoherentRun));
        if (!r.empty()) runs.push_back(std::move(r));
    }
    return runs;
}

TEST(BatchSchedule, AnImagesBlocksGoInSquarePatches) {
    // 64 rows of 64 (a whole block): runs of 4 rows, packets of 16 are 4 x 4 patches, of 8 are
    // 4 rows by 2 columns, of 4 are columns of 4.
    const std::vector<Ray> rays = octant0_image(64, 64);
    const auto check = [&](const std::vector<std::vector<uint32_t>>& runs, int w, int rows,
                           int cols) {
        SCOPED_TRACE(testing::Message() << "W=" << w);
        ASSERT_EQ(runs.size(), 16u);
        for (const auto& run : runs) {
            ASSERT_EQ(run.size(), 256u);
            for (size_t g = 0; g < run.size(); g += static_cast<size_t>(w)) {
                uint32_t x_lo = 64, x_hi = 0, y_lo = 64, y_hi = 0;
                for (size_t k = g; k < g + static_cast<size_t>(w); ++k) {
                    x_lo = std::min(x_lo, run[k] % 64), x_hi = std::max(x_hi, run[k] % 64);
                    y_lo = std::min(y_lo, run[k] / 64), y_hi = std::max(y_hi, run[k] / 64);
                }
                EXPECT_EQ(x_hi - x_lo + 1, static_cast<uint32_t>(cols)) << "packet at " << run[g];
                EXPECT_EQ(y_hi - y_lo + 1, static_cast<uint32_t>(rows)) << "packet at " << run[g];
            }
        }
    };
    check(patch_runs<16>(rays, 64), 16, 4, 4);
    check(patch_runs<8>(rays, 64), 8, 4, 2);
    check(patch_runs<4>(rays, 64), 4, 4, 1);
    // Two rows a block (2 x 8 patches at W = 16), three (bands of three rows and the rest in
    // input order), a remainder past the last band, and invalid rays: every ray answered once.
    const std::vector<Ray> two = octant0_image(2048, 2);
    const auto runs = patch_runs<16>(two, 2048);
    ASSERT_FALSE(runs.empty());
    for (size_t k = 0; k < 16; ++k) {
        EXPECT_EQ(runs[0][k] % 2048, k % 8);
        EXPECT_EQ(runs[0][k] / 2048, k / 8);
    }
    patch_runs<16>(octant0_image(1366, 3), 1366);
    std::vector<Ray> odd = octant0_image(17, 240);
    odd.resize(kBlockRays - 5);
    const std::vector<Ray> bad = invalid_rays();
    for (size_t i = 0; i < odd.size(); i += 31) odd[i] = bad[i % bad.size()];
    for (size_t i = 1; i < odd.size(); i += 53) odd[i].dx = -odd[i].dx;  // another octant
    patch_runs<16>(odd, 17);
    patch_runs<8>(odd, 17);
}

TEST(BatchSchedule, AnEmptyTreeAnswersEveryRayAsAMiss) {
    Rng rng(test_seed());
    const std::vector<Ray> rays = random_rays(rng, 3000);
    const Scheduled s = schedule<false>(KdTree{}, rays);
    for (size_t i = 0; i < rays.size(); ++i) {
        EXPECT_EQ(s.times_traced[i], 0);
        EXPECT_TRUE(is_miss(s.hits[i]));
    }
    EXPECT_EQ(s.counters.invalid_rays, rays.size());
}

TEST(BatchSchedule, AnEmptyBatchRunsNothing) {
    const Scheduled s = schedule<false>(tree_with_bounds(), {});
    EXPECT_TRUE(s.runs.empty());
}

}  // namespace
}  // namespace kdrt::test
