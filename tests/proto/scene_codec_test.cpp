// KDRX pose batches and the geometry-id plane of scene answers (kdrt/proto/scene.h).

#include <gtest/gtest.h>

#include <cmath>
#include <cstring>
#include <limits>
#include <stdexcept>

#include "kdrt/proto/distance.h"
#include "kdrt/proto/multi_hit.h"
#include "kdrt/proto/ray_batch.h"
#include "kdrt/proto/scan.h"
#include "kdrt/proto/scene.h"

namespace kdrt::proto {
namespace {

std::vector<PoseEntry> two_poses() {
    std::vector<PoseEntry> poses(2);
    poses[0].geometry_id = 7;
    poses[0].transform.m = {0, -1, 0, 1.5f, 1, 0, 0, -2, 0, 0, 1, 1e-3f};
    poses[1].geometry_id = 0;
    return poses;
}

TEST(PoseBatch, RoundTripsAndNamesTheFirstNonFiniteEntry) {
    const auto poses = two_poses();
    const auto body = encode_pose_batch(poses);
    ASSERT_EQ(body.size(), 16 + 2 * kPoseRecordBytes);
    auto back = decode_pose_batch(body);
    ASSERT_TRUE(back.ok()) << back.error().detail;
    ASSERT_EQ(back->size(), 2u);
    EXPECT_EQ((*back)[0].geometry_id, 7u);
    EXPECT_EQ((*back)[0].transform, poses[0].transform);
    EXPECT_EQ((*back)[1].transform, Transform{});

    auto nan = body;
    const float q = std::numeric_limits<float>::quiet_NaN();
    std::memcpy(nan.data() + 16 + kPoseRecordBytes + 4 + 4 * 6, &q, 4);  // pose 1, entry [1][2]
    auto e = decode_pose_batch(nan);
    ASSERT_FALSE(e.ok());
    EXPECT_EQ(e.error().code, DecodeErrorCode::kNonFiniteRay);
    EXPECT_EQ(e.error().detail, "pose 1: transform[1][2] is NaN");

    e = decode_pose_batch(body, SceneLimits{1});
    ASSERT_FALSE(e.ok());
    EXPECT_EQ(e.error().code, DecodeErrorCode::kTooManyRays);
    e = decode_pose_batch(std::span(body).first(body.size() - 1));
    ASSERT_FALSE(e.ok());
    EXPECT_EQ(e.error().code, DecodeErrorCode::kLengthMismatch);
    auto magic = body;
    magic[3] = std::byte{'H'};
    EXPECT_EQ(decode_pose_batch(magic).error().code, DecodeErrorCode::kBadMagic);
}

/// Appends a plane to `body`, splits it again and checks the mesh body comes back unchanged.
void round_trip(const std::vector<std::byte>& body, const std::vector<uint32_t>& ids) {
    auto scene = body;
    append_geometry_ids(scene, ids);
    ASSERT_EQ(scene.size(), body.size() + 4 * ids.size());
    EXPECT_NE(std::memcmp(scene.data(), body.data(), 8), 0) << "flag bit 8 set";
    auto split = split_geometry_ids(scene);
    ASSERT_TRUE(split.ok()) << split.error().detail;
    EXPECT_EQ(split->mesh_body, body);
    EXPECT_EQ(split->geometry_ids, ids);
    // Only the first 16 bytes: too short for the plane (or the header), refused.
    EXPECT_FALSE(split_geometry_ids(std::span(scene).first(16)).ok());
    // A mesh answer without the flag is not a scene answer.
    auto plain = split_geometry_ids(body);
    ASSERT_FALSE(plain.ok());
    EXPECT_EQ(plain.error().code, DecodeErrorCode::kBadFlags);
}

TEST(GeometryIds, EveryAnswerFormatCarriesAPlane) {
    const std::vector<Hit> hits = {Hit{5, 7, 0.25f, 0.5f}, Hit{}};
    round_trip(encode_hits(hits), {3, kNoGeometry});

    const std::vector<uint64_t> offsets = {0, 2, 2};
    const std::vector<uint32_t> counts = {3, 0};
    const std::vector<Hit> multi = {Hit{1, 3, 0.25f, 0.5f}, Hit{2, 0, 0, 0.5f}};
    MultiHitsView view;
    view.max_hits = 2;
    view.offsets = offsets;
    view.counts = counts;
    view.hits = multi;
    round_trip(encode_multi_hits(view), {1, 0});

    std::vector<ClosestPoint> closest(2);
    closest[0] = {2, 4, 0.25f, 0.25f, {0.25f, 0.25f, 0}, Feature::kFace, Side::kOutside};
    round_trip(encode_distances(closest, true), {9, kNoGeometry});

    DepthImage depth;
    depth.width = 2;
    depth.height = 1;
    depth.depth = {2.0f, std::numeric_limits<float>::infinity()};
    depth.prim = {4, kNoHit};
    round_trip(encode_depth_image(depth), {2, kNoGeometry});

    PointCloud cloud;
    cloud.channels = 2;
    cloud.azimuth_steps = 4;
    cloud.returns = 2;
    cloud.points = {LidarPoint{2, 0, 0, 2, 1, 0, 0, 7}, LidarPoint{0, 3, 0, 3, 1, 1, 0, 2}};
    round_trip(encode_point_cloud(cloud), {5, 6});
}

TEST(GeometryIds, AScanWrittenInPlaceIsTheEncodedAnswerByteForByte) {
    PointCloud cloud;
    cloud.channels = 2;
    cloud.azimuth_steps = 4;
    cloud.returns = 2;
    cloud.points = {LidarPoint{2, 0, 0, 2, 1, 0, 0, 7}, LidarPoint{0, 3, 0, 3, 1, 1, 0, 2},
                    LidarPoint{-1, 0.5f, 2, 2.3f, 0, 3, 0, 11}};
    const std::vector<uint32_t> ids = {5, 6, kNoGeometry};
    std::vector<std::byte> want = encode_point_cloud(cloud);
    append_geometry_ids(want, ids);
    // Into a larger buffer full of other bytes (a pooled one is not cleared).
    std::vector<std::byte> out(want.size() + 5, std::byte{0xAB});
    const size_t mesh = write_point_cloud(out, cloud);
    EXPECT_EQ(mesh, kdrl_body_size(cloud.points.size()));
    EXPECT_EQ(write_geometry_ids(out, mesh, ids), want.size());
    out.resize(want.size());
    EXPECT_EQ(out, want);
    // No room: refused, never written past the end.
    std::vector<std::byte> small(want.size() - 1);
    EXPECT_THROW(static_cast<void>(write_geometry_ids(small, mesh, ids)), std::length_error);
    small.resize(mesh - 1);
    EXPECT_THROW(static_cast<void>(write_point_cloud(small, cloud)), std::length_error);
}

TEST(GeometryIds, RefusesOtherMagicsAndShortBodies) {
    auto rays = encode_rays(std::vector<Ray>(1), false);
    auto e = split_geometry_ids(rays);
    ASSERT_FALSE(e.ok());
    EXPECT_EQ(e.error().code, DecodeErrorCode::kBadMagic);
    e = split_geometry_ids(std::span(rays).first(3));
    ASSERT_FALSE(e.ok());
    EXPECT_EQ(e.error().code, DecodeErrorCode::kTooShort);
    // A header that claims more records than the limit is refused before the size is used.
    auto hits = encode_hits(std::vector<Hit>(2));
    append_geometry_ids(hits, std::vector<uint32_t>{0, 0});
    DecodeLimits limits;
    limits.max_rays = 1;
    e = split_geometry_ids(hits, limits);
    ASSERT_FALSE(e.ok());
    EXPECT_EQ(e.error().code, DecodeErrorCode::kTooManyRays);
}

}  // namespace
}  // namespace kdrt::proto
