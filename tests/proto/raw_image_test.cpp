// KDRI codec: round trips (bit-exact floats, NaN and -0 included), the header fields, and each
// decoder refusal naming its field; the encoder's preconditions.

#include "kdrt/proto/raw_image.h"

#include <gtest/gtest.h>

#include <bit>
#include <cstring>
#include <functional>
#include <limits>
#include <stdexcept>
#include <string>

namespace kdrt::proto {
namespace {

Image sample(uint32_t width, uint32_t height, uint32_t channels) {
    Image image{width, height, channels, {}};
    for (uint32_t i = 0; i < width * height * channels; ++i)
        image.pixels.push_back(static_cast<float>(i) * 0.375f - 2.0f);
    return image;
}

void put_u32(std::vector<std::byte>& body, size_t at, uint32_t v) {
    for (int b = 0; b < 4; ++b) body[at + b] = static_cast<std::byte>(v >> (8 * b));
}

TEST(RawImage, RoundTripsEveryBitAndWhereTheTileLies) {
    Image image = sample(5, 3, 4);
    image.pixels[0] = std::numeric_limits<float>::quiet_NaN();
    image.pixels[1] = -0.0f;
    image.pixels[2] = std::numeric_limits<float>::infinity();
    const auto body = encode_raw_image(image, 2, 7, 10, 10);
    ASSERT_EQ(body.size(), kdri_body_size(5, 3, 4));
    EXPECT_EQ(std::memcmp(body.data(), "KDRI", 4), 0);
    auto back = decode_raw_image(body);
    ASSERT_TRUE(back) << back.error();
    EXPECT_EQ(back->region, (PixelRegion{2, 7, 5, 3}));
    EXPECT_EQ(back->frame_width, 10u);
    EXPECT_EQ(back->frame_height, 10u);
    EXPECT_EQ(back->image.width, 5u);
    EXPECT_EQ(back->image.height, 3u);
    EXPECT_EQ(back->image.channels, 4u);
    ASSERT_EQ(back->image.pixels.size(), image.pixels.size());
    for (size_t i = 0; i < image.pixels.size(); ++i)
        EXPECT_EQ(std::bit_cast<uint32_t>(back->image.pixels[i]),
                  std::bit_cast<uint32_t>(image.pixels[i]))
            << i;
    // A whole RGB frame.
    auto rgb = decode_raw_image(encode_raw_image(sample(1, 1, 3), 0, 0, 1, 1));
    ASSERT_TRUE(rgb) << rgb.error();
    EXPECT_EQ(rgb->image.pixels, sample(1, 1, 3).pixels);
}

TEST(RawImage, DecoderRefusalsNameTheField) {
    const auto good = encode_raw_image(sample(2, 2, 3), 1, 1, 4, 3);
    struct Case {
        const char* name;
        std::function<void(std::vector<std::byte>&)> damage;
        const char* phrase;
    };
    const Case cases[] = {
        {"short", [](auto& b) { b.resize(31); }, "shorter than its 32-byte header"},
        {"magic", [](auto& b) { b[3] = std::byte{'X'}; }, "bad magic"},
        {"version", [](auto& b) { b[4] = std::byte{2}; }, "KDRI version 2, expected 1"},
        {"channels", [](auto& b) { b[6] = std::byte{2}; }, "KDRI channels 2, expected 3 or 4"},
        {"empty", [](auto& b) { put_u32(b, 8, 0); }, "region is empty (0 x 2)"},
        {"outside x", [](auto& b) { put_u32(b, 16, 3); }, "is not inside the 4 x 3 frame"},
        {"outside y", [](auto& b) { put_u32(b, 28, 2); }, "is not inside the 4 x 2 frame"},
        {"wrapping", [](auto& b) { put_u32(b, 16, 0xFFFFFFFFu); }, "is not inside"},
        {"too long", [](auto& b) { b.push_back(std::byte{0}); }, "but the body has 81 bytes"},
        {"too short", [](auto& b) { b.pop_back(); }, "(80 bytes) but the body has 79 bytes"},
    };
    for (const Case& c : cases) {
        SCOPED_TRACE(c.name);
        auto body = good;
        c.damage(body);
        auto decoded = decode_raw_image(body);
        ASSERT_FALSE(decoded);
        EXPECT_NE(decoded.error().find(c.phrase), std::string::npos) << decoded.error();
    }
    // The pixel limit is checked before the size (and before anything is allocated).
    auto huge = good;
    put_u32(huge, 8, 60000);
    put_u32(huge, 12, 60000);
    put_u32(huge, 16, 0);
    put_u32(huge, 20, 0);
    put_u32(huge, 24, 60000);
    put_u32(huge, 28, 60000);
    auto refused = decode_raw_image(huge, 1000);
    ASSERT_FALSE(refused);
    EXPECT_NE(refused.error().find("3600000000 pixels exceeds the limit of 1000"),
              std::string::npos)
        << refused.error();
}

TEST(RawImage, EncoderRefusesMalformedImagesAndTilesOutsideTheFrame) {
    EXPECT_THROW((void)encode_raw_image(sample(2, 2, 2), 0, 0, 2, 2), std::invalid_argument);
    EXPECT_THROW((void)encode_raw_image(Image{0, 2, 3, {}}, 0, 0, 2, 2), std::invalid_argument);
    Image short_pixels = sample(2, 2, 3);
    short_pixels.pixels.pop_back();
    EXPECT_THROW((void)encode_raw_image(short_pixels, 0, 0, 2, 2), std::invalid_argument);
    EXPECT_THROW((void)encode_raw_image(sample(2, 2, 3), 1, 0, 2, 2), std::invalid_argument);
    EXPECT_THROW((void)encode_raw_image(sample(2, 2, 3), 0, 0xFFFFFFFFu, 2, 2),
                 std::invalid_argument);
}

}  // namespace
}  // namespace kdrt::proto
