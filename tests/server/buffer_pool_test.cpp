#include "core/buffer_pool.h"

#include <gtest/gtest.h>

#include <cstdint>
#include <utility>
#include <vector>

namespace kdrt::server {
namespace {

TEST(VectorPool, ReusesTheSmallestIdleVectorThatFits) {
    VectorPool<int> pool(64u << 20);
    std::vector<int> a = pool.take(1u << 20), b = pool.take(4u << 20);
    const int* a_data = a.data();
    const int* b_data = b.data();
    pool.give(std::move(b));
    pool.give(std::move(a));
    EXPECT_EQ(pool.idle_bytes(), (5u << 20) * sizeof(int));
    std::vector<int> c = pool.take(1u << 19);  // large enough to pool: best fit is a
    EXPECT_EQ(c.data(), a_data);
    EXPECT_TRUE(c.empty());
    std::vector<int> d = pool.take(3u << 20);
    EXPECT_EQ(d.data(), b_data);
    EXPECT_EQ(pool.idle_bytes(), 0u);
}

TEST(VectorPool, SmallRequestsAndSmallVectorsBypassThePool) {
    VectorPool<char> pool(64u << 20);
    std::vector<char> big = pool.take(8u << 20);
    pool.give(std::move(big));
    std::vector<char> small = pool.take(100);  // does not take the 8 MiB vector
    EXPECT_LT(small.capacity(), 1u << 20);
    EXPECT_EQ(pool.idle_bytes(), 8u << 20);
    pool.give(std::move(small));  // too small to keep
    EXPECT_EQ(pool.idle_bytes(), 8u << 20);
}

TEST(VectorPool, NeverHoldsMoreThanItsCap) {
    VectorPool<char> pool(10u << 20);
    std::vector<char> a = pool.take(6u << 20), b = pool.take(6u << 20);
    pool.give(std::move(a));
    pool.give(std::move(b));  // would exceed 10 MiB: freed
    EXPECT_EQ(pool.idle_bytes(), 6u << 20);
    VectorPool<char> off(0);
    std::vector<char> c = off.take(2u << 20);
    off.give(std::move(c));
    EXPECT_EQ(off.idle_bytes(), 0u);
}

TEST(BufferPool, ReusesTheSmallestIdleBufferThatFitsWithinItsBudget) {
    BufferPool pool(8u << 20);
    AlignedBuffer a = pool.take(3u << 20), b = pool.take((1u << 20) + 1);
    EXPECT_EQ(reinterpret_cast<uintptr_t>(a.data()) % AlignedBuffer::kAlignment, 0u);
    EXPECT_EQ(b.capacity(), 2u << 20);  // pooled sizes are whole MiB
    const std::byte* a_data = a.data();
    const std::byte* b_data = b.data();
    pool.give(std::move(a));
    pool.give(std::move(b));
    EXPECT_EQ(pool.idle_bytes(), 5u << 20);
    AlignedBuffer c = pool.take(1u << 20);
    EXPECT_EQ(c.data(), b_data);
    AlignedBuffer d = pool.take(3u << 20);
    EXPECT_EQ(d.data(), a_data);
    EXPECT_EQ(pool.idle_bytes(), 0u);
    pool.give(pool.take(6u << 20));
    pool.give(std::move(d));  // 6 + 3 MiB > the 8 MiB budget: freed, not kept
    EXPECT_EQ(pool.idle_bytes(), 6u << 20);
    AlignedBuffer small = pool.take(100);  // small buffers bypass the pool
    EXPECT_GE(small.capacity(), 100u);
    pool.give(std::move(small));
    EXPECT_EQ(pool.idle_bytes(), 6u << 20);
}

TEST(PooledBuffer, GoesBackToItsPoolWhenDestroyedOrReplaced) {
    BufferPool pool(64u << 20);
    {
        PooledBuffer a(pool, 2u << 20);
        EXPECT_GE(a.capacity(), 2u << 20);
        EXPECT_EQ(pool.idle_bytes(), 0u);
        PooledBuffer b = std::move(a);  // moved-from a gives nothing back
        EXPECT_FALSE(a);  // NOLINT(bugprone-use-after-move): the moved-from state is the test
        EXPECT_TRUE(b);
    }
    EXPECT_EQ(pool.idle_bytes(), 2u << 20);
    PooledBuffer c(pool, 1u << 20);  // reuses the idle one
    EXPECT_EQ(pool.idle_bytes(), 0u);
    c = PooledBuffer(pool, 3u << 20);  // the replaced buffer goes back
    EXPECT_EQ(pool.idle_bytes(), 2u << 20);
    c = PooledBuffer();
    EXPECT_EQ(pool.idle_bytes(), 5u << 20);
}

}  // namespace
}  // namespace kdrt::server
