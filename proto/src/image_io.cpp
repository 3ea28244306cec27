#include "kdrt/proto/image_io.h"

#include <OpenImageIO/filesystem.h>
#include <OpenImageIO/imageio.h>

#include <algorithm>
#include <array>
#include <bit>
#include <cctype>
#include <cmath>
#include <cstring>
#include <limits>
#include <mutex>

#include "kdrt/proto/errors.h"
#include "kdrt/proto/file_io.h"
#include "kdrt/proto/raw_image.h"

namespace kdrt::proto {
namespace {

// ---------------------------------------------------------------------------------------------
// sRGB transfer (IEC 61966-2-1), evaluated in double.

double srgb_eotf(double encoded) {
    return encoded <= 0.04045 ? encoded / 12.92 : std::pow((encoded + 0.055) / 1.055, 2.4);
}

/// kThresholds[k - 1] is the linear value from which a channel encodes to level k or above:
/// the EOTF of the midpoint (k - 0.5) / 255 between two levels. Quantising is then a binary
/// search (8 comparisons, no pow per channel), and equals round(255 * oetf(value)) up to the
/// rounding of the thresholds themselves (~1e-16 relative).
std::array<double, 255> make_thresholds() {
    std::array<double, 255> t{};
    for (int k = 1; k <= 255; ++k) t[static_cast<size_t>(k - 1)] = srgb_eotf((k - 0.5) / 255.0);
    return t;
}

std::array<float, 256> make_levels() {
    std::array<float, 256> levels{};
    for (int k = 0; k <= 255; ++k)
        levels[static_cast<size_t>(k)] = static_cast<float>(srgb_eotf(k / 255.0));
    return levels;
}

const std::array<double, 255>& thresholds() {
    static const std::array<double, 255> table = make_thresholds();
    return table;
}

/// linear_to_srgb8's buckets: positive floats below 1 by their bits >> kBucketShift.
constexpr int kBucketShift = 16;
constexpr size_t kBuckets = (0x3F800000u >> kBucketShift) + 1;

/// The level of the smallest float in each bucket (thresholds <= it, counted exactly).
const std::vector<uint8_t>& bucket_levels() {
    static const std::vector<uint8_t> table = [] {
        std::vector<uint8_t> out(kBuckets);
        const auto& t = thresholds();
        for (size_t b = 0; b < kBuckets; ++b) {
            const double lowest =
                static_cast<double>(std::bit_cast<float>(static_cast<uint32_t>(b << kBucketShift)));
            out[b] = static_cast<uint8_t>(std::upper_bound(t.begin(), t.end(), lowest) - t.begin());
        }
        return out;
    }();
    return table;
}

const std::array<float, 256>& levels() {
    static const std::array<float, 256> table = make_levels();
    return table;
}

uint8_t linear_to_unorm8(float value) noexcept {
    // NaN fails the comparison and becomes 0, like everything below 0.
    const float clamped = value > 0.0f ? std::min(value, 1.0f) : 0.0f;
    return static_cast<uint8_t>(std::lround(clamped * 255.0f));
}

// ---------------------------------------------------------------------------------------------
// OpenImageIO set-up

/// kdrt parallelises with oneTBB; OIIO's and OpenEXR's own thread pools would only oversubscribe
/// the cores (and each call encodes one small image), so every call works on its calling thread.
void configure_oiio_once() {
    static std::once_flag once;
    std::call_once(once, [] {
        OIIO::attribute("threads", 1);
        OIIO::attribute("exr_threads", 1);
    });
}

/// OIIO's global error text (clears it), or `fallback` when there is none.
std::string oiio_global_error(std::string_view fallback) {
    std::string message = OIIO::geterror();
    return message.empty() ? std::string(fallback) : message;
}

template <class Object>
std::string object_error(Object& object, std::string_view fallback) {
    std::string message = object.geterror();
    if (message.empty()) message = OIIO::geterror();
    return message.empty() ? std::string(fallback) : message;
}

std::string_view oiio_extension(ImageFormat format) noexcept {
    switch (format) {
        case ImageFormat::kPng:
            return "png";
        case ImageFormat::kJpeg:
            return "jpg";
        case ImageFormat::kExr:
        case ImageFormat::kRaw:  // never given to OIIO
            return "exr";
    }
    return "png";
}

bool is_known_format(ImageFormat format) noexcept {
    return format == ImageFormat::kPng || format == ImageFormat::kJpeg ||
           format == ImageFormat::kExr;
}

std::string check_image(const Image& image) {
    if (image.channels != 3 && image.channels != 4) {
        return "image has " + std::to_string(image.channels) +
               " channels; only 3 (RGB) or 4 (RGBA) can be encoded";
    }
    if (image.width == 0 || image.height == 0) {
        return "image is empty (" + std::to_string(image.width) + " x " +
               std::to_string(image.height) + " pixels)";
    }
    if (image.width > static_cast<uint32_t>(std::numeric_limits<int>::max()) ||
        image.height > static_cast<uint32_t>(std::numeric_limits<int>::max())) {
        return "image is too large (" + std::to_string(image.width) + " x " +
               std::to_string(image.height) + ")";
    }
    const uint64_t expected = uint64_t{image.width} * image.height * image.channels;
    if (image.pixels.size() != expected) {
        return "image has " + std::to_string(image.pixels.size()) + " floats, expected " +
               std::to_string(expected) + " (" + std::to_string(image.width) + " x " +
               std::to_string(image.height) + " x " + std::to_string(image.channels) + ")";
    }
    return {};
}

/// 8-bit sRGB pixels for PNG/JPEG. `out_channels` is 3 or 4 (4 only when the image has alpha).
/// Image colour with alpha is premultiplied; PNG stores straight alpha, so colour is divided by
/// alpha (in linear light) before the transfer function.
std::vector<unsigned char> to_srgb8(const Image& image, uint32_t out_channels,
                                    EightBitTransfer transfer) {
    const bool data = transfer == EightBitTransfer::kData;
    const size_t pixels = size_t{image.width} * image.height;
    std::vector<unsigned char> out(pixels * out_channels);
    const bool straight_alpha = out_channels == 4;
    for (size_t i = 0; i < pixels; ++i) {
        const float* in = &image.pixels[i * image.channels];
        unsigned char* dst = &out[i * out_channels];
        float scale = 1.0f;
        if (straight_alpha) {
            const float alpha = in[3];
            if (alpha > 0.0f && alpha < 1.0f) scale = 1.0f / alpha;
            dst[3] = linear_to_unorm8(alpha);
        }
        for (int c = 0; c < 3; ++c)
            dst[c] = data ? linear_to_unorm8(in[c] * scale) : linear_to_srgb8(in[c] * scale);
    }
    return out;
}

std::optional<ImageFormat> sniff_format(std::span<const std::byte> bytes) noexcept {
    auto starts_with = [&](std::initializer_list<unsigned char> magic) {
        if (bytes.size() < magic.size()) return false;
        size_t i = 0;
        for (unsigned char m : magic) {
            if (std::to_integer<unsigned char>(bytes[i++]) != m) return false;
        }
        return true;
    };
    if (starts_with({0x89, 'P', 'N', 'G', 0x0D, 0x0A, 0x1A, 0x0A})) return ImageFormat::kPng;
    if (starts_with({0xFF, 0xD8, 0xFF})) return ImageFormat::kJpeg;
    if (starts_with({0x76, 0x2F, 0x31, 0x01})) return ImageFormat::kExr;
    if (starts_with({'K', 'D', 'R', 'I'})) return ImageFormat::kRaw;
    return std::nullopt;
}

uint32_t read_be32(std::span<const std::byte> bytes, size_t at) noexcept {
    return (std::to_integer<uint32_t>(bytes[at]) << 24) |
           (std::to_integer<uint32_t>(bytes[at + 1]) << 16) |
           (std::to_integer<uint32_t>(bytes[at + 2]) << 8) |
           std::to_integer<uint32_t>(bytes[at + 3]);
}

/// Walks the PNG chunk list (length, type, data, CRC) up to IEND; empty when every chunk lies
/// inside `bytes`. libpng is then never asked for bytes past the end: OIIO 2.4's read callback
/// reports a short read by longjmp-ing over a live std::string, which leaks it (and prints
/// "libpng error" to stderr), so truncated files are refused here first.
std::string png_structure_problem(std::span<const std::byte> bytes) {
    size_t at = 8;  // after the signature
    while (true) {
        if (bytes.size() - at < 12) {
            return std::string(image_errors::kTruncatedPng) + ": byte " + std::to_string(at) +
                   " should start a chunk, but the file has " + std::to_string(bytes.size()) +
                   " bytes";
        }
        const uint64_t length = read_be32(bytes, at);
        const bool is_end = read_be32(bytes, at + 4) == 0x49454E44u;  // "IEND"
        if (length > bytes.size() - at - 12) {
            return std::string(image_errors::kTruncatedPng) + ": the chunk at byte " +
                   std::to_string(at) + " needs " + std::to_string(length + 12) +
                   " bytes, the file has " + std::to_string(bytes.size() - at) + " left";
        }
        at += 12 + length;
        if (is_end) return {};
    }
}

}  // namespace

uint8_t linear_to_srgb8(float value) noexcept {
    if (!(value > 0.0f)) return 0;  // NaN too
    if (value >= 1.0f) return 255;  // +inf too; the last threshold is below 1
    // The level is the number of thresholds <= value. A table indexed by the float's top bits
    // gives the level at the start of the value's bucket (buckets are 1/128 of a binade, finer
    // than the levels' spacing), and the thresholds finish the count: one or two comparisons
    // instead of a binary search over all 255 (an image encode calls this for every channel).
    const auto& t = thresholds();
    const auto& start = bucket_levels();
    unsigned level = start[std::bit_cast<uint32_t>(value) >> kBucketShift];
    while (level < 255 && t[level] <= static_cast<double>(value)) ++level;
    return static_cast<uint8_t>(level);
}

float srgb8_to_linear(uint8_t level) noexcept { return levels()[level]; }

Result<std::vector<std::byte>, std::string> encode_image(const Image& image, ImageFormat format,
                                                         const ImageEncodeOptions& options) {
    if (std::string problem = check_image(image); !problem.empty()) return Err{std::move(problem)};
    if (format == ImageFormat::kRaw)
        return encode_raw_image(image, 0, 0, image.width, image.height);
    if (!is_known_format(format)) {
        return Err{"unknown image format " + std::to_string(static_cast<int>(format))};
    }
    if (format == ImageFormat::kJpeg && (options.jpeg_quality < 1 || options.jpeg_quality > 100)) {
        return Err{"jpeg_quality " + std::to_string(options.jpeg_quality) + " must be in 1 .. 100"};
    }
    if (format == ImageFormat::kPng &&
        (options.png_compression < 0 || options.png_compression > kMaxPngCompression)) {
        return Err{"png_compression " + std::to_string(options.png_compression) +
                   " must be in 0 .. " + std::to_string(kMaxPngCompression)};
    }
    if (format == ImageFormat::kExr && options.exr_pixel_type != ExrPixelType::kHalf &&
        options.exr_pixel_type != ExrPixelType::kFloat) {
        return Err{"exr_pixel_type " + std::to_string(static_cast<int>(options.exr_pixel_type)) +
                   " is neither half nor float"};
    }
    configure_oiio_once();

    const auto width = static_cast<int>(image.width), height = static_cast<int>(image.height);
    const uint32_t channels = format == ImageFormat::kJpeg ? 3u : image.channels;
    std::vector<unsigned char> srgb;
    OIIO::ImageSpec spec;
    OIIO::TypeDesc data_type;
    const void* data = nullptr;
    if (format == ImageFormat::kExr) {
        const OIIO::TypeDesc file_type = options.exr_pixel_type == ExrPixelType::kHalf
                                             ? OIIO::TypeDesc::HALF
                                             : OIIO::TypeDesc::FLOAT;
        spec = OIIO::ImageSpec(width, height, static_cast<int>(channels), file_type);
        spec.attribute("compression", "zip");
        spec.attribute("oiio:ColorSpace", "Linear");
        data_type = OIIO::TypeDesc::FLOAT;
        data = image.pixels.data();
    } else {
        spec = OIIO::ImageSpec(width, height, static_cast<int>(channels), OIIO::TypeDesc::UINT8);
        spec.attribute("oiio:ColorSpace", "sRGB");
        if (format == ImageFormat::kJpeg) {
            spec.attribute("Compression", "jpeg:" + std::to_string(options.jpeg_quality));
        } else {
            // The bytes already hold straight alpha (to_srgb8): OIIO must not convert them again.
            spec.attribute("oiio:UnassociatedAlpha", 1);
            // libpng's row filters (png_set_filter): None 0x08, Sub 0x10; 0 = libpng's adaptive
            // choice among all five, which costs more than zlib's fast levels themselves.
            constexpr int kFilterNone = 0x08, kFilterSub = 0x10;
            spec.attribute("png:compressionLevel", options.png_compression);
            if (options.png_compression == 0)
                spec.attribute("png:filter", kFilterNone);
            else if (options.png_compression <= 3)
                spec.attribute("png:filter", kFilterSub);
        }
        srgb = to_srgb8(image, channels, options.transfer);
        data_type = OIIO::TypeDesc::UINT8;
        data = srgb.data();
    }

    std::vector<unsigned char> encoded;
    OIIO::Filesystem::IOVecOutput proxy(encoded);
    const std::string name = std::string("image.") + std::string(oiio_extension(format));
    auto out = OIIO::ImageOutput::create(name, &proxy);
    if (!out)
        return Err{"cannot create an OpenImageIO " + name +
                   " writer: " + oiio_global_error("no plugin")};
    if (!out->supports("ioproxy")) {
        return Err{"the OpenImageIO " + std::string(out->format_name()) +
                   " writer cannot write to memory"};
    }
    if (!out->open(name, spec))
        return Err{"cannot start " + name + ": " + object_error(*out, "open failed")};
    if (!out->write_image(data_type, data)) {
        std::string message = "cannot encode " + name + ": " + object_error(*out, "write failed");
        out->close();
        return Err{std::move(message)};
    }
    if (!out->close())
        return Err{"cannot finish " + name + ": " + object_error(*out, "close failed")};

    std::vector<std::byte> bytes(encoded.size());
    if (!encoded.empty()) std::memcpy(bytes.data(), encoded.data(), encoded.size());
    return bytes;
}

Result<void, std::string> write_image_file(const std::filesystem::path& path, const Image& image,
                                           std::optional<ImageFormat> format,
                                           const ImageEncodeOptions& options) {
    if (!format) format = image_format_from_path(path);
    if (!format) {
        return Err{std::string(image_errors::kUnknownExtension) + " of \"" + path.string() +
                   "\" from its extension (use .png, .jpg, .jpeg or .exr)"};
    }
    auto bytes = encode_image(image, *format, options);
    if (!bytes) return Err{"cannot write \"" + path.string() + "\": " + bytes.error()};
    return write_file_bytes(path, *bytes);
}

Result<Image, std::string> decode_image(std::span<const std::byte> bytes,
                                        const ImageDecodeLimits& limits) {
    const std::optional<ImageFormat> format = sniff_format(bytes);
    if (!format) return Err{std::string(image_errors::kUnknownMagic) + " (unknown magic bytes)"};
    if (*format == ImageFormat::kRaw) {
        auto raw = decode_raw_image(bytes, limits.max_pixels);
        if (!raw) return Err{std::move(raw).error()};
        return std::move(raw->image);
    }
    if (*format == ImageFormat::kPng) {
        if (std::string problem = png_structure_problem(bytes); !problem.empty())
            return Err{std::move(problem)};
    }
    configure_oiio_once();

    OIIO::Filesystem::IOMemReader proxy(bytes.data(), bytes.size());
    const std::string name = std::string("image.") + std::string(oiio_extension(*format));
    OIIO::ImageSpec config;
    // Straight alpha stays straight; the conversion below premultiplies in linear light.
    config.attribute("oiio:UnassociatedAlpha", 1);
    // open() takes the proxy from the configuration (create()'s argument alone is not enough).
    OIIO::Filesystem::IOProxy* proxy_pointer = &proxy;
    config.attribute("oiio:ioproxy", OIIO::TypeDesc::PTR, &proxy_pointer);
    auto in = OIIO::ImageInput::create(name, false, &config, &proxy);
    if (!in)
        return Err{"cannot create an OpenImageIO " + name +
                   " reader: " + oiio_global_error("no plugin")};
    if (!in->supports("ioproxy")) {
        return Err{"the OpenImageIO " + std::string(in->format_name()) +
                   " reader cannot read from memory"};
    }
    OIIO::ImageSpec spec;
    if (!in->open(name, spec, config)) {
        return Err{"cannot read " + std::string(image_format_name(*format)) +
                   " image: " + object_error(*in, "open failed")};
    }
    if (spec.width < 1 || spec.height < 1 || spec.depth > 1) {
        return Err{"image has unsupported dimensions " + std::to_string(spec.width) + " x " +
                   std::to_string(spec.height) + " x " + std::to_string(spec.depth)};
    }
    const uint64_t pixels = uint64_t(spec.width) * uint64_t(spec.height);
    if (pixels > limits.max_pixels) {
        return Err{"image has " + std::to_string(pixels) + " pixels, which " +
                   std::string(errors::kLimitExceeded) + " of " +
                   std::to_string(limits.max_pixels)};
    }
    if (spec.nchannels < 1 || spec.nchannels > 4) {
        return Err{"image has " + std::to_string(spec.nchannels) +
                   " channels; at most 4 are supported"};
    }

    Image image;
    image.width = static_cast<uint32_t>(spec.width);
    image.height = static_cast<uint32_t>(spec.height);
    image.channels = static_cast<uint32_t>(spec.nchannels);
    const size_t values = static_cast<size_t>(pixels) * image.channels;
    image.pixels.resize(values);
    const int alpha =
        spec.alpha_channel >= 0 && spec.alpha_channel < spec.nchannels ? spec.alpha_channel : -1;
    if (*format == ImageFormat::kExr) {
        // Linear, stored premultiplied: take the values as they are.
        if (!in->read_image(0, 0, 0, spec.nchannels, OIIO::TypeDesc::FLOAT, image.pixels.data())) {
            return Err{"cannot decode exr image: " + object_error(*in, "read failed")};
        }
        return image;
    }
    // PNG/JPEG: sRGB levels. 8-bit files go through the exact level table; deeper ones (16-bit
    // PNG) are read as normalised floats and put through the EOTF.
    const bool eight_bit = spec.format == OIIO::TypeDesc::UINT8;
    std::vector<unsigned char> levels8;
    if (eight_bit) {
        levels8.resize(values);
        if (!in->read_image(0, 0, 0, spec.nchannels, OIIO::TypeDesc::UINT8, levels8.data())) {
            return Err{"cannot decode " + std::string(image_format_name(*format)) +
                       " image: " + object_error(*in, "read failed")};
        }
    } else if (!in->read_image(0, 0, 0, spec.nchannels, OIIO::TypeDesc::FLOAT,
                               image.pixels.data())) {
        return Err{"cannot decode " + std::string(image_format_name(*format)) +
                   " image: " + object_error(*in, "read failed")};
    }
    for (size_t p = 0; p < pixels; ++p) {
        float* px = &image.pixels[p * image.channels];
        for (uint32_t c = 0; c < image.channels; ++c) {
            const bool is_alpha = static_cast<int>(c) == alpha;
            if (eight_bit) {
                const unsigned char level = levels8[p * image.channels + c];
                px[c] = is_alpha ? static_cast<float>(level) / 255.0f : srgb8_to_linear(level);
            } else if (!is_alpha) {
                px[c] =
                    static_cast<float>(srgb_eotf(std::clamp(static_cast<double>(px[c]), 0.0, 1.0)));
            }
        }
        if (alpha >= 0) {
            for (uint32_t c = 0; c < image.channels; ++c) {
                if (static_cast<int>(c) != alpha) px[c] *= px[alpha];
            }
        }
    }
    return image;
}

Result<Image, std::string> read_image_file(const std::filesystem::path& path,
                                           const ImageDecodeLimits& limits) {
    auto bytes = read_file_bytes(path);
    if (!bytes) return Err{std::move(bytes).error()};
    auto image = decode_image(*bytes, limits);
    if (!image) return Err{"cannot read image \"" + path.string() + "\": " + image.error()};
    return image;
}

}  // namespace kdrt::proto
