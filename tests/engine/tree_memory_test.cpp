// The memory of a tree's arrays (engine/src/tree_memory.cpp): a big array is a 2 MiB-aligned
// mapping of its own, advised MADV_HUGEPAGE, never a piece of the heap that earlier work may have
// backed with small pages already; a small one is 64-byte aligned.

#include <gtest/gtest.h>

#include <cstdint>
#include <cstdlib>
#include <cstring>
#include <fstream>
#include <sstream>
#include <string>

#include "build_common.h"
#include "kdrt/kdtree.h"

namespace kdrt::test {
namespace {

constexpr uintptr_t kHugePage = uintptr_t{2} << 20;

/// The /proc/self/smaps entry of the mapping holding `addr`: its range, its path (empty for an
/// anonymous mapping, "[heap]" for the brk heap) and its VmFlags line.
struct Mapping {
    uintptr_t start = 0, end = 0;
    std::string path, flags;
    bool found = false;
};

Mapping mapping_of(const void* addr) {
    const auto a = reinterpret_cast<uintptr_t>(addr);
    std::ifstream smaps("/proc/self/smaps");
    Mapping m;
    std::string line;
    bool in = false;
    while (std::getline(smaps, line)) {
        // A mapping's header line starts with "start-end " in hex; field lines with "Name:".
        const size_t dash = line.find('-');
        const size_t space = line.find(' ');
        const bool header = dash != std::string::npos && space != std::string::npos &&
                            dash < space && line.find(':') > space;
        if (header) {
            if (in) break;
            const uintptr_t start = std::stoull(line.substr(0, dash), nullptr, 16);
            const uintptr_t end = std::stoull(line.substr(dash + 1, space - dash - 1), nullptr, 16);
            if (a >= start && a < end) {
                in = true;
                m.found = true;
                m.start = start;
                m.end = end;
                std::istringstream fields(line);
                std::string skip;
                for (int i = 0; i < 5; ++i) fields >> skip;  // range, perms, offset, dev, inode
                std::getline(fields >> std::ws, m.path);
            }
        } else if (in && line.rfind("VmFlags:", 0) == 0) {
            m.flags = line;
        }
    }
    return m;
}

TEST(TreeMemory, BigArraysAreHugePageMappingsEvenWhereTheHeapWasUsedBefore) {
    // Use the heap for something big first: glibc's free of a mapped block raises its mapping
    // threshold, so a later operator new of this size comes from the (already touched) heap.
    for (int i = 0; i < 2; ++i) {
        void* warm = std::malloc(size_t{24} << 20);
        ASSERT_NE(warm, nullptr);
        std::memset(warm, 1, size_t{24} << 20);
        std::free(warm);
    }
    const size_t n = (size_t{9} << 20) / sizeof(float) + 3;  // 9 MiB and a bit: not whole pages
    TreeArray<float> big(n);
    for (size_t i = 0; i < n; i += 1000) big[i] = static_cast<float>(i);
    big[n - 1] = 7.0f;
    const auto p = reinterpret_cast<uintptr_t>(big.data());
    EXPECT_EQ(p % kHugePage, 0u);
    const Mapping m = mapping_of(big.data());
    ASSERT_TRUE(m.found);
    EXPECT_EQ(m.path, "") << "a big tree array must be an anonymous mapping of its own";
    EXPECT_LE(m.start, p);
    EXPECT_GE(m.end, p + n * sizeof(float));
    EXPECT_NE(m.flags.find(" hg"), std::string::npos) << m.flags;
    for (size_t i = 0; i + 1 < n; i += 1000) EXPECT_EQ(big[i], static_cast<float>(i));
    EXPECT_EQ(big[n - 1], 7.0f);

    // Grown and shrunk through the allocator: each array frees exactly what it mapped (a wrong
    // length would unmap a neighbour or leave a hole, and the reads below would fault).
    TreeArray<float> other(n / 2, 2.0f);
    big.resize(3 * n, 5.0f);
    big.shrink_to_fit();
    EXPECT_EQ(big[n - 1], 7.0f);
    EXPECT_EQ(big[3 * n - 1], 5.0f);
    EXPECT_EQ(other[n / 2 - 1], 2.0f);
    EXPECT_EQ(reinterpret_cast<uintptr_t>(big.data()) % kHugePage, 0u);
}

TEST(TreeMemory, SmallArraysAreLineAligned) {
    for (size_t n : {size_t{1}, size_t{17}, size_t{1000}, (size_t{2} << 20) / sizeof(float) - 1}) {
        TreeArray<float> a(n, 1.0f);
        EXPECT_EQ(reinterpret_cast<uintptr_t>(a.data()) % 64, 0u) << n;
        EXPECT_EQ(a[n - 1], 1.0f);
    }
}

// While a RecycleTreeMappings lives, a freed big array's mapping is kept (its pages stay
// touched) and serves later big arrays: the smallest kept range that holds one, split, the rest
// kept. When the last one ends, whatever is kept is unmapped; without one, a free unmaps.
TEST(TreeMemory, FreedMappingsServeLaterArraysWhileABuildRuns) {
    constexpr size_t kMiB = size_t{1} << 20;
    constexpr size_t kGiB = size_t{1} << 30;  // limits that hold everything here
    ASSERT_EQ(detail::recycled_tree_bytes(), 0u);
    {
        void* gone = allocate_tree_memory(4 * kMiB);
        free_tree_memory(gone, 4 * kMiB);
        EXPECT_EQ(detail::recycled_tree_bytes(), 0u) << "no build runs: unmapped";
        EXPECT_FALSE(mapping_of(gone).found);
    }
    void* big = nullptr;
    {
        const detail::RecycleTreeMappings outer(kGiB);
        big = allocate_tree_memory(16 * kMiB);
        void* small = allocate_tree_memory(4 * kMiB - 100);  // takes two whole huge pages
        std::memset(big, 0x5a, 16 * kMiB);
        free_tree_memory(big, 16 * kMiB);
        free_tree_memory(small, 4 * kMiB - 100);
        EXPECT_EQ(detail::recycled_tree_bytes(), 20 * kMiB);
        {
            const detail::RecycleTreeMappings inner(kGiB);  // a second build at the same time
            // The smallest range that holds 3 MiB (rounded to 4): the small array's, whole.
            EXPECT_EQ(allocate_tree_memory(3 * kMiB), small);
            EXPECT_EQ(detail::recycled_tree_bytes(), 16 * kMiB);
            free_tree_memory(small, 3 * kMiB);
        }
        EXPECT_EQ(detail::recycled_tree_bytes(), 20 * kMiB) << "the outer build still runs";
        // 10 MiB: the big range's first 10, its other 6 stay kept; then 6 MiB take those.
        auto* const a = static_cast<unsigned char*>(allocate_tree_memory(10 * kMiB));
        EXPECT_EQ(a, big);
        EXPECT_EQ(detail::recycled_tree_bytes(), 10 * kMiB);
        auto* const b = static_cast<unsigned char*>(allocate_tree_memory(6 * kMiB));
        EXPECT_EQ(b, a + 10 * kMiB);
        EXPECT_EQ(detail::recycled_tree_bytes(), 4 * kMiB);
        // Kept memory is handed out as it is (not zeroed again): the pages were touched before.
        EXPECT_EQ(a[0], 0x5a);
        EXPECT_EQ(b[6 * kMiB - 1], 0x5a);
        // The pieces are arrays of their own: each frees its own range.
        free_tree_memory(a, 10 * kMiB);
        free_tree_memory(b, 6 * kMiB);
        EXPECT_EQ(detail::recycled_tree_bytes(), 20 * kMiB);
        // Nothing kept holds 32 MiB: a fresh mapping.
        void* fresh = allocate_tree_memory(32 * kMiB);
        EXPECT_EQ(detail::recycled_tree_bytes(), 20 * kMiB);
        free_tree_memory(fresh, 32 * kMiB);
    }
    EXPECT_EQ(detail::recycled_tree_bytes(), 0u);
    EXPECT_FALSE(mapping_of(big).found) << "kept ranges are unmapped when the last build ends";
}

// The kept memory is capped by the live builds' limits: a tree freed while a small build runs
// (a cache's eviction) is kept only up to that build's limit, the rest of its mapping unmapped at
// once; when a build ends, what the others' limits do not cover is unmapped; a build with no
// limit keeps nothing.
TEST(TreeMemory, KeptMappingsStayWithinTheLiveBuildsLimits) {
    constexpr size_t kMiB = size_t{1} << 20;
    ASSERT_EQ(detail::recycled_tree_bytes(), 0u);
    {
        const detail::RecycleTreeMappings none(0);
        void* p = allocate_tree_memory(4 * kMiB);
        free_tree_memory(p, 4 * kMiB);
        EXPECT_EQ(detail::recycled_tree_bytes(), 0u) << "a limit of 0 keeps nothing";
        EXPECT_FALSE(mapping_of(p).found);
    }
    auto* const evicted = static_cast<unsigned char*>(allocate_tree_memory(32 * kMiB));
    auto* const other = static_cast<unsigned char*>(allocate_tree_memory(8 * kMiB));
    {
        // 11 MiB: 10 of them in whole 2 MiB pages.
        const detail::RecycleTreeMappings small(11 * kMiB);
        free_tree_memory(evicted, 32 * kMiB);
        EXPECT_EQ(detail::recycled_tree_bytes(), 10 * kMiB);
        EXPECT_TRUE(mapping_of(evicted).found) << "the kept head";
        EXPECT_FALSE(mapping_of(evicted + 10 * kMiB).found) << "the rest is unmapped at once";
        EXPECT_FALSE(mapping_of(evicted + 32 * kMiB - 1).found);
        {
            const detail::RecycleTreeMappings second(8 * kMiB);
            free_tree_memory(other, 8 * kMiB);  // 18 MiB kept, 19 allowed
            EXPECT_EQ(detail::recycled_tree_bytes(), 18 * kMiB);
            void* extra = allocate_tree_memory(12 * kMiB);  // no kept range holds it: fresh
            EXPECT_EQ(detail::recycled_tree_bytes(), 18 * kMiB);
            free_tree_memory(extra, 12 * kMiB);  // room for less than a page: unmapped
            EXPECT_EQ(detail::recycled_tree_bytes(), 18 * kMiB);
            EXPECT_FALSE(mapping_of(extra).found);
        }
        // The second build's 8 MiB are gone: 18 kept against 11 allowed, the biggest range (the
        // 10 MiB head) cut by whole pages to 2 MiB.
        EXPECT_EQ(detail::recycled_tree_bytes(), 10 * kMiB);
        EXPECT_TRUE(mapping_of(evicted).found);
        EXPECT_FALSE(mapping_of(evicted + 2 * kMiB).found);
        EXPECT_TRUE(mapping_of(other + 8 * kMiB - 1).found);
        EXPECT_EQ(allocate_tree_memory(8 * kMiB), other) << "what is kept still serves";
        free_tree_memory(other, 8 * kMiB);
    }
    EXPECT_EQ(detail::recycled_tree_bytes(), 0u);
    EXPECT_FALSE(mapping_of(evicted).found);
    EXPECT_FALSE(mapping_of(other).found);
}

// take_kept_tree_memory (the exact builder's mid-size event buffers) hands out only kept
// mappings, as allocate_tree_memory would take them: with no build running, or none kept, it
// gives nothing, never a fresh mapping; each piece frees as an array of its own.
TEST(TreeMemory, KeptMemoryIsTakenOnlyWhereABuildKeepsSome) {
    constexpr size_t kMiB = size_t{1} << 20;
    ASSERT_EQ(detail::recycled_tree_bytes(), 0u);
    EXPECT_EQ(detail::take_kept_tree_memory(2 * kMiB), nullptr) << "no build runs";
    {
        const detail::RecycleTreeMappings build(size_t{1} << 30);
        EXPECT_EQ(detail::take_kept_tree_memory(2 * kMiB), nullptr) << "nothing kept";
        EXPECT_EQ(detail::recycled_tree_bytes(), 0u);
        auto* const freed = static_cast<unsigned char*>(allocate_tree_memory(4 * kMiB));
        std::memset(freed, 0x5a, 4 * kMiB);
        free_tree_memory(freed, 4 * kMiB);
        EXPECT_EQ(detail::recycled_tree_bytes(), 4 * kMiB);
        EXPECT_EQ(detail::take_kept_tree_memory(kMiB), nullptr) << "a heap array's size";
        auto* const a = static_cast<unsigned char*>(detail::take_kept_tree_memory(2 * kMiB));
        auto* const b = static_cast<unsigned char*>(detail::take_kept_tree_memory(2 * kMiB));
        EXPECT_EQ(a, freed);
        EXPECT_EQ(b, freed + 2 * kMiB);
        EXPECT_EQ(detail::recycled_tree_bytes(), 0u);
        EXPECT_EQ(detail::take_kept_tree_memory(2 * kMiB), nullptr) << "all taken";
        ASSERT_NE(a, nullptr);
        ASSERT_NE(b, nullptr);
        EXPECT_EQ(a[0], 0x5a) << "the kept pages as they were";
        EXPECT_EQ(b[2 * kMiB - 1], 0x5a);
        free_tree_memory(b, 2 * kMiB);
        EXPECT_EQ(detail::recycled_tree_bytes(), 2 * kMiB);
        EXPECT_EQ(allocate_tree_memory(2 * kMiB), b) << "a freed piece serves again";
        free_tree_memory(a, 2 * kMiB);
        free_tree_memory(b, 2 * kMiB);
        EXPECT_EQ(detail::recycled_tree_bytes(), 4 * kMiB);
    }
    EXPECT_EQ(detail::recycled_tree_bytes(), 0u);
}

}  // namespace
}  // namespace kdrt::test
