#pragma once
/// KDRI: a rendered region of a frame as its linear float pixels, before any encoding (the
/// `"format": "raw"` answer of POST /v1/render). A client renders a frame as regions on several
/// servers, places each region's pixels where the header says, and gets exactly the pixels one
/// server renders for the whole frame (the engine's regions stitch bit-exactly), which it can
/// then encode itself. Byte layout and a worked hex example: proto/FORMATS.md.
///
///   offset size field
///        0    4 magic         "KDRI"
///        4    2 version       u16, 1
///        6    2 channels      u16, 3 (RGB) or 4 (RGBA, alpha premultiplied)
///        8    4 width         u32, the region's, >= 1
///       12    4 height        u32, the region's, >= 1
///       16    4 x             u32, the region's left column in the frame
///       20    4 y             u32, the region's top row in the frame
///       24    4 frame width   u32, x + width <= frame width
///       28    4 frame height  u32, y + height <= frame height
///       32    . pixels        f32 x channels per pixel, rows top to bottom, each left to right
///
/// Thread-safe, no shared state; the decoder names the first problem and never throws on bad
/// input (std::bad_alloc aside).

#include <cstddef>
#include <cstdint>
#include <span>
#include <string>
#include <string_view>
#include <vector>

#include "kdrt/image.h"
#include "kdrt/proto/result.h"
#include "kdrt/render_settings.h"

namespace kdrt::proto {

inline constexpr std::string_view kRawImageMagic = "KDRI";
inline constexpr std::string_view kRawImageMediaType = "application/x-kdrt-image";
/// The render request's "format" that asks for a KDRI answer.
inline constexpr std::string_view kRawImageFormatName = "raw";
inline constexpr size_t kRawImageHeaderBytes = 32;
inline constexpr uint16_t kRawImageVersion = 1;

/// A decoded KDRI body: the pixels of `region` of a frame_width x frame_height frame
/// (image.width == region.width, image.height == region.height).
struct RawImage {
    Image image;
    PixelRegion region;
    uint32_t frame_width = 0;
    uint32_t frame_height = 0;
};

/// Size of a KDRI body: 32 + 4 x width x height x channels.
[[nodiscard]] constexpr uint64_t kdri_body_size(uint64_t width, uint64_t height,
                                                uint64_t channels) noexcept {
    return kRawImageHeaderBytes + 4 * width * height * channels;
}

/// Encodes `image`, the pixels of the frame's region at (x, y). Throws std::invalid_argument
/// when the image is malformed (channels not 3 or 4, empty, pixels.size() not matching) or does
/// not lie inside the frame.
[[nodiscard]] std::vector<std::byte> encode_raw_image(const Image& image, uint32_t x, uint32_t y,
                                                      uint32_t frame_width, uint32_t frame_height);

/// Decodes a KDRI body. Checks, in order: size >= 32, magic, version, channels (3 or 4), width
/// and height >= 1, the region inside the frame, width x height <= max_pixels, then the exact
/// size. The error names the field and its value.
[[nodiscard]] Result<RawImage, std::string> decode_raw_image(std::span<const std::byte> body,
                                                             uint64_t max_pixels = uint64_t{1}
                                                                                   << 28);

}  // namespace kdrt::proto
