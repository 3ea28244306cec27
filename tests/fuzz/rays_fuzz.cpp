// KDRR decoder. A decoded batch re-encodes to exactly the input bytes.

#include "fuzz_check.h"
#include "kdrt/proto/ray_batch.h"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
    using namespace kdrt;
    const auto body = fuzz::as_bytes(data, size);
    const auto batch = proto::decode_rays(body);
    if (batch) {
        const auto again = proto::encode_rays(batch->rays, batch->occlusion);
        fuzz::require(again.size() == size && std::equal(again.begin(), again.end(), body.begin()));
        // The strict decode agrees except for refusing non-finite rays.
        const auto strict = proto::decode_rays(body, {.reject_non_finite = true});
        fuzz::require(strict.ok() || strict.error().code == proto::DecodeErrorCode::kNonFiniteRay);
    } else {
        fuzz::require(!batch.error().detail.empty());
    }
    return 0;
}
