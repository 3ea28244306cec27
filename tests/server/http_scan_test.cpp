// POST /v1/meshes/{id}/scan against the real binary: KDRZ, EXR, KDRL and PLY answers are the
// engine's scans byte for byte (intrinsics and look-at pinholes, lidars from elevations and from a
// vertical field of view), and every bad request is a problem+json naming the field, limits
// (max_image_width, max_sensor_beams, max_hits_per_ray, max_scan_points) as 413, before any work.

#include <gtest/gtest.h>

#include <cmath>
#include <cstdio>
#include <cstring>
#include <filesystem>

#include "http_test_util.h"
#include "kdrt/proto/raw_image.h"
#include "kdrt/proto/scan.h"
#include "kdrt/proto/scan_image.h"
#include "kdrt/scan.h"

namespace kdrt::test {
namespace {

class HttpScan : public ::testing::Test {
protected:
    static void SetUpTestSuite() {
        dir_ = new TempDir();
        server_ =
            new ServerProcess({.cache_dir = dir_->path() / "cache",
                               .args = {"--max-image-width", "512", "--max-sensor-beams", "20000",
                                        "--max-hits-per-ray", "8", "--max-scan-points", "100000"}});
        mesh_ = new Mesh(box_mesh(-2, 2));
        append(*mesh_, uv_sphere({0.3f, 0.1f, 0.2f}, 0.8f, 16, 32));
        tree_ = new KdTree(build_kdtree(*mesh_));
        id_ = upload_id(*server_->client(), *mesh_);
    }
    static void TearDownTestSuite() {
        delete server_;
        delete dir_;
        delete mesh_;
        delete tree_;
    }
    static httplib::Result post(const std::string& body, const std::string& id = id_,
                                const std::string& type = "application/json") {
        return server_->client()->Post("/v1/meshes/" + id + "/scan", body, type);
    }
    static std::string ok(const std::string& body, const std::string& media_type) {
        auto res = post(body);
        EXPECT_TRUE(res);
        if (!res) return {};
        EXPECT_EQ(res->status, 200) << res->body;
        EXPECT_EQ(res->get_header_value("Content-Type"), media_type);
        return res->body;
    }
    static TempDir* dir_;
    static ServerProcess* server_;
    static Mesh* mesh_;
    static KdTree* tree_;
    static std::string id_;
};
TempDir* HttpScan::dir_ = nullptr;
ServerProcess* HttpScan::server_ = nullptr;
Mesh* HttpScan::mesh_ = nullptr;
KdTree* HttpScan::tree_ = nullptr;
std::string HttpScan::id_;

TEST_F(HttpScan, PinholeAnswerIsTheEngines) {
    proto::ScanRequest request;
    request.pinhole.intrinsics = {60, 58, 31.5, 24.25, 64, 48};
    request.pinhole.pose.m = {0.8, 0, 0.6, -3, 0, 1, 0, 0.2, -0.6, 0, 0.8, -4, 0, 0, 0, 1};
    for (const DepthKind kind : {DepthKind::kDepth, DepthKind::kRange}) {
        for (const bool normals : {false, true}) {
            request.pinhole.kind = kind;
            request.pinhole.normals = normals;
            request.pinhole.min_range = normals ? 0.5f : 0.0f;
            request.pinhole.max_range = normals ? 7.0f : INFINITY;
            const DepthImage want = scan_pinhole(*tree_, request.pinhole);
            size_t hits = 0;
            for (const uint32_t p : want.prim) hits += p != kNoHit;
            EXPECT_GT(hits, 100u);
            request.format = proto::ScanFormat::kBinary;
            const std::string body = proto::encode_scan_request(request);
            EXPECT_EQ(ok(body, std::string(proto::kDepthImageMediaType)),
                      bytes_to_string(proto::encode_depth_image(want)));
            request.format = proto::ScanFormat::kExr;
            const std::string exr = ok(proto::encode_scan_request(request), "image/x-exr");
            auto back = proto::decode_depth_exr(string_to_bytes(exr));
            ASSERT_TRUE(back) << back.error();
            EXPECT_EQ(back->kind, kind);
            EXPECT_EQ(bytes_to_string(proto::encode_depth_image(*back)),
                      bytes_to_string(proto::encode_depth_image(want)));
        }
    }
}

TEST_F(HttpScan, LookAtPinholeIsTheEnginesConversion) {
    const std::string body =
        R"({"pinhole": {"camera": {"eye": [1, 0.5, -5], "look_at": [0, 0, 0], "fov": 50},
            "width": 40, "height": 30, "output": "range"}})";
    CameraSpec camera;
    camera.eye = {1, 0.5f, -5};
    camera.look_at = {0, 0, 0};
    camera.fov_deg = 50;
    const PinholeCamera pin = pinhole_from_look_at(camera, 40, 30);
    PinholeSpec spec;
    spec.intrinsics = pin.intrinsics;
    spec.pose = pin.pose;
    spec.kind = DepthKind::kRange;
    EXPECT_EQ(ok(body, std::string(proto::kDepthImageMediaType)),
              bytes_to_string(proto::encode_depth_image(scan_pinhole(*tree_, spec))));
}

