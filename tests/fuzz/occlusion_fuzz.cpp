// KDRO decoder. Decoded bytes are 0/1 and re-encode to exactly the input bytes.

#include "fuzz_check.h"
#include "kdrt/proto/ray_batch.h"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
    using namespace kdrt;
    const auto body = fuzz::as_bytes(data, size);
    const auto occluded = proto::decode_occlusion(body);
    if (occluded) {
        for (uint8_t v : *occluded) fuzz::require(v <= 1);
        const auto again = proto::encode_occlusion(*occluded);
        fuzz::require(again.size() == size && std::equal(again.begin(), again.end(), body.begin()));
    } else {
        fuzz::require(!occluded.error().detail.empty());
    }
    return 0;
}
