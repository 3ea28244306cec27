// KDRZ / KDRL / KDRB codecs and the PLY writer: round trips bit for bit, and each decoder refusal
// (header fields, sizes, per-pixel and per-point rules) naming what is wrong.

#include <gtest/gtest.h>

#include <algorithm>
#include <bit>
#include <cmath>
#include <cstring>
#include <limits>
#include <string>

#include "kdrt/proto/scan.h"

namespace kdrt::proto {
namespace {

const float kInf = std::numeric_limits<float>::infinity();

DepthImage sample_image(bool normals) {
    DepthImage image;
    image.width = 3;
    image.height = 2;
    image.kind = DepthKind::kRange;
    image.depth = {1.5f, kInf, 0.0f, 0x1p-140f, 7.25f, kInf};
    image.prim = {3, kNoHit, 0, 0xFFFFFFFEu, 9, kNoHit};
    if (normals) image.normals = {{0, 0, 1}, {}, {1, 0, 0}, {0, -1, 0}, {0.6f, 0.8f, 0}, {}};
    return image;
}

PointCloud sample_cloud() {
    PointCloud cloud;
    cloud.channels = 3;
    cloud.azimuth_steps = 5;
    cloud.returns = 2;
    cloud.points = {LidarPoint{1, 2, 3, 3.5f, 0, 0, 0, 11}, LidarPoint{4, 5, 6, 8.5f, 0, 0, 1, 12},
                    LidarPoint{-1, 0, 2, 2.25f, 2, 0, 0, 1}, LidarPoint{0, 0, 0, 0, 1, 4, 0, 0}};
    return cloud;
}

/// A decoder's refusal with `code` and `words` in its detail.
template <typename T>
void expect_refused(const Result<T, DecodeError>& r, DecodeErrorCode code,
                    const std::string& words) {
    ASSERT_FALSE(r) << "accepted";
    EXPECT_EQ(r.error().code, code) << r.error().to_string();
    EXPECT_NE(r.error().detail.find(words), std::string::npos) << r.error().detail;
}
TEST(ScanCodec, DepthImageRoundTrips) {
    for (const bool normals : {false, true}) {
        const DepthImage image = sample_image(normals);
        const std::vector<std::byte> body = encode_depth_image(image);
        EXPECT_EQ(body.size(), kdrz_body_size(6, normals));
        auto back = decode_depth_image(body);
        ASSERT_TRUE(back) << back.error().to_string();
        EXPECT_EQ(back->width, 3u);
        EXPECT_EQ(back->height, 2u);
        EXPECT_EQ(back->kind, DepthKind::kRange);
        EXPECT_EQ(std::memcmp(back->depth.data(), image.depth.data(), 24), 0);
        EXPECT_EQ(back->prim, image.prim);
        ASSERT_EQ(back->normals.size(), image.normals.size());
        if (normals) {
            EXPECT_EQ(std::memcmp(back->normals.data(), image.normals.data(), 72), 0);
        }
        // Re-encoding gives the same bytes.
        EXPECT_EQ(encode_depth_image(*back), body);
    }
}

TEST(ScanCodec, DepthImageDecoderRefusals) {
    const std::vector<std::byte> good = encode_depth_image(sample_image(true));
    auto edit = [&](size_t at, std::initializer_list<uint8_t> bytes) {
        std::vector<std::byte> b = good;
        for (const uint8_t v : bytes) b[at++] = static_cast<std::byte>(v);
        return b;
    };
    expect_refused(decode_depth_image(std::span(good).first(15)), DecodeErrorCode::kTooShort,
                   "fewer than the 16-byte");
    expect_refused(decode_depth_image(edit(3, {'D'})), DecodeErrorCode::kBadMagic, "KDRZ");
    expect_refused(decode_depth_image(edit(4, {2})), DecodeErrorCode::kBadVersion, "version 2");
    expect_refused(decode_depth_image(edit(6, {4})), DecodeErrorCode::kBadFlags, "0x0004");
    expect_refused(decode_depth_image(edit(8, {0})), DecodeErrorCode::kBadRecord, "0 x 2");
    expect_refused(decode_depth_image(edit(12, {0})), DecodeErrorCode::kBadRecord, "3 x 0");
    expect_refused(decode_depth_image(edit(12, {3})), DecodeErrorCode::kLengthMismatch,
                   "3 x 3 pixels with normals");
    expect_refused(decode_depth_image(good, 5), DecodeErrorCode::kTooManyRays, "6 pixels");
    std::vector<std::byte> longer = good;
    longer.push_back(std::byte{0});
    expect_refused(decode_depth_image(longer), DecodeErrorCode::kLengthMismatch, "body has");
    // Flags say no normals: the body is 72 bytes too long.
    expect_refused(decode_depth_image(edit(6, {1})), DecodeErrorCode::kLengthMismatch, "body has");
    // Pixel 1 (a miss) with a finite depth; pixel 0 with a NaN depth; a negative depth; a miss
    // with a normal; a hit with a NaN normal.
    DepthImage bad = sample_image(true);
    bad.depth[1] = 4.0f;
    expect_refused(decode_depth_image(encode_depth_image(bad)), DecodeErrorCode::kBadRecord,
                   "pixel (1, 0): a miss");
    bad = sample_image(true);
    bad.depth[0] = NAN;
    expect_refused(decode_depth_image(encode_depth_image(bad)), DecodeErrorCode::kBadRecord,
                   "pixel (0, 0): a hit");
    bad = sample_image(true);
    bad.depth[4] = -1.0f;
    expect_refused(decode_depth_image(encode_depth_image(bad)), DecodeErrorCode::kBadRecord,
                   "pixel (1, 1)");
    bad = sample_image(true);
    bad.normals[5] = {0, 0, 1};
    expect_refused(decode_depth_image(encode_depth_image(bad)), DecodeErrorCode::kBadRecord,
                   "pixel (2, 1): a miss");
    bad = sample_image(true);
    bad.normals[3].y = kInf;
    expect_refused(decode_depth_image(encode_depth_image(bad)), DecodeErrorCode::kBadRecord,
                   "pixel (0, 1): a hit");
}

TEST(ScanCodec, PointCloudRoundTrips) {
    const PointCloud cloud = sample_cloud();
    const std::vector<std::byte> body = encode_point_cloud(cloud);
    EXPECT_EQ(body.size(), kdrl_body_size(4));
    auto back = decode_point_cloud(body);
    ASSERT_TRUE(back) << back.error().to_string();
    EXPECT_EQ(back->channels, 3u);
    EXPECT_EQ(back->azimuth_steps, 5u);
    EXPECT_EQ(back->returns, 2u);
    ASSERT_EQ(back->points.size(), 4u);
    EXPECT_EQ(std::memcmp(back->points.data(), cloud.points.data(), 4 * sizeof(LidarPoint)), 0);
    EXPECT_EQ(encode_point_cloud(*back), body);
    PointCloud empty = cloud;
    empty.points.clear();
    EXPECT_TRUE(decode_point_cloud(encode_point_cloud(empty))) << "no returns is valid";
}

TEST(ScanCodec, PointCloudDecoderRefusals) {
    const std::vector<std::byte> good = encode_point_cloud(sample_cloud());
    auto edit = [&](size_t at, std::initializer_list<uint8_t> bytes) {
        std::vector<std::byte> b = good;
        for (const uint8_t v : bytes) b[at++] = static_cast<std::byte>(v);
        return b;
    };
    expect_refused(decode_point_cloud(std::span(good).first(31)), DecodeErrorCode::kTooShort,
                   "32-byte KDRL");
    expect_refused(decode_point_cloud(edit(0, {'K', 'D', 'R', 'D'})), DecodeErrorCode::kBadMagic,
                   "\"KDRD\"");
    expect_refused(decode_point_cloud(edit(4, {0})), DecodeErrorCode::kBadVersion, "version 0");
    expect_refused(decode_point_cloud(edit(6, {1})), DecodeErrorCode::kBadFlags, "0x0001");
    expect_refused(decode_point_cloud(edit(8, {5})), DecodeErrorCode::kLengthMismatch, "5 points");
    expect_refused(decode_point_cloud(edit(12, {0})), DecodeErrorCode::kBadRecord, "channels 0");
    expect_refused(decode_point_cloud(edit(16, {0})), DecodeErrorCode::kBadRecord,
                   "azimuth_steps 0");
    expect_refused(decode_point_cloud(edit(20, {0})), DecodeErrorCode::kBadRecord, "returns 0");
    expect_refused(decode_point_cloud(edit(28, {1})), DecodeErrorCode::kBadReserved, "reserved");
    expect_refused(decode_point_cloud(good, 3), DecodeErrorCode::kTooManyRays, "4 points");
    auto bad_point = [&](auto change, const std::string& words) {
        PointCloud c = sample_cloud();
        change(c);
        expect_refused(decode_point_cloud(encode_point_cloud(c)), DecodeErrorCode::kBadRecord,
                       words);
    };
    bad_point([](PointCloud& c) { c.points[1].y = NAN; }, "point 1: x, y and z must be finite");
    bad_point([](PointCloud& c) { c.points[2].range = -1; }, "point 2: range");
    bad_point([](PointCloud& c) { c.points[0].range = kInf; }, "point 0: range");
    bad_point([](PointCloud& c) { c.points[3].channel = 3; }, "point 3: channel 3 >= channels 3");
    bad_point([](PointCloud& c) { c.points[3].azimuth_index = 5; }, "point 3: azimuth_index 5");
    bad_point([](PointCloud& c) { c.points[1].return_index = 2; }, "point 1: return_index 2 >=");
    bad_point([](PointCloud& c) { c.points[2].prim = kNoHit; }, "point 2: prim 0xffffffff");
    // Out of order: beam (2, 0) before beam (0, 0); a beam's returns not 0, 1, ...
    bad_point([](PointCloud& c) { std::swap(c.points[0], c.points[2]); }, "comes after");
    bad_point([](PointCloud& c) { c.points[1].return_index = 0; }, "point 1: return_index 0 out");
    bad_point([](PointCloud& c) { c.points[2].return_index = 1; }, "point 2: return_index 1 out");
}

TEST(ScanCodec, LidarRangesCarryEachReturnsRangeBeamAndPrim) {
    const PointCloud cloud = sample_cloud();
    const std::vector<std::byte> body = encode_lidar_ranges(cloud);
    EXPECT_EQ(body.size(), kdrb_body_size(4));
    EXPECT_EQ(body.size(), 32u + 12u * 4u);
    std::vector<std::byte> written(body.size() + 5);
    EXPECT_EQ(write_lidar_ranges(written, cloud), body.size());
    EXPECT_TRUE(std::equal(body.begin(), body.end(), written.begin()));
    auto back = decode_lidar_ranges(body);
    ASSERT_TRUE(back) << back.error().to_string();
    EXPECT_EQ(back->channels, 3u);
    EXPECT_EQ(back->azimuth_steps, 5u);
    EXPECT_EQ(back->returns, 2u);
    ASSERT_EQ(back->points.size(), cloud.points.size());
    // Every KDRL field is the KDRB record's or implied by it: channel and azimuth_index by the
    // beam, return_index by the place among the beam's records.
    uint32_t place = 0;
    for (size_t i = 0; i < cloud.points.size(); ++i) {
        SCOPED_TRACE(i);
        const LidarPoint& q = cloud.points[i];
        const LidarRange& r = back->points[i];
        EXPECT_EQ(std::memcmp(&r.range, &q.range, 4), 0);
        EXPECT_EQ(r.prim, q.prim);
        EXPECT_EQ(r.beam % back->channels, q.channel);
        EXPECT_EQ(r.beam / back->channels, q.azimuth_index);
        place = i > 0 && r.beam == back->points[i - 1].beam ? place + 1 : 0;
        EXPECT_EQ(place, q.return_index);
    }
    PointCloud empty = cloud;
    empty.points.clear();
    auto none = decode_lidar_ranges(encode_lidar_ranges(empty));
    ASSERT_TRUE(none) << "no returns is valid";
    EXPECT_TRUE(none->points.empty());
    // Old decoders refuse the new magic rather than misread it.
    EXPECT_FALSE(decode_point_cloud(body));
}

TEST(ScanCodec, LidarRangesDecoderRefusals) {
    const std::vector<std::byte> good = encode_lidar_ranges(sample_cloud());
    auto edit = [&](size_t at, std::initializer_list<uint8_t> bytes) {
        std::vector<std::byte> b = good;
        for (const uint8_t v : bytes) b[at++] = static_cast<std::byte>(v);
        return b;
    };
    auto record = [&](size_t i, size_t field, uint32_t value) {
        std::vector<std::byte> b = good;
        std::memcpy(b.data() + 32 + 12 * i + 4 * field, &value, 4);
        return b;
    };
    expect_refused(decode_lidar_ranges(std::span(good).first(31)), DecodeErrorCode::kTooShort,
                   "32-byte KDRB");
    expect_refused(decode_lidar_ranges(encode_point_cloud(sample_cloud())),
                   DecodeErrorCode::kBadMagic, "\"KDRL\", expected \"KDRB\"");
    expect_refused(decode_lidar_ranges(edit(4, {2})), DecodeErrorCode::kBadVersion, "version 2");
    expect_refused(decode_lidar_ranges(edit(7, {1})), DecodeErrorCode::kBadFlags, "0x0100");
    expect_refused(decode_lidar_ranges(edit(8, {5})), DecodeErrorCode::kLengthMismatch, "5 points");
    expect_refused(decode_lidar_ranges(edit(12, {0})), DecodeErrorCode::kBadRecord, "channels 0");
    expect_refused(decode_lidar_ranges(edit(16, {0})), DecodeErrorCode::kBadRecord,
                   "azimuth_steps 0");
    expect_refused(decode_lidar_ranges(edit(20, {0})), DecodeErrorCode::kBadRecord, "returns 0");
    expect_refused(decode_lidar_ranges(edit(12, {1, 0, 1, 0, 0, 0, 1, 0})),
                   DecodeErrorCode::kBadRecord, "at most 2^32");
    expect_refused(decode_lidar_ranges(edit(24, {1})), DecodeErrorCode::kBadReserved, "reserved");
    expect_refused(decode_lidar_ranges(good, 3), DecodeErrorCode::kTooManyRays, "4 points");
    const auto bits = [](float f) { return std::bit_cast<uint32_t>(f); };
    expect_refused(decode_lidar_ranges(record(1, 0, bits(NAN))), DecodeErrorCode::kBadRecord,
                   "point 1: range must be finite");
    expect_refused(decode_lidar_ranges(record(2, 0, bits(-1.0f))), DecodeErrorCode::kBadRecord,
                   "point 2: range");
    expect_refused(decode_lidar_ranges(record(0, 0, bits(kInf))), DecodeErrorCode::kBadRecord,
                   "point 0: range");
    expect_refused(decode_lidar_ranges(record(3, 1, 15)), DecodeErrorCode::kBadRecord,
                   "point 3: beam 15 >= channels x azimuth_steps 15");
    expect_refused(decode_lidar_ranges(record(2, 2, kNoHit)), DecodeErrorCode::kBadRecord,
                   "point 2: prim 0xffffffff");
    // Beams out of order; a beam with more records than returns.
    expect_refused(decode_lidar_ranges(record(1, 1, 5)), DecodeErrorCode::kBadRecord,
                   "point 2: beam 2 comes after a later beam");
    expect_refused(decode_lidar_ranges(record(2, 1, 0)), DecodeErrorCode::kBadRecord,
                   "point 2: beam 0 has more than returns 2 records");
}

TEST(ScanCodec, PlyIsTheRecordsAfterABinaryHeader) {
    const PointCloud cloud = sample_cloud();
    const std::vector<std::byte> ply = encode_point_cloud_ply(cloud);
    const std::string text(reinterpret_cast<const char*>(ply.data()), ply.size());
    const std::string end = "end_header\n";
    const size_t body = text.find(end);
    ASSERT_NE(body, std::string::npos);
    const std::string header = text.substr(0, body + end.size());
    EXPECT_EQ(header.rfind("ply\nformat binary_little_endian 1.0\n", 0), 0u);
    EXPECT_NE(header.find("\nelement vertex 4\n"), std::string::npos);
    EXPECT_NE(header.find("\ncomment channels 3\n"), std::string::npos);
    EXPECT_NE(header.find("property float x\nproperty float y\nproperty float z\nproperty float "
                          "range\nproperty uint channel\nproperty uint azimuth_index\nproperty "
                          "uint return_index\nproperty uint prim\n"),
              std::string::npos);
    ASSERT_EQ(ply.size(), header.size() + 4 * kLidarPointBytes);
    const std::vector<std::byte> kdrl = encode_point_cloud(cloud);
    EXPECT_EQ(std::memcmp(ply.data() + header.size(), kdrl.data() + kPointCloudHeaderBytes,
                          4 * kLidarPointBytes),
              0);
}

TEST(ScanCodec, PlyWithGeometryIdsAppendsOnePropertyPerVertex) {
    const PointCloud cloud = sample_cloud();
    const std::vector<uint32_t> geoms = {7, 0, 0xFFFFFFFEu, 3};
    const std::vector<std::byte> ply = encode_point_cloud_ply(cloud, geoms);
    const std::string text(reinterpret_cast<const char*>(ply.data()), ply.size());
    const std::string end = "end_header\n";
    const size_t body = text.find(end);
    ASSERT_NE(body, std::string::npos);
    const std::string header = text.substr(0, body + end.size());
    EXPECT_NE(header.find("property uint prim\nproperty uint geometry_id\nend_header\n"),
              std::string::npos)
        << header;
    const size_t stride = kLidarPointBytes + 4;
    ASSERT_EQ(ply.size(), header.size() + 4 * stride);
    const std::vector<std::byte> kdrl = encode_point_cloud(cloud);
    for (size_t i = 0; i < 4; ++i) {
        const std::byte* vertex = ply.data() + header.size() + i * stride;
        EXPECT_EQ(std::memcmp(vertex, kdrl.data() + kPointCloudHeaderBytes + i * kLidarPointBytes,
                              kLidarPointBytes),
                  0)
            << i;
        uint32_t geom = 0;
        std::memcpy(&geom, vertex + kLidarPointBytes, 4);
        EXPECT_EQ(geom, geoms[i]) << i;
    }
    // Without ids, the header and records are the mesh scan's.
    EXPECT_EQ(encode_point_cloud_ply(cloud, {}), encode_point_cloud_ply(cloud));
}

}  // namespace
}  // namespace kdrt::proto