TEST_F(HttpScan, LidarAnswerIsTheEngines) {
    proto::ScanRequest request;
    request.lidar = true;
    request.vertical_fov = true;
    request.fov_lower = -30;
    request.fov_upper = 20;
    request.channels = 16;
    LidarSpec& spec = request.lidar_spec;
    spec.azimuth_steps = 180;
    spec.returns = 3;
    spec.min_range = 0.05f;
    spec.max_range = 10.0f;
    spec.pose.m = {0, -1, 0, 0.1, 1, 0, 0, -0.2, 0, 0, 1, 0.05, 0, 0, 0, 1};
    LidarSpec engine = spec;
    engine.elevation_deg = lidar_elevations(-30, 20, 16);
    const PointCloud want = scan_lidar(*tree_, engine);
    EXPECT_GT(want.points.size(), 16u * 180u) << "from inside, every beam hits the sphere or box";
    const std::string body = proto::encode_scan_request(request);
    EXPECT_EQ(ok(body, std::string(proto::kPointCloudMediaType)),
              bytes_to_string(proto::encode_point_cloud(want)));
    request.format = proto::ScanFormat::kPly;
    EXPECT_EQ(ok(proto::encode_scan_request(request), std::string(proto::kPlyMediaType)),
              bytes_to_string(proto::encode_point_cloud_ply(want)));
    // "ranges" asks for the compact KDRB record of the same returns; without it, KDRL (above).
    request.format = proto::ScanFormat::kRanges;
    EXPECT_EQ(ok(proto::encode_scan_request(request), std::string(proto::kLidarRangesMediaType)),
              bytes_to_string(proto::encode_lidar_ranges(want)));
    // Elevations given one by one.
    const std::string listed =
        R"({"lidar": {"elevation_deg": [-10, 0, 12.5], "azimuth_steps": 64, "returns": 2}})";
    LidarSpec three;
    three.elevation_deg = {-10, 0, 12.5};
    three.azimuth_steps = 64;
    three.returns = 2;
    EXPECT_EQ(ok(listed, std::string(proto::kPointCloudMediaType)),
              bytes_to_string(proto::encode_point_cloud(scan_lidar(*tree_, three))));
}

proto::Problem expect_field(const httplib::Result& res, int status, const std::string& field,
                            const std::string& words = "") {
    const proto::Problem p = expect_problem(res, status);
    EXPECT_NE(p.detail.find("\"" + field + "\""), std::string::npos) << p.detail;
    EXPECT_NE(p.detail.find(words), std::string::npos) << p.detail;
    return p;
}

