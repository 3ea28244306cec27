// The mesh cache in process: deduplication, single-flight builds, LRU eviction and reload,
// corrupt files, removal. (http_cache_test.cpp covers the same through the binary.)

#include "store/mesh_cache.h"

#include <gtest/gtest.h>
#include <unistd.h>

#include <cstring>
#include <filesystem>
#include <fstream>
#include <functional>
#include <thread>

#include "kdrt/distance.h"
#include "kdrt/hit_clearance.h"
#include "kdrt/proto/mesh_id.h"
#include "kdrt/trace.h"
#include "test_util.h"

namespace kdrt::server {
namespace {

namespace fs = std::filesystem;

class MeshCacheTest : public ::testing::Test {
protected:
    void SetUp() override {
        dir_ = fs::temp_directory_path() /
               ("kdrt-cache-test-" + std::to_string(::getpid()) + "-" +
                ::testing::UnitTest::GetInstance()->current_test_info()->name());
        fs::remove_all(dir_);
    }
    void TearDown() override { fs::remove_all(dir_); }

    static Mesh mesh(uint64_t seed, size_t triangles = 300) {
        test::Rng rng(seed);
        return test::random_soup(rng, triangles);
    }

    fs::path dir_;
    Metrics metrics_;
    Compute compute_{2};
};

TEST_F(MeshCacheTest, AddDeduplicatesAndAcquireReturnsTheTree) {
    MeshStore store(dir_);
    MeshCache cache(store, compute_, metrics_, 1ull << 30);
    ASSERT_TRUE(cache.open());
    const Mesh m = mesh(1);
    auto first = cache.add(m);
    ASSERT_TRUE(first);
    EXPECT_TRUE(first->created);
    EXPECT_EQ(first->summary.id, proto::mesh_id(m));
    EXPECT_EQ(first->summary.triangles, 300u);
    EXPECT_EQ(first->summary.bounds, mesh_bounds(m));
    auto second = cache.add(m);
    ASSERT_TRUE(second);
    EXPECT_FALSE(second->created);
    EXPECT_EQ(metrics_.builds(), 1u);

    auto tree = cache.acquire(first->summary.id);
    ASSERT_TRUE(tree);
    const KdTree reference = build_kdtree(m);
    EXPECT_EQ((*tree)->nodes, reference.nodes);
    EXPECT_EQ(metrics_.cache_hits.load(), 1u);
    EXPECT_EQ(cache.mesh_count(), 1u);
    EXPECT_GT(cache.memory_bytes(), 0u);
    EXPECT_GT(cache.disk_bytes(), 0u);

    auto unknown = cache.acquire(std::string(64, '0'));
    ASSERT_FALSE(unknown);
    EXPECT_EQ(unknown.error().code, CacheError::Code::kUnknownMesh);
}

TEST_F(MeshCacheTest, ConcurrentAddsOfOneMeshBuildOnce) {
    MeshStore store(dir_);
    MeshCache cache(store, compute_, metrics_, 1ull << 30);
    ASSERT_TRUE(cache.open());
    const Mesh m = mesh(2, 20000);
    std::atomic<int> created{0};
    std::vector<std::thread> threads;
    threads.reserve(8);
    for (int i = 0; i < 8; ++i)
        threads.emplace_back([&] {
            auto added = cache.add(m);
            ASSERT_TRUE(added);
            created += added->created;
        });
    for (auto& t : threads) t.join();
    EXPECT_EQ(created.load(), 1);
    EXPECT_EQ(metrics_.builds(), 1u);
}

TEST_F(MeshCacheTest, TreeMemoryCountsEveryArrayOfTheTree) {
    // The budget is only as good as this count: every array a resident tree holds, the wide
    // nodes of the single-ray kernel included (11.5 MB of 16 bunnies' tree).
    const KdTree tree = build_kdtree(mesh(6, 2000));
    ASSERT_FALSE(tree.wide_nodes.empty());
    const uint64_t arrays =
        tree.nodes.capacity() * sizeof(KdNode) + tree.wide_nodes.capacity() * sizeof(WideNode) +
        tree.leaf_refs.capacity() * sizeof(uint32_t) + tree.tris.capacity() * sizeof(TriVerts) +
        tree.tri_ids.capacity() * sizeof(uint32_t) + tree.tri_slots.capacity() * sizeof(uint32_t);
    EXPECT_EQ(tree_memory_bytes(tree), sizeof(KdTree) + arrays);
}

TEST_F(MeshCacheTest, BudgetEvictsLeastRecentlyUsed) {
    MeshStore store(dir_);
    const Mesh a = mesh(3), b = mesh(4), c = mesh(5);
    const uint64_t one_tree = tree_memory_bytes(build_kdtree(a));
    MeshCache cache(store, compute_, metrics_, one_tree * 2 + one_tree / 2);  // room for two
    ASSERT_TRUE(cache.open());
    const std::string ia = cache.add(a)->summary.id, ib = cache.add(b)->summary.id;
    EXPECT_EQ(cache.resident_count(), 2u);
    ASSERT_TRUE(cache.acquire(ia));  // a is now the most recent
    const std::string ic = cache.add(c)->summary.id;
    EXPECT_EQ(cache.resident_count(), 2u);
    EXPECT_EQ(metrics_.cache_evictions.load(), 1u);
    EXPECT_FALSE(cache.find(ib)->in_memory.value());  // b was the least recently used
    EXPECT_TRUE(cache.find(ia)->in_memory.value());
    // A held tree survives its eviction; reloading gives the same tree without a build.
    auto held = cache.acquire(ia);
    ASSERT_TRUE(held);
    auto reloaded = cache.acquire(ib);
    ASSERT_TRUE(reloaded);
    EXPECT_EQ((*reloaded)->nodes, build_kdtree(b).nodes);
    EXPECT_EQ(metrics_.cache_misses.load(), 1u);
    EXPECT_EQ(metrics_.builds(), 3u);
    EXPECT_FALSE((*held)->nodes.empty());
    (void)ic;
}

/// Data the cache derives from a tree and keeps with it (a SurfaceIndex, a HitClearance): how to
/// ask for it, build it apart, count its bytes and compare two.
struct DerivedKind {
    std::function<std::shared_ptr<const void>(MeshCache&, const std::string&,
                                              const std::shared_ptr<const KdTree>&)>
        get;
    std::function<std::shared_ptr<const void>(const KdTree&)> build;
    std::function<uint64_t(const void*)> bytes;
    std::function<bool(const void*, const void*)> same;
};

const DerivedKind kSurfaceIndex{
    [](MeshCache& c, const std::string& id, const std::shared_ptr<const KdTree>& t) {
        return std::shared_ptr<const void>(c.surface_index(id, t));
    },
    [](const KdTree& t) {
        return std::shared_ptr<const void>(
            std::make_shared<const SurfaceIndex>(build_surface_index(t)));
    },
    [](const void* x) { return surface_memory_bytes(*static_cast<const SurfaceIndex*>(x)); },
    [](const void* x, const void* y) {
        return static_cast<const SurfaceIndex*>(x)->pseudonormals ==
               static_cast<const SurfaceIndex*>(y)->pseudonormals;
    }};

const DerivedKind kHitClearance{
    [](MeshCache& c, const std::string& id, const std::shared_ptr<const KdTree>& t) {
        return std::shared_ptr<const void>(c.hit_clearance(id, t));
    },
    [](const KdTree& t) {
        return std::shared_ptr<const void>(
            std::make_shared<const HitClearance>(build_hit_clearance(t)));
    },
    [](const void* x) { return static_cast<const HitClearance*>(x)->bytes(); },
    [](const void* x, const void* y) {
        const auto& a = *static_cast<const HitClearance*>(x);
        const auto& b = *static_cast<const HitClearance*>(y);
        return a.size() == b.size() && std::memcmp(a.records().data(), b.records().data(),
                                                   a.size() * sizeof(detail::ClearanceRecord)) == 0;
    }};

/// The derived data of `kind` counts towards the budget and is evicted, reloaded and deleted
/// with its tree; a request holding an evicted tree gets one that is neither kept nor counted.
void expect_kept_with_the_tree(const DerivedKind& kind, const fs::path& dir, Compute& compute,
                               Metrics& metrics) {
    MeshStore store(dir);
    test::Rng ra(6), rb(7), rc(8);
    const Mesh a = test::random_soup(ra, 300), b = test::random_soup(rb, 300),
               c = test::random_soup(rc, 300);
    const KdTree reference = build_kdtree(a);
    const uint64_t one_tree = tree_memory_bytes(reference);
    const auto want = kind.build(reference);
    const uint64_t one_data = kind.bytes(want.get());
    ASSERT_GT(one_data, 300u * 50u);  // 84 bytes a triangle (an index), 52 (a clearance)
    // Room for two trees, not for two trees and the data.
    MeshCache cache(store, compute, metrics, 2 * one_tree + one_data / 2);
    ASSERT_TRUE(cache.open());
    const std::string ia = cache.add(a)->summary.id, ib = cache.add(b)->summary.id;
    ASSERT_EQ(cache.resident_count(), 2u);
    const uint64_t trees_only = cache.memory_bytes();
    auto tree_a = cache.acquire(ia);
    ASSERT_TRUE(tree_a);
    const auto data = kind.get(cache, ia, *tree_a);
    ASSERT_TRUE(data);
    EXPECT_TRUE(kind.same(data.get(), want.get()));
    // a's data is counted: the budget is exceeded, so b (least recently used) is evicted.
    EXPECT_EQ(cache.resident_count(), 1u);
    EXPECT_EQ(metrics.cache_evictions.load(), 1u);
    EXPECT_FALSE(cache.find(ib)->in_memory.value());
    EXPECT_EQ(cache.memory_bytes(), trees_only - tree_memory_bytes(build_kdtree(b)) + one_data);
    // Asked again, the same data, not new.
    EXPECT_EQ(kind.get(cache, ia, *tree_a), data);
    // Evicting a's tree (b and c reloaded and added) drops its data and its bytes.
    ASSERT_TRUE(cache.acquire(ib));
    const std::string ic = cache.add(c)->summary.id;
    EXPECT_FALSE(cache.find(ia)->in_memory.value());
    EXPECT_EQ(cache.memory_bytes(),
              tree_memory_bytes(build_kdtree(b)) + tree_memory_bytes(build_kdtree(c)));
    // The evicted tree still held by a request gets data that is not kept.
    const auto transient = kind.get(cache, ia, *tree_a);
    EXPECT_NE(transient, data);
    EXPECT_TRUE(kind.same(transient.get(), data.get()));
    EXPECT_EQ(cache.memory_bytes(),
              tree_memory_bytes(build_kdtree(b)) + tree_memory_bytes(build_kdtree(c)));
    // Reloaded, a gets its data again (new), counted again; removing a returns its bytes.
    auto reloaded = cache.acquire(ia);
    ASSERT_TRUE(reloaded);
    const auto again = kind.get(cache, ia, *reloaded);
    EXPECT_NE(again, data);
    const uint64_t with_data = cache.memory_bytes();
    EXPECT_TRUE(cache.remove(ia));
    EXPECT_EQ(cache.memory_bytes(), with_data - one_tree - one_data);
    (void)ic;
}

TEST_F(MeshCacheTest, SurfaceIndexCountsTowardsTheBudgetAndIsEvictedWithItsTree) {
    expect_kept_with_the_tree(kSurfaceIndex, dir_, compute_, metrics_);
}

TEST_F(MeshCacheTest, HitClearanceCountsTowardsTheBudgetAndIsEvictedWithItsTree) {
    // What a scene's single-return scans use, kept and counted as the SurfaceIndex is.
    expect_kept_with_the_tree(kHitClearance, dir_, compute_, metrics_);
}

TEST_F(MeshCacheTest, SurfaceIndexAndHitClearanceAreCountedTogetherAndGoWithTheirTree) {
    MeshStore store(dir_);
    const Mesh a = mesh(9);
    const KdTree reference = build_kdtree(a);
    const uint64_t one_tree = tree_memory_bytes(reference);
    const uint64_t one_index = surface_memory_bytes(build_surface_index(reference));
    const uint64_t one_clearance = build_hit_clearance(reference).bytes();
    MeshCache cache(store, compute_, metrics_, 1ull << 30);
    ASSERT_TRUE(cache.open());
    const std::string ia = cache.add(a)->summary.id;
    auto tree = cache.acquire(ia);
    ASSERT_TRUE(tree);
    EXPECT_EQ(cache.memory_bytes(), one_tree);
    ASSERT_TRUE(cache.hit_clearance(ia, *tree));
    EXPECT_EQ(cache.memory_bytes(), one_tree + one_clearance);
    ASSERT_TRUE(cache.surface_index(ia, *tree));
    EXPECT_EQ(cache.memory_bytes(), one_tree + one_clearance + one_index);
    // Each kept in its own place: asking for one again neither rebuilds nor recounts the other.
    EXPECT_EQ(cache.hit_clearance(ia, *tree), cache.hit_clearance(ia, *tree));
    EXPECT_EQ(cache.memory_bytes(), one_tree + one_clearance + one_index);
    EXPECT_TRUE(cache.remove(ia));
    EXPECT_EQ(cache.memory_bytes(), 0u);
}

TEST_F(MeshCacheTest, ReopenFindsEveryMeshAndRebuildsCorruptTrees) {
    const Mesh a = mesh(6), b = mesh(7);
    std::string ia, ib;
    {
        MeshStore store(dir_);
        MeshCache cache(store, compute_, metrics_, 1ull << 30);
        ASSERT_TRUE(cache.open());
        ia = cache.add(a)->summary.id;
        ib = cache.add(b)->summary.id;
    }
    {
        std::fstream f(dir_ / "meshes" / (ib + ".tree"),
                       std::ios::in | std::ios::out | std::ios::binary);
        f.seekp(300);
        f.put('\x7f');
    }
    Metrics metrics;
    MeshStore store(dir_);
    MeshCache cache(store, compute_, metrics, 1ull << 30);
    ASSERT_TRUE(cache.open());
    EXPECT_EQ(cache.mesh_count(), 2u);
    EXPECT_FALSE(cache.find(ia)->in_memory.value());
    ASSERT_TRUE(cache.acquire(ia));
    EXPECT_EQ(metrics.builds(), 0u);
    auto rebuilt = cache.acquire(ib);
    ASSERT_TRUE(rebuilt);
    EXPECT_EQ((*rebuilt)->nodes, build_kdtree(b).nodes);
    EXPECT_EQ(metrics.builds(), 1u);
    EXPECT_EQ(metrics.cache_rebuilds.total(), 1u);
    EXPECT_EQ(metrics.cache_rebuilds.value({{"reason", "corrupt"}}), 1u);
}

TEST_F(MeshCacheTest, RemoveForgetsAndDeletesFiles) {
    MeshStore store(dir_);
    MeshCache cache(store, compute_, metrics_, 1ull << 30);
    ASSERT_TRUE(cache.open());
    const std::string id = cache.add(mesh(8))->summary.id;
    auto held = cache.acquire(id);
    EXPECT_TRUE(cache.remove(id));
    EXPECT_FALSE(cache.remove(id));
    EXPECT_FALSE(cache.find(id));
    EXPECT_EQ(cache.memory_bytes(), 0u);
    EXPECT_EQ(cache.disk_bytes(), 0u);
    EXPECT_FALSE(fs::exists(store.mesh_path(id)));
    EXPECT_FALSE(fs::exists(store.tree_path(id)));
    EXPECT_FALSE(fs::exists(store.summary_path(id)));
    ASSERT_TRUE(held);  // a trace in flight keeps its tree
    EXPECT_FALSE((*held)->tris.empty());
}

TEST_F(MeshCacheTest, EngineRefusalIsAnInvalidMesh) {
    MeshStore store(dir_);
    MeshCache cache(store, compute_, metrics_, 1ull << 30);
    ASSERT_TRUE(cache.open());
    Mesh bad = mesh(9, 1);
    bad.positions[0] = std::numeric_limits<float>::quiet_NaN();  // parsers never produce this
    auto added = cache.add(bad);
    ASSERT_FALSE(added);
    EXPECT_EQ(added.error().code, CacheError::Code::kInvalidMesh);
    EXPECT_EQ(cache.mesh_count(), 0u);
}

}  // namespace
}  // namespace kdrt::server
