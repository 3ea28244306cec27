#pragma once
/// Render + encode, shared by POST /v1/render and the async job worker.

#include <cstddef>
#include <cstdint>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include "core/compute.h"
#include "kdrt/kdtree.h"
#include "kdrt/proto/image_format.h"
#include "kdrt/proto/result.h"
#include "kdrt/render.h"
#include "kdrt/scene.h"

namespace kdrt::server {

struct RenderedImage {
    std::vector<std::byte> bytes;  ///< the encoded file (KDRI for ImageFormat::kRaw)
    RenderStats stats;
    double encode_ms = 0;
};

/// What a render draws and how it is encoded (POST /v1/render, POST /v1/scenes/{id}/render and
/// their async jobs): a mesh's tree, or a scene revision.
struct RenderJob {
    std::string mesh;                    ///< a mesh render: the mesh id
    std::shared_ptr<const KdTree> tree;  ///< held from submission: the job survives eviction
    /// A scene render instead (`tree` null): the revision (which holds its meshes' trees), its
    /// scene id and revision number.
    std::optional<Scene> scene;
    std::string scene_id;
    uint64_t revision = 0;
    RenderSettings settings;  ///< already validated
    proto::ImageFormat format = proto::ImageFormat::kPng;
    proto::ImageEncodeOptions encode;  ///< PNG compression level
};

/// Renders `job`'s mesh or scene inside the compute arena and encodes the image (through
/// the image module, with the shading's 8-bit transfer; kRaw as the KDRI of the settings' region of
/// the frame). Throws what render() throws (RenderError for settings the tree cannot satisfy,
/// RenderCancelled); an encoder failure is returned as an error string.
[[nodiscard]] proto::Result<RenderedImage, std::string> render_and_encode(
    Compute& compute, const RenderJob& job, const RenderControl& control = {});

}  // namespace kdrt::server