TEST_F(HttpScan, ElevationsUpToMaxSensorBeamsAreTakenAndMoreAreRefusedNamingTheField) {
    // lidar.elevation_deg may list max_sensor_beams (20000 here) channels: the documented limit
    // applies, not the request's JSON value bound (16384 before), and a longer list is 413
    // naming the field and max_sensor_beams however long it is (issue 25 item 13).
    proto::ScanRequest request;
    request.lidar = true;
    LidarSpec& spec = request.lidar_spec;
    spec.azimuth_steps = 1;
    for (int i = 0; i < 20000; ++i) spec.elevation_deg.push_back(-60.0f + 0.005f * float(i));
    const PointCloud want = scan_lidar(*tree_, spec);
    // Compared as a bool: a failure would print 400 KiB of points.
    EXPECT_TRUE(ok(proto::encode_scan_request(request), std::string(proto::kPointCloudMediaType)) ==
                bytes_to_string(proto::encode_point_cloud(want)));
    for (const int channels : {20001, 20300, 60000}) {
        SCOPED_TRACE(channels);
        std::string list = "0";
        for (int i = 1; i < channels; ++i) list += ",0";
        const proto::Problem p = expect_field(
            post(R"({"lidar": {"azimuth_steps": 1, "elevation_deg": [)" + list + "]}}"), 413,
            "lidar.elevation_deg", "max_sensor_beams (20000)");
        EXPECT_EQ(p.field, "lidar.elevation_deg");
    }
}

TEST_F(HttpScan, EachErrorNamesItsField) {
    const std::string k =
        R"("intrinsics": {"fx": 10, "fy": 10, "cx": 2, "cy": 2, "width": 4, "height": 4})";
    auto pinhole = [&](const std::string& pose, const std::string& more = "") {
        return R"({"pinhole": {)" + k + R"(, "pose": )" + pose + more + "}}";
    };
    auto lidar = [](const std::string& members) {
        return R"({"lidar": {"azimuth_steps": 16, )" + members + "}}";
    };
    // Not rigid: scaled, sheared, a reflection, a bad last row.
    expect_field(post(pinhole("[[2,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]]")), 400, "pinhole.pose",
                 "not a rigid transform");
    expect_field(post(pinhole("[[1,0.2,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]]")), 400, "pinhole.pose",
                 "orthonormal");
    expect_field(
        post(lidar(R"("elevation_deg": [0], "pose": [[1,0,0,0],[0,1,0,0],[0,0,-1,0],[0,0,0,1]])")),
        400, "lidar.pose", "determinant");
    expect_field(post(pinhole("[[1,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,1,1]]")), 400, "pinhole.pose",
                 "last row");
    expect_field(post(pinhole("[[1,0,0],[0,1,0],[0,0,1]]")), 400, "pinhole.pose", "4 rows");
    // Intrinsics.
    const std::string pose = "[[1,0,0,0],[0,1,0,0],[0,0,1,-5],[0,0,0,1]]";
    expect_field(
        post(
            R"({"pinhole": {"intrinsics": {"fx": 0, "fy": 10, "cx": 2, "cy": 2, "width": 4, "height": 4}, "pose": )" +
            pose + "}}"),
        400, "pinhole.intrinsics.fx", "> 0");
    expect_field(
        post(
            R"({"pinhole": {"intrinsics": {"fx": 1, "fy": -3, "cx": 2, "cy": 2, "width": 4, "height": 4}, "pose": )" +
            pose + "}}"),
        400, "pinhole.intrinsics.fy", "> 0");
    expect_field(
        post(
            R"({"pinhole": {"intrinsics": {"fx": 1, "fy": 1, "cx": 2, "cy": 2, "width": 0, "height": 4}, "pose": )" +
            pose + "}}"),
        400, "pinhole.intrinsics.width");
    expect_field(
        post(
            R"({"pinhole": {"intrinsics": {"fx": 1, "fy": 1, "cx": 2, "cy": 2, "width": 600, "height": 4}, "pose": )" +
            pose + "}}"),
        413, "pinhole.intrinsics.width", "max_image_width");
    expect_field(
        post(
            R"({"pinhole": {"intrinsics": {"fx": 1, "fy": 1, "cx": 2, "cy": 2, "width": 500, "height": 500}, "pose": )" +
            pose + "}}"),
        413, "pinhole.intrinsics.width", "max_scan_points");
    // Range window, output, format.
    expect_field(post(pinhole(pose, R"(, "min_range": 3, "max_range": 2)")), 400,
                 "pinhole.max_range", "greater than min_range");
    expect_field(post(pinhole(pose, R"(, "min_range": -1)")), 400, "pinhole.min_range");
    expect_field(post(pinhole(pose, R"(, "output": "disparity")")), 400, "pinhole.output");
    expect_field(post(R"({"format": "ply", "pinhole": {)" + k + R"(, "pose": )" + pose + "}}"), 400,
                 "format", "expected binary or exr");
    // Look-at camera geometry.
    expect_field(
        post(
            R"({"pinhole": {"camera": {"eye": [0,0,1], "look_at": [0,0,1]}, "width": 4, "height": 4}})"),
        400, "pinhole.camera", "same point");
    expect_field(
        post(
            R"({"pinhole": {"camera": {"eye": [0,0,1], "look_at": [0,0,0], "fov": 180}, "width": 4, "height": 4}})"),
        400, "pinhole.camera", "fov");
    // Lidar: returns 0 and over max_hits_per_ray (8), beams over max_sensor_beams (20000),
    // beams x returns over max_scan_points (100000), channels, elevations, vertical_fov.
    expect_field(post(lidar(R"("elevation_deg": [0], "returns": 0)")), 400, "lidar.returns",
                 "must be in 1 .. 8");
    expect_field(post(lidar(R"("elevation_deg": [0], "returns": 9)")), 413, "lidar.returns",
                 "max_hits_per_ray");
    expect_field(
        post(R"({"lidar": {"vertical_fov": [-10, 10], "channels": 64, "azimuth_steps": 2048}})"),
        413, "lidar.azimuth_steps", "max_sensor_beams");
    expect_field(
        post(
            R"({"lidar": {"vertical_fov": [-10, 10], "channels": 16, "azimuth_steps": 1000, "returns": 8}})"),
        413, "lidar.returns", "max_scan_points");
    expect_field(post(lidar(R"("vertical_fov": [-10, 10], "channels": 0)")), 400, "lidar.channels");
    expect_field(post(lidar(R"("vertical_fov": [10, -10], "channels": 4)")), 400,
                 "lidar.vertical_fov", "lower <= upper");
    expect_field(post(lidar(R"("elevation_deg": [0, 95])")), 400, "lidar.elevation_deg[1]",
                 "[-90, 90]");
    expect_field(post(R"({"lidar": {"elevation_deg": [0], "azimuth_steps": 0}})"), 400,
                 "lidar.azimuth_steps");
    expect_field(post(lidar(R"("elevation_deg": [0], "max_range": 0)")), 400, "lidar.max_range");
    expect_field(post(R"({"lidar": {"elevation_deg": [0], "azimuth_steps": 4}, "format": "exr"})"),
                 400, "format");
    expect_field(post(R"({"pinhole": {}, "lidar": {}})"), 400, "lidar", "exactly one");
    // Not JSON, not a known mesh.
    expect_problem(post("{", id_), 400);
    expect_problem(post(pinhole(pose), id_, "text/plain"), 415);
    expect_problem(post(pinhole(pose), std::string(64, 'a')), 404);
}

}  // namespace
}  // namespace kdrt::test

