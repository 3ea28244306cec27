// proto/FORMATS.md: every hex dump in the document is exactly what the codecs produce for the
// content it describes, in document order (KDRR, KDRH, KDRO, KDRM, KDRC, KDRP, KDRD, KDRI, KDRZ,
// KDRL, KDRB, KDRX, a scene's KDRH, KDRS, raw mesh, binary STL, tree blob), and the tree blob's
// checksum follows the documented algorithm.

#include <gtest/gtest.h>

#include <algorithm>
#include <bit>
#include <cctype>
#include <cstring>
#include <sstream>

#include "kdrt/kdtree.h"
#include "kdrt/proto/distance.h"
#include "kdrt/proto/file_io.h"
#include "kdrt/proto/mesh_io.h"
#include "kdrt/proto/multi_hit.h"
#include "kdrt/proto/raw_image.h"
#include "kdrt/proto/ray_batch.h"
#include "kdrt/proto/scan.h"
#include "kdrt/proto/scene.h"
#include "kdrt/serialize.h"

namespace kdrt {
namespace {

struct Dump {
    size_t line = 0;  ///< line of the opening fence, for messages
    std::vector<std::byte> bytes;
};

bool is_hex_byte(std::string_view token) {
    return token.size() == 2 && std::isxdigit(static_cast<unsigned char>(token[0])) &&
           std::isxdigit(static_cast<unsigned char>(token[1]));
}

/// The hex dumps of a Markdown text: fenced blocks whose lines are "OFFSET  b b b b  b ... notes".
/// The byte columns end at the first run of three spaces; offsets must count the bytes so far.
std::vector<Dump> hex_dumps(const std::string& markdown) {
    std::vector<Dump> dumps;
    std::istringstream in(markdown);
    std::string line;
    size_t number = 0;
    bool in_block = false;
    Dump current;
    while (std::getline(in, line)) {
        ++number;
        if (line.rfind("```", 0) == 0) {
            if (in_block && !current.bytes.empty()) dumps.push_back(current);
            in_block = !in_block;
            current = Dump{number, {}};
            continue;
        }
        if (!in_block || line.size() < 6 || line.substr(4, 2) != "  ") continue;
        const std::string offset = line.substr(0, 4);
        if (!std::all_of(offset.begin(), offset.end(),
                         [](unsigned char c) { return std::isxdigit(c); }))
            continue;
        EXPECT_EQ(std::stoul(offset, nullptr, 16), current.bytes.size())
            << "FORMATS.md line " << number;
        const size_t notes = line.find("   ", 6);
        std::istringstream columns(
            line.substr(6, notes == std::string::npos ? std::string::npos : notes - 6));
        for (std::string token; columns >> token;) {
            EXPECT_TRUE(is_hex_byte(token))
                << "FORMATS.md line " << number << ": \"" << token << "\"";
            current.bytes.push_back(static_cast<std::byte>(std::stoul(token, nullptr, 16)));
        }
    }
    return dumps;
}

std::string hex(std::span<const std::byte> bytes) {
    std::string out;
    char buf[4];
    for (size_t i = 0; i < bytes.size(); ++i) {
        std::snprintf(buf, sizeof buf, "%02x", static_cast<unsigned>(bytes[i]));
        if (i > 0) out.push_back(i % 16 == 0 ? '\n' : ' ');
        out += buf;
    }
    return out;
}

/// The checksum exactly as FORMATS.md describes it.
uint64_t documented_checksum(std::span<const std::byte> data) {
    uint64_t h = 0x9E3779B97F4A7C15ull ^ data.size();
    size_t i = 0;
    const auto mix = [&](uint64_t w) {
        h = std::rotl(h ^ (w * 0xC2B2AE3D27D4EB4Full), 31) * 0x9E3779B97F4A7C15ull;
    };
    for (; i + 8 <= data.size(); i += 8) {
        uint64_t w = 0;
        for (int b = 7; b >= 0; --b)
            w = (w << 8) | static_cast<uint64_t>(data[i + static_cast<size_t>(b)]);
        mix(w);
    }
    uint64_t tail = 0;
    for (size_t b = data.size(); b-- > i;) tail = (tail << 8) | static_cast<uint64_t>(data[b]);
    mix(tail);
    h ^= h >> 33;
    h *= 0xFF51AFD7ED558CCDull;
    h ^= h >> 33;
    return h;
}

TEST(FormatsDoc, HexExamplesAreWhatTheCodecsWrite) {
    auto text = proto::read_file_bytes(std::string(KDRT_SOURCE_DIR) + "/proto/FORMATS.md");
    ASSERT_TRUE(text) << text.error();
    const std::vector<Dump> dumps =
        hex_dumps(std::string(reinterpret_cast<const char*>(text->data()), text->size()));

    const float inf = std::numeric_limits<float>::infinity();
    const std::vector<Ray> rays = {Ray{0, 0, -5, 0, 0, 0, 1, 100},
                                   Ray{1, 2, 3, 0.5f, -1, 0, 0, inf}};
    const std::vector<Hit> hits = {Hit{5, 7, 0.25f, 0.5f}, Hit{}};
    const std::vector<uint64_t> multi_offsets = {0, 2, 2};
    const std::vector<uint32_t> multi_counts = {3, 0};
    const std::vector<Hit> multi_hits = {Hit{1, 3, 0.25f, 0.5f}, Hit{2, 0, 0, 0.5f}};
    proto::MultiHitsView multi_view;
    multi_view.max_hits = 2;
    multi_view.offsets = multi_offsets;
    multi_view.counts = multi_counts;
    multi_view.hits = multi_hits;
    const Image tile{2, 1, 3, {0.5f, 0.25f, 1.0f, 0.0f, 1.0f, 0.125f}};
    Mesh triangle;
    triangle.positions = {0, 0, 0, 1, 0, 0, 0, 1, 0};
    triangle.indices = {0, 1, 2};
    const std::vector<Vec3> query_points = {{0.25f, 0.25f, 2}, {5, 0, 0}};
    std::vector<ClosestPoint> closest(2);
    closest[0] = {2, 4, 0.25f, 0.25f, {0.25f, 0.25f, 0}, Feature::kFace, Side::kOutside};
    DepthImage depth;
    depth.width = 2;
    depth.height = 1;
    depth.depth = {2.0f, inf};
    depth.prim = {4, kNoHit};
    depth.normals = {{0, 0, -1}, {0, 0, 0}};
    PointCloud cloud;
    cloud.channels = 2;
    cloud.azimuth_steps = 4;
    cloud.returns = 2;
    cloud.points = {LidarPoint{2, 0, 0, 2, 1, 0, 0, 7}, LidarPoint{0, 3, 0, 3, 1, 1, 0, 2}};
    std::vector<proto::PoseEntry> poses(1);
    poses[0].geometry_id = 2;
    poses[0].transform.m = {0, -1, 0, 1, 1, 0, 0, 2, 0, 0, 1, 3};
    proto::SceneDocument stored_scene;
    stored_scene.id = "0123456789abcdef0123456789abcdef";
    stored_scene.revision = 3;
    stored_scene.instances = {{"9f86d081884c7d659a2feaa0c55ad015a3bf4f1b2b0b822cd15d6c15b0f00a08",
                               proto::Transform{{0, -1, 0, 1, 1, 0, 0, 2, 0, 0, 1, 3}}, "car"}};
    std::vector<std::byte> scene_hits = proto::encode_hits(hits);
    proto::append_geometry_ids(scene_hits, std::vector<uint32_t>{3, kNoHit});
    KdTree tree = build_kdtree(triangle);
    tree.stats.build_ms = 0;
    const std::vector<std::pair<std::string, std::vector<std::byte>>> expected = {
        {"KDRR", proto::encode_rays(rays, false)},
        {"KDRH", proto::encode_hits(hits)},
        {"KDRO", proto::encode_occlusion(std::vector<uint8_t>{1, 0})},
        {"KDRM", proto::encode_multi_hits(multi_view)},
        {"KDRC", proto::encode_hit_counts(multi_counts)},
        {"KDRP", proto::encode_points(query_points)},
        {"KDRD", proto::encode_distances(closest, true)},
        {"KDRI", proto::encode_raw_image(tile, 1, 0, 3, 2)},
        {"KDRZ", proto::encode_depth_image(depth)},
        {"KDRL", proto::encode_point_cloud(cloud)},
        {"KDRB", proto::encode_lidar_ranges(cloud)},
        {"KDRX", proto::encode_pose_batch(poses)},
        {"KDRH with geometry ids", scene_hits},
        {"KDRS", proto::encode_scene_file(stored_scene)},
        {"raw mesh", proto::write_mesh(triangle, proto::MeshFormat::kRaw)},
        {"binary STL", proto::write_mesh(triangle, proto::MeshFormat::kStl)},
        {"tree blob", serialize_tree(tree)},
    };
    ASSERT_EQ(dumps.size(), expected.size()) << "one hex dump per binary format, in this order";
    for (size_t i = 0; i < expected.size(); ++i) {
        SCOPED_TRACE(expected[i].first + ", FORMATS.md line " + std::to_string(dumps[i].line));
        EXPECT_EQ(hex(dumps[i].bytes), hex(expected[i].second));
    }
    const std::vector<std::byte>& blob = dumps.back().bytes;
    ASSERT_GE(blob.size(), 8u);
    uint64_t stored = 0;
    for (size_t b = 8; b-- > 0;)
        stored = (stored << 8) | static_cast<uint64_t>(blob[blob.size() - 8 + b]);
    EXPECT_EQ(stored, documented_checksum(std::span(blob).first(blob.size() - 8)));
    // And the documented bytes load as the tree they describe.
    const KdTree loaded = deserialize_tree(blob);
    EXPECT_EQ(loaded.nodes, tree.nodes);
    EXPECT_EQ(loaded.bounds, tree.bounds);
}

}  // namespace
}  // namespace kdrt
