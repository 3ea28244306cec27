// `kdrt scan` and Client::scan_pinhole / scan_lidar against a real kdrt-server: the files written
// (EXR, KDRZ, PLY, KDRL) hold the engine's scans exactly, every usage error exits 2 with its
// message before any request, and a refusal by the server (a pose that is not rigid) exits 1
// naming the field.

#include <gtest/gtest.h>

#include <filesystem>

#include "cli_runner.h"
#include "client_test_util.h"
#include "kdrt/proto/mesh_id.h"
#include "kdrt/proto/scan.h"
#include "kdrt/proto/scan_image.h"
#include "kdrt/scan.h"

namespace kdrt::test {
namespace {

class CliScan : public ::testing::Test {
protected:
    static void SetUpTestSuite() {
        dir_ = new TempDir();
        server_ = new ServerProcess({.cache_dir = dir_->path() / "cache"});
        mesh_ = new Mesh(box_mesh(-2, 2));
        append(*mesh_, uv_sphere({0.3f, -0.2f, 0.1f}, 0.9f, 16, 32));
        tree_ = new KdTree(build_kdtree(*mesh_));
        Client client(server_url(*server_), fast_options());
        auto info = client.upload(*mesh_);
        ASSERT_TRUE(info) << info.error().detail;
        id_ = info->id;
    }
    static void TearDownTestSuite() {
        delete server_;
        delete dir_;
        delete mesh_;
        delete tree_;
    }
    static CliRun kdrt(const std::vector<std::string>& args) {
        CliOptions options;
        options.env.push_back("KDRT_SERVER=" + server_url(*server_));
        return run_cli(args, options);
    }
    static std::string path(const std::string& name) { return (dir_->path() / name).string(); }

