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
#include "kdrt/proto/result.h"
#include "kdrt/render_settings.h"

namespace kdrt::proto {

/// Fixed phrases image errors are built from, so tests and callers match on them (the pixel cap
/// uses errors::kLimitExceeded from kdrt/proto/errors.h).
namespace image_errors {
inline constexpr std::string_view kUnknownMagic = "not a PNG, JPEG or OpenEXR image";
inline constexpr std::string_view kTruncatedPng = "PNG is truncated";
inline constexpr std::string_view kUnknownExtension = "cannot tell the image format";
}  // namespace image_errors

/// kRaw is KDRI (kdrt/proto/raw_image.h): the linear float pixels themselves, not an image file
/// format (no OIIO). encode_image writes it as a whole frame; decode_image reads it.
enum class ImageFormat { kPng, kJpeg, kExr, kRaw };

/// "png", "jpeg" or "jpg", "exr", "raw" (exact, lower case) -> format; anything else -> nullopt.
[[nodiscard]] std::optional<ImageFormat> image_format_from_name(std::string_view name) noexcept;

/// Format from the file extension, case-insensitive: .png, .jpg/.jpeg, .exr; else nullopt (also
/// for .raw, a raw mesh's extension).
[[nodiscard]] std::optional<ImageFormat> image_format_from_path(const std::filesystem::path& path);

/// "png", "jpeg", "exr" or "raw".
[[nodiscard]] std::string_view image_format_name(ImageFormat format) noexcept;

/// The HTTP media type: "image/png", "image/jpeg", "image/x-exr", "application/x-kdrt-image".
[[nodiscard]] std::string_view image_media_type(ImageFormat format) noexcept;

/// Sample type of an EXR file.
enum class ExrPixelType { kHalf, kFloat };

/// Largest ImageEncodeOptions::png_compression (zlib's best compression).
inline constexpr int kMaxPngCompression = 9;

/// How PNG and JPEG turn a colour value into an 8-bit level.
enum class EightBitTransfer {
    /// Light (radiance): the sRGB transfer function, what a display expects of a photograph.
    kSrgb,
    /// Data (a fraction, a normal, a false colour): level = round(255 x value), no curve, so a
    /// value of 0.5 shows as the middle grey level 128. Decoding such a file as sRGB does not
    /// give the value back; decode_image always assumes kSrgb.
    kData,
};

struct ImageEncodeOptions {
    /// PNG and JPEG only (EXR always stores the linear values exactly).
    EightBitTransfer transfer = EightBitTransfer::kSrgb;
    /// EXR: 16-bit half (compact; values above 65504 become +inf) or 32-bit float.
    ExrPixelType exr_pixel_type = ExrPixelType::kHalf;
    /// JPEG quality, 1 .. 100.
    int jpeg_quality = 90;
    /// PNG zlib compression level, 0 .. 9 (PNG is lossless: every level decodes to the same
    /// pixels). 0 stores the rows unfiltered and uncompressed; 1 .. 3 use zlib's fast levels with
    /// one cheap row filter (Sub), about 5x faster than 6 and still compact for renders; 4 .. 9
    /// let libpng choose a filter per row (smallest files, slowest; 9 can take seconds).
    int png_compression = 6;
};

/// The 8-bit transfer of a render shaded with `shading`: the sRGB curve for the modes that
/// compute light (eyelight, diffuse); kData for the modes that compute data (ao's unoccluded
/// fraction, normals, depth, primid's false colours), so that an ao value of 0.5 is the middle
/// grey level and not the much lighter sRGB level 188. The server encodes renders with it; a
/// client that stitches a frame from raw regions encodes with it to get the server's bytes.
[[nodiscard]] EightBitTransfer render_transfer(Shading shading) noexcept;

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
