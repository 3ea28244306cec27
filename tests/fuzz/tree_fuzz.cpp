// The store's tree file (server/store/tree_file.cpp: the container naming the mesh id) around the
// engine's tree blob (engine/src/serialize.cpp: sizes, permutation and structure checks). A stored
// tree file is read back from disk on every cache miss, so a damaged or planted file must be
// refused with a reason, never crash the server or load a tree that is unsafe to trace.
//
// Input: one mode byte, then the file. Both formats carry checksums that a mutated input would
// almost never match, so the mode byte can repair them first (bit 0: the container's header
// checksum, bit 1: the blob's trailing checksum, bit 2: the container's blob size, bit 3: the mesh
// id) and the fuzzer reaches the checks behind them.
// Oracles: a refusal has a reason label and a detail; a loaded tree re-serialises to exactly the
// blob it came from, and tracing rays through it (single rays and packets) stays in bounds and
// answers only triangles it holds.

#include <bit>
#include <cmath>
#include <cstring>
#include <string_view>
#include <vector>

#include "fuzz_check.h"
#include "kdrt/serialize.h"
#include "kdrt/trace.h"
#include "store/tree_file.h"

namespace {

constexpr std::string_view kId = "5f0c1e2d3b4a69788796a5b4c3d2e1f00f1e2d3c4b5a69788796a5b4c3d2e1f0";
constexpr size_t kIdOffset = 16, kBlobBytesOffset = 80, kChecksumOffset = 88;

uint64_t fnv1a(const uint8_t* data, size_t size) {
    uint64_t h = 0xcbf29ce484222325ull;
    for (size_t i = 0; i < size; ++i) {
        h ^= data[i];
        h *= 0x100000001b3ull;
    }
    return h;
}

/// The blob's trailing checksum, the same mix as engine/src/serialize.cpp's checksum() (internal
/// there). If the engine's changes, fixed-up inputs stop loading and the fuzzer no longer reaches
/// the checks behind the checksum: the seeds tet_valid and grid_valid (mode 0x0f) must load.
uint64_t blob_checksum(const uint8_t* data, size_t size) {
    uint64_t h = 0x9E3779B97F4A7C15ull ^ size;
    size_t i = 0;
    for (; i + 8 <= size; i += 8) {
        uint64_t w;
        std::memcpy(&w, data + i, 8);
        h = std::rotl(h ^ (w * 0xC2B2AE3D27D4EB4Full), 31) * 0x9E3779B97F4A7C15ull;
    }
    uint64_t tail = 0;
    std::memcpy(&tail, data + i, size - i);
    h = std::rotl(h ^ (tail * 0xC2B2AE3D27D4EB4Full), 31) * 0x9E3779B97F4A7C15ull;
    h ^= h >> 33;
    h *= 0xFF51AFD7ED558CCDull;
    h ^= h >> 33;
    return h;
}

void put_u64(std::vector<uint8_t>& file, size_t offset, uint64_t value) {
    std::memcpy(file.data() + offset, &value, 8);
}

}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
    using namespace kdrt;
    if (size == 0) return 0;
    const uint8_t mode = data[0];
    std::vector<uint8_t> file(data + 1, data + size);
    const size_t header = server::kTreeFileHeaderBytes;
    if (file.size() >= header) {
        if (mode & 8) std::memcpy(file.data() + kIdOffset, kId.data(), kId.size());
        if (mode & 4) put_u64(file, kBlobBytesOffset, file.size() - header);
        if ((mode & 2) && file.size() >= header + 16)
            put_u64(file, file.size() - 8,
                    blob_checksum(file.data() + header, file.size() - header - 8));
        if (mode & 1) put_u64(file, kChecksumOffset, fnv1a(file.data(), kChecksumOffset));
    }
    const auto bytes = fuzz::as_bytes(file.data(), file.size());
    auto tree = server::decode_tree_file(kId, bytes);
    if (!tree) {
        fuzz::require(!server::reason_label(tree.error().reason).empty());
        fuzz::require(!tree.error().detail.empty());
        return 0;
    }
    const auto blob = bytes.subspan(header);
    const std::vector<std::byte> again = serialize_tree(*tree);
    fuzz::require(again.size() == blob.size() &&
                  std::equal(again.begin(), again.end(), blob.begin()));

    // Rays from around the bounds through its centre and corners: 4 directions per point, so
    // packets are formed; a few with NaN and reversed intervals.
    const Aabb& b = tree->bounds;
    std::vector<Ray> rays;
    for (int i = 0; i < 64; ++i) {
        const float sx = (i & 1) ? 1.25f : -0.25f, sy = (i & 2) ? 1.25f : -0.25f;
        const float sz = (i & 4) ? 1.25f : -0.25f;
        const float tx = (i & 8) ? 0.5f : 0.3f, ty = (i & 16) ? 0.5f : 0.7f;
        const float tz = (i & 32) ? 0.5f : 0.1f;
        Ray r{};
        const auto at = [&](int axis, float f) {
            return b.lo[axis] + f * (b.hi[axis] - b.lo[axis]);
        };
        r.ox = at(0, sx), r.oy = at(1, sy), r.oz = at(2, sz);
        r.dx = at(0, tx) - r.ox, r.dy = at(1, ty) - r.oy, r.dz = at(2, tz) - r.oz;
        r.tmin = 0;
        r.tmax = (i % 7 == 0) ? 0.5f : INFINITY;
        if (i == 63) r.dx = NAN;
        if (i == 62) r.tmin = 2, r.tmax = 1;
        rays.push_back(r);
    }
    std::vector<Hit> hits(rays.size()), single(rays.size());
    std::vector<uint8_t> blocked(rays.size());
    intersect_block(*tree, rays, hits);
    intersect_single(*tree, rays, single);
    occluded_block(*tree, rays, blocked);
    const size_t tri_count = tree->tri_ids.size();
    for (size_t i = 0; i < rays.size(); ++i) {
        for (const Hit& h : {hits[i], single[i]}) {
            fuzz::require(h.prim == kNoHit || h.prim < tri_count);
            fuzz::require(h.prim == kNoHit || !(h.t > rays[i].tmax));
        }
        fuzz::require(blocked[i] <= 1);
    }
    return 0;
}
