// Distance queries (kdrt/distance.h): the point-triangle closest point in double, the kD-tree
// nearest-triangle search pruned by cell distance, the brute-force oracle, and the surface index
// behind the sign (angle-weighted pseudonormals, Baerentzen & Aanaes 2005).

#include "kdrt/distance.h"

#include <algorithm>
#include <array>
#include <atomic>
#include <climits>
#include <cmath>
#include <cstdint>
#include <mutex>
#include <tuple>
#include <vector>

#include <tbb/blocked_range.h>
#include <tbb/parallel_for.h>
#include <tbb/partitioner.h>

#include "distance_internal.h"
#include "geometry.h"

namespace kdrt {
namespace {

using D3 = std::array<double, 3>;

D3 vert(const float* v) noexcept { return {v[0], v[1], v[2]}; }
D3 sub(const D3& a, const D3& b) noexcept { return {a[0] - b[0], a[1] - b[1], a[2] - b[2]}; }
D3 sub(const double* a, const D3& b) noexcept { return {a[0] - b[0], a[1] - b[1], a[2] - b[2]}; }
double dot3(const D3& a, const D3& b) noexcept { return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]; }

/// The closest point of segment a + t (b - a), t in [0, 1], as a TriangleClosest with the
/// weights of the segment's ends given by `set`.
template <class SetWeights>
TriangleClosest on_segment(const D3& a, const D3& b, const double p[3], Feature edge, Feature end_a,
                           Feature end_b, SetWeights set) noexcept {
    const D3 ab = sub(b, a), ap = sub(p, a);
    const double len2 = dot3(ab, ab);
    double t = len2 > 0.0 ? dot3(ab, ap) / len2 : 0.0;
    Feature feature = edge;
    if (!(t > 0.0)) {
        t = 0.0;
        feature = end_a;
    } else if (t >= 1.0) {
        t = 1.0;
        feature = end_b;
    }
    TriangleClosest c;
    c.feature = feature;
    set(c, t);
    for (int k = 0; k < 3; ++k) c.point[k] = a[k] + t * ab[k];
    return c;
}

double squared_distance(const double p[3], const double q[3]) noexcept {
    const double x = p[0] - q[0], y = p[1] - q[1], z = p[2] - q[2];
    return x * x + y * y + z * z;
}

/// Squared distance from p to the bounding box of `tri` (a lower bound of its distance).
double box_distance2(const TriVerts& tri, const double p[3]) noexcept {
    double d2 = 0.0;
    for (int a = 0; a < 3; ++a) {
        const double lo = std::min({tri.v0[a], tri.v1[a], tri.v2[a]});
        const double hi = std::max({tri.v0[a], tri.v1[a], tri.v2[a]});
        const double d = p[a] < lo ? lo - p[a] : (p[a] > hi ? p[a] - hi : 0.0);
        d2 += d * d;
    }
    return d2;
}

/// The best triangle so far: smallest d2, then lowest prim.
struct Best {
    double d2;
    uint32_t prim = kNoHit;
    TriangleClosest closest;
};

void consider(const TriVerts& tri, uint32_t prim, const double p[3], Best& best) noexcept {
    const TriangleClosest c = closest_on_triangle(tri, p);
    if (c.feature == Feature::kNone) return;
    if (c.d2 < best.d2 || (c.d2 == best.d2 && prim < best.prim)) best = {c.d2, prim, c};
}

bool valid_query(Vec3 p, const DistanceOptions& options) noexcept {
    return detail::is_finite(p) && options.max_distance >= 0.0f;  // false for a NaN limit
}

ClosestPoint finish(const Best& best, const SurfaceIndex& index, const double p[3],
                    const DistanceOptions& options) noexcept {
    ClosestPoint out;
    if (best.prim == kNoHit) return out;
    const TriangleClosest& c = best.closest;
    out.prim = best.prim;
    out.distance = static_cast<float>(std::sqrt(c.d2));
    out.u = static_cast<float>(c.u);
    out.v = static_cast<float>(c.v);
    out.point = {static_cast<float>(c.point[0]), static_cast<float>(c.point[1]),
                 static_cast<float>(c.point[2])};
    out.feature = c.feature;
    if (options.sign && index.closed) {
        // The interior of a closed mesh lies within its bounding box: a point outside the box is
        // outside, whatever the rounding of a far point's closest feature says (issue 25).
        for (int a = 0; a < 3; ++a) {
            if (p[a] < index.bounds.lo[a] || p[a] > index.bounds.hi[a]) {
                out.side = Side::kOutside;
                return out;
            }
        }
        const float* n =
            &index.pseudonormals[(size_t{best.prim} * 7 + static_cast<size_t>(c.feature)) * 3];
        const double s =
            (p[0] - c.point[0]) * n[0] + (p[1] - c.point[1]) * n[1] + (p[2] - c.point[2]) * n[2];
        out.side = s < 0.0 ? Side::kInside : Side::kOutside;
    }
    return out;
}

using Cell = detail::NearestSearch::Cell;

/// Squared distance from p to the box [lo, hi] (0 inside it). Each axis's difference of two floats
/// is rounded once in double, so the result is within a few ulps of the exact distance.
double cell_distance2(const float lo[3], const float hi[3], const double p[3]) noexcept {
    double d2 = 0.0;
    for (int a = 0; a < 3; ++a) {
        const double d = p[a] < lo[a] ? lo[a] - p[a] : (p[a] > hi[a] ? p[a] - hi[a] : 0.0);
        d2 += d * d;
    }
    return d2;
}

/// Min-heap order on the cells' distance.
bool farther(const Cell& a, const Cell& b) noexcept { return a.d2 > b.d2; }

}  // namespace

