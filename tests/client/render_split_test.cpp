// In-process tests of the two pieces of Client::render_split that need no server: split_rows
// (the bands a frame or tile is cut into) and stitch_regions (the KDRI answers put back
// together). The split render itself is tested against servers in cli_test.cpp (one server) and
// tests/server/scale_out_test.cpp (three replicas behind nginx).

#include <gtest/gtest.h>

#include <algorithm>
#include <cstring>
#include <numeric>
#include <stdexcept>

#include "kdrt/client/client.h"
#include "kdrt/proto/raw_image.h"

namespace kdrt {
namespace {

/// Checks that `bands` are `parts` bands of whole rows covering `region` exactly, top to
/// bottom, each 1 row or more and the heights within one row of each other (as even as whole
/// rows allow). Rows are counted one by one (the oracle), not by the formula split_rows uses.
void expect_exact_cover(const PixelRegion& region, unsigned parts,
                        const std::vector<PixelRegion>& bands) {
    ASSERT_EQ(bands.size(), parts);
    uint64_t next_row = region.y;
    uint32_t lowest = UINT32_MAX, highest = 0;
    for (unsigned k = 0; k < parts; ++k) {
        SCOPED_TRACE(testing::Message() << "band " << k);
        const PixelRegion& b = bands[k];
        EXPECT_EQ(b.x, region.x);
        EXPECT_EQ(b.width, region.width);
        ASSERT_EQ(b.y, next_row) << "a gap or an overlap above the band";
        ASSERT_GE(b.height, 1u);
        next_row += b.height;
        lowest = std::min(lowest, b.height);
        highest = std::max(highest, b.height);
    }
    EXPECT_EQ(next_row, uint64_t{region.y} + region.height) << "the bands do not end at the bottom";
    EXPECT_LE(highest - lowest, 1u);
}

TEST(SplitRows, BandsCoverTheRegionExactlyTopToBottom) {
    for (const PixelRegion& region :
         {PixelRegion{0, 0, 96, 64}, PixelRegion{10, 5, 50, 33}, PixelRegion{0, 0, 1, 1},
          PixelRegion{3, 7, 2, 17}, PixelRegion{0, 0, 16384, 16384}}) {
        SCOPED_TRACE(testing::Message() << region.width << " x " << region.height << " at "
                                        << region.x << ", " << region.y);
        std::vector<unsigned> counts;
        for (unsigned parts = 1; parts <= std::min(region.height, 40u); ++parts)
            counts.push_back(parts);
        counts.push_back(region.height);  // one band per row
        if (region.height > 2) counts.push_back(region.height - 1);
        for (const unsigned parts : counts) {
            SCOPED_TRACE(testing::Message() << parts << " parts");
            expect_exact_cover(region, parts, split_rows(region, parts));
        }
    }
}

TEST(SplitRows, OnePartIsTheRegionAndOnePartPerRowIsEveryRow) {
    const PixelRegion tile{10, 5, 50, 33};
    EXPECT_EQ(split_rows(tile, 1), std::vector<PixelRegion>{tile});
    const std::vector<PixelRegion> rows = split_rows(tile, 33);
    ASSERT_EQ(rows.size(), 33u);
    for (uint32_t k = 0; k < 33; ++k) EXPECT_EQ(rows[k], (PixelRegion{10, 5 + k, 50, 1}));
    // Band k starts at row floor(k h / parts) of the region (the documented formula).
    const std::vector<PixelRegion> six = split_rows(PixelRegion{0, 0, 96, 64}, 6);
    const uint32_t starts[] = {0, 10, 21, 32, 42, 53};
    for (size_t k = 0; k < 6; ++k) EXPECT_EQ(six[k].y, starts[k]) << "band " << k;
}

TEST(SplitRows, TallRegionsDoNotOverflow) {
    // h * k exceeds 32 bits: the row arithmetic is 64-bit.
    const PixelRegion tall{0, 5, 1, UINT32_MAX - 5};
    for (const unsigned parts : {2u, 3u, 7u, 1000u}) {
        SCOPED_TRACE(parts);
        expect_exact_cover(tall, parts, split_rows(tall, parts));
    }
}

TEST(SplitRows, RefusesZeroPartsAndMorePartsThanRows) {
    const auto message = [](const PixelRegion& region, unsigned parts) -> std::string {
        try {
            (void)split_rows(region, parts);
        } catch (const std::invalid_argument& e) {
            return e.what();
        }
        return "no error";
    };
    EXPECT_EQ(message({0, 0, 96, 64}, 0), "split_rows: 0 parts of 64 rows");
    EXPECT_EQ(message({0, 0, 96, 64}, 65), "split_rows: 65 parts of 64 rows");
    EXPECT_EQ(message({4, 4, 8, 3}, 4), "split_rows: 4 parts of 3 rows");
    EXPECT_EQ(message({0, 0, 8, 0}, 1), "split_rows: 1 parts of 0 rows");
}

/// A frame whose every float is distinct (its index), so a misplaced pixel cannot go unseen.
Image numbered_frame(uint32_t width, uint32_t height, uint32_t channels) {
    Image image{width, height, channels, Pixels(size_t{width} * height * channels)};
    std::iota(image.pixels.begin(), image.pixels.end(), 0.5f);
    return image;
}

/// `region` of `frame`, as a KDRI answer decodes it (encode_raw_image, decode_raw_image).
proto::RawImage answer_of(const Image& frame, const PixelRegion& region) {
    Image part{region.width, region.height, frame.channels, {}};
    for (uint32_t y = 0; y < region.height; ++y) {
        const float* row =
            &frame.pixels[(size_t{region.y + y} * frame.width + region.x) * frame.channels];
        part.pixels.insert(part.pixels.end(), row, row + size_t{region.width} * frame.channels);
    }
    auto decoded = proto::decode_raw_image(
        proto::encode_raw_image(part, region.x, region.y, frame.width, frame.height));
    EXPECT_TRUE(decoded) << decoded.error();
    return decoded ? std::move(*decoded) : proto::RawImage{};
}

/// `within` of `frame`, cut out directly (the oracle of a stitch).
Image crop(const Image& frame, const PixelRegion& within) { return answer_of(frame, within).image; }

void expect_same_image(const Image& got, const Image& want) {
    EXPECT_EQ(got.width, want.width);
    EXPECT_EQ(got.height, want.height);
    EXPECT_EQ(got.channels, want.channels);
    ASSERT_EQ(got.pixels.size(), want.pixels.size());
    EXPECT_EQ(std::memcmp(got.pixels.data(), want.pixels.data(), want.pixels.size() * 4), 0);
}

TEST(StitchRegions, BandsInAnyOrderGiveTheFramesPixels) {
    const Image frame = numbered_frame(96, 64, 3);
    for (const PixelRegion& within : {PixelRegion{0, 0, 96, 64}, PixelRegion{10, 5, 50, 33}}) {
        for (const unsigned parts : {1u, 2u, 6u, within.height}) {
            SCOPED_TRACE(testing::Message()
                         << parts << " parts of " << within.width << " x " << within.height);
            std::vector<proto::RawImage> answers;
            for (const PixelRegion& band : split_rows(within, parts))
                answers.push_back(answer_of(frame, band));
            auto stitched = stitch_regions(within, answers);
            ASSERT_TRUE(stitched) << stitched.error();
            expect_same_image(*stitched, crop(frame, within));
            // Answers arrive in any order; where each goes is in its header.
            std::reverse(answers.begin(), answers.end());
            if (answers.size() > 2) std::swap(answers[0], answers[1]);
            auto shuffled = stitch_regions(within, answers);
            ASSERT_TRUE(shuffled) << shuffled.error();
            expect_same_image(*shuffled, crop(frame, within));
        }
    }
    // Not only bands: any tiling of the rectangle (here 2 x 2 tiles, RGBA).
    const Image rgba = numbered_frame(9, 7, 4);
    std::vector<proto::RawImage> tiles = {
        answer_of(rgba, {0, 0, 4, 3}), answer_of(rgba, {4, 0, 5, 3}), answer_of(rgba, {0, 3, 4, 4}),
        answer_of(rgba, {4, 3, 5, 4})};
    auto stitched = stitch_regions({0, 0, 9, 7}, tiles);
    ASSERT_TRUE(stitched) << stitched.error();
    expect_same_image(*stitched, rgba);
}

/// The error of stitching `parts` into `within`, or "stitched" when it succeeds.
std::string stitch_error(const PixelRegion& within, const std::vector<proto::RawImage>& parts) {
    auto stitched = stitch_regions(within, parts);
    return stitched ? "stitched" : stitched.error();
}

TEST(StitchRegions, ErrorsNameTheRegionAndTheProblem) {
    const Image frame = numbered_frame(96, 64, 3);
    const PixelRegion whole{0, 0, 96, 64};
    std::vector<proto::RawImage> bands;
    for (const PixelRegion& band : split_rows(whole, 4)) bands.push_back(answer_of(frame, band));
    ASSERT_EQ(stitch_error(whole, bands), "stitched");

    EXPECT_EQ(stitch_error(whole, {}), "no regions to stitch");
    EXPECT_EQ(stitch_error({0, 0, 96, 0}, bands), "the stitched rectangle is empty");

    // A band of another frame (a 96 x 60 render): named with its place and both frames.
    auto other_frame = bands;
    other_frame[1] = answer_of(numbered_frame(96, 60, 3), bands[1].region);
    EXPECT_EQ(stitch_error(whole, other_frame),
              "region 1 (96 x 16 at 0, 16) belongs to a 96 x 60 frame, region 0 to a 96 x 64 one");

    // A band with an alpha channel among RGB ones.
    auto channels = bands;
    channels[2] = answer_of(numbered_frame(96, 64, 4), bands[2].region);
    EXPECT_EQ(stitch_error(whole, channels),
              "region 2 (96 x 16 at 0, 32) has 4 channels, region 0 3");

    // A band whose pixels do not match its header's region (a tile of another size).
    auto mismatched = bands;
    mismatched[3].image.height = 15;
    mismatched[3].image.pixels.resize(size_t{96} * 15 * 3);
    EXPECT_EQ(stitch_error(whole, mismatched),
              "region 3 (96 x 16 at 0, 48) holds an image of another size");
    auto short_pixels = bands;
    short_pixels[0].image.pixels.pop_back();
    EXPECT_EQ(stitch_error(whole, short_pixels),
              "region 0 (96 x 16 at 0, 0) holds an image of another size");

    // A band outside the rectangle being stitched.
    EXPECT_EQ(stitch_error({0, 0, 96, 48}, bands),
              "region 3 (96 x 16 at 0, 48) lies outside the 96 x 48 rectangle at 0, 0");
    EXPECT_EQ(stitch_error({1, 0, 95, 64}, bands),
              "region 0 (96 x 16 at 0, 0) lies outside the 95 x 64 rectangle at 1, 0");

    // Overlapping bands: the later one is named, with the first row both cover.
    auto overlapping = bands;
    overlapping[2] = answer_of(frame, {0, 30, 96, 18});
    EXPECT_EQ(stitch_error(whole, overlapping),
              "region 2 (96 x 18 at 0, 30) overlaps another region at row 30");
    auto twice = bands;
    twice.push_back(bands[1]);
    EXPECT_EQ(stitch_error(whole, twice),
              "region 4 (96 x 16 at 0, 16) overlaps another region at row 16");

    // A missing band: the first pixel no band covers.
    auto missing = bands;
    missing.erase(missing.begin() + 2);
    EXPECT_EQ(stitch_error(whole, missing), "no region covers pixel (0, 32)");
    auto narrow = bands;
    narrow[1] = answer_of(frame, {0, 16, 95, 16});
    EXPECT_EQ(stitch_error(whole, narrow), "no region covers pixel (95, 16)");
}

}  // namespace
}  // namespace kdrt
