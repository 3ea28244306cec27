// The scene cache in process: a revision's meshes' HitClearance is built at its first
// single-return scan (SceneCache::scan_ready), once per mesh tree, kept with the tree by the mesh
// cache (counted in its budget, evicted with it), inherited by pose updates, and changes no
// answer. (http_scenes_test.cpp covers the routes through the binary.)

#include "store/scene_cache.h"

#include <gtest/gtest.h>
#include <unistd.h>

#include <barrier>
#include <cstring>
#include <filesystem>
#include <thread>

#include "kdrt/hit_clearance.h"
#include "kdrt/scan.h"
#include "kdrt/scene.h"
#include "scenes.h"
#include "test_util.h"

namespace kdrt::server {
namespace {

namespace fs = std::filesystem;

class SceneCacheTest : public ::testing::Test {
protected:
    void SetUp() override {
        dir_ = fs::temp_directory_path() /
               ("kdrt-scene-cache-test-" + std::to_string(::getpid()) + "-" +
                ::testing::UnitTest::GetInstance()->current_test_info()->name());
        fs::remove_all(dir_);
        fs::create_directories(dir_ / "tmp");
    }
    void TearDown() override { fs::remove_all(dir_); }

    /// Instance k of `mesh` on a ring around the origin, turned by its own angle (and mirrored
    /// for odd k), moved by `frame`.
    static proto::SceneInstanceSpec placed(const std::string& mesh, uint32_t k, uint32_t frame) {
        proto::SceneInstanceSpec inst;
        inst.mesh = mesh;
        const double a = 0.7 * k + 0.05 * frame;
        const float c = static_cast<float>(std::cos(a)), s = static_cast<float>(std::sin(a));
        const float mirror = k % 2 == 1 ? -1.0f : 1.0f;
        inst.transform.m = {c, -s, 0, 3 * c, s, c, 0, 3 * s, 0, 0, mirror, 0.1f * k};
        return inst;
    }

    static proto::PoseEntry pose_of(uint32_t k, const proto::SceneInstanceSpec& inst) {
        proto::PoseEntry p;
        p.geometry_id = k;
        p.transform = inst.transform;
        return p;
    }

    /// A lidar in the middle of the ring: most beams hit an instance.
    static LidarSpec lidar() {
        LidarSpec spec;
        spec.elevation_deg = lidar_elevations(-20, 20, 16);
        spec.azimuth_steps = 256;
        return spec;
    }

    static void expect_same_scan(const ScenePointCloud& got, const ScenePointCloud& want) {
        ASSERT_EQ(got.cloud.points.size(), want.cloud.points.size());
        EXPECT_EQ(std::memcmp(got.cloud.points.data(), want.cloud.points.data(),
                              want.cloud.points.size() * sizeof(LidarPoint)),
                  0);
        EXPECT_EQ(got.geom, want.geom);
    }

    /// Every instance of `entry` carries a clearance, the one of its mesh in `want`.
    static void expect_clearances(const SceneEntry& entry,
                                  const std::map<std::string, const HitClearance*>& want) {
        for (uint32_t g = 0; g < entry.scene.size(); ++g)
            EXPECT_EQ(entry.scene.instance(g).clearance.get(), want.at(entry.doc.instances[g].mesh))
                << "instance " << g;
    }

    fs::path dir_;
    Metrics metrics_;
    Compute compute_{2};

    /// A server's stores and caches over `dir_`: trees within `mesh_budget` bytes. Call open().
    struct Caches {
        Caches(SceneCacheTest& t, uint64_t mesh_budget, SceneCacheOptions options = {})
            : mesh_store(t.dir_),
              meshes(mesh_store, t.compute_, t.metrics_, mesh_budget),
              scene_store(t.dir_, t.dir_ / "tmp", 4),
              scenes(scene_store, meshes, t.compute_, t.metrics_, options) {}
        [[nodiscard]] bool open() { return meshes.open() && scene_store.open().ok(); }

