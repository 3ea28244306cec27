#include <algorithm>
#include <chrono>
#include <cmath>

#include "build_internal.h"
#include "kdrt/trace.h"

namespace kdrt {
namespace detail {

std::vector<uint8_t> prepare_triangles(const Mesh& mesh, std::vector<TriVerts>& tris) {
    const size_t n = mesh.triangle_count();
    tris.resize(n);
    std::vector<uint8_t> degenerate(n, 0);
    for (size_t i = 0; i < n; ++i) {
        const Vec3 v0 = mesh.corner(i, 0), v1 = mesh.corner(i, 1), v2 = mesh.corner(i, 2);
        // Zero area, decided exactly: the products of floats are exact in double.
        const double e1[3] = {double{v1.x} - v0.x, double{v1.y} - v0.y, double{v1.z} - v0.z};
        const double e2[3] = {double{v2.x} - v0.x, double{v2.y} - v0.y, double{v2.z} - v0.z};
        const double cx = e1[1] * e2[2] - e1[2] * e2[1];
        const double cy = e1[2] * e2[0] - e1[0] * e2[2];
        const double cz = e1[0] * e2[1] - e1[1] * e2[0];
        const bool is_degenerate = cx == 0.0 && cy == 0.0 && cz == 0.0;
        degenerate[i] = is_degenerate ? 1 : 0;
        // A degenerate triangle becomes a point: every edge function is then exactly zero and the
        // watertight test rejects it for any ray, in the tree and in the brute-force oracle alike.
        const Vec3 c1 = is_degenerate ? v0 : v1, c2 = is_degenerate ? v0 : v2;
        tris[i] = TriVerts{{v0.x, v0.y, v0.z}, {c1.x, c1.y, c1.z}, {c2.x, c2.y, c2.z}};
    }
    return degenerate;
}

Aabb root_cell(const std::vector<TriVerts>& tris, const std::vector<uint8_t>& degenerate) {
    Aabb box;
    for (size_t i = 0; i < tris.size(); ++i) {
        if (degenerate[i]) continue;
        box.extend({tris[i].v0[0], tris[i].v0[1], tris[i].v0[2]});
        box.extend({tris[i].v1[0], tris[i].v1[1], tris[i].v1[2]});
        box.extend({tris[i].v2[0], tris[i].v2[1], tris[i].v2[2]});
    }
    if (box.empty()) return box;
    float scale = 0.0f;
    for (int a = 0; a < 3; ++a)
        scale =
            std::max({scale, std::fabs(box.lo[a]), std::fabs(box.hi[a]), box.hi[a] - box.lo[a]});
    const float pad = scale * 0x1p-18f;
    for (int a = 0; a < 3; ++a) {
        box.lo[a] -= pad;
        box.hi[a] += pad;
    }
    return box;
}

void finish_tree(KdTree& tree, SubTree&& sub) {
    tree.nodes = std::move(sub.nodes);
    tree.leaf_refs = std::move(sub.refs);
    const double build_ms = tree.stats.build_ms;
    tree.stats = compute_stats(tree);
    tree.stats.build_ms = build_ms;
}

}  // namespace detail

std::vector<TriVerts> make_tri_verts(const Mesh& mesh) {
    std::vector<TriVerts> tris;
    detail::prepare_triangles(mesh, tris);
    return tris;
}

KdTree build_kdtree(const Mesh& mesh, const BuildOptions& options) {
    const auto start = std::chrono::steady_clock::now();
    validate_mesh(mesh);
    KdTree tree;
    tree.options = options;
    const std::vector<uint8_t> degenerate = detail::prepare_triangles(mesh, tree.tris);
    tree.bounds = detail::root_cell(tree.tris, degenerate);
    detail::SubTree sub;
    if (!tree.bounds.empty()) {
        if (options.builder == Builder::kMiddle) {
            detail::build_middle(tree.tris, degenerate, tree.bounds, options, sub);
        } else {
            detail::build_sah(tree.tris, degenerate, tree.bounds, options, sub);
        }
    }
    tree.stats.build_ms =
        std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - start).count();
    detail::finish_tree(tree, std::move(sub));
    return tree;
}

}  // namespace kdrt
