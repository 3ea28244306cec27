// The scan request JSON: what each member parses to, encode/decode round trips, and each refusal
// naming its field (unknown members, types, both or neither sensor, limits as over_limit).

#include <gtest/gtest.h>

#include <cmath>
#include <string>

#include "kdrt/proto/scan.h"

namespace kdrt::proto {
namespace {

const char* kPinhole = R"({"pinhole": {"intrinsics": {"fx": 525, "fy": 520.5, "cx": 319.5,
    "cy": 239.5, "width": 640, "height": 480},
    "pose": [[1,0,0,0.5],[0,1,0,0],[0,0,1,-2],[0,0,0,1]], "output": "range", "normals": true,
    "min_range": 0.25, "max_range": 100}, "format": "exr"})";

const char* kLidar = R"({"lidar": {"vertical_fov": [-25, 15], "channels": 64,
    "azimuth_steps": 2048, "returns": 3, "min_range": 0.5,
    "pose": [[1,0,0,0],[0,1,0,0],[0,0,1,1.7],[0,0,0,1]]}, "format": "ply"})";

TEST(ScanJson, PinholeMembers) {
    auto r = decode_scan_request(kPinhole);
    ASSERT_TRUE(r) << r.error().field << ": " << r.error().detail;
    EXPECT_FALSE(r->lidar);
    EXPECT_FALSE(r->look_at);
    const PinholeSpec& s = r->pinhole;
    EXPECT_EQ(s.intrinsics.fx, 525.0);
    EXPECT_EQ(s.intrinsics.fy, 520.5);
    EXPECT_EQ(s.intrinsics.cx, 319.5);
    EXPECT_EQ(s.intrinsics.width, 640u);
    EXPECT_EQ(s.intrinsics.height, 480u);
    EXPECT_EQ(s.pose.m[3], 0.5);
    EXPECT_EQ(s.pose.m[11], -2.0);
    EXPECT_EQ(s.kind, DepthKind::kRange);
    EXPECT_TRUE(s.normals);
    EXPECT_EQ(s.min_range, 0.25f);
    EXPECT_EQ(s.max_range, 100.0f);
    EXPECT_EQ(r->format, ScanFormat::kExr);
    auto back = decode_scan_request(encode_scan_request(*r));
    ASSERT_TRUE(back) << back.error().detail;
    EXPECT_EQ(back->pinhole.pose.m, s.pose.m);
    EXPECT_EQ(back->pinhole.intrinsics.fy, 520.5);
    EXPECT_EQ(back->pinhole.max_range, 100.0f);
    EXPECT_EQ(encode_scan_request(*back), encode_scan_request(*r));
}

TEST(ScanJson, LookAtCameraAndDefaults) {
    auto r = decode_scan_request(
        R"({"pinhole": {"camera": {"eye": [0, 0, 3], "look_at": [0, 0, 0]}, "width": 64,
            "height": 48}})");
    ASSERT_TRUE(r) << r.error().detail;
    EXPECT_TRUE(r->look_at);
    EXPECT_EQ(r->camera.eye.z, 3.0f);
    EXPECT_EQ(r->camera.up.y, 1.0f);
    EXPECT_EQ(r->camera.fov_deg, 40.0f);
    EXPECT_EQ(r->camera_width, 64u);
    EXPECT_EQ(r->camera_height, 48u);
    EXPECT_EQ(r->pinhole.kind, DepthKind::kDepth);
    EXPECT_FALSE(r->pinhole.normals);
    EXPECT_EQ(r->pinhole.min_range, 0.0f);
    EXPECT_TRUE(std::isinf(r->pinhole.max_range));
    EXPECT_EQ(r->format, ScanFormat::kBinary);
    auto back = decode_scan_request(encode_scan_request(*r));
    ASSERT_TRUE(back) << back.error().detail;
    EXPECT_TRUE(back->look_at);
    EXPECT_EQ(back->camera_height, 48u);
}

