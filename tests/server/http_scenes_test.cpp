// Scenes against the real binary: every query answer (closest hit, occlusion, every hit,
// distance, lidar scan) equals the engine's kdrt::Scene built here from the same meshes, bit for
// bit, with the geometry ids; pose updates make revisions (If-Match, 412 on a stale one, pinned
// queries of older revisions); bad input is problem+json naming the instance index and field;
// a mesh a scene uses cannot be deleted (409 naming the scene); scenes and their revisions
// survive kill -9 and a restart.

#include <gtest/gtest.h>

#include <algorithm>
#include <chrono>
#include <csignal>
#include <cstring>
#include <fstream>
#include <thread>

#include "http_test_util.h"
#include "kdrt/proto/distance.h"
#include "kdrt/proto/json_api.h"
#include "kdrt/proto/multi_hit.h"
#include "kdrt/proto/raw_image.h"
#include "kdrt/proto/ray_batch.h"
#include "kdrt/proto/scan.h"
#include "kdrt/proto/scene.h"
#include "kdrt/render.h"
#include "kdrt/scene.h"

namespace kdrt::test {
namespace {

const proto::Transform kIdentity{};
/// Scaled by 0.5 and moved.
const proto::Transform kMoved{{0.5f, 0, 0, 1.25f, 0, 0.5f, 0, 0.1f, 0, 0, 0.5f, -0.2f}};
/// A mirror (negative determinant), moved.
const proto::Transform kMirrored{{-1, 0, 0, 0.9f, 0, 1, 0, 0.3f, 0, 0, 1, 0}};

std::string transform_json(const proto::Transform& t) {
    std::string out = "[";
    for (size_t k = 0; k < 12; ++k) {
        if (k > 0) out += ",";
        char buf[32];
        std::snprintf(buf, sizeof buf, "%.9g", static_cast<double>(t.m[k]));
        out += buf;
    }
    return out + "]";
}

std::string instance_json(const std::string& mesh, const proto::Transform& t,
                          const std::string& name = "") {
    return "{\"mesh\":\"" + mesh + "\",\"transform\":" + transform_json(t) +
           (name.empty() ? "" : ",\"name\":\"" + name + "\"") + "}";
}

Affine3x4 affine(const proto::Transform& t) {
    Affine3x4 a;
    std::memcpy(a.m, t.m.data(), sizeof a.m);
    return a;
}

/// Checks a scene's closest-hit answer `res` (hit records, then the geometry-id plane) against
/// the engine's scene `local` for `batch`, ray by ray and bit for bit (t, prim, u, v and geometry
/// id), naming the first ray that differs. Returns the engine's answers (empty when the answer
/// is not a 200 that decodes, the test having failed).
std::vector<SceneHit> expect_engine_hits(const httplib::Result& res, const Scene& local,
                                         const std::vector<Ray>& batch) {
    if (!res || res->status != 200) {
        ADD_FAILURE() << (res ? res->body : "no response");
        return {};
    }
    auto split = proto::split_geometry_ids(string_to_bytes(res->body));
    if (!split.ok()) {
        ADD_FAILURE() << split.error().detail;
        return {};
    }
    auto hits = proto::decode_hits(split->mesh_body);
    if (!hits.ok() || hits->size() != batch.size() || split->geometry_ids.size() != batch.size()) {
        ADD_FAILURE() << "the answer does not hold " << batch.size() << " hits";
        return {};
    }
    std::vector<SceneHit> expected(batch.size());
    intersect(local, batch, expected);
    for (size_t i = 0; i < batch.size(); ++i) {
        const SceneHit got{(*hits)[i].t, (*hits)[i].prim, (*hits)[i].u, (*hits)[i].v,
                           split->geometry_ids[i]};
        if (got != expected[i]) {
            ADD_FAILURE() << "ray " << i << ": t " << got.t << " prim " << got.prim << " geometry "
                          << got.geom << ", the engine's t " << expected[i].t << " prim "
                          << expected[i].prim << " geometry " << expected[i].geom;
            return {};
        }
    }
    return expected;
}

class HttpScenes : public ::testing::Test {
protected:
    static void SetUpTestSuite() {
        dir_ = new TempDir();
        start();
        a_ = new Mesh(small_mesh(test_seed() + 31, 400));
        b_ = new Mesh(small_mesh(test_seed() + 32, 300));
        a_id_ = upload_id(*server_->client(), *a_);
        b_id_ = upload_id(*server_->client(), *b_);
        a_tree_ = std::make_shared<const KdTree>(build_kdtree(*a_));
        b_tree_ = std::make_shared<const KdTree>(build_kdtree(*b_));
    }
    static void TearDownTestSuite() {
        delete server_;
        delete dir_;
        delete a_;
        delete b_;
        a_tree_.reset();
        b_tree_.reset();
    }
    static void start() {
        server_ =
            new ServerProcess({.cache_dir = dir_->path() / "cache",
                               .args = {"--max-instances", "6", "--scene-revisions-kept", "3"}});
    }

