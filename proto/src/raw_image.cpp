// KDRI: a rendered region's linear float pixels (kdrt/proto/raw_image.h, proto/FORMATS.md).

#include "kdrt/proto/raw_image.h"

#include <cstring>
#include <stdexcept>

#include "byte_io.h"

namespace kdrt::proto {
namespace {

/// "" when a width x height region at (x, y) lies inside the frame, else why not.
std::string region_problem(uint64_t x, uint64_t y, uint64_t width, uint64_t height,
                           uint64_t frame_width, uint64_t frame_height) {
    if (x + width > frame_width || y + height > frame_height)
        return "region " + std::to_string(width) + " x " + std::to_string(height) + " at (" +
               std::to_string(x) + ", " + std::to_string(y) + ") is not inside the " +
               std::to_string(frame_width) + " x " + std::to_string(frame_height) + " frame";
    return {};
}

}  // namespace

std::vector<std::byte> encode_raw_image(const Image& image, uint32_t x, uint32_t y,
                                        uint32_t frame_width, uint32_t frame_height) {
    if ((image.channels != 3 && image.channels != 4) || image.width == 0 || image.height == 0 ||
        image.pixels.size() != uint64_t{image.width} * image.height * image.channels)
        throw std::invalid_argument("encode_raw_image: a malformed image");
    if (std::string problem =
            region_problem(x, y, image.width, image.height, frame_width, frame_height);
        !problem.empty())
        throw std::invalid_argument("encode_raw_image: " + problem);
    std::vector<std::byte> out(kdri_body_size(image.width, image.height, image.channels));
    std::byte* p = out.data();
    std::memcpy(p, kRawImageMagic.data(), 4);
    detail::store_le16(p + 4, kRawImageVersion);
    detail::store_le16(p + 6, static_cast<uint16_t>(image.channels));
    detail::store_le32(p + 8, image.width);
    detail::store_le32(p + 12, image.height);
    detail::store_le32(p + 16, x);
    detail::store_le32(p + 20, y);
    detail::store_le32(p + 24, frame_width);
    detail::store_le32(p + 28, frame_height);
    // Little-endian host (byte_io.h): the floats are their own wire bytes.
    std::memcpy(p + kRawImageHeaderBytes, image.pixels.data(), image.pixels.size() * 4);
    return out;
}

Result<RawImage, std::string> decode_raw_image(std::span<const std::byte> body,
                                               uint64_t max_pixels) {
    if (body.size() < kRawImageHeaderBytes)
        return Err{"KDRI image of " + std::to_string(body.size()) + " bytes is shorter than its " +
                   std::to_string(kRawImageHeaderBytes) + "-byte header"};
    const std::byte* p = body.data();
    if (std::memcmp(p, kRawImageMagic.data(), 4) != 0)
        return Err{std::string("not a KDRI image (bad magic, expected \"KDRI\")")};
    if (const uint16_t version = detail::load_le16(p + 4); version != kRawImageVersion)
        return Err{"KDRI version " + std::to_string(version) + ", expected " +
                   std::to_string(kRawImageVersion)};
    const uint16_t channels = detail::load_le16(p + 6);
    if (channels != 3 && channels != 4)
        return Err{"KDRI channels " + std::to_string(channels) + ", expected 3 or 4"};
    RawImage out;
    out.region = PixelRegion{detail::load_le32(p + 16), detail::load_le32(p + 20),
                             detail::load_le32(p + 8), detail::load_le32(p + 12)};
    out.frame_width = detail::load_le32(p + 24);
    out.frame_height = detail::load_le32(p + 28);
    const PixelRegion& r = out.region;
    if (r.width == 0 || r.height == 0)
        return Err{"KDRI region is empty (" + std::to_string(r.width) + " x " +
                   std::to_string(r.height) + ")"};
    if (std::string problem =
            region_problem(r.x, r.y, r.width, r.height, out.frame_width, out.frame_height);
        !problem.empty())
        return Err{"KDRI " + problem};
    const uint64_t pixels = uint64_t{r.width} * r.height;
    if (pixels > max_pixels)
        return Err{"KDRI region of " + std::to_string(pixels) + " pixels exceeds the limit of " +
                   std::to_string(max_pixels)};
    const uint64_t expected = kdri_body_size(r.width, r.height, channels);
    if (body.size() != expected)
        return Err{"KDRI header says " + std::to_string(r.width) + " x " +
                   std::to_string(r.height) + " x " + std::to_string(channels) + " floats (" +
                   std::to_string(expected) + " bytes) but the body has " +
                   std::to_string(body.size()) + " bytes"};
    out.image.width = r.width;
    out.image.height = r.height;
    out.image.channels = channels;
    out.image.pixels.resize(static_cast<size_t>(pixels) * channels);
    std::memcpy(out.image.pixels.data(), p + kRawImageHeaderBytes, out.image.pixels.size() * 4);
    return out;
}

}  // namespace kdrt::proto