TEST(ScanJson, LidarMembers) {
    auto r = decode_scan_request(kLidar);
    ASSERT_TRUE(r) << r.error().detail;
    EXPECT_TRUE(r->lidar);
    EXPECT_TRUE(r->vertical_fov);
    EXPECT_EQ(r->fov_lower, -25.0);
    EXPECT_EQ(r->fov_upper, 15.0);
    EXPECT_EQ(r->channels, 64u);
    EXPECT_TRUE(r->lidar_spec.elevation_deg.empty()) << "filled by the caller";
    EXPECT_EQ(r->lidar_spec.azimuth_steps, 2048u);
    EXPECT_EQ(r->lidar_spec.returns, 3u);
    EXPECT_EQ(r->lidar_spec.min_range, 0.5f);
    EXPECT_EQ(r->lidar_spec.pose.m[11], 1.7);
    EXPECT_EQ(r->format, ScanFormat::kPly);
    auto back = decode_scan_request(encode_scan_request(*r));
    ASSERT_TRUE(back) << back.error().detail;
    EXPECT_EQ(encode_scan_request(*back), encode_scan_request(*r));

    auto e =
        decode_scan_request(R"({"lidar": {"elevation_deg": [-2, 0.5, 3], "azimuth_steps": 8}})");
    ASSERT_TRUE(e) << e.error().detail;
    EXPECT_EQ(e->lidar_spec.elevation_deg, (std::vector<double>{-2, 0.5, 3}));
    EXPECT_EQ(e->lidar_spec.returns, 1u);
    EXPECT_EQ(e->lidar_spec.pose.m, Pose{}.m);
    EXPECT_EQ(e->format, ScanFormat::kBinary);
    auto eb = decode_scan_request(encode_scan_request(*e));
    ASSERT_TRUE(eb) << eb.error().detail;
    EXPECT_EQ(eb->lidar_spec.elevation_deg, e->lidar_spec.elevation_deg);

    // "ranges" asks for the compact KDRB record (a lidar only), and round trips.
    auto ranges = decode_scan_request(
        R"({"lidar": {"elevation_deg": [0], "azimuth_steps": 8}, "format": "ranges"})");
    ASSERT_TRUE(ranges) << ranges.error().detail;
    EXPECT_EQ(ranges->format, ScanFormat::kRanges);
    auto rb = decode_scan_request(encode_scan_request(*ranges));
    ASSERT_TRUE(rb) << rb.error().detail;
    EXPECT_EQ(rb->format, ScanFormat::kRanges);
}

void expect_error(const std::string& body, const std::string& field, const std::string& words,
                  bool over_limit = false, const ScanLimits& limits = {}) {
    auto r = decode_scan_request(body, limits);
    ASSERT_FALSE(r) << "accepted: " << body;
    EXPECT_EQ(r.error().field, field) << r.error().detail;
    EXPECT_NE(r.error().detail.find(words), std::string::npos) << r.error().detail;
    EXPECT_EQ(r.error().over_limit, over_limit) << r.error().detail;
}

