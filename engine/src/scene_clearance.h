#pragma once
// Internal: the test of a hit against a HitClearance (kdrt/hit_clearance.h; scene_trace.cpp's
// nearest hits).
//
// A merged every-hit query (AllHitsOptions::merge_coincident) reports, as its first hit, the
// lowest prim of the closest hit's coincident group facing each way. The group is the closest hit
// alone unless the next raw hit is within the merge tolerance in t and shares a vertex with the
// closest hit's triangle T. HitClearance rules that out from the hit's position: per triangle T
// (computed once per mesh tree) the three planes through T's edges, perpendicular to T, scaled
// by a factor g in [0, 1] such that every triangle sharing a vertex with T lies at least
// g * (the distance of a point P of T to T's nearest edge) from P (g = 0 when that cannot be
// shown: a neighbour folded over T, a duplicate of T). A neighbour hit within the tolerance lies
// within a few tolerances of the closest hit's point, so a hit whose scaled distance to T's edges
// is above 2^-15 of the tolerance's magnitude (twice the bound's worst case) is alone in its
// group: its window would answer the closest hit itself.

#include <cmath>
#include <limits>

#include "kdrt/hit_clearance.h"
#include "kdrt/kdtree.h"
#include "kdrt/trace.h"

namespace kdrt::detail {

/// True when the merged every-hit query of the object ray `o` from `first.t` (its closest hit,
/// a hit) answers `first` itself as its first hit: no triangle sharing a vertex with first's can
/// hit within the merge tolerance.
[[gnu::always_inline]] inline bool hit_is_alone(const HitClearance& c, const Ray& o,
                                                const Hit& first) noexcept {
    const ClearanceRecord& r = c.records()[first.prim];
    const double t = first.t;
    const double p[3] = {o.ox + t * o.dx, o.oy + t * o.dy, o.oz + t * o.dz};
    double s = std::numeric_limits<double>::infinity();
    for (int i = 0; i < 3; ++i) {
        const float* q = r.plane[i];
        const double si = double{q[0]} * p[0] + double{q[1]} * p[1] + double{q[2]} * p[2] - q[3];
        s = si < s ? si : s;
    }
    float m = r.mag;
    for (const float x : {o.ox, o.oy, o.oz}) m = std::fabs(x) > m ? std::fabs(x) : m;
    return s > 0x1p-15 * static_cast<double>(m);
}

}  // namespace kdrt::detail