namespace detail {

ClosestPoint NearestSearch::run(const KdTree& tree, const SurfaceIndex& index, Vec3 p,
                                const DistanceOptions& options) {
    if (!valid_query(p, options) || tree.bounds.empty()) return {};
    const double q[3] = {p.x, p.y, p.z};
    const double max_d = options.max_distance;
    Best best{max_d * max_d, kNoHit, {}};
    // A cell or triangle box is skipped only when every triangle in it has a computed squared
    // distance strictly above the best one, so the answer (ties to the lowest prim included) is
    // brute force's. A computed closest point lies within a few ulps of the mesh's largest
    // coordinate M of its triangle (closest_on_triangle keeps its weights in the triangle), and
    // its squared distance, like a box's, is within a few ulps of the exact one: the bound grows
    // the best distance by 2^-46 of itself (relative rounding, over 100 ulps) plus 2^-40 M
    // (the closest point's error). The slack does not grow with p's own magnitude, so a far point
    // prunes as well as a near one, until its distance is so large (about 10^13 M) that the
    // triangles' rounded distances tie and all must be tested.
    double magnitude = 0.0;
    for (int a = 0; a < 3; ++a)
        magnitude = std::max({magnitude, std::fabs(double{tree.bounds.lo[a]}),
                              std::fabs(double{tree.bounds.hi[a]})});
    const double slack = magnitude * 0x1p-40;
    auto bound_of = [slack](double d2) {
        const double r = std::sqrt(d2) * (1.0 + 0x1p-46) + slack;
        return r * r;
    };
    double bound2 = bound_of(best.d2);

    const KdNode* nodes = tree.nodes.data();
    const uint32_t* refs = tree.leaf_refs.data();
    const TriVerts* tris = tree.tris.data();
    const uint32_t* ids = tree.tri_ids.data();
    // Best first: the heap holds the cells not visited yet by their box distance; the nearest is
    // taken, and its descent follows the child on p's side (at the same distance) while the
    // other child joins the heap. The search ends when the nearest waiting cell is beyond the
    // bound, which shrinks with every better triangle.
    std::vector<Cell>& heap = heap_;
    heap.clear();
    Cell root{0.0, 0, {}, {}};
    for (int a = 0; a < 3; ++a) {
        root.lo[a] = tree.bounds.lo[a];
        root.hi[a] = tree.bounds.hi[a];
    }
    root.d2 = cell_distance2(root.lo, root.hi, q);
    if (root.d2 <= bound2) heap.push_back(root);
    while (!heap.empty()) {
        std::pop_heap(heap.begin(), heap.end(), farther);
        Cell cell = heap.back();
        heap.pop_back();
        if (cell.d2 > bound2) break;  // every other waiting cell is at least as far
        KdNode node = nodes[cell.node];
        ++work;
        while (!node.is_leaf()) {
            const int axis = node.axis();
            const float split = node.split();
            const bool high_side = q[axis] >= double{split};
            Cell far = cell;
            far.node = high_side ? node.first_child() : node.first_child() + 1;
            (high_side ? far.hi : far.lo)[axis] = split;
            far.d2 = cell_distance2(far.lo, far.hi, q);
            if (far.d2 <= bound2) {
                heap.push_back(far);
                std::push_heap(heap.begin(), heap.end(), farther);
            }
            // The near child keeps the cell's distance.
            (high_side ? cell.lo : cell.hi)[axis] = split;
            cell.node = high_side ? node.first_child() + 1 : node.first_child();
            node = nodes[cell.node];
            ++work;
        }
        const uint32_t end = node.first_ref() + node.prim_count();
        for (uint32_t r = node.first_ref(); r < end; ++r) {
            const uint32_t slot = refs[r] & ~KdTree::kLastRef;
            if (box_distance2(tris[slot], q) > bound2) continue;
            ++work;
            const uint32_t before = best.prim;
            const double before_d2 = best.d2;
            consider(tris[slot], ids[slot], q, best);
            if (best.prim != before || best.d2 != before_d2) bound2 = bound_of(best.d2);
        }
    }
    return finish(best, index, q, options);
}

DistanceBatch::DistanceBatch(const DistanceControl& control) noexcept
    : control_(control), max_work_(control.max_work == 0 ? UINT64_MAX : control.max_work) {}

void DistanceBatch::stop(DistanceStatus status) noexcept {
    int done = static_cast<int>(DistanceStatus::kDone);
    status_.compare_exchange_strong(done, static_cast<int>(status));
}

bool DistanceBatch::stopped() noexcept {
    if (status_.load(std::memory_order_relaxed) != static_cast<int>(DistanceStatus::kDone))
        return true;
    if (control_.cancel != nullptr && control_.cancel->load(std::memory_order_relaxed)) {
        stop(DistanceStatus::kCancelled);
        return true;
    }
    return false;
}

bool DistanceBatch::charge(uint64_t work) {
    const uint64_t before = work_.fetch_add(work, std::memory_order_relaxed);
    const uint64_t after = before + work;
    if (after > max_work_) {
        stop(DistanceStatus::kOverWork);
        return false;
    }
    // The thread whose work crosses a multiple of kDistancePollWork polls.
    if (control_.poll && before / kDistancePollWork != after / kDistancePollWork) {
        if (std::unique_lock lock(poll_mutex_, std::try_to_lock); lock) control_.poll();
    }
    return true;
}

DistanceStats DistanceBatch::stats() const noexcept {
    DistanceStats stats;
    stats.work = work_.load();
    stats.status = static_cast<DistanceStatus>(status_.load());
    return stats;
}

}  // namespace detail

