#pragma once
/// Rendered images (kdrt::Image, linear float RGB/RGBA) <-> PNG, JPEG and OpenEXR, in memory and
/// on disk, through OpenImageIO. Part of kdrt_proto_image, the only target that links OIIO, so
/// programs that never touch image files do not load it.
///
/// Colour: Image values are linear. PNG and JPEG store 8-bit sRGB: each colour channel is clamped
/// to [0, 1] (NaN -> 0), encoded with the sRGB transfer function (IEC 61966-2-1: 12.92 c below
/// 0.0031308, else 1.055 c^(1/2.4) - 0.055) and rounded to the nearest of 256 levels; alpha is
/// clamped and quantised linearly (ImageEncodeOptions::transfer kData stores colour that way too,
/// for images of data rather than light). EXR keeps linear values as half or float. Decoding
/// inverts this: 8-bit sRGB comes back as linear float (exactly the value of the sRGB level), EXR
/// as stored.
///
/// Every function is thread-safe and returns errors instead of throwing (except std::bad_alloc).

#include <cstddef>
#include <cstdint>
#include <filesystem>
#include <optional>
#include <span>
#include <string>
#include <string_view>
#include <vector>

#include "kdrt/image.h"
#include "kdrt/proto/image_format.h"
#include "kdrt/proto/result.h"

namespace kdrt::proto {

/// Fixed phrases image errors are built from, so tests and callers match on them (the pixel cap
/// uses errors::kLimitExceeded from kdrt/proto/errors.h).
namespace image_errors {
inline constexpr std::string_view kUnknownMagic = "not a PNG, JPEG or OpenEXR image";
inline constexpr std::string_view kTruncatedPng = "PNG is truncated";
inline constexpr std::string_view kUnknownExtension = "cannot tell the image format";
}  // namespace image_errors

/// Encodes `image` (3 or 4 channels, width and height >= 1, pixels.size() matching) as a whole
/// file in memory. PNG and EXR keep an alpha channel; JPEG has none and drops it. Errors name the
/// problem: a malformed Image, a bad option, or OpenImageIO's message.
[[nodiscard]] Result<std::vector<std::byte>, std::string> encode_image(
    const Image& image, ImageFormat format, const ImageEncodeOptions& options = {});

/// encode_image, written to `path` (created or truncated). `format` defaults to the one the
/// extension names (an unknown extension is an error naming the path).
[[nodiscard]] Result<void, std::string> write_image_file(
    const std::filesystem::path& path, const Image& image,
    std::optional<ImageFormat> format = std::nullopt, const ImageEncodeOptions& options = {});

/// Caps checked from the header, before the pixels are decoded.
struct ImageDecodeLimits {
    uint64_t max_pixels = uint64_t{1} << 28;  ///< width * height
};

/// Decodes a PNG, JPEG or EXR file held in memory (the format comes from the magic bytes) into a
/// linear float Image with its channel count (1 .. 4; grey stays 1 channel). Only the first
/// subimage is read. Untrusted input: errors, never crashes, for truncated or malformed data.
[[nodiscard]] Result<Image, std::string> decode_image(std::span<const std::byte> bytes,
                                                      const ImageDecodeLimits& limits = {});

/// Reads and decodes an image file. Errors name the path.
[[nodiscard]] Result<Image, std::string> read_image_file(const std::filesystem::path& path,
                                                         const ImageDecodeLimits& limits = {});

/// The 8-bit sRGB level of a linear value: round(255 * srgb_oetf(clamp(value, 0, 1))), NaN -> 0.
[[nodiscard]] uint8_t linear_to_srgb8(float value) noexcept;

/// The linear value of an 8-bit sRGB level (the sRGB EOTF, correctly rounded to float).
[[nodiscard]] float srgb8_to_linear(uint8_t level) noexcept;

}  // namespace kdrt::proto
