#pragma once
/// Depth images (kdrt::DepthImage) as OpenEXR files, through OpenImageIO (kdrt_proto_image).
///
/// Channels, all full resolution, scanline order top row first, zip compression:
///   "Z" (depth) or "range" (range) as 32-bit float, +inf for a miss;
///   "prim" as 32-bit unsigned int, 4294967295 (0xFFFFFFFF) for a miss;
///   with normals, "N.X", "N.Y", "N.Z" as 32-bit float (0 0 0 for a miss);
///   a scene's scan with geometry ids: "geometry_id" as 32-bit unsigned int, last (4294967295 for
///   a miss).
/// The header also carries the string attribute "kdrt:depth_kind" ("depth" or "range").
/// Every value is stored exactly (no half floats), so decoding gives back the same bits. The file
/// also holds OpenImageIO's "DateTime" (the time of encoding): the only bytes two encodings of
/// one image differ in.

#include <cstddef>
#include <cstdint>
#include <span>
#include <string>
#include <vector>

#include "kdrt/proto/result.h"
#include "kdrt/scan_types.h"

namespace kdrt::proto {

/// Encodes `image` (planes matching width x height, see encode_depth_image) as an EXR file in
/// memory, with a "geometry_id" channel when `geometry_ids` is not empty (one per pixel, a scene
/// scan's plane). Errors name the problem (OpenImageIO's message).
[[nodiscard]] Result<std::vector<std::byte>, std::string> encode_depth_exr(
    const DepthImage& image, std::span<const uint32_t> geometry_ids = {});

/// Decodes an EXR written by encode_depth_exr (the channels above, in any order; extra channels
/// are ignored). Errors name a missing channel or a wrong channel type; max_pixels caps
/// width x height before the pixels are read. A non-null `geometry_ids` gets the "geometry_id"
/// channel (one per pixel), or is left empty when the file has none.
[[nodiscard]] Result<DepthImage, std::string> decode_depth_exr(
    std::span<const std::byte> bytes, uint64_t max_pixels = 1ull << 28,
    std::vector<uint32_t>* geometry_ids = nullptr);

}  // namespace kdrt::proto
