// KDRP and KDRD decoders, and query points as text. A body that decodes re-encodes to exactly the
// input bytes; refusals carry a detail; the text parser never accepts a non-finite coordinate.

#include <cmath>
#include <string_view>
#include <vector>

#include "fuzz_check.h"
#include "kdrt/proto/distance.h"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
    using namespace kdrt;
    const auto body = fuzz::as_bytes(data, size);
    for (const bool reject : {false, true}) {
        const auto points = proto::decode_points(body, {.reject_non_finite = reject});
        if (points) {
            const auto again = proto::encode_points(*points);
            fuzz::require(again.size() == size &&
                          std::equal(again.begin(), again.end(), body.begin()));
        } else {
            fuzz::require(!points.error().detail.empty());
        }
    }
    const auto answers = proto::decode_distances(body);
    if (answers) {
        const auto again = proto::encode_distances(answers->points, answers->signed_query);
        fuzz::require(again.size() == size && std::equal(again.begin(), again.end(), body.begin()));
    } else {
        fuzz::require(!answers.error().detail.empty());
    }
    const auto text =
        proto::parse_points_text(std::string_view(reinterpret_cast<const char*>(data), size));
    if (text) {
        for (const Vec3& p : *text)
            fuzz::require(std::isfinite(p.x) && std::isfinite(p.y) && std::isfinite(p.z));
    } else {
        fuzz::require(!text.error().empty());
    }
    return 0;
}
