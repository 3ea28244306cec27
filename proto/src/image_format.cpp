// kdrt::proto: image format names and media types (image_format.h); no OpenImageIO.

#include "kdrt/proto/image_format.h"

#include <cctype>
#include <string>

#include "kdrt/proto/raw_image.h"

namespace kdrt::proto {
namespace {

std::string lower_extension(const std::filesystem::path& path) {
    std::string ext = path.extension().string();
    for (char& ch : ext) ch = static_cast<char>(std::tolower(static_cast<unsigned char>(ch)));
    return ext;
}

}  // namespace

std::optional<ImageFormat> image_format_from_name(std::string_view name) noexcept {
    if (name == "png") return ImageFormat::kPng;
    if (name == "jpeg" || name == "jpg") return ImageFormat::kJpeg;
    if (name == "exr") return ImageFormat::kExr;
    if (name == kRawImageFormatName) return ImageFormat::kRaw;
    return std::nullopt;
}

std::optional<ImageFormat> image_format_from_path(const std::filesystem::path& path) {
    const std::string ext = lower_extension(path);
    if (ext.size() < 2) return std::nullopt;
    const auto format = image_format_from_name(std::string_view(ext).substr(1));
    // ".raw" names a raw mesh (proto/FORMATS.md), never a KDRI image.
    if (format == ImageFormat::kRaw) return std::nullopt;
    return format;
}

std::string_view image_format_name(ImageFormat format) noexcept {
    switch (format) {
        case ImageFormat::kPng:
            return "png";
        case ImageFormat::kJpeg:
            return "jpeg";
        case ImageFormat::kExr:
            return "exr";
        case ImageFormat::kRaw:
            return kRawImageFormatName;
    }
    return "unknown";
}

std::string_view image_media_type(ImageFormat format) noexcept {
    switch (format) {
        case ImageFormat::kPng:
            return "image/png";
        case ImageFormat::kJpeg:
            return "image/jpeg";
        case ImageFormat::kExr:
            return "image/x-exr";
        case ImageFormat::kRaw:
            return kRawImageMediaType;
    }
    return "application/octet-stream";
}

EightBitTransfer render_transfer(Shading shading) noexcept {
    const bool light = shading == Shading::kEyelight || shading == Shading::kDiffuse;
    return light ? EightBitTransfer::kSrgb : EightBitTransfer::kData;
}

}  // namespace kdrt::proto