TEST(ScanJson, EachRefusalNamesItsField) {
    const std::string pose = R"("pose": [[1,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]])";
    const std::string k =
        R"("intrinsics": {"fx": 10, "fy": 10, "cx": 2, "cy": 2, "width": 4, "height": 4})";
    expect_error("{", "", "invalid JSON");
    expect_error("[]", "request", "must be an object");
    expect_error("{}", "pinhole", "exactly one");
    expect_error(R"({"pinhole": {}, "lidar": {}})", "lidar", "exactly one");
    expect_error(R"({"pinhole": {)" + k + "," + pose + R"(}, "colour": 1})", "colour",
                 "unknown member \"colour\"");
    expect_error(R"({"pinhole": {)" + k + "," + pose + R"(, "fov": 3}})", "pinhole.fov",
                 "unknown member \"pinhole.fov\"");
    expect_error(R"({"pinhole": {)" + pose + "}}", "pinhole.intrinsics", "missing member");
    expect_error(R"({"pinhole": {)" + k + "}}", "pinhole.pose", "missing member");
    // A pose beyond the float range (a translation of 1e39) is refused naming the field.
    expect_error(
        R"({"pinhole": {)" + k + R"(, "pose": [[1,0,0,1e39],[0,1,0,0],[0,0,1,0],[0,0,0,1]]}})",
        "pinhole.pose", "row 0 column 3 is outside the range of a float");
    expect_error(R"({"lidar": {"elevation_deg": [0], "azimuth_steps": 4, )"
                 R"("pose": [[1,0,0,0],[0,1,0,0],[0,0,-4e38,0],[0,0,0,1]]}})",
                 "lidar.pose", "row 2 column 2 is outside the range of a float");
    expect_error(
        R"({"pinhole": {"intrinsics": {"fy": 1, "cx": 1, "cy": 1, "width": 1, "height": 1},)" +
            pose + "}}",
        "pinhole.intrinsics.fx", "missing member");
    expect_error(
        R"({"pinhole": {"intrinsics": {"fx": "a", "fy": 1, "cx": 1, "cy": 1, "width": 1, "height": 1},)" +
            pose + "}}",
        "pinhole.intrinsics.fx", "must be a number");
    expect_error(
        R"({"pinhole": {"intrinsics": {"fx": 1, "fy": 1, "cx": 1, "cy": 1, "width": 0, "height": 1},)" +
            pose + "}}",
        "pinhole.intrinsics.width", "must be in 1 .. 8192");
    expect_error(
        R"({"pinhole": {"intrinsics": {"fx": 1, "fy": 1, "cx": 1, "cy": 1, "width": 9000, "height": 1},)" +
            pose + "}}",
        "pinhole.intrinsics.width", "max_image_width", true);
    expect_error(
        R"({"pinhole": {"intrinsics": {"fx": 1, "fy": 1, "cx": 1, "cy": 1, "width": 3, "height": -1},)" +
            pose + "}}",
        "pinhole.intrinsics.height", "non-negative integer");
    expect_error(
        R"({"pinhole": {"intrinsics": {"fx": 1, "fy": 1, "cx": 1, "cy": 1, "width": 100, "height": 100},)" +
            pose + "}}",
        "pinhole.intrinsics.width", "max_scan_points", true, ScanLimits{.max_points = 9999});
    expect_error(R"({"pinhole": {)" + k + R"(, "pose": [[1,0,0],[0,1,0],[0,0,1]]}})",
                 "pinhole.pose", "4 rows of 4 numbers");
    expect_error(R"({"pinhole": {)" + k + "," + pose + R"(, "output": "z"}})", "pinhole.output",
                 "expected depth or range");
    expect_error(R"({"pinhole": {)" + k + "," + pose + R"(, "normals": 1}})", "pinhole.normals",
                 "true or false");
    expect_error(R"({"pinhole": {)" + k + "," + pose + R"(, "min_range": "0"}})",
                 "pinhole.min_range", "must be a number");
    expect_error(R"({"pinhole": {)" + k + "," + pose + R"(, "max_range": 1e300}})",
                 "pinhole.max_range", "range of a float");
    expect_error(R"({"pinhole": {)" + k + "," + pose + R"(}, "format": "ply"})", "format",
                 "expected binary or exr");
    expect_error(R"({"pinhole": {)" + k + "," + pose + R"(}, "format": "ranges"})", "format",
                 "unknown format \"ranges\" for a pinhole scan");
    expect_error(R"({"pinhole": {"camera": {"eye": [0,0,1], "look_at": [0,0,0]}, )" + k + "}}",
                 "pinhole.intrinsics", "not both");
    expect_error(R"({"pinhole": {"camera": {"eye": [0,0,1]}, "width": 2, "height": 2}})",
                 "pinhole.camera.look_at", "missing member");
    expect_error(
        R"({"pinhole": {"camera": {"eye": [0,0], "look_at": [0,0,0]}, "width": 2, "height": 2}})",
        "pinhole.camera.eye", "3 numbers");
    expect_error(R"({"pinhole": {"camera": {"eye": [0,0,1], "look_at": [0,0,0]}, "height": 2}})",
                 "pinhole.width", "missing member");
    expect_error(R"({"pinhole": {)" + k + "," + pose + R"(, "width": 3}})", "pinhole.width",
                 "goes with");

    expect_error(R"({"lidar": {"azimuth_steps": 8}})", "lidar.vertical_fov", "missing member");
    expect_error(R"({"lidar": {"elevation_deg": [], "azimuth_steps": 8}})", "lidar.elevation_deg",
                 "non-empty array");
    expect_error(R"({"lidar": {"elevation_deg": [1, "x"], "azimuth_steps": 8}})",
                 "lidar.elevation_deg[1]", "must be a number");
    expect_error(R"({"lidar": {"elevation_deg": [1], "channels": 3, "azimuth_steps": 8}})",
                 "lidar.channels", "not both");
    expect_error(R"({"lidar": {"vertical_fov": [1], "channels": 3, "azimuth_steps": 8}})",
                 "lidar.vertical_fov", "[lower, upper]");
    expect_error(R"({"lidar": {"vertical_fov": [-1, 1], "azimuth_steps": 8}})", "lidar.channels",
                 "missing member");
    expect_error(R"({"lidar": {"vertical_fov": [-1, 1], "channels": 0, "azimuth_steps": 8}})",
                 "lidar.channels", "must be in 1 ..");
    expect_error(R"({"lidar": {"vertical_fov": [-1, 1], "channels": 4}})", "lidar.azimuth_steps",
                 "missing member");
    expect_error(R"({"lidar": {"vertical_fov": [-1, 1], "channels": 4, "azimuth_steps": 0}})",
                 "lidar.azimuth_steps", "must be in 1 ..");
    expect_error(R"({"lidar": {"vertical_fov": [-1, 1], "channels": 64, "azimuth_steps": 2048}})",
                 "lidar.azimuth_steps", "131072 beams exceeds the limit", true,
                 ScanLimits{.max_beams = 100000});
    expect_error(
        R"({"lidar": {"vertical_fov": [-1, 1], "channels": 4, "azimuth_steps": 8, "returns": 0}})",
        "lidar.returns", "must be in 1 .. 1024");
    expect_error(
        R"({"lidar": {"vertical_fov": [-1, 1], "channels": 4, "azimuth_steps": 8, "returns": 1025}})",
        "lidar.returns", "max_hits_per_ray", true);
    expect_error(
        R"({"lidar": {"vertical_fov": [-1, 1], "channels": 4, "azimuth_steps": 8, "returns": 4}})",
        "lidar.returns", "max_scan_points", true, ScanLimits{.max_points = 100});
    expect_error(
        R"({"lidar": {"vertical_fov": [-1, 1], "channels": 4, "azimuth_steps": 8, "pose": 1}})",
        "lidar.pose", "4 rows");
    expect_error(
        R"({"lidar": {"vertical_fov": [-1, 1], "channels": 4, "azimuth_steps": 8}, "format": "exr"})",
        "format", "expected binary, ply or ranges");
    expect_error(
        R"({"lidar": {"vertical_fov": [-1, 1], "channels": 4, "azimuth_steps": 8, "azimuth_steps": 9}})",
        "", "duplicate member");
}

}  // namespace
}  // namespace kdrt::proto
