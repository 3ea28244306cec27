// kdrt-image-module.so: the image encoders as a module for kdrt-server and `kdrt`
// (kdrt/proto/image_module.h). Built from kdrt_proto_image; exports kdrt_image_module_v1 only.

#include "kdrt/proto/image_io.h"
#include "kdrt/proto/image_module.h"
#include "kdrt/proto/scan_image.h"

namespace {

kdrt::proto::EncodedBytes encode_render(const kdrt::Image& image, std::string_view format,
                                        kdrt::Shading shading, int png_compression) {
    const auto parsed = kdrt::proto::image_format_from_name(format);
    if (!parsed || *parsed == kdrt::proto::ImageFormat::kRaw)
        return kdrt::proto::Err{"unknown image format \"" + std::string(format) + "\""};
    kdrt::proto::ImageEncodeOptions options;
    options.transfer = kdrt::proto::render_transfer(shading);
    options.png_compression = png_compression;
    return kdrt::proto::encode_image(image, *parsed, options);
}

kdrt::proto::EncodedBytes encode_depth_exr(const kdrt::DepthImage& image,
                                           std::span<const uint32_t> geometry_ids) {
    return kdrt::proto::encode_depth_exr(image, geometry_ids);
}

constexpr kdrt::proto::ImageModuleTable kTable{
    .abi = kdrt::proto::kImageModuleAbi,
    .version = KDRT_VERSION,
    .encode_render = encode_render,
    .encode_depth_exr = encode_depth_exr,
};

}  // namespace

extern "C" __attribute__((visibility("default"))) const kdrt::proto::ImageModuleTable*
kdrt_image_module_v1() {
    return &kTable;
}
