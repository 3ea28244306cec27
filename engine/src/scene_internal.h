#pragma once
// Internal: a scene's data (per-instance transforms, inverses and world boxes, the top-level
// kD-tree) and the top-level traversals every scene query shares (scene.cpp builds it;
// scene_trace.cpp, scene_distance.cpp and scene_scan.cpp query it).

#include <immintrin.h>

#include <array>
#include <cmath>
#include <cstddef>
#include <cstdint>
#include <optional>
#include <span>
#include <vector>

#include "kdrt/scene.h"
#include "kdrt/trace.h"
// ray_is_valid: the mesh kernels' rule (finite origin and direction, non-zero direction,
// tmin <= tmax), which scene rays follow too.
#include "ray_prep.h"

namespace kdrt::detail {

/// What a query needs of one instance, fixed at build time.
struct InstanceData {
    std::array<double, 9> lin{};  ///< L, row-major (the float entries, exact in double)
    std::array<double, 3> trans{};
    std::array<double, 9> inv{};  ///< L^-1 in double
    double det = 1.0;
    bool identity_linear = false;  ///< L is exactly I (then normals and points are the mesh's)
    std::optional<double> scale;   ///< similarity scale, when L is one
    Aabb world;                    ///< exact image of the tree's root box, rounded outwards
    /// The rounding of object_ray, mapped back to world space, is below kMarginUlps ulps of
    /// kappa * (|o| + |t| + |t_hit d|) (kappa = the inf-norm of |L| |L^-1|), and the mesh
    /// kernel's own rounding of t below lin_bounds = |L|_inf * (largest coordinate of the root
    /// box).
    double kappa = 1.0;
    double trans_mag = 0.0;
    double lin_bounds = 0.0;
    /// The largest |coordinate| of the mesh tree's root box (object space), in double.
    double root_mag = 0.0;
};

/// A top-level node: the KdNode encoding (kdrt/kdtree.h) kept in a type of its own, so the mesh
/// tree's layout may change without touching scenes. word0: axis (0..2) or 3 = leaf in bits 0..1,
/// first child / reference count above; word1: split (f32 bits) or first reference.
struct TopNode {
    uint32_t word0 = 3;
    uint32_t word1 = 0;
    [[nodiscard]] bool is_leaf() const noexcept { return (word0 & 3u) == 3u; }
    [[nodiscard]] int axis() const noexcept { return static_cast<int>(word0 & 3u); }
    [[nodiscard]] uint32_t first_child() const noexcept { return word0 >> 2; }
    [[nodiscard]] uint32_t count() const noexcept { return word0 >> 2; }
    [[nodiscard]] uint32_t first_ref() const noexcept { return word1; }
    [[nodiscard]] float split() const noexcept {
        float s;
        static_assert(sizeof s == sizeof word1);
        __builtin_memcpy(&s, &word1, sizeof s);
        return s;
    }
};
static_assert(sizeof(TopNode) == 8);

/// Depth cap of the top level (the traversal stack has room for it).
inline constexpr int kTopMaxDepth = 48;

struct SceneData {
    std::vector<SceneInstance> instances;
    std::vector<InstanceData> inst;
    std::vector<TopNode> nodes;  ///< nodes[0] is the root (a leaf for an empty scene)
    std::vector<uint32_t> refs;  ///< geometry ids, per leaf contiguous and ascending
    /// No instance is listed in two leaves, so a ray's walk (each leaf once) reaches each
    /// instance once at most, and the batches' rounds need no mailbox.
    bool refs_unique = false;
    Aabb bounds;  ///< union of the world boxes (the root cell)
    /// Traversal margin (margin()): the largest kappa, and the largest of |t|, |L| * box and the
    /// root's coordinates.
    double kappa_max = 1.0;
    double size_max = 0.0;
    /// The first instance with geometry whose transform is not a similarity, and the first
    /// without a surface index (check_distance_query).
    std::optional<uint32_t> first_not_similar, first_without_surface;
    SceneBuildOptions options;
    SceneStats stats;
};

/// The rounding of object_ray is at most a few float ulps of the quantities in InstanceData's
/// comment; the margin takes 2^-18 of them (16 ulps and more), as the mesh kernel widens its cells
/// by 2^-20 of its coordinates.
inline constexpr double kMarginScale = 0x1p-18;

/// Spatial margin of the top-level traversal for a ray with origin magnitude `origin_mag`: any
/// instance that can hold a hit at parameter t has its world box within this distance of the world
/// ray's point at t. The hit's t is bounded by the root box, so t |d| <= |o| + root + margin.
inline float margin(const SceneData& s, double origin_mag) noexcept {
    return static_cast<float>(kMarginScale * s.kappa_max * (3.0 * origin_mag + 3.0 * s.size_max));
}

/// The world ray of every top-level query: origin, reciprocal direction, and the margin.
struct TopRay {
    float org[3];
    float dir[3];
    float inv[3];
    float delta;   ///< spatial margin
    float eps[3];  ///< delta in t along each axis (0 for a zero direction component)
};

/// What ray_is_valid(r) answers (valid) and whether a direction component is zero (flat, +0 or
/// -0: clip_widened's own case), from the ray's two halves as SSE vectors (origin and tmin,
/// direction and tmax): lane by lane the same comparisons (|x| < inf is isfinite, false for a
/// NaN; x == 0 for a zero), a dozen instructions instead of ray_is_valid's chain of branches.
/// Static: each translation unit keeps its own copy, compiled for its own target (ray_prep.h).
struct RayShape {
    bool valid, flat;
};
[[gnu::always_inline]] static inline RayShape ray_shape(const Ray& r) noexcept {
    using V4 = float __attribute__((vector_size(16)));
    using M4 = int32_t __attribute__((vector_size(16)));
    static_assert(offsetof(Ray, tmin) == 3 * sizeof(float) &&
                  offsetof(Ray, tmax) == 7 * sizeof(float));
    V4 o, d;
    __builtin_memcpy(&o, &r.ox, sizeof o);  // ox oy oz tmin
    __builtin_memcpy(&d, &r.dx, sizeof d);  // dx dy dz tmax
    const M4 abs_mask = M4{} + 0x7fffffff;
    const V4 abs_o = reinterpret_cast<V4>(reinterpret_cast<M4>(o) & abs_mask);
    const V4 abs_d = reinterpret_cast<V4>(reinterpret_cast<M4>(d) & abs_mask);
    const V4 inf = V4{} + __builtin_inff();
    const unsigned finite = static_cast<unsigned>(
        _mm_movemask_ps(reinterpret_cast<__m128>((abs_o < inf) & (abs_d < inf))));
    const unsigned zero =
        static_cast<unsigned>(_mm_movemask_ps(reinterpret_cast<__m128>(d == V4{})));
    const bool ordered = o[3] <= d[3];  // tmin <= tmax, false for a NaN
    const bool valid = ((finite & 7u) == 7u) & ((zero & 7u) != 7u) & ordered;
    return {valid, (zero & 7u) != 0u};
}

[[gnu::always_inline]] inline TopRay make_top_ray(const SceneData& s, const Ray& r) noexcept {
    TopRay p;
    p.org[0] = r.ox, p.org[1] = r.oy, p.org[2] = r.oz;
    p.dir[0] = r.dx, p.dir[1] = r.dy, p.dir[2] = r.dz;
    double mag = 0.0;
    for (int a = 0; a < 3; ++a) {
        p.inv[a] = 1.0f / p.dir[a];
        mag = std::max(mag, static_cast<double>(std::fabs(p.org[a])));
    }
    p.delta = margin(s, mag);
    for (int a = 0; a < 3; ++a) p.eps[a] = p.dir[a] == 0.0f ? 0.0f : p.delta * std::fabs(p.inv[a]);
    return p;
}

/// make_top_ray(s, r) for a ray `r` with the origin of `same`'s ray (bit for bit the same floats):
/// the margin depends on the origin only, so it is `same`'s, and only the direction is new.
[[gnu::always_inline]] inline TopRay make_top_ray_from(const TopRay& same, const Ray& r) noexcept {
    TopRay p;
    p.org[0] = same.org[0], p.org[1] = same.org[1], p.org[2] = same.org[2];
    p.dir[0] = r.dx, p.dir[1] = r.dy, p.dir[2] = r.dz;
    for (int a = 0; a < 3; ++a) p.inv[a] = 1.0f / p.dir[a];
    p.delta = same.delta;
    for (int a = 0; a < 3; ++a) p.eps[a] = p.dir[a] == 0.0f ? 0.0f : p.delta * std::fabs(p.inv[a]);
    return p;
}

/// Clips [tmin, tmax] to `box` widened by the margin; false when the ray passes farther away.
[[gnu::always_inline]] inline bool clip_widened(const TopRay& p, const Aabb& box, float& tmin,
                                                float& tmax) noexcept {
    for (int a = 0; a < 3; ++a) {
        const float lo = box.lo[a] - p.delta, hi = box.hi[a] + p.delta;
        if (p.dir[a] == 0.0f) {
            if (p.org[a] < lo || p.org[a] > hi) return false;
            continue;
        }
        float t0 = (lo - p.org[a]) * p.inv[a], t1 = (hi - p.org[a]) * p.inv[a];
        if (t0 > t1) std::swap(t0, t1);
        // The rounding of these products is covered by the margin (it is far above an ulp of
        // (|o| + |box|) / |d|), so the widened entry never lies beyond a real hit's t.
        tmin = t0 > tmin ? t0 : tmin;
        tmax = t1 < tmax ? t1 : tmax;
    }
    return tmin <= tmax;
}

/// A ray's widened segment in a box: clip_box's [entry, exit] (empty when entry > exit).
struct TopSegment {
    float entry, exit;
};

/// clip_widened(p, box, tmin, tmax) for a ray with no zero direction component, the three axes
/// side by side: [entry, exit] are clip_widened's clipped tmin and tmax bit for bit (its answer is
/// entry <= exit). Per axis the same float operations (the box widened by the margin,
/// (x - org) * inv, the swap); then each axis' entry is taken where it compares greater than
/// tmin (else tmin), and the entries x, y, z in turn where one compares greater than the latest
/// so far, as clip_widened takes them one axis at a time (so the same value, the sign of a zero
/// too: a lane that is not greater leaves the running value as it is, and an axis clip_widened
/// skips gives tmin, never greater than the running value); the exits alike with less. A NaN (from
/// the infinite reciprocal of a subnormal component) never compares, in either. Static: each
/// translation unit keeps its own copy, compiled for its own target.
[[gnu::always_inline]] static inline TopSegment clip_box(const TopRay& p, const Aabb& box,
                                                         float tmin, float tmax) noexcept {
    using V4 = float __attribute__((vector_size(16)));
    static_assert(sizeof(Aabb) == 6 * sizeof(float) && offsetof(TopRay, dir) == 3 * sizeof(float) &&
                  offsetof(TopRay, delta) == offsetof(TopRay, inv) + 3 * sizeof(float));
    V4 org, inv, lo, hi_shifted;
    // org[0..2] then dir[0], inv[0..2] then delta; lo.xyz then hi.x, lo.z then hi.xyz (the
    // fourth lane of each is not used).
    __builtin_memcpy(&org, p.org, sizeof org);
    __builtin_memcpy(&inv, p.inv, sizeof inv);
    __builtin_memcpy(&lo, &box.lo.x, sizeof lo);
    __builtin_memcpy(&hi_shifted, &box.lo.z, sizeof hi_shifted);
    const V4 hi = __builtin_shufflevector(hi_shifted, hi_shifted, 1, 2, 3, 3);
    const V4 delta = V4{} + p.delta;
    const V4 a0 = ((lo - delta) - org) * inv, a1 = ((hi + delta) - org) * inv;
    const V4 n0 = a0 > a1 ? a1 : a0, n1 = a0 > a1 ? a0 : a1;
    // Broadcast as they are (V4{} + tmin would make a -0 +0).
    const V4 vmin = {tmin, tmin, tmin, tmin}, vmax = {tmax, tmax, tmax, tmax};
    const V4 e = n0 > vmin ? n0 : vmin, x = n1 < vmax ? n1 : vmax;
    float entry = e[0], exit = x[0];
    entry = e[1] > entry ? e[1] : entry;
    entry = e[2] > entry ? e[2] : entry;
    exit = x[1] < exit ? x[1] : exit;
    exit = x[2] < exit ? x[2] : exit;
    return {entry, exit};
}

/// A cell of the top level still to visit: its node and the widened [tmin, tmax] of the ray in it.
struct TopCell {
    uint32_t node;
    float tmin, tmax;
};

/// Room a TopWalk's stack needs (the depth cap, and the root).
inline constexpr int kTopStack = kTopMaxDepth + 2;

/// A front-to-back walk of the top level along one ray that can stop at any leaf and resume later
/// (a batch's rounds keep one per ray). The walk is widened by the margin as the mesh kernel
/// widens its cells. The stack (kTopStack cells) is the caller's.
struct TopWalk {
    TopCell* stack = nullptr;
    int size = 0;

