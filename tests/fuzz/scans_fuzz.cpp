// KDRZ (depth image) and KDRL (point cloud) decoders. A body that decodes re-encodes to exactly
// the input bytes (and, for KDRL, as PLY to a header plus the same records); refusals carry a
// detail.

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
    return 0;
}
