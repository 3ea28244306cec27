#pragma once
// Generated scenes shared by the tests and kdrt-bench: a closed UV sphere, the "teapot in a
// stadium", and grids of copies of a mesh (the benchmark's million-triangle scene).

#include <cmath>
#include <cstdint>

#include "kdrt/mesh.h"
#include "kdrt/types.h"

namespace kdrt::test {

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

/// A closed, finely tessellated UV sphere with shared vertices (watertight as an index mesh).
inline Mesh uv_sphere(Vec3 centre, float radius, uint32_t rings, uint32_t segments) {
    Mesh m;
    add_vertex(m, centre + Vec3{0, 0, radius});
    for (uint32_t r = 1; r < rings; ++r) {
        const double theta = 3.14159265358979 * r / rings;
        for (uint32_t s = 0; s < segments; ++s) {
            const double phi = 2 * 3.14159265358979 * s / segments;
            add_vertex(m,
                       centre + Vec3{static_cast<float>(radius * std::sin(theta) * std::cos(phi)),
                                     static_cast<float>(radius * std::sin(theta) * std::sin(phi)),
                                     static_cast<float>(radius * std::cos(theta))});
        }
    }
    const uint32_t south = add_vertex(m, centre + Vec3{0, 0, -radius});
    auto ring_vertex = [&](uint32_t r, uint32_t s) {
        return 1 + (r - 1) * segments + s % segments;
    };
    for (uint32_t s = 0; s < segments; ++s) {
        add_indices(m, 0, ring_vertex(1, s), ring_vertex(1, s + 1));
        add_indices(m, south, ring_vertex(rings - 1, s + 1), ring_vertex(rings - 1, s));
    }
    for (uint32_t r = 1; r + 1 < rings; ++r) {
        for (uint32_t s = 0; s < segments; ++s) {
            const uint32_t a = ring_vertex(r, s), b = ring_vertex(r, s + 1),
                           c = ring_vertex(r + 1, s), d = ring_vertex(r + 1, s + 1);
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

/// The closed box [lo, hi]^3: 12 triangles wound outwards, 8 shared vertices.
inline Mesh box_mesh(float lo, float hi) {
    Mesh m;
    const Vec3 c[8] = {{lo, lo, lo}, {hi, lo, lo}, {hi, hi, lo}, {lo, hi, lo},
                       {lo, lo, hi}, {hi, lo, hi}, {hi, hi, hi}, {lo, hi, hi}};
    for (const Vec3& v : c) add_vertex(m, v);
    const uint32_t faces[6][4] = {{0, 3, 2, 1}, {4, 5, 6, 7}, {0, 1, 5, 4},
                                  {2, 3, 7, 6}, {1, 2, 6, 5}, {0, 4, 7, 3}};
    for (const auto& f : faces) {
        add_indices(m, f[0], f[1], f[2]);
        add_indices(m, f[0], f[2], f[3]);
    }
    return m;
}

/// "Teapot in a stadium": a huge closed box (12 triangles, size `stadium`) around a tiny, finely
/// tessellated sphere at its centre.
inline Mesh teapot_in_stadium(float stadium = 1000.0f, uint32_t rings = 60,
                              uint32_t segments = 120) {
    const float h = stadium * 0.5f;
    Mesh m = box_mesh(-h, h);
    append(m, uv_sphere({0.3f, -0.2f, 0.1f}, 1.0f, rings, segments));
    return m;
}

/// `copies` copies of `mesh` on a square grid in x and z (copies rounded up to a square number),
/// each shifted by 1.1 times the mesh's extent so they do not touch.
inline Mesh replicate_grid(const Mesh& mesh, uint32_t copies) {
    uint32_t side = 1;
    while (side * side < copies) ++side;
    const Aabb b = mesh_bounds(mesh);
    const Vec3 e = b.extent();
    Mesh out;
    out.positions.reserve(mesh.positions.size() * copies);
    out.indices.reserve(mesh.indices.size() * copies);
    for (uint32_t c = 0; c < copies; ++c) {
        const uint32_t column = c % side, row = c / side;
        const float dx = 1.1f * e.x * static_cast<float>(column),
                    dz = 1.1f * e.z * static_cast<float>(row);
        const auto base = static_cast<uint32_t>(out.vertex_count());
        for (size_t v = 0; v < mesh.vertex_count(); ++v) {
            const Vec3 p = mesh.vertex(v);
            add_vertex(out, {p.x + dx, p.y, p.z + dz});
        }
        for (uint32_t i : mesh.indices) out.indices.push_back(i + base);
    }
    return out;
}

}  // namespace kdrt::test
