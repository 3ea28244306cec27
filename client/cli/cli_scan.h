#pragma once
/// The sensor of kdrt scan and kdrt scene scan, from the command line (internal to the CLI).

#include <cstdint>
#include <optional>
#include <span>
#include <string>
#include <vector>

#include "cli_args.h"
#include "cli_context.h"
#include "kdrt/proto/result.h"
#include "kdrt/proto/scan.h"
#include "kdrt/scan_types.h"

namespace kdrt::cli {

/// The options of a scan command: the sensor's, -o and --format.
inline constexpr OptionSpec kScanOptions[] = {
    {"pinhole", false}, {"lidar", false},       {"output", true, 'o'}, {"intrinsics", true},
    {"size", true},     {"pose", true},         {"eye", true},         {"look-at", true},
    {"up", true},       {"fov", true},          {"range", false},      {"normals", false},
    {"channels", true}, {"vertical-fov", true}, {"elevations", true},  {"azimuth-steps", true},
    {"returns", true},  {"min-range", true},    {"max-range", true},   {"format", true},
};

/// Fills `request` from exactly one of --pinhole and --lidar and their options (kdrt scan's help
/// lists them); on a usage error prints it and returns its exit code.
[[nodiscard]] std::optional<int> scan_request_from_args(Context& ctx, proto::ScanRequest& request);

/// What a scan's -o FILE is, from its extension or --format: the binary answer (KDRZ for a
/// pinhole, KDRL for a lidar) or the user file (EXR, PLY).
/// The server's binary answer (KDRZ / KDRL) written as it came, a user file (EXR / PLY) encoded
/// here, or a lidar's compact KDRB answer (.kdrb) written as it came.
enum class ScanFile { kBinary, kUser, kRanges };

/// The format of `output` for a pinhole or a lidar scan; a usage error (printed) otherwise, as its
/// exit code. For an EXR it loads the image module first (before any request is sent), so a
/// missing module is an error before the scan.
[[nodiscard]] proto::Result<ScanFile, int> scan_file_format(Context& ctx, const std::string& output,
                                                            bool pinhole);

/// The user file of a scan, encoded as the server would (kdrt scan and kdrt scene scan share it):
/// exactly one of `depth` (an EXR, through the image module) and `cloud` (a binary PLY), with a
/// "geometry_id" channel / vertex property when `geometry_ids` is not empty (a scene's scan: one
/// id per pixel or point). An encoder failure is printed and returned as its exit code.
[[nodiscard]] proto::Result<std::vector<std::byte>, int> encode_scan_file(
    Context& ctx, const DepthImage* depth, const PointCloud* cloud,
    std::span<const uint32_t> geometry_ids = {});

}  // namespace kdrt::cli