    /// The engine's scene of `instances` (mesh a or b by id).
    static Scene local_scene(const std::vector<std::pair<std::string, proto::Transform>>& inst) {
        std::vector<SceneInstance> out;
        for (const auto& [mesh, t] : inst) {
            SceneInstance s;
            s.tree = mesh == a_id_ ? a_tree_ : b_tree_;
            s.transform = affine(t);
            out.push_back(s);
        }
        return build_scene(std::move(out));
    }

    static httplib::Result create(const std::string& body) {
        return server_->client()->Post("/v1/scenes", body, "application/json");
    }
    static std::string create_id(const std::string& body) {
        auto res = create(body);
        if (!res || res->status != 201) {
            ADD_FAILURE() << (res ? res->body : "no response");
            return {};
        }
        auto doc = proto::decode_scene_json(res->body, {}, true);
        EXPECT_TRUE(doc.ok()) << res->body;
        EXPECT_EQ(res->get_header_value("ETag"), "\"1\"");
        return doc ? doc->id : std::string();
    }
    static httplib::Result query(const std::string& id, const std::string& route,
                                 const std::string& body, const std::string& type) {
        return server_->client()->Post("/v1/scenes/" + id + "/" + route, body, type);
    }

    static std::vector<Ray> rays(size_t n, uint64_t seed) {
        return random_rays(Aabb{{-0.5f, -0.5f, -0.5f}, {2.0f, 1.5f, 1.5f}}, n, seed);
    }