TriangleClosest closest_on_triangle(const TriVerts& tri, const double p[3]) noexcept {
    double n[3];
    if (detail::edge_cross(tri, n) == 0.0) return {};  // zero area: no surface (the builder's rule)
    // Ericson, Real-Time Collision Detection 5.1.5: the Voronoi region of p among the corners,
    // edges and face, from dot products of edge vectors (exact differences of floats).
    const D3 a = vert(tri.v0), b = vert(tri.v1), c = vert(tri.v2);
    const D3 ab = sub(b, a), ac = sub(c, a), ap = sub(p, a);
    TriangleClosest r;
    auto at_corner = [&](const D3& q, Feature f, double u, double v) {
        r.feature = f;
        r.u = u;
        r.v = v;
        for (int k = 0; k < 3; ++k) r.point[k] = q[k];
    };
    auto on_edge = [&](const D3& from, const D3& along, double t, Feature f, double u, double v) {
        r.feature = f;
        r.u = u;
        r.v = v;
        for (int k = 0; k < 3; ++k) r.point[k] = from[k] + t * along[k];
    };
    const double d1 = dot3(ab, ap), d2 = dot3(ac, ap);
    const D3 bp = sub(p, b);
    const double d3 = dot3(ab, bp), d4 = dot3(ac, bp);
    const D3 cp = sub(p, c);
    const double d5 = dot3(ab, cp), d6 = dot3(ac, cp);
    const double vc = d1 * d4 - d3 * d2, vb = d5 * d2 - d1 * d6, va = d3 * d6 - d5 * d4;
    if (d1 <= 0.0 && d2 <= 0.0) {
        at_corner(a, Feature::kVertex0, 0.0, 0.0);
    } else if (d3 >= 0.0 && d4 <= d3) {
        at_corner(b, Feature::kVertex1, 1.0, 0.0);
    } else if (d6 >= 0.0 && d5 <= d6) {
        at_corner(c, Feature::kVertex2, 0.0, 1.0);
    } else if (vc <= 0.0 && d1 >= 0.0 && d3 <= 0.0) {
        const double t = d1 / (d1 - d3);
        on_edge(a, ab, t, Feature::kEdge01, t, 0.0);
    } else if (vb <= 0.0 && d2 >= 0.0 && d6 <= 0.0) {
        const double t = d2 / (d2 - d6);
        on_edge(a, ac, t, Feature::kEdge20, 0.0, t);
    } else if (va <= 0.0 && d4 - d3 >= 0.0 && d5 - d6 >= 0.0) {
        const double t = (d4 - d3) / ((d4 - d3) + (d5 - d6));
        on_edge(b, sub(c, b), t, Feature::kEdge12, 1.0 - t, t);
    } else if (const double denom = va + vb + vc;
               va >= 0.0 && vb >= 0.0 && vc >= 0.0 && denom > 0.0 && std::isfinite(denom)) {
        // The weights are all >= 0, so the point is on the triangle up to rounding: the kD search
        // relies on every computed closest point lying within a few ulps of its triangle.
        const double v = vb / denom, w = vc / denom;
        r.feature = Feature::kFace;
        r.u = v;
        r.v = w;
        for (int k = 0; k < 3; ++k) r.point[k] = a[k] + ab[k] * v + ac[k] * w;
    } else {
        // A sliver so thin, or a point so far, that the region tests disagree in rounding: the
        // nearest of its edges.
        const TriangleClosest e[3] = {
            on_segment(a, b, p, Feature::kEdge01, Feature::kVertex0, Feature::kVertex1,
                       [](TriangleClosest& x, double t) { x.u = t, x.v = 0.0; }),
            on_segment(b, c, p, Feature::kEdge12, Feature::kVertex1, Feature::kVertex2,
                       [](TriangleClosest& x, double t) { x.u = 1.0 - t, x.v = t; }),
            on_segment(c, a, p, Feature::kEdge20, Feature::kVertex2, Feature::kVertex0,
                       [](TriangleClosest& x, double t) { x.u = 0.0, x.v = 1.0 - t; }),
        };
        int pick = 0;
        double best = squared_distance(p, e[0].point);
        for (int k = 1; k < 3; ++k) {
            const double d = squared_distance(p, e[k].point);
            if (d < best) best = d, pick = k;
        }
        r = e[pick];
    }
    r.d2 = squared_distance(p, r.point);
    return r;
}

