#pragma once
/// Depth images (kdrt::DepthImage) as OpenEXR files, through OpenImageIO (kdrt_proto_image).
///
/// Channels, all full resolution, scanline order top row first, zip compression:
///   "Z" (depth) or "range" (range) as 32-bit float, +inf for a miss;
///   "prim" as 32-bit unsigned int, 4294967295 (0xFFFFFFFF) for a miss;
///   with normals, "N.X", "N.Y", "N.Z" as 32-bit float (0 0 0 for a miss).
/// The header also carries the string attribute "kdrt:depth_kind" ("depth" or "range").
/// Every value is stored exactly (no half floats), so decoding gives back the same bits. The file
/// also holds OpenImageIO's "DateTime" (the time of encoding): the only bytes two encodings of
/// one image differ in.

#include <cstddef>
#include <span>
#include <string>
#include <vector>

#include "kdrt/proto/result.h"
#include "kdrt/scan_types.h"

namespace kdrt::proto {

/// Encodes `image` (planes matching width x height, see encode_depth_image) as an EXR file in
/// memory. Errors name the problem (OpenImageIO's message).
[[nodiscard]] Result<std::vector<std::byte>, std::string> encode_depth_exr(const DepthImage& image);

/// Decodes an EXR written by encode_depth_exr (the channels above, in any order; extra channels
/// are ignored). Errors name a missing channel or a wrong channel type; max_pixels caps
/// width x height before the pixels are read.
[[nodiscard]] Result<DepthImage, std::string> decode_depth_exr(std::span<const std::byte> bytes,
                                                               uint64_t max_pixels = 1ull << 28);

}  // namespace kdrt::proto
