#pragma once
/// The sensor of kdrt scan and kdrt scene scan, from the command line (internal to the CLI).

#include <optional>

#include "cli_args.h"
#include "cli_context.h"
#include "kdrt/proto/scan.h"

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

}  // namespace kdrt::cli