    static TempDir* dir_;
    static ServerProcess* server_;
    static Mesh* mesh_;
    static KdTree* tree_;
    static std::string id_;
};
TempDir* CliScan::dir_ = nullptr;
ServerProcess* CliScan::server_ = nullptr;
Mesh* CliScan::mesh_ = nullptr;
KdTree* CliScan::tree_ = nullptr;
std::string CliScan::id_;

const char* kPoseText = "0.8,0,0.6,-3,0,1,0,0.2,-0.6,0,0.8,-4,0,0,0,1";

PinholeSpec cli_pinhole() {
    PinholeSpec spec;
    spec.intrinsics = {40, 38, 19.5, 15, 40, 30};
    spec.pose.m = {0.8, 0, 0.6, -3, 0, 1, 0, 0.2, -0.6, 0, 0.8, -4, 0, 0, 0, 1};
    return spec;
}

TEST_F(CliScan, Help) {
    const CliRun run = run_cli({"scan", "--help"});
    EXPECT_EQ(run.exit_code, 0);
    EXPECT_EQ(run.out.rfind("usage: kdrt scan", 0), 0u) << run.out;
    const CliRun all = run_cli({"--help"});
    EXPECT_TRUE(contains(all.out, "\n  scan ")) << all.out;
}

TEST_F(CliScan, PinholeFilesHoldTheEnginesScan) {
    PinholeSpec spec = cli_pinhole();
    spec.kind = DepthKind::kRange;
    spec.normals = true;
    spec.max_range = 9.0f;
    const DepthImage want = scan_pinhole(*tree_, spec);
    const CliRun exr =
        kdrt({"scan", id_, "--pinhole", "-o", path("depth.exr"), "--intrinsics", "40,38,19.5,15",
              "--size", "40x30", "--pose", kPoseText, "--range", "--normals", "--max-range", "9"});
    ASSERT_EQ(exr.exit_code, 0) << exr.err;
    EXPECT_TRUE(contains(exr.err, "wrote " + path("depth.exr"))) << exr.err;
    EXPECT_TRUE(contains(exr.err, "40x30 range")) << exr.err;
    auto back = proto::decode_depth_exr(read_bytes(path("depth.exr")));
    ASSERT_TRUE(back) << back.error();
    EXPECT_EQ(as_string(proto::encode_depth_image(*back)),
              as_string(proto::encode_depth_image(want)));

    spec.kind = DepthKind::kDepth;
    spec.normals = false;
    spec.max_range = INFINITY;
    spec.min_range = 0.5f;
    const CliRun bin =
        kdrt({"scan", id_, "--pinhole", "-o", path("depth.kdrz"), "--intrinsics", "40,38,19.5,15",
              "--size", "40x30", "--pose", kPoseText, "--min-range", "0.5"});
    ASSERT_EQ(bin.exit_code, 0) << bin.err;
    EXPECT_EQ(as_string(read_bytes(path("depth.kdrz"))),
              as_string(proto::encode_depth_image(scan_pinhole(*tree_, spec))));
}

TEST_F(CliScan, LookAtPinhole) {
    const CliRun run = kdrt({"scan", id_, "--pinhole", "-o", path("look.kdrz"), "--eye",
                             "1,0.5,-1.5", "--look-at", "0,0,0", "--fov", "60", "--size", "32x24"});
    ASSERT_EQ(run.exit_code, 0) << run.err;
    CameraSpec camera;
    camera.eye = {1, 0.5f, -1.5f};
    camera.look_at = {0, 0, 0};
    camera.fov_deg = 60;
    const PinholeCamera pin = pinhole_from_look_at(camera, 32, 24);
    PinholeSpec spec;
    spec.intrinsics = pin.intrinsics;
    spec.pose = pin.pose;
    EXPECT_EQ(as_string(read_bytes(path("look.kdrz"))),
              as_string(proto::encode_depth_image(scan_pinhole(*tree_, spec))));
}

TEST_F(CliScan, LidarFilesHoldTheEnginesScan) {
    LidarSpec spec;
    spec.elevation_deg = lidar_elevations(-30, 30, 12);
    spec.azimuth_steps = 90;
    spec.returns = 3;
    spec.pose.m = {1, 0, 0, 0.1, 0, 1, 0, 0.2, 0, 0, 1, -0.1, 0, 0, 0, 1};
    const PointCloud want = scan_lidar(*tree_, spec);
    EXPECT_GT(want.points.size(), 12u * 90u);
    const std::vector<std::string> sensor = {
        "--channels",      "12",
        "--vertical-fov",  "-30,30",
        "--azimuth-steps", "90",
        "--returns",       "3",
        "--pose",          "1,0,0,0.1,0,1,0,0.2,0,0,1,-0.1,0,0,0,1"};
    for (const auto& [file, bytes] :
         {std::pair{std::string("cloud.ply"), proto::encode_point_cloud_ply(want)},
          std::pair{std::string("cloud.kdrl"), proto::encode_point_cloud(want)},
          std::pair{std::string("cloud.kdrb"), proto::encode_lidar_ranges(want)}}) {
        std::vector<std::string> args = {"scan", id_, "--lidar", "-o", path(file)};
        args.insert(args.end(), sensor.begin(), sensor.end());
        const CliRun run = kdrt(args);
        ASSERT_EQ(run.exit_code, 0) << run.err;
        EXPECT_TRUE(contains(run.err, std::to_string(want.points.size()) + " points")) << run.err;
        EXPECT_EQ(as_string(read_bytes(path(file))), as_string(bytes)) << file;
    }
    // --elevations, and the library call.
    LidarSpec listed;
    listed.elevation_deg = {-5, 0, 7.5};
    listed.azimuth_steps = 16;
    const CliRun run = kdrt({"scan", id_, "--lidar", "-o", path("three.kdrl"), "--elevations",
                             "-5,0,7.5", "--azimuth-steps", "16"});
    ASSERT_EQ(run.exit_code, 0) << run.err;
    EXPECT_EQ(as_string(read_bytes(path("three.kdrl"))),
              as_string(proto::encode_point_cloud(scan_lidar(*tree_, listed))));
    Client client(server_url(*server_), fast_options());
    proto::ScanRequest request;
    request.lidar = true;
    request.lidar_spec = listed;
    auto cloud = client.scan_lidar(id_, request);
    ASSERT_TRUE(cloud) << cloud.error().detail;
    EXPECT_EQ(as_string(proto::encode_point_cloud(*cloud)),
              as_string(proto::encode_point_cloud(scan_lidar(*tree_, listed))));
    auto wrong = client.scan_pinhole(id_, request);
    ASSERT_FALSE(wrong);
    EXPECT_EQ(wrong.error().kind, ErrorKind::kInput);
}

TEST_F(CliScan, UsageErrorsExitTwoBeforeAnyRequest) {
    struct Case {
        std::vector<std::string> args;
        std::string message;
    };
    const std::string out = path("never.exr"), cloud = path("never.ply");
    const std::vector<std::string> k = {
        "--intrinsics", "10,10,2,2", "--size", "4x4", "--pose", "1,0,0,0,0,1,0,0,0,0,1,0,0,0,0,1"};
    auto pin = [&](std::vector<std::string> more) {
        std::vector<std::string> a = {"scan", id_, "--pinhole", "-o", out};
        a.insert(a.end(), k.begin(), k.end());
        a.insert(a.end(), more.begin(), more.end());
        return a;
    };
    auto lid = [&](std::vector<std::string> more) {
        std::vector<std::string> a = {"scan", id_, "--lidar", "-o", cloud};
        a.insert(a.end(), more.begin(), more.end());
        return a;
    };
    const std::vector<Case> cases = {
        {{"scan"}, "kdrt scan: missing ID"},
        {{"scan", id_, "-o", out}, "give exactly one of --pinhole and --lidar"},
        {{"scan", id_, "--pinhole", "--lidar", "-o", out}, "give exactly one of"},
        {{"scan", id_, "--pinhole"}, "missing -o FILE"},
        {{"scan", id_, "--pinhole", "-o", path("x.png")}, "a pinhole scan is .exr or .kdrz"},
        {{"scan", id_, "--lidar", "-o", path("x.exr")}, "a lidar scan is .ply, .kdrl or .kdrb"},
        {{"scan", id_, "--pinhole", "-o", out}, "a pinhole needs --intrinsics"},
        {{"scan", id_, "--pinhole", "-o", out, "--intrinsics", "1,2,3"},
         "--intrinsics: \"1,2,3\" is not four numbers"},
        {{"scan", id_, "--pinhole", "-o", out, "--intrinsics", "1,2,3,4", "--pose",
          "1,0,0,0,0,1,0,0,0,0,1,0,0,0,0,1"},
         "--intrinsics needs --size"},
        {{"scan", id_, "--pinhole", "-o", out, "--intrinsics", "1,2,3,4", "--size", "4x4"},
         "--intrinsics needs --pose"},
        {pin({"--size", "4"}), "--size: \"4\" is not WIDTHxHEIGHT"},
        {{"scan", id_, "--pinhole", "-o", out, "--intrinsics", "1,2,3,4", "--size", "4x4", "--pose",
          "1,2,3"},
         "--pose: \"1,2,3\" is not 16 comma-separated numbers"},
        {pin({"--eye", "0,0,1"}), "give either --eye/--look-at"},
        {{"scan", id_, "--pinhole", "-o", out, "--eye", "0,0,1"},
         "a look-at camera needs both --eye and --look-at"},
        {{"scan", id_, "--pinhole", "-o", out, "--eye", "0,0", "--look-at", "0,0,0"},
         "--eye: \"0,0\" is not three numbers"},
        {{"scan", id_, "--pinhole", "-o", out, "--eye", "0,0,1", "--look-at", "0,0,0", "--fov",
          "0"},
         "--fov: \"0\" is not a number of degrees in (0, 180)"},
        {pin({"--min-range", "-1"}), "--min-range: \"-1\" is not a number >= 0"},
        {pin({"--max-range", "x"}), "--max-range: \"x\" is not a number >= 0"},
        {pin({"--returns", "2"}), "--returns applies to --lidar only"},
        {lid({"--normals"}), "--normals applies to --pinhole only"},
        {lid({"--azimuth-steps", "8"}), "a lidar needs --channels N with --vertical-fov"},
        {lid({"--channels", "0", "--vertical-fov", "-1,1", "--azimuth-steps", "8"}),
         "--channels: \"0\" is not in 1 .."},
        {lid({"--channels", "4", "--vertical-fov", "-1", "--azimuth-steps", "8"}),
         "--vertical-fov: \"-1\" is not two numbers"},
        {lid({"--elevations", "1,a", "--azimuth-steps", "8"}), "--elevations: \"1,a\" is not"},
        {lid({"--elevations", "1", "--channels", "3", "--azimuth-steps", "8"}),
         "give either --elevations or --channels"},
        {lid({"--elevations", "1"}), "a lidar needs --azimuth-steps N"},
        {lid({"--elevations", "1", "--azimuth-steps", "0"}), "--azimuth-steps: \"0\" is not in"},
        {lid({"--elevations", "1", "--azimuth-steps", "4", "--returns", "0"}),
         "--returns: \"0\" is not in"},
    };
    for (const Case& c : cases) {
        SCOPED_TRACE(c.message);
        // No server at this address: a usage error must come before any connection.
        const CliRun run = run_cli([&] {
            std::vector<std::string> a = c.args;
            a.insert(a.begin(), {"--server", "http://127.0.0.1:1"});
            return a;
        }());
        EXPECT_EQ(run.exit_code, 2) << run.err;
        EXPECT_TRUE(contains(run.err, c.message)) << run.err;
    }
    EXPECT_FALSE(std::filesystem::exists(out));
    EXPECT_FALSE(std::filesystem::exists(cloud));
}

TEST_F(CliScan, ServerRefusalsNameTheField) {
    const CliRun run =
        kdrt({"scan", id_, "--pinhole", "-o", path("bad.exr"), "--intrinsics", "10,10,2,2",
              "--size", "4x4", "--pose", "2,0,0,0,0,1,0,0,0,0,1,0,0,0,0,1"});
    EXPECT_EQ(run.exit_code, 1) << run.err;
    EXPECT_TRUE(contains(run.err, "\"pinhole.pose\"")) << run.err;
    const CliRun lidar = kdrt({"scan", id_, "--lidar", "-o", path("bad.ply"), "--elevations",
                               "0,100", "--azimuth-steps", "4"});
    EXPECT_EQ(lidar.exit_code, 1) << lidar.err;
    EXPECT_TRUE(contains(lidar.err, "\"lidar.elevation_deg[1]\"")) << lidar.err;
    EXPECT_FALSE(std::filesystem::exists(path("bad.exr")));
}

}  // namespace
}  // namespace kdrt::test
