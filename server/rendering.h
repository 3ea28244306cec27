#pragma once
/// Render + encode, shared by POST /v1/render and the async job worker.

#include <cstddef>
#include <string>
#include <vector>

#include "compute.h"
#include "kdrt/kdtree.h"
#include "kdrt/proto/image_io.h"
#include "kdrt/proto/result.h"
#include "kdrt/render.h"

namespace kdrt::server {

struct RenderedImage {
    std::vector<std::byte> bytes;  ///< the encoded file
    RenderStats stats;
    double encode_ms = 0;
};

/// Renders inside the compute arena and encodes the image. Throws what render() throws
/// (RenderError for settings the tree cannot satisfy, RenderCancelled); an encoder failure is
/// returned as an error string.
[[nodiscard]] proto::Result<RenderedImage, std::string> render_and_encode(
    Compute& compute, const KdTree& tree, const RenderSettings& settings, proto::ImageFormat format,
    const proto::ImageEncodeOptions& encode, const RenderControl& control = {});

}  // namespace kdrt::server
