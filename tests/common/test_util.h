#pragma once
// Shared helpers for the engine tests: seeds, a small RNG, scene generators and ray generators.

#include <cmath>
#include <cstdint>
#include <cstdlib>
#include <string>
#include <vector>

#include "kdrt/kdtree.h"
#include "kdrt/mesh.h"
#include "kdrt/types.h"

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
inline size_t scaled(size_t n) { return std::max<size_t>(1, static_cast<size_t>(static_cast<double>(n) * test_scale())); }

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
    Vec3 in_box(const Aabb& b) { return {uniform(b.lo.x, b.hi.x), uniform(b.lo.y, b.hi.y), uniform(b.lo.z, b.hi.z)}; }
    Vec3 on_sphere() {
        const float z = uniform(-1.0f, 1.0f), phi = uniform(0.0f, 6.2831853f);
        const float r = std::sqrt(std::max(0.0f, 1.0f - z * z));
        return {r * std::cos(phi), r * std::sin(phi), z};
    }

private:
    uint64_t state_;
};

inline uint32_t add_vertex(Mesh& m, Vec3 v) {
    // push_back, not insert({...}): GCC 12 reports a false stringop-overflow for the latter.
    m.positions.push_back(v.x);
    m.positions.push_back(v.y);
    m.positions.push_back(v.z);
    return static_cast<uint32_t>(m.vertex_count() - 1);
}
inline void add_indices(Mesh& m, uint32_t i, uint32_t j, uint32_t k) {
    m.indices.push_back(i);
    m.indices.push_back(j);
    m.indices.push_back(k);
}
inline void add_triangle(Mesh& m, Vec3 a, Vec3 b, Vec3 c) {
    const uint32_t i = add_vertex(m, a), j = add_vertex(m, b), k = add_vertex(m, c);
    add_indices(m, i, j, k);
}

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

/// A closed, finely tessellated UV sphere with shared vertices (watertight as an index mesh).
inline Mesh uv_sphere(Vec3 centre, float radius, uint32_t rings, uint32_t segments) {
    Mesh m;
    add_vertex(m, centre + Vec3{0, 0, radius});
    for (uint32_t r = 1; r < rings; ++r) {
        const double theta = 3.14159265358979 * r / rings;
        for (uint32_t s = 0; s < segments; ++s) {
            const double phi = 2 * 3.14159265358979 * s / segments;
            add_vertex(m, centre + Vec3{static_cast<float>(radius * std::sin(theta) * std::cos(phi)),
                                        static_cast<float>(radius * std::sin(theta) * std::sin(phi)),
                                        static_cast<float>(radius * std::cos(theta))});
        }
    }
    const uint32_t south = add_vertex(m, centre + Vec3{0, 0, -radius});
    auto ring_vertex = [&](uint32_t r, uint32_t s) { return 1 + (r - 1) * segments + s % segments; };
    for (uint32_t s = 0; s < segments; ++s) {
        add_indices(m, 0, ring_vertex(1, s), ring_vertex(1, s + 1));
        add_indices(m, south, ring_vertex(rings - 1, s + 1), ring_vertex(rings - 1, s));
    }
    for (uint32_t r = 1; r + 1 < rings; ++r) {
        for (uint32_t s = 0; s < segments; ++s) {
            const uint32_t a = ring_vertex(r, s), b = ring_vertex(r, s + 1), c = ring_vertex(r + 1, s),
                           d = ring_vertex(r + 1, s + 1);
            add_indices(m, a, c, b);
            add_indices(m, b, c, d);
        }
    }
    return m;
}

/// Appends `src` to `dst` (indices rebased).
inline void append(Mesh& dst, const Mesh& src) {
    const auto base = static_cast<uint32_t>(dst.vertex_count());
    dst.positions.insert(dst.positions.end(), src.positions.begin(), src.positions.end());
    for (uint32_t i : src.indices) dst.indices.push_back(i + base);
}

/// "Teapot in a stadium": a huge closed box (12 triangles, size `stadium`) around a tiny, finely
/// tessellated sphere at its centre.
inline Mesh teapot_in_stadium(float stadium = 1000.0f, uint32_t rings = 60, uint32_t segments = 120) {
    Mesh m;
    const float h = stadium * 0.5f;
    const Vec3 c[8] = {{-h, -h, -h}, {h, -h, -h}, {h, h, -h}, {-h, h, -h}, {-h, -h, h}, {h, -h, h}, {h, h, h}, {-h, h, h}};
    for (const Vec3& v : c) add_vertex(m, v);
    const uint32_t faces[6][4] = {{0, 3, 2, 1}, {4, 5, 6, 7}, {0, 1, 5, 4}, {2, 3, 7, 6}, {1, 2, 6, 5}, {0, 4, 7, 3}};
    for (const auto& f : faces) {
        add_indices(m, f[0], f[1], f[2]);
        add_indices(m, f[0], f[2], f[3]);
    }
    append(m, uv_sphere({0.3f, -0.2f, 0.1f}, 1.0f, rings, segments));
    return m;
}

inline Ray make_ray(Vec3 o, Vec3 d, float tmin = 0.0f, float tmax = INFINITY) {
    return Ray{o.x, o.y, o.z, tmin, d.x, d.y, d.z, tmax};
}

/// Bounds of a mesh enlarged by `margin` of its size on each side.
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
                const KdNode& n = *inner_nodes[rng.below(static_cast<uint32_t>(inner_nodes.size()))];
                o[n.axis()] = n.split();
                Vec3 d = rng.on_sphere();
                d[n.axis()] = 0.0f;
                if (rng.below(2)) d[(n.axis() + 1) % 3] = 0.0f;  // also axis-parallel inside the plane
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

}  // namespace kdrt::test
