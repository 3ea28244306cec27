// `kdrt scene` against a real kdrt-server: create from the text and JSON forms, get, list, poses
// (text, with --if-revision refused when stale), rm; the query files (trace, hits, distance,
// scan) are the bytes the server answers to one request for the whole batch (the CSV is proto's
// of the engine's answers), sent in chunks; usage errors and refusals with their exit codes.

#include <gtest/gtest.h>

#include <cstring>
#include <limits>

#include "cli_runner.h"
#include "client_test_util.h"
#include "kdrt/proto/distance.h"
#include "kdrt/proto/mesh_id.h"
#include "kdrt/proto/ray_batch.h"
#include "kdrt/proto/scan.h"
#include "kdrt/proto/scene.h"
#include "kdrt/scene.h"
#include "scenes.h"

namespace kdrt::test {
namespace {

bool contains(const std::string& text, const std::string& part) {
    return text.find(part) != std::string::npos;
}

std::string first_word(const std::string& text) {
    return text.substr(0, text.find_first_of(" \n"));
}

class CliScene : public ::testing::Test {
protected:
    static void SetUpTestSuite() {
        dir_ = new TempDir();
        server_ = new ServerProcess({.cache_dir = dir_->path() / "cache"});
        const Mesh ball = uv_sphere({0.5f, 0.5f, 0.5f}, 0.4f, 10, 16);
        Rng rng(test_seed() + 91);
        const Mesh soup = random_soup(rng, 200, 0.2f);
        Client c(server_url(*server_), fast_options());
        ball_id_ = new std::string(c.upload(ball)->id);
        soup_id_ = new std::string(c.upload(soup)->id);
        ball_tree_ = std::make_shared<const KdTree>(build_kdtree(ball));
    }
    static void TearDownTestSuite() {
        delete server_;
        delete dir_;
        delete ball_id_;
        delete soup_id_;
        ball_tree_.reset();
    }
    static CliRun kdrt(const std::vector<std::string>& args) {
        CliOptions options;
        options.env.push_back("KDRT_SERVER=" + server_url(*server_));
        return run_cli(args, options);
    }
    static std::string path(const std::string& name) { return (dir_->path() / name).string(); }
    /// A scene of three instances made with `kdrt scene create` from text; its id.
    static std::string create_text_scene() {
        const std::string file = path("scene.txt");
        write_text(file, "# geometry ids 0, 1, 2\n" + *ball_id_ + "\n" + *soup_id_ +
                             " 0.5 0 0 1.2  0 0.5 0 0.1  0 0 0.5 0  crate\n" + *ball_id_ +
                             ", -1, 0.5, 0, far\n");
        const CliRun run = kdrt({"scene", "create", file, "--quiet"});
        EXPECT_EQ(run.exit_code, 0) << run.err;
        return first_word(run.out);
    }
    /// POSTs `body` to the scene route in one request: the server's answer bytes.
    static std::string one_request(const std::string& id, const std::string& route,
                                   const std::string& body, const std::string& type) {
        httplib::Client cli("127.0.0.1", server_->port());
        auto res = cli.Post("/v1/scenes/" + id + "/" + route, body, type);
        EXPECT_TRUE(res);
        if (!res) return {};
        EXPECT_EQ(res->status, 200) << res->body;
        return res->body;
    }