ClosestPoint closest_point(const KdTree& tree, const SurfaceIndex& index, Vec3 p,
                           const DistanceOptions& options) {
    detail::NearestSearch search;
    return search.run(tree, index, p, options);
}

DistanceStats closest_points(const KdTree& tree, const SurfaceIndex& index,
                             std::span<const Vec3> points, std::span<ClosestPoint> out,
                             const DistanceOptions& options, const DistanceControl& control) {
    detail::DistanceBatch batch(control);
    tbb::parallel_for(
        tbb::blocked_range<size_t>(0, points.size(), detail::kDistanceBlockPoints),
        [&](const tbb::blocked_range<size_t>& range) {
            detail::NearestSearch search;
            for (size_t i = range.begin(); i != range.end(); ++i) {
                if (batch.stopped()) return;
                search.work = 0;
                out[i] = search.run(tree, index, points[i], options);
                if (!batch.charge(search.work)) return;
            }
        },
        tbb::simple_partitioner());
    return batch.stats();
}

ClosestPoint brute_force_closest_point(std::span<const TriVerts> tris, const SurfaceIndex& index,
                                       Vec3 p, const DistanceOptions& options) noexcept {
    if (!valid_query(p, options)) return {};
    const double q[3] = {p.x, p.y, p.z};
    const double max_d = options.max_distance;
    Best best{max_d * max_d, kNoHit, {}};
    for (uint32_t prim = 0; prim < tris.size(); ++prim) consider(tris[prim], prim, q, best);
    return finish(best, index, q, options);
}

