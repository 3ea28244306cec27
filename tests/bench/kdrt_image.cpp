// kdrt-image: writes a float image as PNG, JPEG or OpenEXR through kdrt::proto (OpenImageIO).
// kdrt-bench's helper for `render --out`, so that kdrt-bench itself never loads OpenImageIO.
//
//   kdrt-image raw WIDTH HEIGHT CHANNELS OUT [--exr-type half|float] [--jpeg-quality Q]
//
// reads WIDTH * HEIGHT * CHANNELS native floats (a kdrt::Image's pixels: linear, row-major, top
// row first) from standard input and writes OUT in the format its extension names. Exit status:
// 0 success, 1 failure (message on stderr), 2 bad command line.

#include <unistd.h>

#include <algorithm>
#include <array>
#include <cerrno>
#include <charconv>
#include <cstring>
#include <exception>
#include <iostream>
#include <optional>
#include <string>
#include <string_view>
#include <system_error>

#include "bench_args.h"
#include "kdrt/proto/image_io.h"
#include "kdrt/render.h"

namespace kdrt::bench {
namespace {

constexpr std::string_view kUsage =
    R"(usage: kdrt-image raw WIDTH HEIGHT CHANNELS OUT [--exr-type half|float] [--jpeg-quality Q]

Reads WIDTH x HEIGHT x CHANNELS native-endian floats (linear RGB or RGBA, top row first) from
standard input and writes OUT: .png (8-bit sRGB), .jpg/.jpeg (8-bit sRGB, no alpha) or .exr
(linear half, or float with --exr-type float). kdrt-bench runs it for `render --out`.
)";

Image read_raw_image(uint32_t width, uint32_t height, uint32_t channels) {
    Image image{width, height, channels, Pixels(size_t{width} * height * channels)};
    auto* data = reinterpret_cast<char*>(image.pixels.data());
    const size_t want = image.pixels.size() * sizeof(float);
    size_t have = 0;
    while (have < want) {
        const ssize_t n = ::read(STDIN_FILENO, data + have, want - have);
        if (n < 0 && errno == EINTR) continue;
        if (n < 0)
            throw BenchError("cannot read the image from standard input: " +
                             std::generic_category().message(errno));
        if (n == 0) {
            throw BenchError("standard input ended after " + std::to_string(have) + " of " +
                             std::to_string(want) + " bytes");
        }
        have += static_cast<size_t>(n);
    }
    return image;
}

int run(const Args& args) {
    static constexpr std::array<std::string_view, 5> kNames = {"raw", "WIDTH", "HEIGHT", "CHANNELS",
                                                               "OUT"};
    args.expect_positional(kNames);
    if (args.positional()[0] != "raw")
        throw UsageError("unknown command '" + args.positional()[0] + "'");
    auto number = [&](size_t index, const char* name, uint64_t min_value, uint64_t max_value) {
        const std::string& text = args.positional()[index];
        uint64_t value = 0;
        const auto [ptr, ec] = std::from_chars(text.data(), text.data() + text.size(), value);
        if (text.empty() || ec != std::errc() || ptr != text.data() + text.size() ||
            value < min_value || value > max_value) {
            throw UsageError(std::string(name) + " '" + text + "' is not an integer in [" +
                             std::to_string(min_value) + ", " + std::to_string(max_value) + "]");
        }
        return static_cast<uint32_t>(value);
    };
    const uint32_t width = number(1, "WIDTH", 1, kMaxImageSize);
    const uint32_t height = number(2, "HEIGHT", 1, kMaxImageSize);
    const uint32_t channels = number(3, "CHANNELS", 3, 4);  // RGB or RGBA
    const std::string& out = args.positional()[4];
    proto::ImageEncodeOptions options;
    const std::string exr_type = args.get("exr-type").value_or("half");
    if (exr_type == "float") {
        options.exr_pixel_type = proto::ExrPixelType::kFloat;
    } else if (exr_type != "half") {
        throw UsageError("option '--exr-type': '" + exr_type + "' is not one of half, float");
    }
    options.jpeg_quality = static_cast<int>(args.get_uint("jpeg-quality", 90, 1, 100));
    if (!proto::image_format_from_path(out)) {
        throw UsageError(std::string(proto::image_errors::kUnknownExtension) + " of '" + out +
                         "' (use .png, .jpg, .jpeg or .exr)");
    }
    const Image image = read_raw_image(width, height, channels);
    auto written = proto::write_image_file(out, image, std::nullopt, options);
    if (!written) throw BenchError(written.error());
    return 0;
}

}  // namespace
}  // namespace kdrt::bench

int main(int argc, char** argv) {
    using namespace kdrt::bench;
    static constexpr std::array<std::string_view, 2> kOptions = {"exr-type", "jpeg-quality"};
    try {
        const Args args(
            std::span<char* const>(argv + 1, static_cast<size_t>(std::max(argc - 1, 0))), kOptions);
        if (args.help()) {
            std::cout << kUsage;
            return 0;
        }
        return run(args);
    } catch (const UsageError& e) {
        std::cerr << "kdrt-image: " << e.what() << "\n\n" << kUsage;
        return 2;
    } catch (const std::exception& e) {
        std::cerr << "kdrt-image: error: " << e.what() << "\n";
        return 1;
    }
}
