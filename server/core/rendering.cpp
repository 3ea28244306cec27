#include "core/rendering.h"

#include <chrono>

#include "kdrt/proto/image_module.h"
#include "kdrt/proto/raw_image.h"

namespace kdrt::server {

proto::Result<RenderedImage, std::string> render_and_encode(Compute& compute, const RenderJob& job,
                                                            const RenderControl& control) {
    const RenderSettings& settings = job.settings;
    const proto::ImageFormat format = job.format;
    RenderedImage out;
    const Image image = compute.run([&] {
        return job.scene ? render(*job.scene, settings, control, &out.stats)
                         : render(*job.tree, settings, control, &out.stats);
    });
    const auto start = std::chrono::steady_clock::now();
    if (format == proto::ImageFormat::kRaw) {
        const PixelRegion region =
            settings.region.value_or(PixelRegion{0, 0, settings.width, settings.height});
        out.bytes =
            proto::encode_raw_image(image, region.x, region.y, settings.width, settings.height);
        out.encode_ms =
            std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - start)
                .count();
        return out;
    }
    // The encoders are the image module's (kdrt/proto/image_module.h): encode_render applies
    // the shading's transfer (proto::render_transfer) and job.encode's PNG level (the server sets
    // no other option).
    auto module = proto::image_module();
    if (!module) return proto::Err{module.error()};
    auto encoded = (*module)->encode_render(image, proto::image_format_name(format),
                                            settings.shading, job.encode.png_compression);
    if (!encoded) return proto::Err{"encoding the image failed: " + encoded.error()};
    out.encode_ms =
        std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - start).count();
    out.bytes = std::move(*encoded);
    return out;
}

}  // namespace kdrt::server
