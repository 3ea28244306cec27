// The incremental KDRR decoder (proto::RayStreamDecoder), which the server feeds a ray batch with
// as it arrives. Input: two control bytes, then the body. Control byte 0: bit 0 declares the body's
// size in advance (as a Content-Length does), bit 1 refuses non-finite rays, bit 2 writes the
// records through next_window()/commit() instead of feed(); control byte 1 seeds the piece sizes.
// Oracle: whatever the pieces, the verdict is decode_rays's for the same bytes (same code and
// detail), and an accepted batch holds exactly the rays decode_rays gives.

#include <algorithm>
#include <cstring>
#include <vector>

#include "fuzz_check.h"
#include "kdrt/proto/ray_batch.h"
#include "kdrt/proto/ray_stream_decoder.h"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
    using namespace kdrt;
    if (size < 2) return 0;
    const uint8_t mode = data[0];
    uint32_t piece_seed = data[1] * 2654435761u + 1;
    const auto body = fuzz::as_bytes(data + 2, size - 2);
    const proto::DecodeLimits limits{.max_rays = 4096, .reject_non_finite = (mode & 2) != 0};

    std::vector<Ray> storage;
    bool asked = false;
    proto::RayStreamDecoder decoder(
        limits,
        [&](uint32_t count, bool) {
            fuzz::require(!asked && count <= limits.max_rays);
            asked = true;
            storage.assign(count, Ray{});
            return std::span<Ray>(storage);
        },
        (mode & 1) ? std::optional<uint64_t>(body.size()) : std::nullopt);

    size_t at = 0;
    bool going = true;
    while (at < body.size()) {
        piece_seed = piece_seed * 1103515245u + 12345u;
        size_t n = std::min<size_t>(body.size() - at, 1 + (piece_seed >> 16) % 97);
        const auto window = decoder.next_window();
        if ((mode & 4) && going && !window.empty()) {
            n = std::min(n, window.size());
            std::memcpy(window.data(), body.data() + at, n);
            going = decoder.commit(n);
        } else {
            going = decoder.feed(body.subspan(at, n)) && going;
        }
        at += n;
        fuzz::require(decoder.bytes_seen() == at);
        fuzz::require(decoder.rays_ready() <= storage.size());
    }
    const auto verdict = decoder.finish();
    const auto whole = proto::decode_rays(body, limits);
    fuzz::require(verdict.ok() == whole.ok());
    if (!whole.ok()) {
        fuzz::require(verdict.error().code == whole.error().code);
        fuzz::require(verdict.error().detail == whole.error().detail);
        return 0;
    }
    fuzz::require(decoder.occlusion() == whole->occlusion);
    fuzz::require(storage.size() == whole->rays.size());
    fuzz::require(storage.empty() || std::memcmp(storage.data(), whole->rays.data(),
                                                 storage.size() * sizeof(Ray)) == 0);
    return 0;
}