SurfaceIndex build_surface_index(const KdTree& tree) {
    const std::vector<TriVerts> tris = triangles_by_id(tree);
    const size_t n = tris.size();
    SurfaceIndex index;
    index.pseudonormals.assign(n * 21, 0.0f);

    // Vertex ids: corners with equal positions (-0 and +0 alike) share one.
    using Key = std::tuple<float, float, float, uint32_t>;
    std::vector<Key> corners;
    corners.reserve(n * 3);
    for (uint32_t t = 0; t < n; ++t) {
        const float* c[3] = {tris[t].v0, tris[t].v1, tris[t].v2};
        for (uint32_t k = 0; k < 3; ++k) index.bounds.extend({c[k][0], c[k][1], c[k][2]});
        for (uint32_t k = 0; k < 3; ++k)
            corners.emplace_back(c[k][0] + 0.0f, c[k][1] + 0.0f, c[k][2] + 0.0f, t * 3 + k);
    }
    std::sort(corners.begin(), corners.end());
    std::vector<uint32_t> vertex_of(n * 3);
    uint32_t vertex_count = 0;
    for (size_t i = 0; i < corners.size(); ++i) {
        if (i > 0 && (std::get<0>(corners[i]) != std::get<0>(corners[i - 1]) ||
                      std::get<1>(corners[i]) != std::get<1>(corners[i - 1]) ||
                      std::get<2>(corners[i]) != std::get<2>(corners[i - 1])))
            ++vertex_count;
        vertex_of[std::get<3>(corners[i])] = vertex_count;
    }
    ++vertex_count;
    corners.clear();
    corners.shrink_to_fit();

    // Face normals (double) and the angle-weighted corner sums.
    std::vector<D3> face(n, D3{0, 0, 0});
    std::vector<uint8_t> degenerate(n, 0);
    std::vector<D3> vertex_sum(vertex_count, D3{0, 0, 0});
    for (uint32_t t = 0; t < n; ++t) {
        double cr[3];
        const double len = detail::edge_cross(tris[t], cr);
        if (!(len > 0.0) || !std::isfinite(len)) {
            degenerate[t] = 1;
            ++index.degenerate_triangles;
            continue;
        }
        face[t] = {cr[0] / len, cr[1] / len, cr[2] / len};
        const D3 v[3] = {vert(tris[t].v0), vert(tris[t].v1), vert(tris[t].v2)};
        for (int k = 0; k < 3; ++k) {
            const D3 e1 = sub(v[(k + 1) % 3], v[k]), e2 = sub(v[(k + 2) % 3], v[k]);
            const D3 x = {e1[1] * e2[2] - e1[2] * e2[1], e1[2] * e2[0] - e1[0] * e2[2],
                          e1[0] * e2[1] - e1[1] * e2[0]};
            const double angle = std::atan2(std::sqrt(dot3(x, x)), dot3(e1, e2));
            D3& s = vertex_sum[vertex_of[t * 3 + k]];
            for (int a = 0; a < 3; ++a) s[a] += angle * face[t][a];
        }
    }
    auto store = [&](uint32_t t, int slot, const D3& v) {
        const double len = std::sqrt(dot3(v, v));
        if (!(len > 0.0)) return;
        for (int a = 0; a < 3; ++a)
            index.pseudonormals[(size_t{t} * 7 + slot) * 3 + a] = static_cast<float>(v[a] / len);
    };
    for (uint32_t t = 0; t < n; ++t) {
        if (degenerate[t]) continue;
        store(t, 0, face[t]);
        for (int k = 0; k < 3; ++k) store(t, 4 + k, vertex_sum[vertex_of[t * 3 + k]]);
    }

    // Edges: (low vertex, high vertex, triangle, edge k, runs low -> high).
    struct Edge {
        uint32_t lo, hi, tri;
        uint8_t k, forward;
    };
    std::vector<Edge> edges;
    edges.reserve(n * 3);
    for (uint32_t t = 0; t < n; ++t) {
        if (degenerate[t]) continue;
        for (uint8_t k = 0; k < 3; ++k) {
            const uint32_t a = vertex_of[t * 3 + k], b = vertex_of[t * 3 + (k + 1) % 3];
            edges.push_back(
                {std::min(a, b), std::max(a, b), t, k, a < b ? uint8_t{1} : uint8_t{0}});
        }
    }
    std::sort(edges.begin(), edges.end(), [](const Edge& x, const Edge& y) {
        return std::tie(x.lo, x.hi, x.tri, x.k) < std::tie(y.lo, y.hi, y.tri, y.k);
    });
    for (size_t i = 0; i < edges.size();) {
        size_t j = i + 1;
        while (j < edges.size() && edges[j].lo == edges[i].lo && edges[j].hi == edges[i].hi) ++j;
        D3 sum{0, 0, 0};
        uint32_t forward = 0;
        for (size_t m = i; m < j; ++m) {
            for (int a = 0; a < 3; ++a) sum[a] += face[edges[m].tri][a];
            forward += edges[m].forward;
        }
        if (j - i == 1) {
            ++index.boundary_edges;
        } else if (j - i > 2) {
            ++index.nonmanifold_edges;
        } else if (forward != 1) {
            ++index.misoriented_edges;
        }
        for (size_t m = i; m < j; ++m) store(edges[m].tri, 1 + edges[m].k, sum);
        i = j;
    }
    index.closed = !edges.empty() && index.boundary_edges == 0 && index.nonmanifold_edges == 0 &&
                   index.misoriented_edges == 0;
    return index;
}

}  // namespace kdrt
