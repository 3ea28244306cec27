// KDRM and KDRC decoders. A body that decodes re-encodes to exactly the input bytes.

#include <vector>

#include "fuzz_check.h"
#include "kdrt/proto/multi_hit.h"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
    using namespace kdrt;
    const auto body = fuzz::as_bytes(data, size);
    const auto all = proto::decode_multi_hits(body);
    if (all) {
        std::vector<Hit> hits;
        std::vector<Vec3> normals, points;
        for (const proto::HitRecord& r : all->hits) {
            hits.push_back(Hit{r.t, r.prim, r.u, r.v});
            normals.push_back(r.normal);
            points.push_back(r.point);
        }
        proto::MultiHitsView view;
        view.layout = all->layout;
        view.merged = all->merged;
        view.max_hits = all->max_hits;
        view.offsets = all->offsets;
        view.counts = all->counts;
        view.hits = hits;
        view.normals = normals;
        view.points = points;
        const auto again = proto::encode_multi_hits(view);
        fuzz::require(again.size() == size && std::equal(again.begin(), again.end(), body.begin()));
    } else {
        fuzz::require(!all.error().detail.empty());
    }
    const auto counts = proto::decode_hit_counts(body);
    if (counts) {
        const auto again = proto::encode_hit_counts(*counts);
        fuzz::require(again.size() == size && std::equal(again.begin(), again.end(), body.begin()));
    } else {
        fuzz::require(!counts.error().detail.empty());
    }
    return 0;
}
