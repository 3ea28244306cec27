// Depth images as EXR: every channel comes back bit for bit through decode_depth_exr, and read
// with OpenImageIO directly the file has the documented channel names and types.

#include <OpenImageIO/filesystem.h>
#include <OpenImageIO/imageio.h>
#include <gtest/gtest.h>

#include <algorithm>
#include <cstring>
#include <limits>

#include "kdrt/proto/scan_image.h"

namespace kdrt::proto {
namespace {

DepthImage sample(bool normals, DepthKind kind) {
    DepthImage image;
    image.width = 3;
    image.height = 2;
    image.kind = kind;
    const float inf = std::numeric_limits<float>::infinity();
    image.depth = {1.5f, inf, 0.0f, 0x1p-140f, 7.25f, 123456.789f};
    image.prim = {3, kNoHit, 0, 0xFFFFFFFEu, 9, 70000};
    if (normals)
        image.normals = {{0, 0, 1}, {}, {1, 0, 0}, {0, -1, 0}, {0.6f, 0.8f, 0}, {0, 0, -1}};
    return image;
}

/// The header of an EXR in memory, read with OpenImageIO directly.
bool spec_of(const std::vector<std::byte>& bytes, OIIO::ImageSpec& spec) {
    OIIO::Filesystem::IOMemReader proxy(bytes.data(), bytes.size());
    OIIO::ImageSpec config;
    OIIO::Filesystem::IOProxy* p = &proxy;
    config.attribute("oiio:ioproxy", OIIO::TypeDesc::PTR, &p);
    auto in = OIIO::ImageInput::create("x.exr", false, &config, &proxy);
    return in && in->open("x.exr", spec, config);
}

TEST(ScanExr, RoundTripsBitForBit) {
    for (const bool normals : {false, true}) {
        for (const DepthKind kind : {DepthKind::kDepth, DepthKind::kRange}) {
            const DepthImage image = sample(normals, kind);
            auto bytes = encode_depth_exr(image);
            ASSERT_TRUE(bytes) << bytes.error();
            auto back = decode_depth_exr(*bytes);
            ASSERT_TRUE(back) << back.error();
            EXPECT_EQ(back->width, 3u);
            EXPECT_EQ(back->height, 2u);
            EXPECT_EQ(back->kind, kind);
            EXPECT_EQ(std::memcmp(back->depth.data(), image.depth.data(), 24), 0);
            EXPECT_EQ(back->prim, image.prim);
            ASSERT_EQ(back->normals.size(), image.normals.size());
            if (normals) {
                EXPECT_EQ(std::memcmp(back->normals.data(), image.normals.data(), 72), 0);
            }
        }
    }
}

TEST(ScanExr, ChannelsAsDocumented) {
    auto bytes = encode_depth_exr(sample(true, DepthKind::kDepth));
    ASSERT_TRUE(bytes) << bytes.error();
    OIIO::ImageSpec spec;
    ASSERT_TRUE(spec_of(*bytes, spec));
    ASSERT_EQ(spec.nchannels, 5);
    std::vector<std::string> names(spec.channelnames.begin(), spec.channelnames.end());
    std::sort(names.begin(), names.end());
    EXPECT_EQ(names, (std::vector<std::string>{"N.X", "N.Y", "N.Z", "Z", "prim"}));
    for (int c = 0; c < spec.nchannels; ++c) {
        const auto want = spec.channelnames[static_cast<size_t>(c)] == "prim"
                              ? OIIO::TypeDesc::UINT
                              : OIIO::TypeDesc::FLOAT;
        EXPECT_EQ(spec.channelformat(c), want) << spec.channelnames[static_cast<size_t>(c)];
    }
    EXPECT_EQ(spec.get_string_attribute("kdrt:depth_kind"), "depth");
}

TEST(ScanExr, GeometryIdChannelIsLastAndRoundTrips) {
    const DepthImage image = sample(true, DepthKind::kRange);
    const std::vector<uint32_t> geoms = {0, kNoHit, 5, 0xFFFFFFFEu, 1, 70000};
    auto bytes = encode_depth_exr(image, geoms);
    ASSERT_TRUE(bytes) << bytes.error();
    std::vector<uint32_t> back_geoms = {42};
    auto back = decode_depth_exr(*bytes, 1ull << 28, &back_geoms);
    ASSERT_TRUE(back) << back.error();
    EXPECT_EQ(back_geoms, geoms);
    EXPECT_EQ(back->prim, image.prim);
    EXPECT_EQ(std::memcmp(back->depth.data(), image.depth.data(), 24), 0);
    // Read with OpenImageIO directly: a sixth channel "geometry_id", uint, last.
    OIIO::ImageSpec spec;
    ASSERT_TRUE(spec_of(*bytes, spec));
    ASSERT_EQ(spec.nchannels, 6);
    std::vector<std::string> names(spec.channelnames.begin(), spec.channelnames.end());
    EXPECT_NE(std::find(names.begin(), names.end(), "geometry_id"), names.end());
    // Without the plane the channel is absent, and the decoder leaves the vector empty.
    auto plain = encode_depth_exr(image);
    ASSERT_TRUE(plain);
    ASSERT_TRUE(decode_depth_exr(*plain, 1ull << 28, &back_geoms));
    EXPECT_TRUE(back_geoms.empty());
    // A plane of another size is refused.
    EXPECT_FALSE(encode_depth_exr(image, std::vector<uint32_t>(5, 0)));
}

TEST(ScanExr, RefusalsNameTheProblem) {
    const std::vector<std::byte> junk(100, std::byte{7});
    auto r = decode_depth_exr(junk);
    ASSERT_FALSE(r);
    EXPECT_NE(r.error().find("cannot"), std::string::npos) << r.error();
    auto bytes = encode_depth_exr(sample(false, DepthKind::kRange));
    ASSERT_TRUE(bytes);
    auto capped = decode_depth_exr(*bytes, 5);
    ASSERT_FALSE(capped);
    EXPECT_NE(capped.error().find("6 pixels"), std::string::npos) << capped.error();
    DepthImage bad = sample(false, DepthKind::kDepth);
    bad.prim.pop_back();
    EXPECT_FALSE(encode_depth_exr(bad));
}

}  // namespace
}  // namespace kdrt::proto
