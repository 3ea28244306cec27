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

/// `options` with the 8-bit transfer of the shading mode: the sRGB curve for the modes that
/// compute light (eyelight, diffuse); none for the modes that compute data (ao's unoccluded
/// fraction, normals, depth, primid's false colours), so that an ao value of 0.5 is the middle
/// grey level and not the much lighter sRGB level 188. EXR is unaffected (always linear).
[[nodiscard]] proto::ImageEncodeOptions eight_bit_options(const RenderSettings& settings,
                                                          proto::ImageEncodeOptions options);

/// Renders inside the compute arena and encodes the image (with eight_bit_options). Throws what
/// render() throws (RenderError for settings the tree cannot satisfy, RenderCancelled); an encoder
/// failure is returned as an error string.
[[nodiscard]] proto::Result<RenderedImage, std::string> render_and_encode(
    Compute& compute, const KdTree& tree, const RenderSettings& settings, proto::ImageFormat format,
    const proto::ImageEncodeOptions& encode, const RenderControl& control = {});

}  // namespace kdrt::server
