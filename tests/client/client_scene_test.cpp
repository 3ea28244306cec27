// Client's scene calls against a real kdrt-server: documents (create, get, list, poses by
// geometry id as KDRX and by name as JSON, instance edits, conditional changes refused with 412,
// delete); every query (closest hit, occlusion, every hit, counts, distance, scans) equals the
// engine's kdrt::Scene built here, bit for bit, with the geometry ids, sent in chunks that all
// answer from one revision; refusals name the instance and field.

#include <gtest/gtest.h>

#include <atomic>
#include <chrono>
#include <cmath>
#include <cstring>
#include <limits>
#include <optional>
#include <span>
#include <string>
#include <thread>

#include "client_test_util.h"
#include "kdrt/distance.h"
#include "kdrt/scan.h"
#include "kdrt/scene.h"
#include "scenes.h"

namespace kdrt::test {
namespace {

/// The server's max_distance_points in this suite: smaller than the point batches sent.
constexpr uint32_t kSceneServerMaxPoints = 300;

proto::PoseEntry pose_of(std::optional<uint32_t> geometry_id, std::string name,
                         const proto::Transform& transform) {
    proto::PoseEntry p;
    p.geometry_id = geometry_id;
    p.name = std::move(name);
    p.transform = transform;
    return p;
}

proto::Transform moved(float scale, Vec3 t) {
    return proto::Transform{{scale, 0, 0, t.x, 0, scale, 0, t.y, 0, 0, scale, t.z}};
}

/// The client's closest hits equal the engine's on `scene` (into `want`), hit records and geometry
/// ids, bit for bit; and at least a tenth of the rays hit.
void expect_engine_hits(const Scene& scene, std::span<const Ray> batch, const SceneHits& got,
                        std::vector<SceneHit>& want) {
    want.resize(batch.size());
    intersect(scene, batch, want);
    ASSERT_EQ(got.hits.size(), batch.size());
    size_t hit_count = 0;
    for (size_t i = 0; i < batch.size(); ++i) {
        ASSERT_EQ(std::memcmp(&got.hits[i], &want[i], sizeof(Hit)), 0) << i;
        ASSERT_EQ(got.geometry_ids[i], want[i].geom) << i;
        hit_count += want[i].is_hit();
    }
    EXPECT_GT(hit_count, batch.size() / 10);
}

class ClientScene : public ::testing::Test {
protected:
    static void SetUpTestSuite() {
        dir_ = new TempDir();
        server_ = new ServerProcess(
            {.cache_dir = dir_->path() / "cache",
             .args = {"--max-distance-points", std::to_string(kSceneServerMaxPoints)}});
        sphere_ = new Mesh(uv_sphere({0.5f, 0.5f, 0.5f}, 0.4f, 12, 20));
        Rng rng(test_seed() + 23);
        soup_ = new Mesh(random_soup(rng, 300, 0.2f));
        sphere_tree_ = std::make_shared<const KdTree>(build_kdtree(*sphere_));
        soup_tree_ = std::make_shared<const KdTree>(build_kdtree(*soup_));
        Client c = client();
        sphere_id_ = new std::string(c.upload(*sphere_)->id);
        soup_id_ = new std::string(c.upload(*soup_)->id);
    }
    static void TearDownTestSuite() {
        delete server_;
        delete dir_;
        delete sphere_;
        delete soup_;
        delete sphere_id_;
        delete soup_id_;
        sphere_tree_.reset();
        soup_tree_.reset();
    }
    static Client client(ClientOptions options = fast_options()) {
        return Client(server_url(*server_), std::move(options));
    }
    static std::vector<proto::SceneInstanceSpec> instances() {
        return {{*sphere_id_, moved(1.0f, {0, 0, 0}), "ball"},
                {*soup_id_, moved(0.5f, {1.2f, 0.1f, 0}), ""},
                {*sphere_id_, moved(2.0f, {-0.5f, 1.0f, 0.3f}), "big"}};
    }
    /// The engine's scene of `doc` (the meshes by id).
    static Scene local(const SceneDocument& doc) {
        std::vector<SceneInstance> out;
        for (const proto::SceneInstanceSpec& inst : doc.instances) {
            SceneInstance s;
            s.tree = inst.mesh == *sphere_id_ ? sphere_tree_ : soup_tree_;
            std::memcpy(s.transform.m, inst.transform.m.data(), sizeof s.transform.m);
            out.push_back(std::move(s));
        }
        return build_scene(std::move(out));
    }
    static std::vector<Ray> rays(size_t n, uint64_t seed) {
        Rng rng(seed);
        std::vector<Ray> out(n);
        for (Ray& r : out) {
            const Vec3 o = rng.in_box({{-2, -1, -2}, {3, 3, 2}});
            const Vec3 d = rng.in_box({{-1, -0.5f, 0}, {2, 2, 1}}) - o;
            r = Ray{o.x, o.y, o.z, 0.0f, d.x, d.y, d.z, std::numeric_limits<float>::infinity()};
        }
        return out;
    }

