// KDRZ (depth image), KDRL (point cloud) and KDRB (lidar ranges) decoders. A body that decodes
// re-encodes to exactly the input bytes (for KDRL also as PLY to a header plus the same records;
// for KDRB through the PointCloud its beams and order imply); refusals carry a detail.

#include <algorithm>
#include <cstring>

#include "fuzz_check.h"
#include "kdrt/proto/scan.h"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
    using namespace kdrt;
    const auto body = fuzz::as_bytes(data, size);
    const auto image = proto::decode_depth_image(body, 1u << 20);
    if (image) {
        const auto again = proto::encode_depth_image(*image);
        fuzz::require(again.size() == size && std::equal(again.begin(), again.end(), body.begin()));
    } else {
        fuzz::require(!image.error().detail.empty());
    }
    const auto cloud = proto::decode_point_cloud(body, 1u << 20);
    if (cloud) {
        const auto again = proto::encode_point_cloud(*cloud);
        fuzz::require(again.size() == size && std::equal(again.begin(), again.end(), body.begin()));
        const auto ply = proto::encode_point_cloud_ply(*cloud);
        const size_t records = size - proto::kPointCloudHeaderBytes;
        fuzz::require(ply.size() > records &&
                      std::memcmp(ply.data() + (ply.size() - records),
                                  body.data() + proto::kPointCloudHeaderBytes, records) == 0);
    } else {
        fuzz::require(!cloud.error().detail.empty());
    }
    const auto ranges = proto::decode_lidar_ranges(body, 1u << 20);
    if (ranges) {
        PointCloud implied;
        implied.channels = ranges->channels;
        implied.azimuth_steps = ranges->azimuth_steps;
        implied.returns = ranges->returns;
        uint32_t place = 0;
        for (size_t i = 0; i < ranges->points.size(); ++i) {
            const proto::LidarRange& r = ranges->points[i];
            place = i > 0 && r.beam == ranges->points[i - 1].beam ? place + 1 : 0;
            fuzz::require(place < ranges->returns);
            implied.points.push_back(LidarPoint{0, 0, 0, r.range, r.beam % ranges->channels,
                                                r.beam / ranges->channels, place, r.prim});
        }
        const auto again = proto::encode_lidar_ranges(implied);
        fuzz::require(again.size() == size && std::equal(again.begin(), again.end(), body.begin()));
    } else {
        fuzz::require(!ranges.error().detail.empty());
    }
    return 0;
}
