// `kdrt scene` against a real kdrt-server: create from the text and JSON forms, get, list, poses
// (text, with --if-revision refused when stale), rm; the query files (trace, hits, distance,
// scan) are the bytes the server answers to one request for the whole batch (the CSV is proto's
// of the engine's answers), sent in chunks; usage errors and refusals with their exit codes.

#include <gtest/gtest.h>

#include <algorithm>
#include <cstring>
#include <filesystem>
#include <limits>
#include <sstream>

#include "cli_runner.h"
#include "client_test_util.h"
#include "kdrt/proto/distance.h"
#include "kdrt/proto/mesh_id.h"
#include "kdrt/proto/ray_batch.h"
#include "kdrt/proto/scan.h"
#include "kdrt/proto/scan_image.h"
#include "kdrt/proto/scene.h"
#include "kdrt/scene.h"
#include "scenes.h"

namespace kdrt::test {
namespace {

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

    // Occlusion (KDRO) and counts (KDRC) carry no plane: the summary says which revision
    // answered, here the current one (2, after a pose change), not 0.
    write_text(path("pose.txt"), "crate 0 0 0.5\n");
    ASSERT_EQ(kdrt({"scene", "poses", id, path("pose.txt"), "-q"}).exit_code, 0);
    const std::string shadow_body = as_string(proto::encode_rays(rays, true));
    write_text(path("shadow.kdrr"), shadow_body);
    run = kdrt({"scene", "trace", id, path("shadow.kdrr"), "-o", path("occ.kdro"), "--chunk-rays",
                "700", "--json"});
    ASSERT_EQ(run.exit_code, 0) << run.err;
    EXPECT_TRUE(contains(run.out, "\"revision\":2")) << run.out;
    EXPECT_EQ(as_string(read_bytes(path("occ.kdro"))),
              one_request(id, "intersect", shadow_body, kRays));
    run = kdrt({"scene", "trace", id, path("shadow.kdrr"), "-o", path("occ.kdro")});
    ASSERT_EQ(run.exit_code, 0) << run.err;
    EXPECT_TRUE(contains(run.err, "(revision 2)")) << run.err;
    run = kdrt({"scene", "hits", id, path("rays.kdrr"), "--all", "--count-only", "-o",
                path("n.kdrc"), "--chunk-rays", "700", "--json"});
    ASSERT_EQ(run.exit_code, 0) << run.err;
    EXPECT_TRUE(contains(run.out, "\"revision\":2")) << run.out;
    run = kdrt({"scene", "trace", id, path("shadow.kdrr"), "-o", path("occ1.kdro"), "--revision",
                "1", "--json"});
    ASSERT_EQ(run.exit_code, 0) << run.err;
    EXPECT_TRUE(contains(run.out, "\"revision\":1")) << run.out;

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
    // .kdrb asks for the compact record, written as it came.
    run = kdrt({"scene", "scan", id, "--lidar", "--elevations", "-10,0,10", "--azimuth-steps", "60",
                "--pose", "1,0,0,0.5,0,1,0,-2,0,0,1,0.4,0,0,0,1", "-o", path("s.kdrb")});
    ASSERT_EQ(run.exit_code, 0) << run.err;
    request.format = proto::ScanFormat::kRanges;
    const std::string kdrb = as_string(read_bytes(path("s.kdrb")));
    EXPECT_EQ(kdrb.substr(0, 4), "KDRB");
    EXPECT_EQ(kdrb,
              one_request(id, "scan", proto::encode_scan_request(request), "application/json"));
}

TEST_F(CliScene, ScanUserFilesCarryTheGeometryIdsOfTheBinaryAnswer) {
    const std::string id = create_text_scene();
    // A pinhole that sees the three instances: EXR and KDRZ of the same scan.
    const std::vector<std::string> camera = {"--pinhole", "--eye",    "0.1,0.4,4", "--look-at",
                                             "0.1,0.4,0", "--fov",    "50",        "--size",
                                             "48x36",     "--normals"};
    auto scan = [&](const std::vector<std::string>& sensor, const std::string& file) {
        std::vector<std::string> args = {"scene", "scan", id, "-o", path(file), "--json"};
        args.insert(args.end(), sensor.begin(), sensor.end());
        return kdrt(args);
    };
    CliRun run = scan(camera, "s.exr");
    ASSERT_EQ(run.exit_code, 0) << run.err;
    EXPECT_TRUE(contains(run.out, "\"revision\":1")) << run.out;
    run = scan(camera, "s.kdrz");
    ASSERT_EQ(run.exit_code, 0) << run.err;
    auto kdrz = proto::split_geometry_ids(read_bytes(path("s.kdrz")));
    ASSERT_TRUE(kdrz) << kdrz.error().to_string();
    auto want = proto::decode_depth_image(kdrz->mesh_body);
    ASSERT_TRUE(want) << want.error().to_string();
    std::vector<uint32_t> exr_geoms;
    auto exr = proto::decode_depth_exr(read_bytes(path("s.exr")), 1ull << 28, &exr_geoms);
    ASSERT_TRUE(exr) << exr.error();
    EXPECT_EQ(exr_geoms, kdrz->geometry_ids);
    EXPECT_EQ(exr->prim, want->prim);
    ASSERT_EQ(exr->depth.size(), want->depth.size());
    EXPECT_EQ(std::memcmp(exr->depth.data(), want->depth.data(), 4 * want->depth.size()), 0);
    ASSERT_EQ(exr->normals.size(), want->normals.size());
    EXPECT_EQ(std::memcmp(exr->normals.data(), want->normals.data(), 12 * want->normals.size()), 0);
    // The scan is worth comparing: it hits at least two instances, and misses somewhere.
    std::vector<uint32_t> seen = kdrz->geometry_ids;
    std::sort(seen.begin(), seen.end());
    seen.erase(std::unique(seen.begin(), seen.end()), seen.end());
    EXPECT_GE(seen.size(), 3u) << "hit instances and kNoHit";
    for (size_t p = 0; p < want->prim.size(); ++p)
        EXPECT_EQ(want->prim[p] == kNoHit, kdrz->geometry_ids[p] == kNoHit) << p;

    // A lidar: PLY and KDRL of the same scan.
    const std::vector<std::string> lidar = {"--lidar",
                                            "--elevations",
                                            "-10,0,10",
                                            "--azimuth-steps",
                                            "90",
                                            "--returns",
                                            "2",
                                            "--pose",
                                            "1,0,0,0.5,0,1,0,-2,0,0,1,0.4,0,0,0,1"};
    run = scan(lidar, "s.ply");
    ASSERT_EQ(run.exit_code, 0) << run.err;
    run = scan(lidar, "s.kdrl");
    ASSERT_EQ(run.exit_code, 0) << run.err;
    auto kdrl = proto::split_geometry_ids(read_bytes(path("s.kdrl")));
    ASSERT_TRUE(kdrl) << kdrl.error().to_string();
    auto cloud = proto::decode_point_cloud(kdrl->mesh_body);
    ASSERT_TRUE(cloud) << cloud.error().to_string();
    ASSERT_GT(cloud->points.size(), 0u);
    const std::string ply = as_string(read_bytes(path("s.ply")));
    const std::string end = "end_header\n";
    const size_t body = ply.find(end);
    ASSERT_NE(body, std::string::npos);
    // Parse the header: the vertex count and the properties, in order.
    std::istringstream header(ply.substr(0, body));
    std::string line;
    size_t vertices = 0;
    std::vector<std::string> properties;
    while (std::getline(header, line)) {
        std::istringstream words(line);
        std::string key, a, b;
        words >> key >> a >> b;
        if (key == "element" && a == "vertex") vertices = std::stoul(b);
        if (key == "property") properties.push_back(a + " " + b);
    }
    EXPECT_EQ(vertices, cloud->points.size());
    EXPECT_EQ(properties,
              (std::vector<std::string>{"float x", "float y", "float z", "float range",
                                        "uint channel", "uint azimuth_index", "uint return_index",
                                        "uint prim", "uint geometry_id"}));
    const size_t stride = 9 * 4;
    ASSERT_EQ(ply.size(), body + end.size() + vertices * stride);
    std::vector<uint32_t> ply_geoms;
    for (size_t i = 0; i < vertices; ++i) {
        const char* vertex = ply.data() + body + end.size() + i * stride;
        EXPECT_EQ(std::memcmp(vertex, &cloud->points[i], 32), 0) << i;
        uint32_t g = 0;
        std::memcpy(&g, vertex + 32, 4);
        ply_geoms.push_back(g);
    }
    EXPECT_EQ(ply_geoms, kdrl->geometry_ids);
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
    // A scan output of no scan format.
    const std::string id = create_text_scene();
    run = kdrt({"scene", "scan", id, "--lidar", "--elevations", "0", "--azimuth-steps", "8", "-o",
                path("never.exr")});
    EXPECT_EQ(run.exit_code, 2);
    EXPECT_TRUE(contains(run.err, "a lidar scan is .ply, .kdrl or .kdrb")) << run.err;
    EXPECT_FALSE(std::filesystem::exists(path("never.exr")));
    // An unreachable server: exit 3.
    CliOptions options;
    options.env.push_back("KDRT_SERVER=http://127.0.0.1:1");
    run = run_cli({"scene", "list", "--retries", "0"}, options);
    EXPECT_EQ(run.exit_code, 3) << run.err;
}

}  // namespace
}  // namespace kdrt::test
