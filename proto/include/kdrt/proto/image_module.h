#pragma once
/// The image encoders as a run-time module, for kdrt-server and the kdrt CLI. Encoding PNG, JPEG
/// and EXR needs OpenImageIO, whose dependencies are ~250 shared libraries and half a second of
/// CPU to load (more under ASan); a process that never encodes an image must not pay for it. So
/// the encoders (kdrt_proto_image) live in a shared module, kdrt-image-module.so, which the
/// server loads on its first PNG/JPEG/EXR render or EXR scan, and `kdrt render --split` and `kdrt
/// scan -o X.exr` load when they run. The loader is kdrt_image_module_loader (no OpenImageIO).
///
/// Where it is looked for, relative to the running executable (/proc/self/exe), so the build
/// tree and any install prefix work without configuration:
///   <dir of the program>/kdrt-image-module.so     the build tree (the module is built beside
///                                                 kdrt, and linked beside kdrt-server)
///   <dir of the program>/<KDRT_IMAGE_MODULE_RELDIR>/kdrt-image-module.so
///                                                 the install: bindir/../<libdir>/kdrt
/// The module and the program exchange C++ types (Image, DepthImage, Result), so they must come
/// from the same build: the module's entry point returns its ABI number and kdrt version, and a
/// module of another version is refused with a message saying so.

#include <cstddef>
#include <cstdint>
#include <span>
#include <string>
#include <vector>

#include <string_view>

#include "kdrt/image.h"
#include "kdrt/proto/result.h"
#include "kdrt/render_settings.h"
#include "kdrt/scan_types.h"

namespace kdrt::proto {

/// The file name of the module.
inline constexpr const char* kImageModuleFile = "kdrt-image-module.so";

/// The name of the function the module exports (extern "C", returns const ImageModuleTable*).
inline constexpr const char* kImageModuleEntry = "kdrt_image_module_v1";

/// Bumped whenever ImageModuleTable or a type it passes changes layout.
inline constexpr uint32_t kImageModuleAbi = 2;

using EncodedBytes = Result<std::vector<std::byte>, std::string>;

/// What the module exports: its identity and the encoders of kdrt_proto_image.
struct ImageModuleTable {
    uint32_t abi;         ///< kImageModuleAbi of the build that made the module
    const char* version;  ///< KDRT_VERSION of that build
    /// A rendered frame as the server encodes it: proto::encode_image in the format the API
    /// names `format` ("png", "jpg"/"jpeg", "exr"; anything else is an error), with the 8-bit
    /// transfer of `shading` (proto::render_transfer) and PNG level `png_compression`.
    EncodedBytes (*encode_render)(const Image& image, std::string_view format, Shading shading,
                                  int png_compression);
    /// proto::encode_depth_exr (with a "geometry_id" channel when geometry_ids is not empty).
    EncodedBytes (*encode_depth_exr)(const DepthImage& image,
                                     std::span<const uint32_t> geometry_ids);
};

/// The module's table, loaded on the first call (thread-safe; later calls return the same
/// answer). The error is a sentence for the user: which paths were tried and what to install
/// (the module itself, or the OpenImageIO library it needs, by Debian package name), or dlerror's
/// message and why the module was refused.
[[nodiscard]] Result<const ImageModuleTable*, std::string> image_module();

/// The paths image_module() tries, in order (exposed for the tests and the error message).
[[nodiscard]] std::vector<std::string> image_module_candidates();

}  // namespace kdrt::proto
