// KDRI decoder (the "format": "raw" render answer, kdrt/proto/raw_image.h). A body that decodes
// holds a region inside its frame, pixels matching the header, at most max_pixels, and re-encodes
// to exactly the input bytes; a refusal carries a detail.

#include <algorithm>
#include <cstdint>

#include "fuzz_check.h"
#include "kdrt/proto/raw_image.h"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
    using namespace kdrt;
    const auto body = fuzz::as_bytes(data, size);
    // The default limit (2^28 pixels) and a small one, so the fuzzer reaches both sides of it.
    for (const uint64_t max_pixels : {uint64_t{1} << 28, uint64_t{64}}) {
        const auto raw = proto::decode_raw_image(body, max_pixels);
        if (!raw) {
            fuzz::require(!raw.error().empty());
            continue;
        }
        const PixelRegion& r = raw->region;
        fuzz::require(r.width >= 1 && r.height >= 1);
        fuzz::require(uint64_t{r.x} + r.width <= raw->frame_width &&
                      uint64_t{r.y} + r.height <= raw->frame_height);
        fuzz::require(uint64_t{r.width} * r.height <= max_pixels);
        fuzz::require(raw->image.width == r.width && raw->image.height == r.height);
        fuzz::require(raw->image.channels == 3 || raw->image.channels == 4);
        fuzz::require(raw->image.pixels.size() ==
                      uint64_t{r.width} * r.height * raw->image.channels);
        fuzz::require(size == proto::kdri_body_size(r.width, r.height, raw->image.channels));
        // Floats are copied as bits (NaN payloads included): the encoder gives the input back.
        const auto again =
            proto::encode_raw_image(raw->image, r.x, r.y, raw->frame_width, raw->frame_height);
        fuzz::require(again.size() == size && std::equal(again.begin(), again.end(), body.begin()));
    }
    return 0;
}
