#pragma once
/// The image formats of the API and their encoding options: names, media types, the 8-bit
/// transfer of a render. Part of kdrt_proto (no OpenImageIO), so the server validates and names
/// formats without linking the encoders; the encoders themselves are kdrt/proto/image_io.h
/// (kdrt_proto_image), which the server and the CLI load as a module (kdrt/proto/image_module.h).

#include <filesystem>
#include <optional>
#include <string_view>

#include "kdrt/render_settings.h"

namespace kdrt::proto {

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

}  // namespace kdrt::proto
