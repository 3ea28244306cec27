#include "rendering.h"

#include <chrono>

namespace kdrt::server {

proto::ImageEncodeOptions eight_bit_options(const RenderSettings& settings,
                                            proto::ImageEncodeOptions options) {
    const Shading mode = settings.shading;
    const bool light = mode == Shading::kEyelight || mode == Shading::kDiffuse;
    options.transfer = light ? proto::EightBitTransfer::kSrgb : proto::EightBitTransfer::kData;
    return options;
}

proto::Result<RenderedImage, std::string> render_and_encode(Compute& compute, const KdTree& tree,
                                                            const RenderSettings& settings,
                                                            proto::ImageFormat format,
                                                            const proto::ImageEncodeOptions& encode,
                                                            const RenderControl& control) {
    RenderedImage out;
    const Image image = compute.run([&] { return render(tree, settings, control, &out.stats); });
    const auto start = std::chrono::steady_clock::now();
    auto encoded = proto::encode_image(image, format, eight_bit_options(settings, encode));
    if (!encoded) return proto::Err{"encoding the image failed: " + encoded.error()};
    out.encode_ms =
        std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - start).count();
    out.bytes = std::move(*encoded);
    return out;
}

}  // namespace kdrt::server
