// HitClearance (scene_clearance.h): per triangle, how far its vertex neighbours stay from a point
// of it, as a factor of that point's distance to the triangle's edges.
//
// Why a hit passing hit_is_alone is alone in its merged group. Let t0 be the closest hit's t on
// triangle T, P* the exact point where the ray meets T's plane, and M the tolerance's magnitude
// (the largest |coordinate| of T and the object origin; tol = 2^-18 M / dmax, |d| <= sqrt(3)
// dmax). The tolerance is made to cover the rounding of the kernel's t, so a computed t is within
// tol of the exact one; a neighbour N's raw hit at t1 in [t0, t0 + tol] then meets the ray within
// 3 tol of t0*, at a point within sqrt(3) 3 tol dmax = 5.2 2^-18 M of P* (and within a few float
// ulps of M of N: the watertight test's edge functions). The computed point P = o + t0 d lies
// within sqrt(3) 2^-18 M of P*. So such an N comes within 7 2^-18 M of P; the planes' rounding to
// float (below 2^-21 M at such points) and eta below add less than 0.2 2^-18 M, and hit_is_alone
// asks for more than 8 2^-18 M = 2^-15 M.
//
// The bound on the distance: every N sharing a vertex (by position, as merge_groups compares)
// with T is shown to lie in a closed half-space whose boundary is perpendicular to T's plane:
//  - one of T's three edge planes, N outside it: then dist(P, N) >= the distance of P to that
//    edge, >= the distance to T's nearest edge;
//  - or a plane through one of N's edges, T's vertices on the other side at distances f_j >= 0:
//    the distance of P is the barycentric sum of the f_j, and barycentric coordinate j is at
//    least (the distance to T's nearest edge) / h_j (h_j: T's height over vertex j), so
//    dist(P, N) >= g_N (distance to T's nearest edge) with g_N = sum_j f_j / h_j.
// Otherwise (N folded over T, or a copy of it) g = 0 and the hit always gets its window. The
// tests' tolerance eta (2^-36 of the coordinates) absorbs the double rounding at shared vertices.

#include "scene_clearance.h"

#include <algorithm>
#include <array>
#include <bit>
#include <cmath>

#include <tbb/blocked_range.h>
#include <tbb/parallel_for.h>
#include <tbb/parallel_sort.h>
#include <tbb/task_arena.h>

namespace kdrt::detail {
namespace {

using V3 = std::array<double, 3>;

V3 vert(const TriVerts& t, int j) {
    const float* v = j == 0 ? t.v0 : j == 1 ? t.v1 : t.v2;
    return {v[0], v[1], v[2]};
}
V3 sub(const V3& a, const V3& b) { return {a[0] - b[0], a[1] - b[1], a[2] - b[2]}; }
V3 cross(const V3& a, const V3& b) {
    return {a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]};
}
double dot(const V3& a, const V3& b) { return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]; }
double norm(const V3& a) { return std::sqrt(dot(a, a)); }

float max_abs(const TriVerts& t) {
    float m = 0.0f;
    for (const float* v : {t.v0, t.v1, t.v2})
        for (int a = 0; a < 3; ++a) m = std::max(m, std::fabs(v[a]));
    return m;
}

/// A plane n . x = c with unit n; `ok` false when the direction was zero.
struct Plane {
    V3 n{};
    double c = 0.0;
    bool ok = false;
    [[nodiscard]] double at(const V3& x) const { return dot(n, x) - c; }
};

Plane plane_through(const V3& normal, const V3& a, const V3& b) {
    Plane p;
    const V3 m = cross(normal, sub(b, a));
    const double len = norm(m);
    if (!(len > 0.0) || !std::isfinite(len)) return p;
    p.n = {m[0] / len, m[1] / len, m[2] / len};
    p.c = dot(p.n, a);
    p.ok = true;
    return p;
}

/// A vertex position as merge_groups compares it (float ==: -0 and +0 are one position).
std::array<uint32_t, 3> key(const float* v) {
    return {std::bit_cast<uint32_t>(v[0] + 0.0f), std::bit_cast<uint32_t>(v[1] + 0.0f),
            std::bit_cast<uint32_t>(v[2] + 0.0f)};
}

struct Corner {
    std::array<uint32_t, 3> key;
    uint32_t tri;
    uint32_t j;  ///< which of the triangle's corners
    bool operator<(const Corner& o) const {
        if (key[0] != o.key[0]) return key[0] < o.key[0];
        if (key[1] != o.key[1]) return key[1] < o.key[1];
        if (key[2] != o.key[2]) return key[2] < o.key[2];
        return tri < o.tri;
    }
};

/// Corners at one vertex position beyond which its triangles are not looked at (a closed
/// manifold mesh has about six).
constexpr size_t kMaxCornersAtAVertex = 64;

