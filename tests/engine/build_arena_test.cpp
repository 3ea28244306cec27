// The binned levels' reference arrays (build_arena.h): ranges carved from a few blocks, merged
// again when given back.

#include <gtest/gtest.h>

#include <algorithm>
#include <cstdint>
#include <thread>
#include <utility>
#include <vector>

#include "build_arena.h"
#include "test_util.h"

namespace kdrt::test {
namespace {

using Arena = detail::ArrayArena<uint32_t>;

// Fills `a` with values only `tag` writes, and checks them.
void fill(Arena::Array& a, uint32_t tag) {
    for (size_t i = 0; i < a.size(); ++i) a[i] = tag * 7919u + static_cast<uint32_t>(i);
}
bool holds(const Arena::Array& a, uint32_t tag) {
    for (size_t i = 0; i < a.size(); ++i)
        if (a[i] != tag * 7919u + static_cast<uint32_t>(i)) return false;
    return true;
}

// A freed range serves several smaller requests (best fit, the rest left free), and ranges given
// back in any order merge again into one that holds the whole block.
TEST(ArrayArena, FreedRangesAreSplitAndMergedAgain) {
    Arena arena;
    Arena::Array big = arena.take(1000);
    EXPECT_EQ(big.size(), 1000u);
    arena.give(std::move(big));
    EXPECT_EQ(big.size(), 0u);
    Arena::Array a = arena.take(300), b = arena.take(300), c = arena.take(400);
    EXPECT_EQ(arena.block_elements(), 1000u);  // all three from the freed range
    fill(a, 1);
    fill(b, 2);
    fill(c, 3);
    EXPECT_TRUE(holds(a, 1) && holds(b, 2) && holds(c, 3));
    arena.give(std::move(a));
    arena.give(std::move(c));
    arena.give(std::move(b));  // merges with both neighbours
    Arena::Array whole = arena.take(1000);
    EXPECT_EQ(arena.block_elements(), 1000u);
    // Too big for any free range: a new block.
    Arena::Array more = arena.take(1001);
    EXPECT_EQ(arena.block_elements(), 2001u);
    // Best fit: a 10-element request takes the smaller of two free ranges.
    arena.give(std::move(more));
    arena.give(std::move(whole));
    Arena::Array keep = arena.take(990);  // the 1000 block, 10 left
    Arena::Array small = arena.take(10);
    EXPECT_EQ(small.data(), keep.data() + 990);
    Arena::Array rest = arena.take(1001);  // the untouched 1001 block
    EXPECT_EQ(arena.block_elements(), 2001u);
    // A shrunk array gives back its whole range.
    rest.shrink(5);
    EXPECT_EQ(rest.size(), 5u);
    arena.give(std::move(rest));
    Arena::Array again = arena.take(1001);
    EXPECT_EQ(arena.block_elements(), 2001u);
    EXPECT_EQ(arena.take(0).size(), 0u);
}

// Random takes and gives, as the binned levels make them on two threads: no live array ever
// shares an element with another (each keeps what it was filled with), and memory is reused
// (the blocks stay far below the sum of all requests).
TEST(ArrayArena, LiveArraysNeverOverlap) {
    Arena arena;
    std::vector<size_t> requested_by(2, 0);
    auto work = [&](uint32_t thread) {
        Rng rng(test_seed() + 900 + thread);
        std::vector<std::pair<Arena::Array, uint32_t>> live;
        uint32_t tag = thread << 24;
        for (int step = 0; step < 4000; ++step) {
            if (live.size() < 24 && (live.empty() || rng.uniform() < 0.55)) {
                const auto n =
                    static_cast<size_t>(1 + rng.uniform() * (rng.uniform() < 0.1 ? 20000 : 500));
                requested_by[thread] += n;
                Arena::Array a = arena.take(n);
                ASSERT_EQ(a.size(), n);
                fill(a, ++tag);
                live.emplace_back(std::move(a), tag);
            } else {
                const auto k =
                    static_cast<size_t>(rng.uniform() * static_cast<double>(live.size())) %
                    live.size();
                std::swap(live[k], live.back());
                arena.give(std::move(live.back().first));
                live.pop_back();
            }
            if (step % 50 == 0) {
                for (const auto& [a, t] : live) {
                    ASSERT_TRUE(holds(a, t)) << "step " << step;
                }
            }
        }
        for (const auto& [a, t] : live) {
            ASSERT_TRUE(holds(a, t));
        }
    };
    std::thread other(work, 1u);
    work(0u);
    other.join();
    const size_t requested = requested_by[0] + requested_by[1];
    EXPECT_LT(arena.block_elements(), requested / 4);
}

}  // namespace
}  // namespace kdrt::test
