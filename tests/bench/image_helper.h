#pragma once
/// `kdrt-bench render --out FILE`: images are written by the kdrt-image helper, not by kdrt-bench.
/// Linking OpenImageIO pulls in ~260 shared libraries and adds about 0.2 s to every process start
/// (measured on Debian 12), which would slow every kdrt-bench command; the helper pays it only
/// when an image is actually written.

#include <filesystem>

#include "kdrt/render.h"

namespace kdrt::bench {

/// Writes `image` to `path` (.png, .jpg/.jpeg: 8-bit sRGB; .exr: half) by running the kdrt-image
/// executable that sits next to the running kdrt-bench and piping the float pixels to it.
/// Throws BenchError when the helper is missing, cannot be started or reports a failure (its own
/// message goes to stderr).
void write_image_with_helper(const std::filesystem::path& path, const Image& image);

}  // namespace kdrt::bench