    /// Starts the walk of `ray` (valid) at the root, clipped to [ray.tmin, ray.tmax].
    [[gnu::always_inline]] void start(const SceneData& s, const Ray& ray, const TopRay& p,
                                      TopCell* storage) noexcept {
        stack = storage;
        size = 0;
        float tmin = ray.tmin, tmax = ray.tmax;
        if (!s.refs.empty() && clip_widened(p, s.bounds, tmin, tmax))
            stack[size++] = {0, tmin, tmax};
    }

    [[nodiscard]] bool done() const noexcept { return size == 0; }

    /// The next leaf along the ray whose cell starts at or before `limit` (the current upper bound
    /// of t, which never grows), or nullptr when there is none. A cell starting beyond the limit
    /// is dropped, but the walk goes on: the widened cells are not strictly front to back (a far
    /// cell pushed inside a near subtree may start up to 2 eps later than one pushed before it,
    /// which lies below it on the stack), so a later cell may still start at or before the limit.
    [[gnu::always_inline]] const TopNode* next_leaf(const SceneData& s, const TopRay& p,
                                                    float limit) noexcept {
        TopCell cell;
        do {
            if (size == 0) return nullptr;
            cell = stack[--size];
        } while (cell.tmin > limit);
        uint32_t index = cell.node;
        float tmin = cell.tmin, tmax = cell.tmax;
        const TopNode* node = &s.nodes[index];
        while (!node->is_leaf()) {
            const int axis = node->axis();
            const uint32_t low = node->first_child(), high = low + 1;
            const float split = node->split();
            uint32_t near, far;
            bool need_near, need_far;
            float near_max = tmax, far_min = tmin;
            if (p.dir[axis] == 0.0f) {
                // Parallel to the plane: the origin's side, and the other when within the margin.
                const bool low_side = p.org[axis] < split;
                near = low_side ? low : high;
                far = low_side ? high : low;
                need_near = true;
                need_far = std::fabs(p.org[axis] - split) <= p.delta;
            } else {
                const bool forward = p.dir[axis] > 0.0f;
                near = forward ? low : high;
                far = forward ? high : low;
                const float t_split = (split - p.org[axis]) * p.inv[axis];
                near_max = t_split + p.eps[axis];
                far_min = t_split - p.eps[axis];
                need_near = !(near_max < tmin);
                need_far = !(far_min > tmax);
            }
            if (need_near && need_far) {
                stack[size++] = {far, far_min > tmin ? far_min : tmin, tmax};
                tmax = near_max < tmax ? near_max : tmax;
                index = near;
            } else {
                index = need_near ? near : far;
                if (!need_near) tmin = far_min > tmin ? far_min : tmin;
                if (!need_far) tmax = near_max < tmax ? near_max : tmax;
            }
            node = &s.nodes[index];
        }
        return node;
    }
};

/// Front-to-back traversal of the top level along `ray` (valid). For each instance referenced by
/// a leaf the ray's widened segment reaches, calls visit(geom, entry) with `entry` the widened box
/// entry t (instances are offered once per leaf that holds them; the caller de-duplicates if it
/// matters). limit() is the current upper bound of t (the best hit so far for closest hit): cells
/// starting beyond it are skipped and the walk stops. visit returns false to stop at once (any
/// hit).
template <class Limit, class Visit>
void walk_top(const SceneData& s, const Ray& ray, const TopRay& p, Limit&& limit, Visit&& visit) {
    std::array<TopCell, kTopStack> stack;
    TopWalk walk;
    walk.start(s, ray, p, stack.data());
    while (const TopNode* leaf = walk.next_leaf(s, p, limit())) {
        const uint32_t end = leaf->first_ref() + leaf->count();
        for (uint32_t r = leaf->first_ref(); r < end; ++r) {
            const uint32_t geom = s.refs[r];
            float t0 = ray.tmin, t1 = limit();
            if (!clip_widened(p, s.inst[geom].world, t0, t1)) continue;
            if (!visit(geom, t0)) return;
        }
    }
}

/// A tiny mailbox: the last few instances a ray traced, so an instance referenced by several
/// leaves along the ray is traced once (correctness does not depend on it: a second trace of an
/// instance with a smaller tmax finds nothing new).
struct Mailbox {
    std::array<uint32_t, 8> geoms;
    uint32_t next = 0;
    Mailbox() noexcept { geoms.fill(kNoHit); }
    /// True when `geom` was seen; records it otherwise.
    bool seen(uint32_t geom) noexcept {
        for (uint32_t g : geoms)
            if (g == geom) return true;
        geoms[next++ & 7u] = geom;
        return false;
    }
};

/// object_ray with the instance data at hand: per object axis i,
///   origin[i] = float(inv[i][0] * o[0] + inv[i][1] * o[1] + inv[i][2] * o[2]), o = org - trans,
///   dir[i]    = float(inv[i][0] * d[0] + inv[i][1] * d[1] + inv[i][2] * d[2]),
/// in double, summed left to right (to_object_reference, which the tests hold it to bit for bit).
/// The origin's and the direction's sums of one row go together in one two-lane vector (SSE2, the
/// x86-64 baseline): each lane is that scalar arithmetic (IEEE products and sums, no contraction:
/// -ffp-contract=off), half the instructions.
[[gnu::always_inline]] inline Ray to_object(const InstanceData& d, const Ray& r) noexcept {
    using D2 = double __attribute__((vector_size(16)));
    using F2 = float __attribute__((vector_size(8)));
    // Lane 0 the origin, lane 1 the direction, per world axis.
    const D2 x = {static_cast<double>(r.ox) - d.trans[0], static_cast<double>(r.dx)};
    const D2 y = {static_cast<double>(r.oy) - d.trans[1], static_cast<double>(r.dy)};
    const D2 z = {static_cast<double>(r.oz) - d.trans[2], static_cast<double>(r.dz)};
    F2 row[3];
    for (int i = 0; i < 3; ++i) {
        const double* m = &d.inv[3 * i];
        row[i] = __builtin_convertvector(m[0] * x + m[1] * y + m[2] * z, F2);
    }
    return Ray{row[0][0], row[1][0], row[2][0], r.tmin, row[0][1], row[1][1], row[2][1], r.tmax};
}

/// to_object in plain scalar arithmetic (what to_object must equal, bit for bit).
inline Ray to_object_reference(const InstanceData& d, const Ray& r) noexcept {
    const double o[3] = {static_cast<double>(r.ox) - d.trans[0],
                         static_cast<double>(r.oy) - d.trans[1],
                         static_cast<double>(r.oz) - d.trans[2]};
    const double v[3] = {r.dx, r.dy, r.dz};
    float oo[3], dd[3];
    for (int i = 0; i < 3; ++i) {
        const double* row = &d.inv[3 * i];
        oo[i] = static_cast<float>(row[0] * o[0] + row[1] * o[1] + row[2] * o[2]);
        dd[i] = static_cast<float>(row[0] * v[0] + row[1] * v[1] + row[2] * v[2]);
    }
    return Ray{oo[0], oo[1], oo[2], r.tmin, dd[0], dd[1], dd[2], r.tmax};
}

/// The nearest `max_hits` hits of each ray over every instance, as intersect_all's batch keeps
/// them (the same hits, bits and order: each instance's intersect_all on its object ray, the
/// minimum by the tie rule), but without the counts (SceneAllHits::counts is left empty), so
/// each ray stops at the first top-level cell beyond its max_hits-th hit and each instance is
/// traced only as far as that hit (plus the merge tolerance). What scan_lidar uses. `isa`
/// (default and unsupported: default_isa()) picks the packet walk's registers and the mesh
/// kernels'; every ISA gives the same answers. Parallel over the current arena; throws
/// std::bad_alloc.
SceneAllHits nearest_hits(const Scene& scene, std::span<const Ray> rays, uint32_t max_hits,
                          bool merge_coincident, std::optional<Isa> isa = std::nullopt);

/// The depth-first walk of coherent batches (scene_trace.cpp: packets of up to kPacketLanes rays
/// walk the top level, and the lanes reaching an instance go into it at once through the mesh's
/// caller-packet kernels), over every ray of `rays` in blocks, on the calling thread: each answer
/// is intersect's / occluded's, and `visits` gains the instance visits, which are the single-ray
/// walk's. `isa` must be supported. Tests call it for every ISA on any rays.
void depth_first_intersect(const SceneData& s, std::span<const Ray> rays, std::span<SceneHit> hits,
                           Isa isa, uint64_t& visits);
void depth_first_occluded(const SceneData& s, std::span<const Ray> rays,
                          std::span<uint8_t> occluded_out, Isa isa, uint64_t& visits);

/// The tie rule: (t, geom, prim) lexicographically.
inline bool scene_hit_less(const SceneHit& a, const SceneHit& b) noexcept {
    if (a.t != b.t) return a.t < b.t;
    if (a.geom != b.geom) return a.geom < b.geom;
    return a.prim < b.prim;
}

/// L * p + t in double, rounded to float.
inline Vec3 to_world(const InstanceData& d, const double p[3]) noexcept {
    Vec3 w;
    for (int i = 0; i < 3; ++i) {
        const double* row = &d.lin[3 * i];
        w[i] = static_cast<float>(row[0] * p[0] + row[1] * p[1] + row[2] * p[2] + d.trans[i]);
    }
    return w;
}

}  // namespace kdrt::detail