    static TempDir* dir_;
    static ServerProcess* server_;
    static std::string *ball_id_, *soup_id_;
    static std::shared_ptr<const KdTree> ball_tree_;
};
TempDir* CliScene::dir_ = nullptr;
ServerProcess* CliScene::server_ = nullptr;
std::string* CliScene::ball_id_ = nullptr;
std::string* CliScene::soup_id_ = nullptr;
std::shared_ptr<const KdTree> CliScene::ball_tree_;

TEST_F(CliScene, CreateGetListPosesAndRemove) {
    const std::string id = create_text_scene();
    ASSERT_TRUE(proto::is_scene_id(id)) << id;
    // get --json: the stored document, as the text said.
    CliRun run = kdrt({"scene", "get", id, "--json"});
    ASSERT_EQ(run.exit_code, 0) << run.err;
    auto doc = proto::decode_scene_json(run.out, {}, true);
    ASSERT_TRUE(doc) << run.out;
    ASSERT_EQ(doc->instances.size(), 3u);
    EXPECT_EQ(doc->instances[1].name, "crate");
    EXPECT_EQ(doc->instances[1].transform.m[3], 1.2f);
    EXPECT_EQ(doc->instances[2].transform.m[3], -1.0f);
    EXPECT_EQ(doc->instances[2].name, "far");
    // get -o FILE, then create FILE: a copy with the same instances.
    run = kdrt({"scene", "get", id, "-o", path("copy.json"), "--quiet"});
    ASSERT_EQ(run.exit_code, 0) << run.err;
    run = kdrt({"scene", "create", path("copy.json"), "--json"});
    ASSERT_EQ(run.exit_code, 0) << run.err;
    auto copy = proto::decode_scene_json(run.out, {}, true);
    ASSERT_TRUE(copy) << run.out;
    EXPECT_NE(copy->id, id);
    EXPECT_EQ(copy->instances, doc->instances);
    // list names both.
    run = kdrt({"scene", "list"});
    ASSERT_EQ(run.exit_code, 0) << run.err;
    EXPECT_TRUE(contains(run.out, id + "  revision 1  3 instances")) << run.out;
    EXPECT_TRUE(contains(run.out, copy->id)) << run.out;
    // poses from text: by name and by geometry id; one new revision.
    write_text(path("poses.txt"), "crate 0 0 1\n0 1 0 0 0.25 0 1 0 0 0 0 1 0\n");
    run = kdrt({"scene", "poses", id, path("poses.txt"), "--if-revision", "1", "--quiet"});
    ASSERT_EQ(run.exit_code, 0) << run.err;
    EXPECT_EQ(run.out, "2\n");
    run = kdrt({"scene", "get", id, "--json"});
    doc = proto::decode_scene_json(run.out, {}, true);
    ASSERT_TRUE(doc) << run.out;
    EXPECT_EQ(doc->instances[1].transform,
              (proto::Transform{{1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 1}}));
    EXPECT_EQ(doc->instances[0].transform.m[3], 0.25f);
    // A stale condition: refused by the server (exit 1), naming the revision.
    run = kdrt({"scene", "poses", id, path("poses.txt"), "--if-revision", "1"});
    EXPECT_EQ(run.exit_code, 1) << run.err;
    EXPECT_TRUE(contains(run.err, "412")) << run.err;
    // rm, then it is gone (exit 1, 404).
    run = kdrt({"scene", "rm", id, copy->id});
    ASSERT_EQ(run.exit_code, 0) << run.err;
    EXPECT_EQ(run.out, "removed " + id + "\nremoved " + copy->id + "\n");
    run = kdrt({"scene", "get", id});
    EXPECT_EQ(run.exit_code, 1);
    EXPECT_TRUE(contains(run.err, "404")) << run.err;
}

TEST_F(CliScene, QueryFilesAreTheServersAnswers) {
    const std::string id = create_text_scene();
    Rng ray_rng(test_seed() + 92);
    std::vector<Ray> rays(3000);
    for (Ray& r : rays) {
        const Vec3 o = ray_rng.in_box({{-3, -2, -2}, {3, 3, 3}});
        const Vec3 d = ray_rng.in_box({{-1.5f, -0.5f, -0.5f}, {2, 1.5f, 1.5f}}) - o;
        r = Ray{o.x, o.y, o.z, 0.0f, d.x, d.y, d.z, std::numeric_limits<float>::infinity()};
    }
    const std::string rays_body = as_string(proto::encode_rays(rays, false));
    write_text(path("rays.kdrr"), rays_body);
    const std::string kRays(proto::kRaysMediaType);

    CliRun run = kdrt({"scene", "trace", id, path("rays.kdrr"), "-o", path("hits.kdrh"),
                       "--chunk-rays", "700", "--json"});
    ASSERT_EQ(run.exit_code, 0) << run.err;
    EXPECT_TRUE(contains(run.out, "\"revision\":1")) << run.out;
    EXPECT_EQ(as_string(read_bytes(path("hits.kdrh"))),
              one_request(id, "intersect", rays_body, kRays));

    run = kdrt({"scene", "hits", id, path("rays.kdrr"), "--all", "-o", "-", "--chunk-rays", "1000",
                "--max-hits", "4", "--normal", "--quiet"});
    ASSERT_EQ(run.exit_code, 0) << run.err;
    EXPECT_EQ(run.out, one_request(id, "intersect_all?max_hits=4&normal=true", rays_body, kRays));

    // Distances as CSV: proto's CSV of the engine's answers, with the geometry ids.
    Rng rng(test_seed() + 93);
    std::vector<Vec3> points;
    for (int i = 0; i < 200; ++i) points.push_back(rng.in_box({{-1.5f, -1, -1}, {2, 2, 2}}));
    write_text(path("points.kdrp"), as_string(proto::encode_points(points)));
    run = kdrt({"scene", "distance", id, path("points.kdrp"), "-o", path("d.csv")});
    ASSERT_EQ(run.exit_code, 0) << run.err;
    Client c(server_url(*server_), fast_options());
    auto got = c.scene_distance(id, points);
    ASSERT_TRUE(got) << got.error().to_string();
    const std::string csv = as_string(read_bytes(path("d.csv")));
    EXPECT_EQ(csv, proto::distances_csv(points, got->points, got->geometry_ids));
    EXPECT_TRUE(contains(csv.substr(0, csv.find('\n')), ",geometry_id")) << csv.substr(0, 200);
    run = kdrt({"scene", "distance", id, path("points.kdrp"), "-o", path("d.kdrd")});
    ASSERT_EQ(run.exit_code, 0) << run.err;
    EXPECT_EQ(as_string(read_bytes(path("d.kdrd"))),
              one_request(id, "distance", as_string(proto::encode_points(points)),
                          std::string(proto::kPointMediaType)));

    // A lidar scan.
    run = kdrt({"scene", "scan", id, "--lidar", "--elevations", "-10,0,10", "--azimuth-steps", "60",
                "--pose", "1,0,0,0.5,0,1,0,-2,0,0,1,0.4,0,0,0,1", "-o", path("s.kdrl")});
    ASSERT_EQ(run.exit_code, 0) << run.err;
    proto::ScanRequest request;
    request.lidar = true;
    request.lidar_spec.elevation_deg = {-10, 0, 10};
    request.lidar_spec.azimuth_steps = 60;
    const double pose[16] = {1, 0, 0, 0.5, 0, 1, 0, -2, 0, 0, 1, 0.4, 0, 0, 0, 1};
    for (int k = 0; k < 16; ++k) request.lidar_spec.pose.m[k] = pose[k];
    EXPECT_EQ(as_string(read_bytes(path("s.kdrl"))),
              one_request(id, "scan", proto::encode_scan_request(request), "application/json"));
}

TEST_F(CliScene, UsageErrorsAndRefusals) {
    CliRun run = kdrt({"scene"});
    EXPECT_EQ(run.exit_code, 2);
    EXPECT_TRUE(contains(run.err, "missing subcommand")) << run.err;
    run = kdrt({"scene", "frobnicate"});
    EXPECT_EQ(run.exit_code, 2);
    EXPECT_TRUE(contains(run.err, "unknown subcommand \"frobnicate\"")) << run.err;
    run = kdrt({"scene", "--help"});
    EXPECT_EQ(run.exit_code, 0);
    EXPECT_TRUE(contains(run.out, "scene poses ID FILE")) << run.out;
    run = kdrt({"scene", "trace", "--help"});
    EXPECT_EQ(run.exit_code, 0);
    EXPECT_TRUE(contains(run.out, "usage: kdrt scene trace")) << run.out;
    // A bad text line: named, exit 2, nothing sent.
    write_text(path("bad.txt"), *ball_id_ + "\n" + *ball_id_ + " 1 2\n");
    run = kdrt({"scene", "create", path("bad.txt")});
    EXPECT_EQ(run.exit_code, 2);
    EXPECT_TRUE(contains(run.err, "line 2: 2 transform numbers")) << run.err;
    run = kdrt({"scene", "create", path("bad.txt"), "--revision", "3"});
    EXPECT_EQ(run.exit_code, 2);
    EXPECT_TRUE(contains(run.err, "--revision applies to get and the queries")) << run.err;
    // An unknown mesh: the server names the instance (exit 1).
    write_text(path("unknown.txt"), *ball_id_ + "\n" + std::string(64, 'e') + "\n");
    run = kdrt({"scene", "create", path("unknown.txt")});
    EXPECT_EQ(run.exit_code, 1);
    EXPECT_TRUE(contains(run.err, "instance 1")) << run.err;
    // A scan output that cannot carry geometry ids.
    const std::string id = create_text_scene();
    run = kdrt({"scene", "scan", id, "--lidar", "--elevations", "0", "--azimuth-steps", "8", "-o",
                path("s.ply")});
    EXPECT_EQ(run.exit_code, 2);
    EXPECT_TRUE(contains(run.err, "a scene scan is written as .kdrl")) << run.err;
    // An unreachable server: exit 3.
    CliOptions options;
    options.env.push_back("KDRT_SERVER=http://127.0.0.1:1");
    run = run_cli({"scene", "list", "--retries", "0"}, options);
    EXPECT_EQ(run.exit_code, 3) << run.err;
}

}  // namespace
}  // namespace kdrt::test
