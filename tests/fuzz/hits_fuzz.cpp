// KDRH decoder. Decoded hits re-encode to exactly the input bytes.

#include "fuzz_check.h"
#include "kdrt/proto/ray_batch.h"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
    using namespace kdrt;
    const auto body = fuzz::as_bytes(data, size);
    const auto hits = proto::decode_hits(body);
    if (hits) {
        const auto again = proto::encode_hits(*hits);
        fuzz::require(again.size() == size && std::equal(again.begin(), again.end(), body.begin()));
    } else {
        fuzz::require(!hits.error().detail.empty());
    }
    return 0;
}