    static TempDir* dir_;
    static ServerProcess* server_;
    static Mesh *sphere_, *soup_;
    static std::string *sphere_id_, *soup_id_;
    static std::shared_ptr<const KdTree> sphere_tree_, soup_tree_;
};
TempDir* ClientScene::dir_ = nullptr;
ServerProcess* ClientScene::server_ = nullptr;
Mesh* ClientScene::sphere_ = nullptr;
Mesh* ClientScene::soup_ = nullptr;
std::string* ClientScene::sphere_id_ = nullptr;
std::string* ClientScene::soup_id_ = nullptr;
std::shared_ptr<const KdTree> ClientScene::sphere_tree_, ClientScene::soup_tree_;

TEST_F(ClientScene, DocumentsRevisionsAndConditionalChanges) {
    Client c = client();
    auto created = c.create_scene(instances());
    ASSERT_TRUE(created) << created.error().to_string();
    EXPECT_EQ(created->revision, 1u);
    EXPECT_EQ(created->instances, instances());
    auto got = c.scene(created->id);
    ASSERT_TRUE(got) << got.error().to_string();
    EXPECT_EQ(*got, *created);
    auto listed = c.scenes();
    ASSERT_TRUE(listed);
    EXPECT_TRUE(std::any_of(listed->begin(), listed->end(), [&](const SceneRevision& r) {
        return r.id == created->id && r.revision == 1 && r.instances == 3;
    }));

    // By geometry id (sent as KDRX), then by name (JSON): one revision each.
    const proto::PoseEntry by_id = pose_of(1, "", moved(0.5f, {1.5f, 0, 0}));
    auto r2 = c.set_poses(created->id, std::span(&by_id, 1));
    ASSERT_TRUE(r2) << r2.error().to_string();
    EXPECT_EQ(r2->revision, 2u);
    const proto::PoseEntry by_name = pose_of(std::nullopt, "big", moved(1.0f, {0, 2, 0}));
    auto r3 = c.set_poses(created->id, std::span(&by_name, 1), 2);
    ASSERT_TRUE(r3) << r3.error().to_string();
    EXPECT_EQ(r3->revision, 3u);
    auto now = c.scene(created->id);
    ASSERT_TRUE(now);
    EXPECT_EQ(now->instances[1].transform, by_id.transform);
    EXPECT_EQ(now->instances[2].transform, by_name.transform);
    // The old revision is still there to be pinned.
    auto first = c.scene(created->id, 1);
    ASSERT_TRUE(first);
    EXPECT_EQ(first->instances, instances());
    // A stale condition is refused, and changes nothing.
    auto stale = c.set_poses(created->id, std::span(&by_id, 1), 2);
    ASSERT_FALSE(stale);
    EXPECT_EQ(stale.error().status, 412) << stale.error().to_string();
    // Instance edits.
    proto::InstanceEdit edit;
    edit.remove.emplace_back(std::string("ball"));
    edit.add.push_back({*soup_id_, moved(1.0f, {0, 0, 1}), "added"});
    auto edited = c.edit_scene(created->id, edit, 3);
    ASSERT_TRUE(edited) << edited.error().to_string();
    EXPECT_EQ(edited->revision, 4u);
    ASSERT_EQ(edited->instances.size(), 3u);
    EXPECT_EQ(edited->instances[2].name, "added");
    // Delete: a stale condition refused, then gone.
    auto refused = c.remove_scene(created->id, 1);
    ASSERT_FALSE(refused);
    EXPECT_EQ(refused.error().status, 412);
    ASSERT_TRUE(c.remove_scene(created->id, 4));
    auto gone = c.scene(created->id);
    ASSERT_FALSE(gone);
    EXPECT_EQ(gone.error().status, 404);
}

TEST_F(ClientScene, RefusalsNameTheInstanceAndField) {
    Client c = client();
    std::vector<proto::SceneInstanceSpec> bad = instances();
    bad[1].mesh = std::string(64, 'e');  // not stored
    auto created = c.create_scene(bad);
    ASSERT_FALSE(created);
    EXPECT_EQ(created.error().index, 1u) << created.error().to_string();
    EXPECT_EQ(created.error().field, "instances[1].mesh") << created.error().to_string();
    bad = instances();
    bad[2].transform = proto::Transform{{1, 0, 0, 0, 0, 0, 0, 0, 0, 0, 1, 0}};  // singular
    created = c.create_scene(bad);
    ASSERT_FALSE(created);
    EXPECT_EQ(created.error().index, 2u) << created.error().to_string();
    EXPECT_EQ(created.error().field.rfind("instances[2].transform", 0), 0u)
        << created.error().to_string();
    // Checked here before sending: a NaN entry, an entry naming no instance.
    auto scene = c.create_scene(instances());
    ASSERT_TRUE(scene);
    proto::PoseEntry nan = pose_of(0, "", proto::Transform{});
    nan.transform.m[6] = std::nanf("");
    auto refused = c.set_poses(scene->id, std::span(&nan, 1));
    ASSERT_FALSE(refused);
    EXPECT_EQ(refused.error().kind, ErrorKind::kInput);
    EXPECT_NE(refused.error().detail.find("poses[0].transform[1][2]"), std::string::npos)
        << refused.error().detail;
    const proto::PoseEntry unknown = pose_of(7, "", proto::Transform{});
    refused = c.set_poses(scene->id, std::span(&unknown, 1));
    ASSERT_FALSE(refused);
    EXPECT_EQ(refused.error().status, 422) << refused.error().to_string();
    EXPECT_EQ(refused.error().field, "poses[0].geometry_id");
}

TEST_F(ClientScene, ASplitQueryAnswersFromOneRevisionInParallelParts) {
    // ClientOptions::split: parts with routing keys (the server ignores them), the first alone,
    // the others pinned to its revision over three connections; the answer is the engine's.
    ClientOptions options = fast_options();
    options.split = 5;
    options.connections = 3;
    options.chunk_rays = 150;  // more chunks than parts: 1000 rays in 7
    Client c = client(options);
    auto created = c.create_scene(instances());
    ASSERT_TRUE(created);
    std::vector<proto::PoseEntry> poses(1);
    poses[0].geometry_id = 1;
    poses[0].transform = moved(0.7f, {0.9f, -0.2f, 0.1f});
    ASSERT_TRUE(c.set_poses(created->id, poses));
    auto current = c.scene(created->id);
    ASSERT_TRUE(current);
    ASSERT_EQ(current->revision, 2u);
    const std::vector<Ray> batch = rays(1000, test_seed() + 15);
    const auto route =
        "kdrt_http_requests_total{route=\"/v1/scenes/{id}/intersect\","
        "method=\"POST\",status=\"200\"}";
    for (const auto& [pinned, doc] : {std::pair{std::optional<uint64_t>{}, *current},
                                      std::pair{std::optional<uint64_t>{1}, *created}}) {
        SCOPED_TRACE("revision " + std::to_string(doc.revision));
        const Scene scene = local(doc);
        const double before = server_->metric(route).value_or(0);
        auto hits = c.intersect_scene(created->id, batch, pinned);
        ASSERT_TRUE(hits) << hits.error().to_string();
        EXPECT_EQ(hits->revision, doc.revision);
        std::vector<SceneHit> want;
        expect_engine_hits(scene, batch, *hits, want);
        auto occluded = c.occluded_scene(created->id, batch, pinned);
        ASSERT_TRUE(occluded) << occluded.error().to_string();
        std::vector<uint8_t> want_occluded(batch.size());
        kdrt::occluded(scene, batch, want_occluded);
        EXPECT_EQ(occluded->occluded, want_occluded);
        // 7 parts each (ceil(1000 / 150)); the server counts a request just after answering it.
        double now = 0;
        for (int i = 0; i < 100 && (now = server_->metric(route).value_or(0)) != before + 14; ++i)
            std::this_thread::sleep_for(std::chrono::milliseconds(50));
        EXPECT_EQ(now, before + 14);
    }
}

TEST_F(ClientScene, QueriesEqualTheEngineInChunksOfOneRevision) {
    ClientOptions options = fast_options();
    options.chunk_rays = 250;  // several requests per call
    Client c = client(options);
    auto created = c.create_scene(instances());
    ASSERT_TRUE(created);
    const Scene scene = local(*created);
    const std::vector<Ray> batch = rays(1000, test_seed() + 5);

    auto hits = c.intersect_scene(created->id, batch);
    ASSERT_TRUE(hits) << hits.error().to_string();
    EXPECT_EQ(hits->revision, 1u);
    std::vector<SceneHit> want;
    expect_engine_hits(scene, batch, *hits, want);

    auto occluded = c.occluded_scene(created->id, batch);
    ASSERT_TRUE(occluded) << occluded.error().to_string();
    std::vector<uint8_t> want_occluded(batch.size());
    kdrt::occluded(scene, batch, want_occluded);
    EXPECT_EQ(occluded->occluded, want_occluded);
    EXPECT_EQ(occluded->revision, 1u);

    proto::MultiHitQuery query;
    query.max_hits = 8;
    auto all = c.intersect_all_scene(created->id, batch, query);
    ASSERT_TRUE(all) << all.error().to_string();
    const SceneAllHits want_all = intersect_all(scene, batch, {query.max_hits, false});
    EXPECT_EQ(all->all.offsets, want_all.offsets);
    EXPECT_EQ(all->all.counts, want_all.counts);
    ASSERT_EQ(all->all.hits.size(), want_all.hits.size());
    for (size_t k = 0; k < want_all.hits.size(); ++k) {
        EXPECT_EQ(all->all.hits[k].t, want_all.hits[k].t) << k;
        EXPECT_EQ(all->all.hits[k].prim, want_all.hits[k].prim) << k;
        EXPECT_EQ(all->geometry_ids[k], want_all.hits[k].geom) << k;
    }
    auto counts = c.count_scene_intersections(created->id, batch, false);
    ASSERT_TRUE(counts);
    EXPECT_EQ(counts->counts, want_all.counts);
    EXPECT_EQ(counts->revision, 1u);

    // More points than the server takes at once: the client shrinks its chunks.
    Rng rng(test_seed() + 6);
    std::vector<Vec3> points;
    for (int i = 0; i < 800; ++i) points.push_back(rng.in_box({{-1, -1, -1}, {3, 3, 2}}));
    auto distance = c.scene_distance(created->id, points);
    ASSERT_TRUE(distance) << distance.error().to_string();
    std::vector<SceneClosestPoint> want_points(points.size());
    closest_points(scene, points, want_points, {});
    for (size_t i = 0; i < points.size(); ++i) {
        ASSERT_EQ(distance->points[i].distance, want_points[i].closest.distance) << i;
        ASSERT_EQ(distance->points[i].prim, want_points[i].closest.prim) << i;
        ASSERT_EQ(distance->geometry_ids[i], want_points[i].geom) << i;
    }

    // A lidar scan.
    proto::ScanRequest request;
    request.lidar = true;
    request.lidar_spec.elevation_deg = {-20, -10, 0, 10, 20};
    request.lidar_spec.azimuth_steps = 90;
    request.lidar_spec.returns = 2;
    request.lidar_spec.pose.m[3] = 0.5;
    request.lidar_spec.pose.m[7] = -2.0;
    auto scan = c.scan_scene(created->id, request);
    ASSERT_TRUE(scan) << scan.error().to_string();
    ASSERT_TRUE(scan->cloud);
    const ScenePointCloud want_cloud = scan_lidar(scene, request.lidar_spec);
    ASSERT_EQ(scan->cloud->points.size(), want_cloud.cloud.points.size());
    EXPECT_GT(want_cloud.cloud.points.size(), 0u);
    EXPECT_EQ(scan->geometry_ids, want_cloud.geom);
    for (size_t k = 0; k < want_cloud.cloud.points.size(); ++k)
        ASSERT_EQ(std::memcmp(&scan->cloud->points[k], &want_cloud.cloud.points[k],
                              sizeof want_cloud.cloud.points[k]),
                  0)
            << k;
    // The same scan as the compact KDRB record: each return's range, beam and prim, and the same
    // geometry ids.
    request.format = proto::ScanFormat::kRanges;
    auto compact = c.scan_scene(created->id, request);
    ASSERT_TRUE(compact) << compact.error().to_string();
    ASSERT_TRUE(compact->ranges);
    EXPECT_FALSE(compact->cloud);
    EXPECT_EQ(compact->geometry_ids, want_cloud.geom);
    ASSERT_EQ(compact->ranges->points.size(), want_cloud.cloud.points.size());
    EXPECT_EQ(compact->ranges->channels, 5u);
    for (size_t k = 0; k < want_cloud.cloud.points.size(); ++k) {
        const LidarPoint& q = want_cloud.cloud.points[k];
        const proto::LidarRange& r = compact->ranges->points[k];
        ASSERT_EQ(std::memcmp(&r.range, &q.range, 4), 0) << k;
        ASSERT_EQ(r.beam, q.azimuth_index * 5 + q.channel) << k;
        ASSERT_EQ(r.prim, q.prim) << k;
    }
    request.format = proto::ScanFormat::kBinary;

    // Moved: the current revision answers for the new poses, and revision 1 still for the old.
    const proto::PoseEntry pose = pose_of(0, "", moved(1.0f, {0.3f, 0.2f, 0}));
    ASSERT_TRUE(c.set_poses(created->id, std::span(&pose, 1)));
    auto now = c.scene(created->id);
    ASSERT_TRUE(now);
    const Scene moved_scene = local(*now);
    auto after = c.intersect_scene(created->id, batch);
    auto pinned = c.intersect_scene(created->id, batch, 1);
    ASSERT_TRUE(after && pinned);
    EXPECT_EQ(after->revision, 2u);
    EXPECT_EQ(pinned->revision, 1u);
    std::vector<SceneHit> want_moved(batch.size());
    intersect(moved_scene, batch, want_moved);
    size_t changed = 0;
    for (size_t i = 0; i < batch.size(); ++i) {
        ASSERT_EQ(after->hits[i].t, want_moved[i].t) << i;
        ASSERT_EQ(after->geometry_ids[i], want_moved[i].geom) << i;
        ASSERT_EQ(pinned->hits[i].t, want[i].t) << i;
        changed += want_moved[i].t != want[i].t;
    }
    EXPECT_GT(changed, 0u);
}

// Occlusion and hit counts have no geometry-id plane; their chunked answers still come from one
// revision (the first chunk's, pinned by ?revision=N on the others) while poses change between
// the chunks, and say which one: each answer equals the engine's for the revision it reports.
TEST_F(ClientScene, ChunkedOcclusionAndCountsHoldOneRevisionWhilePosesChange) {
    ClientOptions options = fast_options();
    options.chunk_rays = 100;  // ten requests a call
    Client c = client(options);
    auto created = c.create_scene(instances());
    ASSERT_TRUE(created);
    const std::vector<Ray> batch = rays(1000, test_seed() + 7);
    // Revision r has the ball 0.3 (r - 1) further along x.
    const auto at = [](uint64_t r) {
        return moved(1.0f, {0.3f * static_cast<float>(r - 1), 0, 0});
    };
    const auto scene_at = [&](uint64_t r) {
        SceneDocument doc = *created;
        doc.instances[0].transform = at(r);
        return local(doc);
    };
    constexpr uint64_t kLast = 7;  // fewer changes than scene_revisions_kept (8)
    std::atomic<bool> done{false};
    std::thread mover([&] {
        Client m = client();
        for (uint64_t r = 2; r <= kLast; ++r) {
            const proto::PoseEntry pose = pose_of(0, "", at(r));
            auto changed = m.set_poses(created->id, std::span(&pose, 1));
            EXPECT_TRUE(changed && changed->revision == r) << r;
            std::this_thread::sleep_for(std::chrono::milliseconds(25));
        }
        done = true;
    });
    for (int k = 0; k < 400 && (k < 4 || !done); ++k) {
        auto occluded = c.occluded_scene(created->id, batch);
        auto counts = c.count_scene_intersections(created->id, batch, false);
        EXPECT_TRUE(occluded && counts);
        if (!occluded || !counts) break;
        std::vector<uint8_t> want(batch.size());
        kdrt::occluded(scene_at(occluded->revision), batch, want);
        EXPECT_EQ(occluded->occluded, want) << "revision " << occluded->revision;
        EXPECT_EQ(counts->counts,
                  intersect_all(scene_at(counts->revision), batch, {8, false}).counts)
            << "revision " << counts->revision;
    }
    mover.join();
    // The revisions differ in their answers (else the check above could not fail) ...
    std::vector<uint8_t> first(batch.size()), last(batch.size());
    kdrt::occluded(scene_at(1), batch, first);
    kdrt::occluded(scene_at(kLast), batch, last);
    EXPECT_NE(first, last);
    // ... and the current one answers last.
    auto final_answer = c.occluded_scene(created->id, batch);
    ASSERT_TRUE(final_answer);
    EXPECT_EQ(final_answer->revision, kLast);
    EXPECT_EQ(final_answer->occluded, last);
}

}  // namespace
}  // namespace kdrt::test
