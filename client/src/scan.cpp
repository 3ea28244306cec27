// Client::scan_pinhole / scan_lidar / scan_lidar_ranges: the scan answer decoded with proto
// (kdrt/proto/scan.h).

#include <limits>

#include "kdrt/client/client.h"
#include "kdrt/proto/scan.h"

namespace kdrt {

Result<DepthImage> Client::scan_pinhole(std::string_view id, proto::ScanRequest request) {
    if (request.lidar)
        return proto::Err{make_client_error(ErrorKind::kInput, "not a pinhole scan",
                                            "scan_pinhole was given a lidar request")};
    request.format = proto::ScanFormat::kBinary;
    auto bytes = scan(id, request);
    if (!bytes) return proto::Err{std::move(bytes).error()};
    auto image = proto::decode_depth_image(*bytes, std::numeric_limits<uint64_t>::max());
    if (!image)
        return proto::Err{make_client_error(ErrorKind::kProtocol, "bad response",
                                            "the KDRZ scan answer: " + image.error().to_string())};
    return std::move(*image);
}

Result<PointCloud> Client::scan_lidar(std::string_view id, proto::ScanRequest request) {
    if (!request.lidar)
        return proto::Err{make_client_error(ErrorKind::kInput, "not a lidar scan",
                                            "scan_lidar was given a pinhole request")};
    request.format = proto::ScanFormat::kBinary;
    auto bytes = scan(id, request);
    if (!bytes) return proto::Err{std::move(bytes).error()};
    auto cloud = proto::decode_point_cloud(*bytes, std::numeric_limits<uint32_t>::max());
    if (!cloud)
        return proto::Err{make_client_error(ErrorKind::kProtocol, "bad response",
                                            "the KDRL scan answer: " + cloud.error().to_string())};
    return std::move(*cloud);
}

Result<proto::LidarRanges> Client::scan_lidar_ranges(std::string_view id,
                                                     proto::ScanRequest request) {
    if (!request.lidar)
        return proto::Err{make_client_error(ErrorKind::kInput, "not a lidar scan",
                                            "scan_lidar_ranges was given a pinhole request")};
    request.format = proto::ScanFormat::kRanges;
    auto bytes = scan(id, request);
    if (!bytes) return proto::Err{std::move(bytes).error()};
    auto ranges = proto::decode_lidar_ranges(*bytes, std::numeric_limits<uint32_t>::max());
    if (!ranges)
        return proto::Err{make_client_error(ErrorKind::kProtocol, "bad response",
                                            "the KDRB scan answer: " + ranges.error().to_string())};
    return std::move(*ranges);
}

}  // namespace kdrt