    static TempDir* dir_;
    static ServerProcess* server_;
    static Mesh *a_, *b_;
    static std::string a_id_, b_id_;
    static std::shared_ptr<const KdTree> a_tree_, b_tree_;
};
TempDir* HttpScenes::dir_ = nullptr;
ServerProcess* HttpScenes::server_ = nullptr;
Mesh* HttpScenes::a_ = nullptr;
Mesh* HttpScenes::b_ = nullptr;
std::string HttpScenes::a_id_, HttpScenes::b_id_;
std::shared_ptr<const KdTree> HttpScenes::a_tree_, HttpScenes::b_tree_;

TEST_F(HttpScenes, EveryQueryEqualsTheEngineWithGeometryIds) {
    const std::vector<std::pair<std::string, proto::Transform>> inst = {
        {a_id_, kIdentity}, {b_id_, kMoved}, {a_id_, kMirrored}};
    const std::string id =
        create_id("{\"instances\":[" + instance_json(a_id_, kIdentity, "one") + "," +
                  instance_json(b_id_, kMoved) + "," + instance_json(a_id_, kMirrored) + "]}");
    ASSERT_FALSE(id.empty());
    const Scene local = local_scene(inst);
    const std::vector<Ray> batch = rays(3000, test_seed() + 5);

    // Closest hit.
    auto res = query(id, "intersect", bytes_to_string(proto::encode_rays(batch, false)),
                     "application/x-kdrt-rays");
    ASSERT_TRUE(res);
    EXPECT_EQ(res->get_header_value("X-Kdrt-Scene-Revision"), "1");
    const std::vector<SceneHit> expected = expect_engine_hits(res, local, batch);
    ASSERT_EQ(expected.size(), batch.size());
    size_t hit_count = 0;
    std::vector<size_t> per_geom(3, 0);
    for (const SceneHit& h : expected) {
        if (h.is_hit()) {
            ++hit_count;
            ++per_geom[h.geom];
        }
    }
    EXPECT_GT(hit_count, batch.size() / 10);
    for (size_t g = 0; g < 3; ++g) EXPECT_GT(per_geom[g], 0u) << "geometry " << g;

    // Occlusion.
    res = query(id, "intersect", bytes_to_string(proto::encode_rays(batch, true)),
                "application/x-kdrt-rays");
    ASSERT_TRUE(res);
    ASSERT_EQ(res->status, 200) << res->body;
    auto occ = proto::decode_occlusion(string_to_bytes(res->body));
    ASSERT_TRUE(occ.ok());
    for (size_t i = 0; i < batch.size(); ++i)
        ASSERT_EQ((*occ)[i] != 0, expected[i].is_hit()) << "ray " << i;

    // Every hit.
    res = query(id, "intersect_all?max_hits=8", bytes_to_string(proto::encode_rays(batch, false)),
                "application/x-kdrt-rays");
    ASSERT_TRUE(res);
    ASSERT_EQ(res->status, 200) << res->body;
    auto split = proto::split_geometry_ids(string_to_bytes(res->body));
    ASSERT_TRUE(split.ok()) << split.error().detail;
    auto multi = proto::decode_multi_hits(split->mesh_body);
    ASSERT_TRUE(multi.ok()) << multi.error().detail;
    const SceneAllHits all = intersect_all(local, batch, AllHitsOptions{8, false});
    ASSERT_EQ(multi->offsets, all.offsets);
    ASSERT_EQ(multi->counts, all.counts);
    ASSERT_EQ(multi->hits.size(), all.hits.size());
    for (size_t k = 0; k < all.hits.size(); ++k) {
        ASSERT_EQ(multi->hits[k].t, all.hits[k].t) << k;
        ASSERT_EQ(multi->hits[k].prim, all.hits[k].prim) << k;
        ASSERT_EQ(split->geometry_ids[k], all.hits[k].geom) << k;
    }

    // A lidar scan.
    res = query(id, "scan",
                "{\"lidar\": {\"vertical_fov\": [-30, 30], \"channels\": 16, \"azimuth_steps\": "
                "64, \"returns\": 2, \"pose\": [[1,0,0,0.5],[0,1,0,0.5],[0,0,1,0.5],[0,0,0,1]]}}",
                "application/json");
    ASSERT_TRUE(res);
    ASSERT_EQ(res->status, 200) << res->body;
    split = proto::split_geometry_ids(string_to_bytes(res->body));
    ASSERT_TRUE(split.ok()) << split.error().detail;
    auto cloud = proto::decode_point_cloud(split->mesh_body);
    ASSERT_TRUE(cloud.ok()) << cloud.error().detail;
    LidarSpec spec;
    spec.elevation_deg = lidar_elevations(-30, 30, 16);
    spec.azimuth_steps = 64;
    spec.returns = 2;
    spec.pose.m[3] = spec.pose.m[7] = spec.pose.m[11] = 0.5;
    const ScenePointCloud local_cloud = scan_lidar(local, spec);
    ASSERT_EQ(cloud->points.size(), local_cloud.cloud.points.size());
    EXPECT_EQ(split->geometry_ids, local_cloud.geom);
    EXPECT_EQ(std::memcmp(cloud->points.data(), local_cloud.cloud.points.data(),
                          cloud->points.size() * sizeof(LidarPoint)),
              0);
    EXPECT_EQ(res->get_header_value("Content-Type"), proto::kPointCloudMediaType)
        << "a request without \"format\" (an old client's) still gets KDRL";

    // The same scan as "format": "ranges": the compact KDRB record of the same returns, with the
    // same geometry-id plane.
    res = query(id, "scan",
                "{\"lidar\": {\"vertical_fov\": [-30, 30], \"channels\": 16, \"azimuth_steps\": "
                "64, \"returns\": 2, \"pose\": [[1,0,0,0.5],[0,1,0,0.5],[0,0,1,0.5],[0,0,0,1]]}, "
                "\"format\": \"ranges\"}",
                "application/json");
    ASSERT_TRUE(res);
    ASSERT_EQ(res->status, 200) << res->body;
    EXPECT_EQ(res->get_header_value("Content-Type"), proto::kLidarRangesMediaType);
    std::vector<std::byte> want_ranges = proto::encode_lidar_ranges(local_cloud.cloud);
    proto::append_geometry_ids(want_ranges, local_cloud.geom);
    EXPECT_EQ(res->body, bytes_to_string(want_ranges));
    split = proto::split_geometry_ids(string_to_bytes(res->body));
    ASSERT_TRUE(split.ok()) << split.error().detail;
    EXPECT_EQ(split->geometry_ids, local_cloud.geom);
    EXPECT_TRUE(proto::decode_lidar_ranges(split->mesh_body).ok());

    // Single returns: the first such scan gives the revision its meshes' HitClearance
    // (SceneCache::scan_ready); it and the next answer as the engine without them.
    spec.returns = 1;
    const ScenePointCloud single = scan_lidar(local, spec);
    std::vector<std::byte> want_single = proto::encode_point_cloud(single.cloud);
    proto::append_geometry_ids(want_single, single.geom);
    for (const char* which : {"first", "second"}) {
        res = query(id, "scan",
                    "{\"lidar\": {\"vertical_fov\": [-30, 30], \"channels\": 16, "
                    "\"azimuth_steps\": 64, \"returns\": 1, \"pose\": "
                    "[[1,0,0,0.5],[0,1,0,0.5],[0,0,1,0.5],[0,0,0,1]]}}",
                    "application/json");
        ASSERT_TRUE(res);
        ASSERT_EQ(res->status, 200) << res->body;
        EXPECT_EQ(res->body, bytes_to_string(want_single)) << "the " << which << " scan";
    }

    // A pinhole cannot have it; a format without geometry ids is refused naming "format".
    res = query(id, "scan",
                "{\"pinhole\": {\"camera\": {\"eye\": [0, 0, 3], \"look_at\": [0, 0, 0]}, "
                "\"width\": 4, \"height\": 4}, \"format\": \"ranges\"}",
                "application/json");
    ASSERT_TRUE(res);
    EXPECT_EQ(res->status, 400);
    EXPECT_NE(res->body.find("unknown format"), std::string::npos) << res->body;
    res = query(id, "scan",
                "{\"lidar\": {\"elevation_deg\": [0], \"azimuth_steps\": 8}, \"format\": \"ply\"}",
                "application/json");
    ASSERT_TRUE(res);
    EXPECT_EQ(res->status, 400);
    EXPECT_NE(res->body.find("\\\"ranges\\\" (KDRB)"), std::string::npos) << res->body;
}

TEST_F(HttpScenes, RendersEqualTheEngineSyncAndAsyncWithinTheMeshLimits) {
    const std::vector<std::pair<std::string, proto::Transform>> inst = {{a_id_, kIdentity},
                                                                        {b_id_, kMirrored}};
    const std::string id = create_id("{\"instances\":[" + instance_json(a_id_, kIdentity) + "," +
                                     instance_json(b_id_, kMirrored) + "]}");
    const Scene local = local_scene(inst);
    const std::string body =
        "{\"width\":48,\"height\":32,\"shading\":\"primid\",\"format\":\"raw\"}";
    auto want_request = proto::decode_render_request(body, {}, true);
    ASSERT_TRUE(want_request.ok());
    const Image want = render(local, want_request->settings);
    auto expect_render = [&](const std::string& bytes) {
        auto raw = proto::decode_raw_image(string_to_bytes(bytes));
        ASSERT_TRUE(raw.ok()) << raw.error();
        ASSERT_EQ(raw->image.pixels.size(), want.pixels.size());
        EXPECT_EQ(std::memcmp(raw->image.pixels.data(), want.pixels.data(),
                              want.pixels.size() * sizeof(float)),
                  0);
    };
    // Synchronous: the engine's pixels, bit for bit (primid tells the instances apart).
    auto res = query(id, "render", body, "application/json");
    ASSERT_TRUE(res);
    ASSERT_EQ(res->status, 200) << res->body;
    EXPECT_EQ(res->get_header_value("X-Kdrt-Scene-Revision"), "1");
    expect_render(res->body);
    // "geomid" (one colour an instance) is the engine's too.
    const std::string geomid =
        "{\"width\":48,\"height\":32,\"shading\":\"geomid\",\"format\":\"raw\"}";
    auto geomid_request = proto::decode_render_request(geomid, {}, true);
    ASSERT_TRUE(geomid_request.ok()) << geomid_request.error().detail;
    EXPECT_EQ(geomid_request->settings.shading, Shading::kGeomId);
    res = query(id, "render", geomid, "application/json");
    ASSERT_TRUE(res);
    ASSERT_EQ(res->status, 200) << res->body;
    auto raw_geomid = proto::decode_raw_image(string_to_bytes(res->body));
    ASSERT_TRUE(raw_geomid.ok()) << raw_geomid.error();
    EXPECT_EQ(raw_geomid->image.pixels, render(local, geomid_request->settings).pixels);
    // Asynchronous: a job naming the scene and revision, with the same image.
    httplib::Headers prefer = {{"Prefer", "respond-async"}};
    res = server_->client()->Post("/v1/scenes/" + id + "/render", prefer, body, "application/json");
    ASSERT_TRUE(res);
    ASSERT_EQ(res->status, 202) << res->body;
    auto job = proto::decode_job_status(res->body);
    ASSERT_TRUE(job.ok()) << res->body;
    EXPECT_EQ(job->scene, id);
    EXPECT_EQ(job->revision, 1u);
    EXPECT_TRUE(job->mesh.empty());
    for (int i = 0; i < 600 && job->state != proto::JobState::kDone; ++i) {
        std::this_thread::sleep_for(std::chrono::milliseconds(20));
        res = server_->client()->Get("/v1/jobs/" + job->id);
        ASSERT_TRUE(res);
        job = proto::decode_job_status(res->body);
        ASSERT_TRUE(job.ok()) << res->body;
    }
    ASSERT_EQ(job->state, proto::JobState::kDone);
    res = server_->client()->Get("/v1/jobs/" + job->id + "/result");
    ASSERT_TRUE(res);
    ASSERT_EQ(res->status, 200);
    expect_render(res->body);
    // The mesh render's checks, with its problems: a "mesh" member (the path names the scene), a
    // bad setting, a cost over max_render_rays; an unknown scene.
    auto p = expect_problem(query(id, "render", "{\"mesh\":\"" + a_id_ + "\"}", "application/json"),
                            400);
    EXPECT_NE(p.detail.find("unknown member \"mesh\""), std::string::npos) << p.detail;
    p = expect_problem(query(id, "render", "{\"width\":0}", "application/json"), 400);
    EXPECT_NE(p.detail.find("width"), std::string::npos) << p.detail;
    p = expect_problem(
        query(id, "render", "{\"width\":4096,\"height\":4096,\"spp\":1024,\"shading\":\"ao\"}",
              "application/json"),
        400);
    EXPECT_NE(p.detail.find("exceeds max_render_rays"), std::string::npos) << p.detail;
    expect_problem(query(std::string(32, 'f'), "render", body, "application/json"), 404);
}

TEST_F(HttpScenes, DistanceNeedsSimilarityTransformsAndAnswersAsTheEngine) {
    const std::vector<std::pair<std::string, proto::Transform>> inst = {{a_id_, kIdentity},
                                                                        {b_id_, kMoved}};
    const std::string id = create_id("{\"instances\":[" + instance_json(a_id_, kIdentity) + "," +
                                     instance_json(b_id_, kMoved) + "]}");
    const Scene local = local_scene(inst);
    Rng rng(test_seed() + 9);
    std::vector<Vec3> points;
    for (int i = 0; i < 200; ++i) points.push_back(rng.in_box({{-0.5f, -0.5f, -0.5f}, {2, 2, 2}}));
    auto res = query(id, "distance", bytes_to_string(proto::encode_points(points)),
                     std::string(proto::kPointMediaType));
    ASSERT_TRUE(res);
    ASSERT_EQ(res->status, 200) << res->body;
    auto split = proto::split_geometry_ids(string_to_bytes(res->body));
    ASSERT_TRUE(split.ok());
    auto got = proto::decode_distances(split->mesh_body);
    ASSERT_TRUE(got.ok());
    std::vector<SceneClosestPoint> expected(points.size());
    closest_points(local, points, expected, DistanceOptions{});
    for (size_t i = 0; i < points.size(); ++i) {
        EXPECT_EQ(got->points[i].distance, expected[i].closest.distance) << i;
        EXPECT_EQ(got->points[i].prim, expected[i].closest.prim) << i;
        EXPECT_EQ(split->geometry_ids[i], expected[i].geom) << i;
    }
    // A sheared instance has no single world distance scale: refused naming it.
    const proto::Transform sheared{{1, 0.5f, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0}};
    const std::string bad = create_id("{\"instances\":[" + instance_json(a_id_, kIdentity) + "," +
                                      instance_json(a_id_, sheared) + "]}");
    res = query(bad, "distance", bytes_to_string(proto::encode_points(points)),
                std::string(proto::kPointMediaType));
    const auto p = expect_problem(res, 400);
    EXPECT_EQ(p.index, 1u);
    EXPECT_EQ(p.field.rfind("instances[1]", 0), 0u) << p.field;
}

TEST_F(HttpScenes, PoseUpdatesMakeRevisionsAndStaleOnesAreRefused) {
    const std::string id = create_id("{\"instances\":[" + instance_json(a_id_, kIdentity, "car") +
                                     "," + instance_json(b_id_, kIdentity) + "]}");
    const auto cli = server_->client();
    const std::string poses =
        "{\"poses\":[{\"name\":\"car\",\"transform\":" + transform_json(kMoved) +
        "},{\"geometry_id\":1,\"transform\":" + transform_json(kMirrored) + "}]}";
    httplib::Headers headers{{"If-Match", "\"1\""}};
    auto res = cli->Patch("/v1/scenes/" + id + "/poses", headers, poses, "application/json");
    ASSERT_TRUE(res);
    ASSERT_EQ(res->status, 200) << res->body;
    EXPECT_EQ(res->get_header_value("ETag"), "\"2\"");
    // The same base revision again: stale.
    res = cli->Patch("/v1/scenes/" + id + "/poses", headers, poses, "application/json");
    auto p = expect_problem(res, 412);
    EXPECT_EQ(p.field, "If-Match");
    // A malformed If-Match.
    res = cli->Patch("/v1/scenes/" + id + "/poses", {{"If-Match", "\"two\""}}, poses,
                     "application/json");
    p = expect_problem(res, 400);
    EXPECT_EQ(p.field, "If-Match");
    // KDRX, without If-Match (applies to the current revision), through POST.
    std::vector<proto::PoseEntry> binary(1);
    binary[0].geometry_id = 0;
    binary[0].transform = kIdentity;
    res =
        cli->Post("/v1/scenes/" + id + "/poses", bytes_to_string(proto::encode_pose_batch(binary)),
                  std::string(proto::kPoseBatchMediaType));
    ASSERT_TRUE(res);
    ASSERT_EQ(res->status, 200) << res->body;
    EXPECT_EQ(res->get_header_value("ETag"), "\"3\"");

    // Revision 2 (pinned) and 3 (current) answer as their own poses.
    const std::vector<Ray> batch = rays(800, test_seed() + 11);
    const std::string body = bytes_to_string(proto::encode_rays(batch, false));
    for (const auto& [revision, pose0, pose1] :
         {std::tuple{2, kMoved, kMirrored}, std::tuple{3, kIdentity, kMirrored}}) {
        const Scene local = local_scene({{a_id_, pose0}, {b_id_, pose1}});
        res = query(id, "intersect?revision=" + std::to_string(revision), body,
                    "application/x-kdrt-rays");
        SCOPED_TRACE("revision " + std::to_string(revision));
        ASSERT_EQ(expect_engine_hits(res, local, batch).size(), batch.size());
    }
    // Bad poses name the entry and field.
    res = cli->Patch(
        "/v1/scenes/" + id + "/poses",
        "{\"poses\":[{\"name\":\"bus\",\"transform\":" + transform_json(kIdentity) + "}]}",
        "application/json");
    p = expect_problem(res, 422);
    EXPECT_EQ(p.field, "poses[0].name");
    res = cli->Patch("/v1/scenes/" + id + "/poses",
                     "{\"poses\":[{\"geometry_id\":0,\"transform\":[1,0,0,0,0,1,0,0,0,0,1,0]},"
                     "{\"geometry_id\":1,\"transform\":[1,0,0,0,0,0,0,0,0,0,1,0]}]}",
                     "application/json");
    p = expect_problem(res, 400);
    EXPECT_EQ(p.field, "poses[1].transform");
    EXPECT_EQ(p.index, 1u);
    // Checked while the revision was written under tmp/: refused, nothing stored or left there.
    EXPECT_EQ(cli->Get("/v1/scenes/" + id)->get_header_value("ETag"), "\"3\"");
    for (const auto& e :
         std::filesystem::recursive_directory_iterator(dir_->path() / "cache" / "tmp"))
        EXPECT_FALSE(e.is_regular_file() && e.path().extension() == ".tmp") << e.path();
    // Revisions older than the kept 3 are gone; a revision never written does not exist.
    for (int k = 0; k < 3; ++k)
        ASSERT_EQ(cli->Post("/v1/scenes/" + id + "/poses",
                            bytes_to_string(proto::encode_pose_batch(binary)),
                            std::string(proto::kPoseBatchMediaType))
                      ->status,
                  200);
    expect_problem(cli->Get("/v1/scenes/" + id + "?revision=2"), 404);
    expect_problem(cli->Get("/v1/scenes/" + id + "?revision=99"), 404);
    res = cli->Get("/v1/scenes/" + id);
    ASSERT_EQ(res->status, 200);
    EXPECT_EQ(res->get_header_value("ETag"), "\"6\"");
}

TEST_F(HttpScenes, BadScenesNameTheInstanceAndField) {
    const std::string unknown(64, '0');
    auto p = expect_problem(create("{\"instances\":[" + instance_json(a_id_, kIdentity) + "," +
                                   instance_json(unknown, kIdentity) + "]}"),
                            422);
    EXPECT_EQ(p.field, "instances[1].mesh");
    EXPECT_EQ(p.index, 1u);
    EXPECT_NE(p.detail.find(unknown), std::string::npos);

    const proto::Transform singular{{1, 0, 0, 0, 0, 0, 0, 0, 0, 0, 1, 0}};
    p = expect_problem(create("{\"instances\":[" + instance_json(a_id_, kIdentity) + "," +
                              instance_json(a_id_, singular) + "]}"),
                       400);
    EXPECT_EQ(p.field, "instances[1].transform");
    EXPECT_EQ(p.index, 1u);

    p = expect_problem(create("{\"instances\":[{\"mesh\":\"" + a_id_ +
                              "\",\"transform\":[1,0,0,0,0,1,1e39,0,0,0,1,0]}]}"),
                       400);
    EXPECT_EQ(p.field, "instances[0].transform[1][2]");

    p = expect_problem(create("{\"instances\":[{\"mesh\":\"" + a_id_ + "\",\"transform\":[1,0]}]}"),
                       400);
    EXPECT_EQ(p.field, "instances[0].transform");

    std::string seven = "{\"instances\":[";
    for (int i = 0; i < 7; ++i) {
        if (i > 0) seven += ',';
        seven += instance_json(a_id_, kIdentity);
    }
    p = expect_problem(create(seven + "]}"), 413);
    EXPECT_EQ(p.field, "instances");
    EXPECT_EQ(p.limit, 6u);

    expect_problem(create("{\"instances\":[], \"x\": 1}"), 400);
    expect_problem(server_->client()->Get("/v1/scenes/" + std::string(32, 'f')), 404);
    expect_problem(server_->client()->Get("/v1/scenes/nonsense"), 404);
}

TEST_F(HttpScenes, InstanceEditsAndMeshesInUse) {
    const Mesh c = small_mesh(test_seed() + 77, 100);
    const std::string c_id = upload_id(*server_->client(), c);
    const std::string id = create_id("{\"instances\":[" + instance_json(c_id, kIdentity, "x") +
                                     "," + instance_json(a_id_, kMoved) + "]}");
    const auto cli = server_->client();
    auto p = expect_problem(cli->Delete("/v1/meshes/" + c_id), 409);
    EXPECT_NE(p.detail.find(id), std::string::npos) << p.detail;

    auto res =
        cli->Post("/v1/scenes/" + id + "/instances",
                  "{\"remove\":[\"x\"],\"add\":[" + instance_json(b_id_, kIdentity, "y") + "]}",
                  "application/json");
    ASSERT_TRUE(res);
    ASSERT_EQ(res->status, 200) << res->body;
    auto doc = proto::decode_scene_json(res->body, {}, true);
    ASSERT_TRUE(doc.ok());
    ASSERT_EQ(doc->instances.size(), 2u);
    EXPECT_EQ(doc->instances[0].mesh, a_id_);
    EXPECT_EQ(doc->instances[1].name, "y");
    EXPECT_EQ(doc->revision, 2u);
    // The current revision no longer uses c: it may go. Kept revision 1 then answers 409.
    res = cli->Delete("/v1/meshes/" + c_id);
    ASSERT_TRUE(res);
    EXPECT_EQ(res->status, 204);
    p = expect_problem(
        query(id, "intersect?revision=1", bytes_to_string(proto::encode_rays(rays(4, 1), false)),
              "application/x-kdrt-rays"),
        409);
    EXPECT_EQ(p.field, "instances[0].mesh");

    p = expect_problem(
        cli->Post("/v1/scenes/" + id + "/instances",
                  "{\"add\":[" + instance_json(std::string(64, '1'), kIdentity) + "]}",
                  "application/json"),
        422);
    EXPECT_EQ(p.field, "add[0].mesh");

    res = cli->Delete("/v1/scenes/" + id, {{"If-Match", "\"1\""}});
    expect_problem(res, 412);
    res = cli->Delete("/v1/scenes/" + id);
    ASSERT_TRUE(res);
    EXPECT_EQ(res->status, 204);
    expect_problem(cli->Get("/v1/scenes/" + id), 404);
    expect_problem(cli->Delete("/v1/scenes/" + id), 404);
}

TEST_F(HttpScenes, WithOneEngineThreadPosesAreCheckedBeforeTheWriteAndBuiltAfterTheCommit) {
    // The arena has no worker for enqueued tasks: the check and the build run on the calling
    // thread (SceneCache::update), a refused update writes nothing.
    TempDir dir;
    ServerProcess one({.cache_dir = dir.path() / "cache", .args = {"--threads", "1"}});
    const auto cli = one.client();
    const std::string mesh = upload_id(*cli, *a_);
    auto res = cli->Post("/v1/scenes",
                         "{\"instances\":[" + instance_json(mesh, kIdentity) + "," +
                             instance_json(mesh, kMoved) + "]}",
                         "application/json");
    ASSERT_TRUE(res);
    ASSERT_EQ(res->status, 201) << res->body;
    const std::string id = proto::decode_scene_json(res->body, {}, true)->id;
    res = cli->Patch(
        "/v1/scenes/" + id + "/poses",
        "{\"poses\":[{\"geometry_id\":1,\"transform\":" + transform_json(kMirrored) + "}]}",
        "application/json");
    ASSERT_TRUE(res);
    ASSERT_EQ(res->status, 200) << res->body;
    EXPECT_EQ(res->get_header_value("ETag"), "\"2\"");
    res = cli->Patch("/v1/scenes/" + id + "/poses",
                     "{\"poses\":[{\"geometry_id\":0,\"transform\":[1,0,0,0,0,0,0,0,0,0,1,0]}]}",
                     "application/json");
    EXPECT_EQ(expect_problem(res, 400).field, "poses[0].transform");
    EXPECT_EQ(cli->Get("/v1/scenes/" + id)->get_header_value("ETag"), "\"2\"");
    for (const auto& e :
         std::filesystem::recursive_directory_iterator(dir.path() / "cache" / "tmp"))
        EXPECT_FALSE(e.is_regular_file() && e.path().extension() == ".tmp") << e.path();
    // Revision 2 answers as its poses (the engine's scene of the same instances).
    const Scene local = local_scene({{a_id_, kIdentity}, {a_id_, kMirrored}});
    const std::vector<Ray> batch = rays(400, test_seed() + 17);
    res = cli->Post("/v1/scenes/" + id + "/intersect",
                    bytes_to_string(proto::encode_rays(batch, false)), "application/x-kdrt-rays");
    const std::vector<SceneHit> expected = expect_engine_hits(res, local, batch);
    ASSERT_EQ(expected.size(), batch.size());
    EXPECT_GT(std::count_if(expected.begin(), expected.end(),
                            [](const SceneHit& h) { return h.is_hit(); }),
              0);
}

TEST_F(HttpScenes, AcknowledgedRevisionsSurviveKillMinus9) {
    const std::string id = create_id("{\"instances\":[" + instance_json(a_id_, kIdentity) + "]}");
    std::vector<proto::PoseEntry> pose(1);
    pose[0].geometry_id = 0;
    uint64_t last = 1;
    for (int k = 1; k <= 5; ++k) {
        pose[0].transform.m[3] = 0.1f * static_cast<float>(k);
        auto res = server_->client()->Post("/v1/scenes/" + id + "/poses",
                                           bytes_to_string(proto::encode_pose_batch(pose)),
                                           std::string(proto::kPoseBatchMediaType));
        ASSERT_TRUE(res);
        ASSERT_EQ(res->status, 200);
        last = std::stoull(res->get_header_value("X-Kdrt-Scene-Revision"));
    }
    server_->stop(SIGKILL, std::chrono::seconds(10));
    delete server_;
    start();
    auto res = server_->client()->Get("/v1/scenes/" + id);
    ASSERT_TRUE(res);
    ASSERT_EQ(res->status, 200) << res->body;
    auto doc = proto::decode_scene_json(res->body, {}, true);
    ASSERT_TRUE(doc.ok());
    EXPECT_EQ(doc->revision, last);
    EXPECT_EQ(doc->instances[0].transform.m[3], 0.5f);
    res = server_->client()->Get("/v1/scenes");
    ASSERT_TRUE(res);
    EXPECT_NE(res->body.find(id), std::string::npos);
    EXPECT_NE(server_->client()->Get("/metrics")->body.find("kdrt_scenes{state=\"stored\"}"),
              std::string::npos);
}

// A store written by an earlier kdrt-server (one file per revision: JSON before KDRS, then KDRS)
// is served as it is, and the scene's next pose update moves it into a revision log, logged; a
// restart reads the log.
TEST_F(HttpScenes, RevisionFilesOfAnEarlierServerAreServedThenMovedIntoALog) {
    const std::string id = "0123456789abcdef0123456789abcdef";
    const auto scene_dir = dir_->path() / "cache" / "scenes" / id;
    std::filesystem::create_directories(scene_dir);
    const auto doc_of = [&](uint64_t revision) {
        proto::SceneDocument doc;
        doc.id = id;
        doc.revision = revision;
        proto::Transform t = kIdentity;
        t.m[3] = 0.25f * static_cast<float>(revision);
        doc.instances = {{a_id_, t, "a"}, {b_id_, kMirrored, ""}};
        return doc;
    };
    for (uint64_t r = 1; r <= 4; ++r) {
        char name[32];
        std::snprintf(name, sizeof name, "%020llu.json", static_cast<unsigned long long>(r));
        std::ofstream f(scene_dir / name, std::ios::binary);
        if (r <= 2) {
            f << proto::encode_scene_json(doc_of(r));
        } else {
            const auto bytes = proto::encode_scene_file(doc_of(r));
            f.write(reinterpret_cast<const char*>(bytes.data()),
                    static_cast<std::streamsize>(bytes.size()));
        }
    }
    server_->stop(SIGTERM, std::chrono::seconds(10));
    delete server_;
    start();
    EXPECT_NE(server_->log().find("scenes stored as revision files"), std::string::npos)
        << server_->log();
    auto cli = server_->client();
    const auto get_doc = [&](const std::string& path) -> std::optional<proto::SceneDocument> {
        auto res = cli->Get(path);
        if (!res || res->status != 200) return std::nullopt;
        auto doc = proto::decode_scene_json(res->body, {}, true);
        if (!doc) return std::nullopt;
        return std::move(doc).value();
    };
    EXPECT_EQ(get_doc("/v1/scenes/" + id), doc_of(4));
    EXPECT_EQ(get_doc("/v1/scenes/" + id + "?revision=2"), doc_of(2)) << "JSON, kept (3)";
    auto res =
        cli->Patch("/v1/scenes/" + id + "/poses", {{"If-Match", "\"4\""}},
                   "{\"poses\":[{\"geometry_id\":0,\"transform\":[1,0,0,1.25,0,1,0,0,0,0,1,0]}]}",
                   "application/json");
    ASSERT_TRUE(res);
    ASSERT_EQ(res->status, 200) << res->body;
    EXPECT_EQ(res->get_header_value("ETag"), "\"5\"");
    EXPECT_NE(server_->log().find("moved 2 of its 4 revision files into revisions.kdrs"),
              std::string::npos)
        << server_->log();
    std::vector<std::string> files;
    for (const auto& e : std::filesystem::directory_iterator(scene_dir))
        files.push_back(e.path().filename().string());
    EXPECT_EQ(files, std::vector<std::string>{"revisions.kdrs"});
    // After a kill, a fresh server reads the log: revision 5, and the kept 3 and 4.
    server_->stop(SIGKILL, std::chrono::seconds(10));
    delete server_;
    start();
    cli = server_->client();
    proto::SceneDocument five = doc_of(4);
    five.revision = 5;
    five.instances[0].transform.m[3] = 1.25f;
    EXPECT_EQ(get_doc("/v1/scenes/" + id), five);
    EXPECT_EQ(get_doc("/v1/scenes/" + id + "?revision=3"), doc_of(3));
    res = cli->Get("/v1/scenes/" + id + "?revision=2");
    ASSERT_TRUE(res);
    EXPECT_EQ(res->status, 404) << "older than the kept revisions";
    ASSERT_EQ(cli->Delete("/v1/scenes/" + id)->status, 204);
}

}  // namespace
}  // namespace kdrt::test
