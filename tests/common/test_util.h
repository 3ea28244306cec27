#pragma once
// Shared helpers for the engine tests: seeds, a small RNG, scene generators and ray generators.

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstdlib>
#include <span>
#include <string>
#include <utility>
#include <vector>

#include "kdrt/kdtree.h"
#include "kdrt/mesh.h"
#include "kdrt/trace.h"
#include "kdrt/types.h"
#include "scenes.h"

namespace kdrt::test {

/// KDRT_TEST_SEED when set, else `fallback`. Tests print it with SCOPED_TRACE to replay failures.
inline uint64_t test_seed(uint64_t fallback = 20261129) {
    if (const char* s = std::getenv("KDRT_TEST_SEED")) return std::strtoull(s, nullptr, 10);
    return fallback;
}

/// Scale for expensive oracle loops: KDRT_TEST_SCALE (e.g. 0.1 under sanitizers), default 1.
inline double test_scale() {
    if (const char* s = std::getenv("KDRT_TEST_SCALE")) return std::max(0.001, std::atof(s));
    return 1.0;
}
inline size_t scaled(size_t n) {
    return std::max<size_t>(1, static_cast<size_t>(static_cast<double>(n) * test_scale()));
}
/// An image side for an oracle over `res` x `res` pixels, scaled so the pixel count follows
/// test_scale(), and at least `floor`.
inline uint32_t scaled_res(uint32_t res, uint32_t floor = 32) {
    const double side = static_cast<double>(res) * std::sqrt(std::min(1.0, test_scale()));
    return std::max(floor, static_cast<uint32_t>(side));
}

/// Every instruction set this CPU can run, narrowest first (the tests run each).
inline std::vector<Isa> supported_isas() {
    std::vector<Isa> isas;
    for (Isa isa : {Isa::kScalar, Isa::kSse4, Isa::kAvx2, Isa::kAvx512})
        if (isa_supported(isa)) isas.push_back(isa);
    return isas;
}

/// splitmix64: small, fast, good enough for test data.
class Rng {
public:
    explicit Rng(uint64_t seed) : state_(seed) {}
    uint64_t next() {
        uint64_t z = (state_ += 0x9E3779B97F4A7C15ull);
        z = (z ^ (z >> 30)) * 0xBF58476D1CE4E5B9ull;
        z = (z ^ (z >> 27)) * 0x94D049BB133111EBull;
        return z ^ (z >> 31);
    }
    /// Uniform in [0, 1).
    float uniform() { return static_cast<float>(next() >> 40) * 0x1p-24f; }
    float uniform(float lo, float hi) { return lo + (hi - lo) * uniform(); }
    uint32_t below(uint32_t n) { return static_cast<uint32_t>(next() % n); }
    Vec3 in_box(const Aabb& b) {
        return {uniform(b.lo.x, b.hi.x), uniform(b.lo.y, b.hi.y), uniform(b.lo.z, b.hi.z)};
    }
    Vec3 on_sphere() {
        const float z = uniform(-1.0f, 1.0f), phi = uniform(0.0f, 6.2831853f);
        const float r = std::sqrt(std::max(0.0f, 1.0f - z * z));
        return {r * std::cos(phi), r * std::sin(phi), z};
    }

private:
    uint64_t state_;
};

/// `count` random triangles in the unit cube, of random size up to `max_edge`.
inline Mesh random_soup(Rng& rng, size_t count, float max_edge = 0.15f) {
    Mesh m;
    const Aabb unit{{0, 0, 0}, {1, 1, 1}};
    for (size_t i = 0; i < count; ++i) {
        const Vec3 c = rng.in_box(unit);
        const float s = rng.uniform(0.01f, max_edge);
        add_triangle(m, c + rng.on_sphere() * s, c + rng.on_sphere() * s, c + rng.on_sphere() * s);
    }
    return m;
}

/// `count` triangles of the unit cube with their vertices snapped to a grid of `grid` (vertices up
/// to `spread` from a random centre): many shared positions (ties between candidate planes), and
/// every fourth triangle flat in an axis plane (planar events, planes through vertices).
inline Mesh snapped_soup(Rng& rng, size_t count, float grid, float spread = 0.2f) {
    Mesh m;
    auto snap = [&](Vec3 v) {
        return Vec3{std::round(v.x / grid) * grid, std::round(v.y / grid) * grid,
                    std::round(v.z / grid) * grid};
    };
    for (size_t i = 0; i < count; ++i) {
        const Vec3 c = rng.in_box({{0, 0, 0}, {1, 1, 1}});
        Vec3 v[3];
        for (Vec3& x : v) x = snap(c + rng.on_sphere() * rng.uniform(0.0f, spread));
        if (i % 4 == 0) {  // flat in an axis plane
            const int a = static_cast<int>(i / 4 % 3);
            float* coords[3] = {&v[0].x, &v[1].x, &v[2].x};
            for (float* q : coords) q[a] = coords[0][a];
        }
        add_triangle(m, v[0], v[1], v[2]);
    }
    return m;
}

inline Ray make_ray(Vec3 o, Vec3 d, float tmin = 0.0f, float tmax = INFINITY) {
    return Ray{o.x, o.y, o.z, tmin, d.x, d.y, d.z, tmax};
}

/// Bounds of a mesh enlarged by `margin` of its size on each side.
/// `count` rays from points of the box [-1, 2]^3 towards points of the unit cube (seeded): a
/// batch in which most rays hit a mesh in the unit cube and some miss.
inline std::vector<Ray> rays_towards_unit_cube(size_t count, uint64_t seed) {
    Rng rng(seed);
    std::vector<Ray> rays(count);
    for (Ray& r : rays) {
        const Vec3 o = rng.in_box({{-1, -1, -1}, {2, 2, 2}}),
                   t = rng.in_box({{0, 0, 0}, {1, 1, 1}});
        r = make_ray(o, t - o);
    }
    return rays;
}

inline Aabb grown_bounds(const Mesh& m, float margin) {
    Aabb b = mesh_bounds(m);
    const Vec3 e = b.extent();
    const float s = std::max({e.x, e.y, e.z}) * margin;
    b.lo = b.lo - Vec3{s, s, s};
    b.hi = b.hi + Vec3{s, s, s};
    return b;
}

/// A mixed bag of rays for oracle tests: from outside towards random points, from inside the
/// bounds, axis-parallel ones, rays lying in the tree's split planes, random tmin/tmax windows,
/// and rays aimed exactly at vertices and edge midpoints.
inline std::vector<Ray> oracle_rays(Rng& rng, const Mesh& mesh, const KdTree& tree, size_t count) {
    std::vector<Ray> rays;
    rays.reserve(count);
    const Aabb inner = mesh_bounds(mesh);
    const Aabb outer = grown_bounds(mesh, 0.5f);
    std::vector<const KdNode*> inner_nodes;
    for (const KdNode& n : tree.nodes)
        if (!n.is_leaf()) inner_nodes.push_back(&n);
    while (rays.size() < count) {
        const uint32_t kind = rng.below(7);
        Vec3 o = rng.in_box(outer), target = rng.in_box(inner);
        Ray r;
        switch (kind) {
            case 0:  // outside -> inside
                r = make_ray(o, target - o);
                break;
            case 1:  // from inside, any direction
                r = make_ray(rng.in_box(inner), rng.on_sphere());
                break;
            case 2: {  // axis-parallel, both signs, zero components exactly
                Vec3 d{0, 0, 0};
                d[static_cast<int>(rng.below(3))] = rng.below(2) ? 1.0f : -1.0f;
                r = make_ray(rng.in_box(outer), d);
                break;
            }
            case 3: {  // in a split plane of the tree, parallel to it
                if (inner_nodes.empty()) continue;
                const KdNode& n =
                    *inner_nodes[rng.below(static_cast<uint32_t>(inner_nodes.size()))];
                o[n.axis()] = n.split();
                Vec3 d = rng.on_sphere();
                d[n.axis()] = 0.0f;
                if (rng.below(2))
                    d[(n.axis() + 1) % 3] = 0.0f;  // also axis-parallel inside the plane
                r = make_ray(o, d);
                break;
            }
            case 4: {  // aimed at a vertex or an edge midpoint
                const auto tri = rng.below(static_cast<uint32_t>(mesh.triangle_count()));
                const Vec3 a = mesh.corner(tri, 0), b = mesh.corner(tri, 1);
                const Vec3 p = rng.below(2) ? a : (a + b) * 0.5f;
                r = make_ray(o, p - o);
                break;
            }
            case 5: {  // a window [tmin, tmax] on the segment
                r = make_ray(o, target - o);
                r.tmin = rng.uniform(0.0f, 1.0f);
                r.tmax = r.tmin + rng.uniform(0.0f, 1.0f);
                break;
            }
            default: {  // crossing a split plane from inside, unnormalised direction
                r = make_ray(target, (rng.in_box(outer) - target) * rng.uniform(0.01f, 100.0f));
                break;
            }
        }
        rays.push_back(r);
    }
    return rays;
}

/// A tree's nodes in depth-first order from the root (low child first), indices dropped:
/// (axis, split bits) for an inner node, (word0, word1) for a leaf. Two layouts of one tree give
/// the same sequence.
inline std::vector<std::pair<uint32_t, uint32_t>> tree_shape(std::span<const KdNode> nodes) {
    std::vector<std::pair<uint32_t, uint32_t>> out;
    std::vector<uint32_t> stack{0};
    while (!stack.empty()) {
        const KdNode n = nodes[stack.back()];
        stack.pop_back();
        if (n.is_leaf()) {
            out.emplace_back(n.word0(), n.word1());
            continue;
        }
        out.emplace_back(static_cast<uint32_t>(n.axis()), n.word1());
        stack.push_back(n.first_child() + 1);
        stack.push_back(n.first_child());
    }
    return out;
}

}  // namespace kdrt::test