        MeshStore mesh_store;
        MeshCache meshes;
        SceneStore scene_store;
        SceneCache scenes;
    };
};

const Mesh& scene_sphere() {
    static const Mesh m = test::uv_sphere({0, 0, 0}, 0.8f, 24, 32);
    return m;
}

const Mesh& scene_soup() {
    static const Mesh m = [] {
        test::Rng rng(5);
        return test::random_soup(rng, 600, 0.4f);
    }();
    return m;
}

TEST_F(SceneCacheTest, ClearanceIsBuiltAtTheFirstSingleReturnScanAndInheritedByPoseUpdates) {
    Caches caches(*this, 1ull << 30);
    ASSERT_TRUE(caches.open());
    MeshCache& meshes = caches.meshes;
    SceneCache& scenes = caches.scenes;
    const std::string a = meshes.add(scene_sphere())->summary.id,
                      b = meshes.add(scene_soup())->summary.id;
    const uint64_t trees = meshes.memory_bytes();
    std::vector<proto::SceneInstanceSpec> instances;
    for (uint32_t k = 0; k < 12; ++k) instances.push_back(placed(k % 3 == 2 ? b : a, k, 0));
    auto created = scenes.create(instances);
    ASSERT_TRUE(created);
    const SceneCache::EntryPtr plain = *created;
    // Made without clearances: a scene never scanned pays neither their time nor their bytes.
    for (uint32_t g = 0; g < plain->scene.size(); ++g)
        EXPECT_FALSE(plain->scene.instance(g).clearance) << "instance " << g;
    EXPECT_EQ(meshes.memory_bytes(), trees);

    const SceneCache::EntryPtr ready = scenes.scan_ready(plain);
    ASSERT_NE(ready, plain);
    auto tree_a = meshes.acquire(a), tree_b = meshes.acquire(b);
    ASSERT_TRUE(tree_a && tree_b);
    const auto clear_a = meshes.hit_clearance(a, *tree_a),
               clear_b = meshes.hit_clearance(b, *tree_b);
    const std::map<std::string, const HitClearance*> kept{{a, clear_a.get()}, {b, clear_b.get()}};
    expect_clearances(*ready, kept);  // one per mesh, the mesh cache's, counted there once
    EXPECT_EQ(meshes.memory_bytes(), trees + clear_a->bytes() + clear_b->bytes());
    EXPECT_EQ(ready->doc, plain->doc);
    EXPECT_EQ(ready->scene.stats().nodes, plain->scene.stats().nodes);
    // Kept in place of the plain revision: asked again, the same entry, nothing built.
    EXPECT_EQ(scenes.scan_ready(ready), ready);
    EXPECT_EQ(*scenes.get(plain->doc.id), ready);
    EXPECT_EQ(*scenes.get(plain->doc.id, 1), ready);

    // The first scan's answers are those of the plain revision and of every later scan.
    const LidarSpec spec = lidar();
    const ScenePointCloud want = scan_lidar(plain->scene, spec);
    EXPECT_GT(want.cloud.points.size(), 1000u);
    expect_same_scan(scan_lidar(ready->scene, spec), want);
    expect_same_scan(scan_lidar(ready->scene, spec), want);

    // A pose update's revision carries the same clearances: its scans build nothing.
    std::vector<proto::PoseEntry> poses;
    for (uint32_t k = 0; k < 12; ++k) poses.push_back(pose_of(k, placed(instances[k].mesh, k, 1)));
    auto moved = scenes.set_poses(plain->doc.id, 1, poses);
    ASSERT_TRUE(moved);
    EXPECT_EQ(moved->revision, 2u);
    auto next = scenes.get(plain->doc.id);
    ASSERT_TRUE(next);
    EXPECT_EQ((*next)->doc.revision, 2u);
    expect_clearances(**next, kept);
    EXPECT_EQ(scenes.scan_ready(*next), *next);
    EXPECT_EQ(meshes.memory_bytes(), trees + clear_a->bytes() + clear_b->bytes());
    // And answers as the same poses built without them.
    std::vector<SceneInstance> bare = (*next)->scene.instances();
    for (SceneInstance& inst : bare) inst.clearance = nullptr;
    expect_same_scan(scan_lidar((*next)->scene, spec), scan_lidar(build_scene(bare), spec));
}

TEST_F(SceneCacheTest, RevisionsOlderThanTheKeptOnesLeaveTheCacheAsTheNewestMovesOn) {
    // The store keeps 4 revisions (Caches); a budget that would hold every revision made here.
    Caches caches(*this, 1ull << 30);
    ASSERT_TRUE(caches.open());
    SceneCache& scenes = caches.scenes;
    const std::string a = caches.meshes.add(scene_sphere())->summary.id;
    std::vector<proto::SceneInstanceSpec> instances;
    for (uint32_t k = 0; k < 6; ++k) instances.push_back(placed(a, k, 0));
    std::string id;
    uint64_t one = 0;
    std::vector<std::weak_ptr<const SceneEntry>> made;  // revision r at r - 1
    {
        auto created = scenes.create(instances);
        ASSERT_TRUE(created);
        id = (*created)->doc.id;
        one = (*created)->bytes;
        made.push_back(*created);
    }
    ASSERT_GT(one, 0u);
    EXPECT_EQ(scenes.memory_bytes(), one);  // 4 revisions of these would fit the budget many times
    for (uint32_t frame = 1; frame <= 10; ++frame) {
        std::vector<proto::PoseEntry> poses;
        for (uint32_t k = 0; k < 6; ++k) poses.push_back(pose_of(k, placed(a, k, frame)));
        auto moved = scenes.set_poses(id, frame, poses);
        ASSERT_TRUE(moved) << frame;
        auto now = scenes.get(id);
        ASSERT_TRUE(now);
        EXPECT_EQ((*now)->doc.revision, frame + 1u);
        made.push_back(*now);
        // The newest four are kept and counted; the older ones are refused by get() and gone
        // from memory as well.
        uint64_t counted = 0;
        for (uint64_t r = 1; r <= frame + 1; ++r) {
            const bool servable = r + 4 > frame + 1;
            EXPECT_EQ(bool(scenes.get(id, r)), servable) << "revision " << r << " at " << frame;
            EXPECT_EQ(made[r - 1].expired(), !servable) << "revision " << r << " at " << frame;
            if (auto entry = made[r - 1].lock(); entry && servable) counted += entry->bytes;
        }
        EXPECT_EQ(scenes.memory_bytes(), counted) << frame;
    }
}

TEST_F(SceneCacheTest, ARevisionWhoseMeshWasDeletedTriesItsClearancesOnce) {
    // A revision taken before one of its meshes was deleted (a scan that got it just before the
    // delete; the current revision no longer uses the mesh, so the delete was allowed): its first
    // single-return scan attaches the clearances it can, and the revision remembers that, so its
    // later scans neither build nor replace anything; the answers stay the plain revision's.
    Caches caches(*this, 1ull << 30);
    ASSERT_TRUE(caches.open());
    MeshCache& meshes = caches.meshes;
    SceneCache& scenes = caches.scenes;
    const std::string a = meshes.add(scene_sphere())->summary.id,
                      b = meshes.add(scene_soup())->summary.id;
    std::vector<proto::SceneInstanceSpec> instances;
    for (uint32_t k = 0; k < 6; ++k) instances.push_back(placed(k % 2 == 1 ? b : a, k, 0));
    auto created = scenes.create(instances);
    ASSERT_TRUE(created);
    const SceneCache::EntryPtr plain = *created;
    const std::string id = plain->doc.id;
    proto::InstanceEdit edit;
    for (uint32_t k = 1; k < 6; k += 2) edit.remove.emplace_back(k);
    auto edited = scenes.edit(id, 1, edit);
    ASSERT_TRUE(edited);
    EXPECT_EQ((*edited)->doc.revision, 2u);
    EXPECT_TRUE(scenes.mesh_users(b).empty());
    ASSERT_TRUE(meshes.remove(b));
    ASSERT_FALSE(meshes.find(b));

    const SceneCache::EntryPtr ready = scenes.scan_ready(plain);
    ASSERT_NE(ready, plain);
    EXPECT_TRUE(ready->scan_ready);
    for (uint32_t g = 0; g < ready->scene.size(); ++g)
        EXPECT_EQ(static_cast<bool>(ready->scene.instance(g).clearance), g % 2 == 0)
            << "instance " << g;
    // Tried once: the same revision back, nothing built, the bytes as they were.
    const uint64_t bytes = meshes.memory_bytes(), kept = scenes.memory_bytes();
    for (int scan = 0; scan < 3; ++scan) EXPECT_EQ(scenes.scan_ready(ready), ready);
    EXPECT_EQ(meshes.memory_bytes(), bytes);
    EXPECT_EQ(scenes.memory_bytes(), kept);
    // Asked for again by revision: refused as before (its mesh is gone).
    auto again = scenes.get(id, 1);
    ASSERT_FALSE(again);
    EXPECT_EQ(again.error().code, SceneProblem::Code::kMeshGone);
    // Its scans answer as the plain revision's.
    const ScenePointCloud want = scan_lidar(plain->scene, lidar());
    EXPECT_GT(want.cloud.points.size(), 500u);
    expect_same_scan(scan_lidar(ready->scene, lidar()), want);
}

TEST_F(SceneCacheTest, ConcurrentFirstScansKeepOneClearancePerMesh) {
    Caches caches(*this, 1ull << 30);
    ASSERT_TRUE(caches.open());
    MeshCache& meshes = caches.meshes;
    SceneCache& scenes = caches.scenes;
    const std::string a = meshes.add(scene_sphere())->summary.id;
    const uint64_t trees = meshes.memory_bytes();
    std::vector<proto::SceneInstanceSpec> instances;
    for (uint32_t k = 0; k < 8; ++k) instances.push_back(placed(a, k, 0));
    auto created = scenes.create(instances);
    ASSERT_TRUE(created);
    constexpr int kThreads = 6;
    std::vector<SceneCache::EntryPtr> got(kThreads);
    std::barrier start(kThreads);
    std::vector<std::thread> threads;
    for (int t = 0; t < kThreads; ++t)
        threads.emplace_back([&, t] {
            start.arrive_and_wait();
            got[t] = scenes.scan_ready(*created);
        });
    for (std::thread& t : threads) t.join();
    // Built once, or by several at once and one kept: every caller gets the kept one, and its
    // bytes are counted once.
    auto tree = meshes.acquire(a);
    ASSERT_TRUE(tree);
    const auto kept = meshes.hit_clearance(a, *tree);
    for (int t = 0; t < kThreads; ++t) {
        ASSERT_TRUE(got[t]) << "thread " << t;
        expect_clearances(*got[t], {{a, kept.get()}});
    }
    EXPECT_EQ(meshes.memory_bytes(), trees + kept->bytes());
    const ScenePointCloud want = scan_lidar((*created)->scene, lidar());
    for (int t = 0; t < kThreads; ++t) expect_same_scan(scan_lidar(got[t]->scene, lidar()), want);
}

TEST_F(SceneCacheTest, AnEvictedTreesClearanceGoesWithItAndIsBuiltAgainForAReloadedRevision) {
    const uint64_t one_tree = tree_memory_bytes(build_kdtree(scene_sphere()));
    const uint64_t one_clearance = build_hit_clearance(build_kdtree(scene_sphere())).bytes();
    test::Rng rb(11), rc(12);
    const Mesh mb = test::random_soup(rb, 500), mc = test::random_soup(rc, 500);
    const uint64_t tree_b = tree_memory_bytes(build_kdtree(mb)),
                   tree_c = tree_memory_bytes(build_kdtree(mc));
    // Room for the sphere's tree and clearance, or for two other trees, not for more.
    const uint64_t budget = one_tree + one_clearance + 1000;
    ASSERT_LE(tree_b + tree_c, budget);
    ASSERT_GT(one_clearance + tree_c, budget - one_tree);
    // A scene budget of one revision: the newest is kept, older ones are read again.
    SceneCacheOptions options;
    options.memory_budget = 1;
    Caches caches(*this, budget, options);
    ASSERT_TRUE(caches.open());
    MeshCache& meshes = caches.meshes;
    SceneCache& scenes = caches.scenes;
    const std::string a = meshes.add(scene_sphere())->summary.id;
    std::vector<proto::SceneInstanceSpec> instances;
    for (uint32_t k = 0; k < 6; ++k) instances.push_back(placed(a, k, 0));
    auto first = scenes.create(instances);
    ASSERT_TRUE(first);
    const SceneCache::EntryPtr ready = scenes.scan_ready(*first);
    EXPECT_EQ(meshes.memory_bytes(), one_tree + one_clearance);
    const ScenePointCloud want = scan_lidar(ready->scene, lidar());
    // Two more meshes evict the sphere's tree, and its clearance with it.
    const std::string b = meshes.add(mb)->summary.id, c = meshes.add(mc)->summary.id;
    EXPECT_FALSE(meshes.find(a)->in_memory.value());
    EXPECT_EQ(meshes.memory_bytes(), tree_b + tree_c);
    // The revision that holds them scans as before.
    expect_same_scan(scan_lidar(ready->scene, lidar()), want);
    // Another scene evicts the first's revision; read again from the store it comes without a
    // clearance (its tree reloaded), and its first scan builds one, kept and counted anew.
    auto other = scenes.create({placed(b, 0, 0), placed(c, 1, 0)});
    ASSERT_TRUE(other);
    auto reloaded = scenes.get(ready->doc.id);
    ASSERT_TRUE(reloaded);
    EXPECT_NE(*reloaded, ready);
    EXPECT_FALSE((*reloaded)->scene.instance(0).clearance);
    const SceneCache::EntryPtr again = scenes.scan_ready(*reloaded);
    auto tree = meshes.acquire(a);
    ASSERT_TRUE(tree);
    const auto kept = meshes.hit_clearance(a, *tree);
    EXPECT_NE(kept, ready->scene.instance(0).clearance);
    expect_clearances(*again, {{a, kept.get()}});
    EXPECT_EQ(meshes.memory_bytes(), one_tree + one_clearance);
    expect_same_scan(scan_lidar(again->scene, lidar()), want);
}

}  // namespace
}  // namespace kdrt::server