/// The records of build_hit_clearance, by mesh triangle id.
std::vector<ClearanceRecord> clearance_records(const KdTree& tree) {
    const std::vector<TriVerts> tris = triangles_by_id(tree);
    const size_t n = tris.size();
    // Every corner by position, so a triangle's vertex neighbours are the runs of its corners.
    std::vector<Corner> corners(3 * n);
    for (size_t i = 0; i < n; ++i) {
        const float* v[3] = {tris[i].v0, tris[i].v1, tris[i].v2};
        for (int j = 0; j < 3; ++j)
            corners[3 * i + j] = {key(v[j]), static_cast<uint32_t>(i), static_cast<uint32_t>(j)};
    }
    tbb::parallel_sort(corners.begin(), corners.end());
    // run_of[3 i + j]: the first corner at triangle i's vertex j's position; run_end[first]: the
    // end of that position's run of corners.
    std::vector<uint32_t> run_of(3 * n), run_end(corners.size());
    {
        size_t first = 0;
        for (size_t c = 0; c < corners.size(); ++c) {
            if (corners[c].key != corners[first].key) {
                run_end[first] = static_cast<uint32_t>(c);
                first = c;
            }
            run_of[3 * size_t{corners[c].tri} + corners[c].j] = static_cast<uint32_t>(first);
        }
        if (!corners.empty()) run_end[first] = static_cast<uint32_t>(corners.size());
    }
    std::vector<float> mags(n);
    for (size_t i = 0; i < n; ++i) mags[i] = max_abs(tris[i]);
    std::vector<ClearanceRecord> out(n);
    tbb::parallel_for(
        tbb::blocked_range<size_t>(0, n, 256), [&](const tbb::blocked_range<size_t>& r) {
            std::vector<uint32_t> neighbours;
            for (size_t i = r.begin(); i != r.end(); ++i) {
                ClearanceRecord& rec = out[i];
                rec = ClearanceRecord{};
                const TriVerts& t = tris[i];
                rec.mag = mags[i];
                const V3 v[3] = {vert(t, 0), vert(t, 1), vert(t, 2)};
                const V3 normal = cross(sub(v[1], v[0]), sub(v[2], v[0]));
                if (!(norm(normal) > 0.0)) continue;  // degenerate: never hit
                // Edge plane j: through the edge opposite vertex j, inwards; h[j] its height.
                Plane edge[3];
                double h[3];
                bool ok = true;
                for (int j = 0; j < 3 && ok; ++j) {
                    edge[j] = plane_through(normal, v[(j + 1) % 3], v[(j + 2) % 3]);
                    ok = edge[j].ok;
                    if (!ok) break;
                    if (edge[j].at(v[j]) < 0.0) {
                        edge[j].n = {-edge[j].n[0], -edge[j].n[1], -edge[j].n[2]};
                        edge[j].c = -edge[j].c;
                    }
                    h[j] = edge[j].at(v[j]);
                    ok = h[j] > 0.0 && std::isfinite(h[j]);
                }
                if (!ok) continue;
                // The vertex neighbours, each once (one sharing an edge is in two runs). A vertex
                // shared by more than kMaxCornersAtAVertex corners (a fan, a pole) is not looked
                // at: its triangles always get their window, and the work stays linear in the mesh.
                bool crowded = false;
                for (int j = 0; j < 3; ++j) {
                    const size_t first = run_of[3 * i + j];
                    crowded = crowded || run_end[first] - first > kMaxCornersAtAVertex;
                }
                if (crowded) continue;
                neighbours.clear();
                for (int j = 0; j < 3; ++j) {
                    const size_t first = run_of[3 * i + j];
                    for (size_t c = first; c < run_end[first]; ++c)
                        if (corners[c].tri != i) neighbours.push_back(corners[c].tri);
                }
                std::sort(neighbours.begin(), neighbours.end());
                neighbours.erase(std::unique(neighbours.begin(), neighbours.end()),
                                 neighbours.end());
                double g = 1.0;
                for (const uint32_t other : neighbours) {
                    if (!(g > 0.0)) break;
                    const TriVerts& nt = tris[other];
                    const V3 w[3] = {vert(nt, 0), vert(nt, 1), vert(nt, 2)};
                    const double eta =
                        0x1p-36 * static_cast<double>(std::max(rec.mag, mags[other]));
                    // One of T's edge planes with N outside it.
                    bool separated = false;
                    for (int e = 0; e < 3 && !separated; ++e)
                        separated = edge[e].at(w[0]) <= eta && edge[e].at(w[1]) <= eta &&
                                    edge[e].at(w[2]) <= eta;
                    if (separated) continue;
                    // A plane through one of N's edges, perpendicular to T.
                    double best = 0.0;
                    for (int e = 0; e < 3; ++e) {
                        const Plane q = plane_through(normal, w[e], w[(e + 1) % 3]);
                        if (!q.ok) continue;
                        const double fn[3] = {q.at(w[0]), q.at(w[1]), q.at(w[2])};
                        const double ft[3] = {q.at(v[0]), q.at(v[1]), q.at(v[2])};
                        for (const double sign : {1.0, -1.0}) {
                            bool fits = true;
                            for (int k = 0; k < 3; ++k)
                                fits = fits && sign * fn[k] <= eta && sign * ft[k] >= -eta;
                            if (!fits) continue;
                            double gn = 0.0;
                            for (int k = 0; k < 3; ++k) gn += std::max(sign * ft[k], 0.0) / h[k];
                            best = std::max(best, gn);
                        }
                    }
                    g = std::min(g, best);
                }
                // The bound holds up to 2 eta; below the tolerance's 2^-18 M by far, and covered by
                // the factor 8 in hit_is_alone. A g that small is worth nothing anyway.
                if (!(g >= 0x1p-20)) g = 0.0;
                for (int j = 0; j < 3; ++j) {
                    for (int a = 0; a < 3; ++a)
                        rec.plane[j][a] = static_cast<float>(g * edge[j].n[a]);
                    rec.plane[j][3] = static_cast<float>(g * edge[j].c);
                }
            }
        });
    return out;
}

}  // namespace
}  // namespace kdrt::detail

namespace kdrt {

HitClearance build_hit_clearance(const KdTree& tree) {
    HitClearance out;
    out.tris_ = detail::clearance_records(tree);
    return out;
}

}  // namespace kdrt
