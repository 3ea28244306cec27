#pragma once
/// Render + encode, shared by POST /v1/render and the async job worker.

#include <cstddef>
#include <string>
#include <vector>

#include "core/compute.h"
#include "kdrt/kdtree.h"
#include "kdrt/proto/image_io.h"
#include "kdrt/proto/result.h"
#include "kdrt/render.h"

namespace kdrt::server {

struct RenderedImage {
    std::vector<std::byte> bytes;  ///< the encoded file (KDRI for ImageFormat::kRaw)
    RenderStats stats;
    double encode_ms = 0;
};

/// `options` with the 8-bit transfer of the shading mode (proto::render_transfer).
[[nodiscard]] proto::ImageEncodeOptions eight_bit_options(const RenderSettings& settings,
                                                          proto::ImageEncodeOptions options);

/// Renders inside the compute arena and encodes the image (with eight_bit_options; kRaw as the
/// KDRI of the settings' region of the frame). Throws what
/// render() throws (RenderError for settings the tree cannot satisfy, RenderCancelled); an encoder
/// failure is returned as an error string.
[[nodiscard]] proto::Result<RenderedImage, std::string> render_and_encode(
    Compute& compute, const KdTree& tree, const RenderSettings& settings, proto::ImageFormat format,
    const proto::ImageEncodeOptions& encode, const RenderControl& control = {});

}  // namespace kdrt::server
