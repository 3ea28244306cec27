#include "rendering.h"

#include <chrono>

namespace kdrt::server {

proto::Result<RenderedImage, std::string> render_and_encode(Compute& compute, const KdTree& tree,
                                                            const RenderSettings& settings,
                                                            proto::ImageFormat format,
                                                            const proto::ImageEncodeOptions& encode,
                                                            const RenderControl& control) {
    RenderedImage out;
    const Image image = compute.run([&] { return render(tree, settings, control, &out.stats); });
    const auto start = std::chrono::steady_clock::now();
    auto encoded = proto::encode_image(image, format, encode);
    if (!encoded) return proto::Err{"encoding the image failed: " + encoded.error()};
    out.encode_ms =
        std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - start).count();
    out.bytes = std::move(*encoded);
    return out;
}

}  // namespace kdrt::server