namespace kdrt::test {
namespace {

TEST(HttpScanBudget, AScanThatCouldNeverFitIs413) {
    TempDir dir;
    ServerProcess server(
        {.cache_dir = dir.path() / "cache", .args = {"--batch-memory-budget", "1M"}});
    const std::string id = upload_id(*server.client(), box_mesh(-1, 1));
    // 200 x 100 pixels x 128 bytes > 1 MiB.
    auto res = server.client()->Post(
        "/v1/meshes/" + id + "/scan",
        R"({"pinhole": {"intrinsics": {"fx": 100, "fy": 100, "cx": 100, "cy": 50, "width": 200, "height": 100}, "pose": [[1,0,0,0],[0,1,0,0],[0,0,1,-5],[0,0,0,1]]}})",
        "application/json");
    const proto::Problem p = expect_problem(res, 413);
    EXPECT_NE(p.detail.find("batch_memory_budget"), std::string::npos) << p.detail;
    EXPECT_EQ(p.limit, 1u << 20);
}

// kdrt-server links no image library: OpenImageIO's ~250 libraries cost every server start half a
// second of CPU. Its encoders are the image module, beside the server in the build tree.
TEST(HttpImageModule, TheServerLinksNoImageLibrary) {
    std::string libs;
    FILE* pipe = ::popen(("ldd '" + std::string(KDRT_SERVER_BINARY) + "' 2>&1").c_str(), "r");
    ASSERT_TRUE(pipe);
    char buf[4096];
    while (std::fgets(buf, sizeof buf, pipe)) libs += buf;
    ::pclose(pipe);
    EXPECT_NE(libs.find("libc.so"), std::string::npos) << libs;
    EXPECT_EQ(libs.find("not found"), std::string::npos) << libs;
    for (const char* image_library : {"OpenImageIO", "libOpenEXR", "libpng", "libjpeg"})
        EXPECT_EQ(libs.find(image_library), std::string::npos) << image_library << " in\n" << libs;
    EXPECT_TRUE(std::filesystem::exists(std::filesystem::path(KDRT_SERVER_BINARY).parent_path() /
                                        "kdrt-image-module.so"));
}

// A server whose image module (kdrt/proto/image_module.h) is missing: the server binary alone in a
// directory. Image answers (PNG and EXR renders, sync and async, and EXR scans) are a problem+json
// naming the module, the paths tried and the OpenImageIO package; every other answer (KDRI renders,
// KDRZ scans, uploads, health) works as usual.
TEST(HttpImageModule, WithoutTheModuleImagesAreAProblemAndTheRestWorks) {
    TempDir dir;
    const std::filesystem::path bin = dir.path() / "bin";
    std::filesystem::create_directories(bin);
    std::filesystem::copy_file(KDRT_SERVER_BINARY, bin / "kdrt-server");
    ServerProcess server({.cache_dir = dir.path() / "cache", .binary = bin / "kdrt-server"});
    ASSERT_TRUE(server.running());
    auto cli = server.client();
    const std::string id = upload_id(*cli, box_mesh(-1, 1));
    ASSERT_FALSE(id.empty());
    const auto expect_no_module = [&](const httplib::Result& res) {
        ASSERT_TRUE(res);
        EXPECT_EQ(res->status, 500) << res->body;
        EXPECT_EQ(res->get_header_value("Content-Type"), "application/problem+json");
        EXPECT_NE(res->body.find("kdrt-image-module.so"), std::string::npos) << res->body;
        EXPECT_NE(res->body.find((bin / "kdrt-image-module.so").string()), std::string::npos)
            << res->body;
        EXPECT_NE(res->body.find("libopenimageio"), std::string::npos) << res->body;
    };
    const std::string render = R"({"mesh":")" + id + R"(","width":16,"height":12)";
    for (const char* format : {"png", "jpg", "exr"})
        expect_no_module(cli->Post("/v1/render", render + R"(,"format":")" + format + R"("})",
                                   "application/json"));
    expect_no_module(cli->Post("/v1/render", httplib::Headers{{"Prefer", "respond-async"}},
                               render + "}", "application/json"));
    auto raw = cli->Post("/v1/render", render + R"(,"format":"raw"})", "application/json");
    ASSERT_TRUE(raw);
    EXPECT_EQ(raw->status, 200) << raw->body;
    EXPECT_EQ(raw->get_header_value("Content-Type"), proto::kRawImageMediaType);

    proto::ScanRequest scan;
    scan.pinhole.intrinsics = {20, 20, 8, 6, 16, 12};
    scan.pinhole.pose.m = {1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, -4, 0, 0, 0, 1};
    const std::string path = "/v1/meshes/" + id + "/scan";
    auto kdrz = cli->Post(path, proto::encode_scan_request(scan), "application/json");
    ASSERT_TRUE(kdrz);
    EXPECT_EQ(kdrz->status, 200) << kdrz->body;
    scan.format = proto::ScanFormat::kExr;
    expect_no_module(cli->Post(path, proto::encode_scan_request(scan), "application/json"));
    // The server is still up and well.
    auto health = cli->Get("/healthz");
    ASSERT_TRUE(health);
    EXPECT_EQ(health->status, 200);
    EXPECT_TRUE(server.running());
}

}  // namespace
}  // namespace kdrt::test
