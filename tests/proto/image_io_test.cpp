// Image encoding: PNG/JPEG/EXR written through OpenImageIO and read back (with OIIO directly and
// with decode_image) match the float buffer; the sRGB transfer is the standard's; bad input gives
// errors, never crashes.

#include "kdrt/proto/image_io.h"

#include <OpenImageIO/imageio.h>
#include <gtest/gtest.h>

#include <cmath>
#include <cstring>
#include <filesystem>
#include <limits>
#include <string>
#include <vector>

#include "kdrt/kdtree.h"
#include "kdrt/proto/errors.h"
#include "kdrt/proto/file_io.h"
#include "kdrt/proto/mesh_io.h"
#include "kdrt/render.h"

namespace kdrt::proto {
namespace {

constexpr float kNaN = std::numeric_limits<float>::quiet_NaN();
constexpr float kInf = std::numeric_limits<float>::infinity();

/// The sRGB OETF in double, written out independently of the library's threshold table.
double srgb_oetf(double linear) {
    return linear <= 0.0031308 ? 12.92 * linear : 1.055 * std::pow(linear, 1.0 / 2.4) - 0.055;
}

double clamp01(float value) {
    return value > 0.0f ? std::min(static_cast<double>(value), 1.0) : 0.0;
}

int expected_level(float linear) {
    return static_cast<int>(std::lround(255.0 * srgb_oetf(clamp01(linear))));
}

/// A scratch directory for one test, removed afterwards.
class TempDir {
public:
    TempDir() {
        const auto* info = testing::UnitTest::GetInstance()->current_test_info();
        path_ = std::filesystem::temp_directory_path() /
                (std::string("kdrt_image_io_") + info->test_suite_name() + "_" + info->name());
        std::filesystem::remove_all(path_);
        std::filesystem::create_directories(path_);
    }
    ~TempDir() {
        std::error_code ignored;
        std::filesystem::remove_all(path_, ignored);
    }
    [[nodiscard]] std::filesystem::path file(const std::string& name) const { return path_ / name; }

private:
    std::filesystem::path path_;
};

/// A width x height image whose channels sweep [-0.1, 1.2] in different directions, with a few
/// NaN/Inf values at fixed places, so every level and the clamps are exercised.
Image gradient(uint32_t width, uint32_t height, uint32_t channels, bool specials = true) {
    Image image{width, height, channels, Pixels(size_t{width} * height * channels)};
    for (uint32_t y = 0; y < height; ++y) {
        for (uint32_t x = 0; x < width; ++x) {
            float* px = &image.pixels[(size_t{y} * width + x) * channels];
            const float u = static_cast<float>(x) / static_cast<float>(std::max(1u, width - 1));
            const float v = static_cast<float>(y) / static_cast<float>(std::max(1u, height - 1));
            px[0] = -0.1f + 1.3f * u;
            px[1] = -0.1f + 1.3f * v;
            px[2] = u * v;
            if (channels == 4) px[3] = 1.0f;
        }
    }
    if (specials) {
        image.pixels[0] = kNaN;
        image.pixels[1] = kInf;
        image.pixels[2] = -kInf;
    }
    return image;
}

struct RawImage {
    OIIO::ImageSpec spec;
    std::vector<unsigned char> bytes;  // UINT8 reads
    std::vector<float> floats;         // FLOAT reads
};

/// Reads a file with OpenImageIO directly (not through decode_image), straight alpha kept.
RawImage read_with_oiio(const std::filesystem::path& path, const OIIO::TypeDesc& type) {
    OIIO::ImageSpec config;
    config.attribute("oiio:UnassociatedAlpha", 1);
    auto in = OIIO::ImageInput::open(path.string(), &config);
    RawImage raw;
    if (!in) {
        ADD_FAILURE() << "OIIO cannot open " << path << ": " << OIIO::geterror();
        return raw;
    }
    raw.spec = in->spec();
    const size_t values = size_t(raw.spec.width) * raw.spec.height * raw.spec.nchannels;
    bool ok = false;
    if (type == OIIO::TypeDesc::UINT8) {
        raw.bytes.resize(values);
        ok = in->read_image(0, 0, 0, raw.spec.nchannels, type, raw.bytes.data());
    } else {
        raw.floats.resize(values);
        ok = in->read_image(0, 0, 0, raw.spec.nchannels, type, raw.floats.data());
    }
    EXPECT_TRUE(ok) << in->geterror();
    return raw;
}

Image render_bunny(uint32_t res, bool alpha) {
    auto mesh = load_mesh_file(std::string(KDRT_TEST_DATA_DIR) + "/bunny00.off");
    EXPECT_TRUE(mesh.ok());
    const KdTree tree = build_kdtree(*mesh);
    RenderSettings settings;
    settings.width = settings.height = res;
    settings.shading = Shading::kEyelight;
    settings.alpha = alpha;
    settings.spp = 4;  // partly covered pixels on the silhouette: alpha strictly inside (0, 1)
    return render(tree, settings);
}

// ---------------------------------------------------------------------------------------------
// Names and the transfer function

TEST(ImageFormatNames, NamesExtensionsAndMediaTypes) {
    EXPECT_EQ(image_format_from_name("png"), ImageFormat::kPng);
    EXPECT_EQ(image_format_from_name("jpeg"), ImageFormat::kJpeg);
    EXPECT_EQ(image_format_from_name("jpg"), ImageFormat::kJpeg);
    EXPECT_EQ(image_format_from_name("exr"), ImageFormat::kExr);
    EXPECT_EQ(image_format_from_name("PNG"), std::nullopt);
    EXPECT_EQ(image_format_from_name("tiff"), std::nullopt);
    EXPECT_EQ(image_format_from_path("out/frame.PNG"), ImageFormat::kPng);
    EXPECT_EQ(image_format_from_path("a.JPeG"), ImageFormat::kJpeg);
    EXPECT_EQ(image_format_from_path("depth.exr"), ImageFormat::kExr);
    EXPECT_EQ(image_format_from_path("noextension"), std::nullopt);
    EXPECT_EQ(image_format_from_path("image.tif"), std::nullopt);
    EXPECT_EQ(image_format_from_name("raw"), ImageFormat::kRaw);
    EXPECT_EQ(image_format_from_path("mesh.raw"), std::nullopt);  // a raw mesh, not KDRI
    for (ImageFormat f :
         {ImageFormat::kPng, ImageFormat::kJpeg, ImageFormat::kExr, ImageFormat::kRaw}) {
        EXPECT_EQ(image_format_from_name(image_format_name(f)), f);
    }
    EXPECT_EQ(image_media_type(ImageFormat::kPng), "image/png");
    EXPECT_EQ(image_media_type(ImageFormat::kJpeg), "image/jpeg");
    EXPECT_EQ(image_media_type(ImageFormat::kExr), "image/x-exr");
    EXPECT_EQ(image_media_type(ImageFormat::kRaw), "application/x-kdrt-image");
}

TEST(ImageIoRaw, EncodesAWholeFrameKdriAndDecodesItBitExact) {
    const Image image{3, 2, 4, {0.1f, -2, 3e9f, 0.5f, 1,  2,  3,  4,  5,  6,  7,  8,
                                9,    10, 11,   12,   13, 14, 15, 16, 17, 18, 19, 0.25f}};
    auto bytes = encode_image(image, ImageFormat::kRaw);
    ASSERT_TRUE(bytes) << bytes.error();
    EXPECT_EQ(std::memcmp(bytes->data(), "KDRI", 4), 0);
    auto back = decode_image(*bytes);
    ASSERT_TRUE(back) << back.error();
    EXPECT_EQ(back->width, 3u);
    EXPECT_EQ(back->height, 2u);
    EXPECT_EQ(back->channels, 4u);
    EXPECT_EQ(back->pixels, image.pixels);
    auto limited = decode_image(*bytes, ImageDecodeLimits{.max_pixels = 5});
    ASSERT_FALSE(limited);
    EXPECT_NE(limited.error().find("exceeds the limit of 5"), std::string::npos);
}

TEST(RenderTransfer, LightThroughTheCurveDataAsIs) {
    EXPECT_EQ(render_transfer(Shading::kEyelight), EightBitTransfer::kSrgb);
    EXPECT_EQ(render_transfer(Shading::kDiffuse), EightBitTransfer::kSrgb);
    for (Shading data : {Shading::kAo, Shading::kNormals, Shading::kDepth, Shading::kPrimId})
        EXPECT_EQ(render_transfer(data), EightBitTransfer::kData);
}

TEST(SrgbTransfer, KnownLevelsAndClamps) {
    EXPECT_EQ(linear_to_srgb8(0.0f), 0);
    EXPECT_EQ(linear_to_srgb8(1.0f), 255);
    EXPECT_EQ(linear_to_srgb8(0.5f), 188);   // not 186 (gamma 2.2) or 128 (linear)
    EXPECT_EQ(linear_to_srgb8(0.18f), 118);  // middle grey
    EXPECT_EQ(linear_to_srgb8(0.001f), 3);   // the linear segment: 12.92 * 0.001 * 255 = 3.29
    EXPECT_EQ(linear_to_srgb8(-0.5f), 0);
    EXPECT_EQ(linear_to_srgb8(7.0f), 255);
    EXPECT_EQ(linear_to_srgb8(kNaN), 0);
    EXPECT_EQ(linear_to_srgb8(kInf), 255);
    EXPECT_EQ(linear_to_srgb8(-kInf), 0);
    EXPECT_EQ(srgb8_to_linear(0), 0.0f);
    EXPECT_EQ(srgb8_to_linear(255), 1.0f);
    EXPECT_NEAR(srgb8_to_linear(188), 0.5029, 1e-4);
}

TEST(SrgbTransfer, MatchesTheStandardFormulaEverywhere) {
    // Dense sweep plus every level's own value: the threshold table equals round(255 * oetf).
    for (int i = 0; i <= 200000; ++i) {
        const float v = static_cast<float>(i) / 200000.0f;
        ASSERT_EQ(linear_to_srgb8(v), expected_level(v)) << "v=" << v;
    }
    for (int level = 0; level < 256; ++level) {
        const float linear = srgb8_to_linear(static_cast<uint8_t>(level));
        EXPECT_EQ(linear_to_srgb8(linear), level) << "the decoded level encodes to itself";
        if (level > 0) {
            EXPECT_GT(linear, srgb8_to_linear(static_cast<uint8_t>(level - 1)));
        }
    }
}

// ---------------------------------------------------------------------------------------------
// PNG

TEST(ImageIoPng, FileReadByOiioHasTheSrgbLevelsOfTheBuffer) {
    const TempDir dir;
    const Image image = gradient(37, 23, 3);
    const auto path = dir.file("gradient.png");
    ASSERT_TRUE(write_image_file(path, image).ok());
    const RawImage raw = read_with_oiio(path, OIIO::TypeDesc::UINT8);
    ASSERT_EQ(raw.spec.width, 37);
    ASSERT_EQ(raw.spec.height, 23);
    ASSERT_EQ(raw.spec.nchannels, 3);
    EXPECT_EQ(raw.spec.format, OIIO::TypeDesc::UINT8);
    ASSERT_EQ(raw.bytes.size(), image.pixels.size());
    for (size_t i = 0; i < image.pixels.size(); ++i) {
        ASSERT_EQ(raw.bytes[i], expected_level(image.pixels[i]))
            << "value " << i << " = " << image.pixels[i];
    }
}

TEST(ImageIoPng, DataTransferStoresTheValuesWithoutTheCurve) {
    // EightBitTransfer::kData (ao, normals, primid): level = round(255 x clamp(value)), so 0.5 is
    // level 128 where sRGB would give 188; the same image as EXR is untouched.
    const TempDir dir;
    const Image image = gradient(37, 23, 3);
    const auto path = dir.file("data.png");
    ImageEncodeOptions options;
    options.transfer = EightBitTransfer::kData;
    ASSERT_TRUE(write_image_file(path, image, ImageFormat::kPng, options).ok());
    const RawImage raw = read_with_oiio(path, OIIO::TypeDesc::UINT8);
    ASSERT_EQ(raw.bytes.size(), image.pixels.size());
    size_t differ_from_srgb = 0;
    for (size_t i = 0; i < image.pixels.size(); ++i) {
        const float v = image.pixels[i];
        const float clamped = v > 0.0f ? std::min(v, 1.0f) : 0.0f;  // NaN -> 0
        ASSERT_EQ(raw.bytes[i], static_cast<unsigned char>(std::lround(clamped * 255.0f)))
            << "value " << i << " = " << v;
        differ_from_srgb += raw.bytes[i] != expected_level(v);
    }
    EXPECT_GT(differ_from_srgb, image.pixels.size() / 2);

    const Image half{1, 1, 3, {0.5f, 0.25f, 1.0f}};
    auto bytes = encode_image(half, ImageFormat::kPng, options);
    ASSERT_TRUE(bytes);
    auto decoded = decode_image(*bytes);  // decoding assumes sRGB levels
    ASSERT_TRUE(decoded);
    EXPECT_EQ(decoded->pixels[0], srgb8_to_linear(128));
    EXPECT_EQ(decoded->pixels[1], srgb8_to_linear(64));
    EXPECT_EQ(decoded->pixels[2], 1.0f);
    auto exr = encode_image(half, ImageFormat::kExr, options);
    ASSERT_TRUE(exr);
    auto exr_decoded = decode_image(*exr);
    ASSERT_TRUE(exr_decoded);
    EXPECT_EQ(exr_decoded->pixels, half.pixels);
}

TEST(ImageIoPng, DecodeMatchesTheBufferWithin8BitQuantisation) {
    const Image image = gradient(64, 40, 3);
    auto bytes = encode_image(image, ImageFormat::kPng);
    ASSERT_TRUE(bytes.ok()) << bytes.error();
    auto decoded = decode_image(*bytes);
    ASSERT_TRUE(decoded.ok()) << decoded.error();
    ASSERT_EQ(decoded->width, 64u);
    ASSERT_EQ(decoded->height, 40u);
    ASSERT_EQ(decoded->channels, 3u);
    for (size_t i = 0; i < image.pixels.size(); ++i) {
        // Within half a level in the encoded (sRGB) domain of the clamped value.
        const double got = srgb_oetf(decoded->pixels[i]);
        const double want = srgb_oetf(clamp01(image.pixels[i]));
        ASSERT_LE(std::fabs(got - want), 0.5 / 255.0 + 1e-6)
            << "value " << i << " = " << image.pixels[i];
    }
}

TEST(ImageIoPng, AlphaIsStoredStraightAndDecodedPremultiplied) {
    const TempDir dir;
    // Premultiplied colour, as the renderer makes it with a black background.
    // clang-format off
    Image image{3, 1, 4, {0.5f, 0.25f, 0.1f, 1.0f,   // opaque
                          0.2f, 0.1f, 0.05f, 0.5f,   // half covered: straight colour 0.4, 0.2, 0.1
                          0.0f, 0.0f, 0.0f, 0.0f}};  // background
    // clang-format on
    const auto path = dir.file("alpha.png");
    ASSERT_TRUE(write_image_file(path, image).ok());
    const RawImage raw = read_with_oiio(path, OIIO::TypeDesc::UINT8);
    ASSERT_EQ(raw.spec.nchannels, 4);
    EXPECT_EQ(raw.spec.alpha_channel, 3);
    // clang-format off
    const std::vector<int> want = {expected_level(0.5f), expected_level(0.25f), expected_level(0.1f), 255,
                                   expected_level(0.4f), expected_level(0.2f),  expected_level(0.1f), 128,
                                   0,                    0,                     0,                    0};
    // clang-format on
    ASSERT_EQ(raw.bytes.size(), want.size());
    for (size_t i = 0; i < want.size(); ++i) EXPECT_EQ(raw.bytes[i], want[i]) << i;

    auto decoded = read_image_file(path);
    ASSERT_TRUE(decoded.ok()) << decoded.error();
    ASSERT_EQ(decoded->channels, 4u);
    EXPECT_EQ(decoded->pixels[3], 1.0f);
    EXPECT_NEAR(decoded->pixels[7], 0.5f, 0.5f / 255.0f + 1e-6f);
    EXPECT_NEAR(decoded->pixels[4], 0.2f, 0.005f) << "premultiplied again";
    EXPECT_EQ(decoded->pixels[11], 0.0f);
}

TEST(ImageIoPng, RenderedBunnyRoundTrips) {
    const TempDir dir;
    const Image image = render_bunny(64, true);
    const auto path = dir.file("bunny.png");
    ASSERT_TRUE(write_image_file(path, image).ok());
    auto decoded = read_image_file(path);
    ASSERT_TRUE(decoded.ok()) << decoded.error();
    ASSERT_EQ(decoded->pixels.size(), image.pixels.size());
    size_t partial = 0;
    for (size_t p = 0; p < size_t{image.width} * image.height; ++p) {
        const float alpha = image.pixels[p * 4 + 3];
        EXPECT_NEAR(decoded->pixels[p * 4 + 3], alpha, 0.5f / 255.0f + 1e-6f);
        partial += alpha > 0.0f && alpha < 1.0f;
        if (alpha != 1.0f) continue;  // straight colour of partial pixels is amplified by 1/alpha
        for (int c = 0; c < 3; ++c) {
            const double got = srgb_oetf(decoded->pixels[p * 4 + c]);
            const double want = srgb_oetf(clamp01(image.pixels[p * 4 + c]));
            ASSERT_LE(std::fabs(got - want), 0.5 / 255.0 + 1e-6) << "pixel " << p;
        }
    }
    EXPECT_GT(partial, 0u) << "the silhouette has partly covered pixels";
}

// ---------------------------------------------------------------------------------------------
// EXR

TEST(ImageIoExr, FloatIsBitExactAndLinear) {
    const TempDir dir;
    Image image = gradient(19, 11, 4, /*specials=*/false);
    image.pixels[5] = 1234.5f;  // linear values above 1 survive
    image.pixels[6] = 1e-8f;
    const auto path = dir.file("linear.exr");
    ImageEncodeOptions options;
    options.exr_pixel_type = ExrPixelType::kFloat;
    ASSERT_TRUE(write_image_file(path, image, std::nullopt, options).ok());
    const RawImage raw = read_with_oiio(path, OIIO::TypeDesc::FLOAT);
    EXPECT_EQ(raw.spec.format, OIIO::TypeDesc::FLOAT);
    ASSERT_EQ(raw.spec.nchannels, 4);
    EXPECT_EQ(raw.spec.channelnames[0], "R");
    EXPECT_EQ(raw.spec.channelnames[3], "A");
    ASSERT_EQ(raw.floats.size(), image.pixels.size());
    EXPECT_EQ(
        std::memcmp(raw.floats.data(), image.pixels.data(), image.pixels.size() * sizeof(float)),
        0);

    auto decoded = read_image_file(path);
    ASSERT_TRUE(decoded.ok()) << decoded.error();
    ASSERT_EQ(decoded->pixels.size(), image.pixels.size());
    EXPECT_EQ(std::memcmp(decoded->pixels.data(), image.pixels.data(),
                          image.pixels.size() * sizeof(float)),
              0);
}

TEST(ImageIoExr, HalfKeepsHalfPrecision) {
    Image image = gradient(23, 17, 3, /*specials=*/false);
    image.pixels[4] = 70000.0f;  // above the largest half
    // Half is the default pixel type.
    auto bytes = encode_image(image, ImageFormat::kExr);
    ASSERT_TRUE(bytes.ok()) << bytes.error();
    auto decoded = decode_image(*bytes);
    ASSERT_TRUE(decoded.ok()) << decoded.error();
    ASSERT_EQ(decoded->pixels.size(), image.pixels.size());
    for (size_t i = 0; i < image.pixels.size(); ++i) {
        if (i == 4) {
            EXPECT_EQ(decoded->pixels[i], kInf);
            continue;
        }
        const float want = image.pixels[i];
        // 11 significant bits; values below 2^-14 are subnormal halves with absolute steps 2^-24.
        EXPECT_NEAR(decoded->pixels[i], want, std::max(std::fabs(want) * 0x1p-11f, 0x1p-24f)) << i;
    }
    // Half files are about half the size of float files.
    ImageEncodeOptions as_float;
    as_float.exr_pixel_type = ExrPixelType::kFloat;
    auto float_bytes = encode_image(image, ImageFormat::kExr, as_float);
    ASSERT_TRUE(float_bytes.ok());
    EXPECT_LT(bytes->size(), float_bytes->size());
}

// ---------------------------------------------------------------------------------------------
// JPEG

TEST(ImageIoJpeg, CloseToTheBufferAndAlphaDropped) {
    const Image image = render_bunny(64, true);
    ImageEncodeOptions options;
    options.jpeg_quality = 95;
    auto bytes = encode_image(image, ImageFormat::kJpeg, options);
    ASSERT_TRUE(bytes.ok()) << bytes.error();
    auto decoded = decode_image(*bytes);
    ASSERT_TRUE(decoded.ok()) << decoded.error();
    ASSERT_EQ(decoded->channels, 3u) << "JPEG has no alpha";
    ASSERT_EQ(decoded->width, image.width);
    double error = 0;
    const size_t pixels = size_t{image.width} * image.height;
    for (size_t p = 0; p < pixels; ++p) {
        for (int c = 0; c < 3; ++c) {
            error += std::fabs(srgb_oetf(decoded->pixels[p * 3 + c]) -
                               srgb_oetf(clamp01(image.pixels[p * 4 + c])));
        }
    }
    EXPECT_LT(error / static_cast<double>(pixels * 3), 2.0 / 255.0) << "mean error in sRGB levels";

    options.jpeg_quality = 10;
    auto small = encode_image(image, ImageFormat::kJpeg, options);
    ASSERT_TRUE(small.ok());
    EXPECT_LT(small->size(), bytes->size()) << "quality reaches the encoder";
}

// ---------------------------------------------------------------------------------------------
// Errors

TEST(ImageIoErrors, MalformedImagesAndOptions) {
    Image two_channels{2, 2, 2, Pixels(8)};
    auto r = encode_image(two_channels, ImageFormat::kPng);
    ASSERT_FALSE(r.ok());
    EXPECT_NE(r.error().find("channels"), std::string::npos) << r.error();

    Image empty{0, 4, 3, {}};
    r = encode_image(empty, ImageFormat::kExr);
    ASSERT_FALSE(r.ok());
    EXPECT_NE(r.error().find("empty"), std::string::npos) << r.error();

    Image short_buffer{4, 4, 3, Pixels(47)};
    r = encode_image(short_buffer, ImageFormat::kPng);
    ASSERT_FALSE(r.ok());
    EXPECT_NE(r.error().find("expected 48"), std::string::npos) << r.error();

    ImageEncodeOptions options;
    options.jpeg_quality = 0;
    r = encode_image(gradient(4, 4, 3), ImageFormat::kJpeg, options);
    ASSERT_FALSE(r.ok());
    EXPECT_NE(r.error().find("jpeg_quality"), std::string::npos) << r.error();
}

TEST(ImageIoErrors, UndecodableBytesGiveErrors) {
    const std::vector<std::byte> nothing;
    EXPECT_FALSE(decode_image(nothing).ok());
    std::vector<std::byte> text(64, std::byte{'x'});
    auto r = decode_image(text);
    ASSERT_FALSE(r.ok());
    EXPECT_NE(r.error().find(image_errors::kUnknownMagic), std::string::npos) << r.error();

    // Every prefix of valid files fails cleanly (or, for a prefix that happens to hold every
    // pixel, decodes the right size): never a crash.
    for (ImageFormat format : {ImageFormat::kPng, ImageFormat::kJpeg, ImageFormat::kExr}) {
        SCOPED_TRACE(image_format_name(format));
        auto bytes = encode_image(gradient(16, 8, 3), format);
        ASSERT_TRUE(bytes.ok()) << bytes.error();
        size_t failures = 0;
        for (size_t cut = 0; cut < bytes->size(); cut += std::max<size_t>(1, bytes->size() / 97)) {
            auto prefix = decode_image(std::span<const std::byte>(bytes->data(), cut));
            if (!prefix.ok()) {
                ++failures;
                EXPECT_FALSE(prefix.error().empty());
            } else {
                EXPECT_EQ(prefix->width, 16u);
            }
        }
        EXPECT_GT(failures, 0u);
        // A corrupted body is an error or an image of the declared size, nothing else.
        std::vector<std::byte> corrupt = *bytes;
        for (size_t i = corrupt.size() / 2; i < corrupt.size(); i += 7)
            corrupt[i] = std::byte{0xA5};
        auto damaged = decode_image(corrupt);
        if (damaged.ok()) {
            EXPECT_EQ(damaged->pixels.size(), size_t{16} * 8 * damaged->channels);
        }
    }
}

TEST(ImageIoErrors, TruncatedPngIsRefusedBeforeOiioReadsIt) {
    auto bytes = encode_image(gradient(16, 8, 3), ImageFormat::kPng);
    ASSERT_TRUE(bytes.ok());
    for (size_t cut : {size_t{8}, size_t{20}, bytes->size() / 2, bytes->size() - 1}) {
        auto r = decode_image(std::span<const std::byte>(bytes->data(), cut));
        ASSERT_FALSE(r.ok()) << "cut at " << cut;
        EXPECT_NE(r.error().find(image_errors::kTruncatedPng), std::string::npos) << r.error();
    }
    // Bytes after IEND are ignored, as PNG decoders do.
    std::vector<std::byte> padded = *bytes;
    padded.resize(padded.size() + 5, std::byte{0});
    EXPECT_TRUE(decode_image(padded).ok());
}

TEST(ImageIoErrors, PixelLimitIsCheckedBeforeDecoding) {
    auto bytes = encode_image(gradient(40, 30, 3), ImageFormat::kPng);
    ASSERT_TRUE(bytes.ok());
    ImageDecodeLimits limits;
    limits.max_pixels = 1199;
    auto r = decode_image(*bytes, limits);
    ASSERT_FALSE(r.ok());
    EXPECT_NE(r.error().find(errors::kLimitExceeded), std::string::npos) << r.error();
    limits.max_pixels = 1200;
    EXPECT_TRUE(decode_image(*bytes, limits).ok());
}

TEST(ImageIoErrors, FileErrorsNameThePath) {
    const TempDir dir;
    auto w = write_image_file(dir.file("frame.tiff"), gradient(2, 2, 3));
    ASSERT_FALSE(w.ok());
    EXPECT_NE(w.error().find("frame.tiff"), std::string::npos) << w.error();
    EXPECT_NE(w.error().find(image_errors::kUnknownExtension), std::string::npos) << w.error();
    // An explicit format overrides the extension.
    EXPECT_TRUE(write_image_file(dir.file("frame.bin"), gradient(2, 2, 3), ImageFormat::kPng).ok());
    EXPECT_TRUE(read_image_file(dir.file("frame.bin")).ok()) << "decoding goes by magic bytes";

    auto r = read_image_file(dir.file("missing.png"));
    ASSERT_FALSE(r.ok());
    EXPECT_NE(r.error().find("missing.png"), std::string::npos) << r.error();

    ASSERT_TRUE(
        write_file_bytes(dir.file("junk.png"), std::vector<std::byte>(10, std::byte{1})).ok());
    r = read_image_file(dir.file("junk.png"));
    ASSERT_FALSE(r.ok());
    EXPECT_NE(r.error().find("junk.png"), std::string::npos) << r.error();

    w = write_image_file(dir.file("no-such-dir/frame.png"), gradient(2, 2, 3));
    ASSERT_FALSE(w.ok());
    EXPECT_NE(w.error().find("no-such-dir"), std::string::npos) << w.error();
}

}  // namespace
}  // namespace kdrt::proto
