#include <algorithm>
#include <array>
#include <chrono>
#include <cmath>
#include <cstddef>
#include <memory>
#include <span>
#include <stdexcept>
#include <string>
#include <utility>

#include <tbb/parallel_for.h>
#include <tbb/parallel_invoke.h>

#include "build_internal.h"
#include "kdrt/trace.h"
#include "node_layout.h"

namespace kdrt {
namespace detail {
namespace {

/// Triangles per chunk of the per-triangle passes before the tree build; meshes of more than one
/// chunk run them in parallel (on 16 bunnies they were about 1% of the build's instructions, all
/// on one thread).
constexpr size_t kTriangleChunk = size_t{1} << 14;

/// Calls body(chunk, begin, end) for the fixed chunks of [0, n), in parallel when there are
/// several. The chunks do not depend on the thread count, so neither does anything combined
/// from them in chunk order.
template <typename Body>
void for_triangle_chunks(size_t n, const Body& body) {
    const size_t chunks = (n + kTriangleChunk - 1) / kTriangleChunk;
    if (chunks <= 1) {
        if (n > 0) body(size_t{0}, size_t{0}, n);
        return;
    }
    tbb::parallel_for(size_t{0}, chunks, [&](size_t c) {
        body(c, c * kTriangleChunk, std::min(n, (c + 1) * kTriangleChunk));
    });
}

/// `node` of a subtree whose local node 1 lands at `node_offset` and local reference 0 at
/// `ref_offset` (splice's rebasing).
KdNode rebased(KdNode node, size_t node_offset, size_t ref_offset) noexcept {
    return node.is_leaf()
               ? KdNode::leaf(node.prim_count(),
                              node.first_ref() + static_cast<uint32_t>(ref_offset))
               : KdNode::inner(node.axis(), node.split(),
                               node.first_child() + static_cast<uint32_t>(node_offset - 1));
}

/// Writes the deferred subtrees of `src` into `nodes` / `refs`, as splice appends them: after
/// src's own `own_nodes` nodes and `own_refs` references and the deferred subtrees before each,
/// where src's local node 1 lands at `node_offset`, its root at `root_at` and its first
/// reference at `ref_offset`. Each subtree's root overwrites its placeholder slot among src's.
void flatten_children(const SubTree& src, size_t own_nodes, size_t own_refs, KdNode* nodes,
                      uint32_t* refs, size_t root_at, size_t node_offset, size_t ref_offset,
                      bool parallel);

/// Writes `src` (with its deferred subtrees) into `nodes` / `refs`: its root at `root_at`, its
/// local node i >= 1 at node_offset + i - 1, its references from `ref_offset`.
void flatten_into(const SubTree& src, KdNode* nodes, uint32_t* refs, size_t root_at,
                  size_t node_offset, size_t ref_offset, bool parallel) {
    nodes[root_at] = rebased(src.nodes[0], node_offset, ref_offset);
    for (size_t i = 1; i < src.nodes.size(); ++i)
        nodes[node_offset + i - 1] = rebased(src.nodes[i], node_offset, ref_offset);
    std::copy(src.refs.begin(), src.refs.end(), refs + ref_offset);
    // After the own nodes: the placeholders they hold are overwritten by the subtrees' roots.
    flatten_children(src, src.nodes.size(), src.refs.size(), nodes, refs, root_at, node_offset,
                     ref_offset, parallel);
}

void flatten_children(const SubTree& src, size_t own_nodes, size_t own_refs, KdNode* nodes,
                      uint32_t* refs, size_t root_at, size_t node_offset, size_t ref_offset,
                      bool parallel) {
    // Where each subtree goes: root slot, local node 1, first reference.
    std::vector<std::array<size_t, 3>> at(src.deferred.size());
    size_t next_node = own_nodes, next_ref = own_refs;  // local positions in src
    for (size_t k = 0; k < at.size(); ++k) {
        const SubTree::Deferred& d = src.deferred[k];
        at[k] = {d.slot == 0 ? root_at : node_offset + d.slot - 1, node_offset + next_node - 1,
                 ref_offset + next_ref};
        next_node += d.node_count - 1;
        next_ref += d.ref_count;
    }
    auto child = [&](size_t k) {
        flatten_into(*src.deferred[k].tree, nodes, refs, at[k][0], at[k][1], at[k][2], parallel);
    };
    if (parallel && at.size() > 1) {
        tbb::parallel_for(size_t{0}, at.size(), child);
    } else {
        for (size_t k = 0; k < at.size(); ++k) child(k);
    }
}

}  // namespace

void flatten_deferred(SubTree& tree, bool parallel) {
    if (tree.deferred.empty()) return;
    const size_t own_nodes = tree.nodes.size(), own_refs = tree.refs.size();
    tree.nodes.resize(tree.node_count());
    tree.refs.resize(tree.ref_count());
    // The tree's own nodes stay where they are: its local indices are the final ones.
    flatten_children(tree, own_nodes, own_refs, tree.nodes.data(), tree.refs.data(), 0, 1, 0,
                     parallel);
    tree.deferred.clear();
}

void splice(SubTree& tree, uint32_t slot, SubTree& child) {
    if (!tree.deferred.empty()) flatten_deferred(tree, false);
    if (!child.deferred.empty()) flatten_deferred(child, false);
    const size_t node_base = tree.nodes.size(), ref_base = tree.refs.size();
    // Local child index i >= 1 lands at node_base + i - 1 (the child's root goes to `slot`).
    tree.nodes[slot] = rebased(child.nodes[0], node_base, ref_base);
    tree.nodes.reserve(node_base + child.nodes.size() - 1);
    for (size_t i = 1; i < child.nodes.size(); ++i)
        tree.nodes.push_back(rebased(child.nodes[i], node_base, ref_base));
    tree.refs.insert(tree.refs.end(), child.refs.begin(), child.refs.end());
    tree.max_depth = std::max(tree.max_depth, child.max_depth);
}

void defer_splice(SubTree& tree, uint32_t slot, SubTree&& child) {
    const size_t node_count = child.node_count(), ref_count = child.ref_count();
    tree.max_depth = std::max(tree.max_depth, child.max_depth);
    tree.deferred.push_back(
        {slot, node_count, ref_count, std::make_unique<SubTree>(std::move(child))});
}

std::vector<uint8_t> prepare_triangles(const Mesh& mesh, TreeArray<TriVerts>& tris) {
    const size_t n = mesh.triangle_count();
    // Not zero-filled: every element is written below, by the chunk that first touches it.
    tris = uninitialized_tree_array<TriVerts>(n);
    std::vector<uint8_t> degenerate(n, 0);
    for_triangle_chunks(n, [&](size_t, size_t begin, size_t end) {
        for (size_t i = begin; i < end; ++i) {
            const Vec3 v0 = mesh.corner(i, 0), v1 = mesh.corner(i, 1), v2 = mesh.corner(i, 2);
            // Zero area, decided exactly: the products of floats are exact in double.
            const double e1[3] = {double{v1.x} - v0.x, double{v1.y} - v0.y, double{v1.z} - v0.z};
            const double e2[3] = {double{v2.x} - v0.x, double{v2.y} - v0.y, double{v2.z} - v0.z};
            const double cx = e1[1] * e2[2] - e1[2] * e2[1];
            const double cy = e1[2] * e2[0] - e1[0] * e2[2];
            const double cz = e1[0] * e2[1] - e1[1] * e2[0];
            const bool is_degenerate = cx == 0.0 && cy == 0.0 && cz == 0.0;
            degenerate[i] = is_degenerate ? 1 : 0;
            tris[i] = mesh_triangle(mesh, i, is_degenerate);
        }
    });
    return degenerate;
}

Aabb root_cell(std::span<const TriVerts> tris, const std::vector<uint8_t>& degenerate,
               Aabb* tight) {
    // Per-chunk bounds, combined in chunk order.
    std::vector<Aabb> partial((tris.size() + kTriangleChunk - 1) / kTriangleChunk);
    for_triangle_chunks(tris.size(), [&](size_t c, size_t begin, size_t end) {
        Aabb& b = partial[c];
        for (size_t i = begin; i < end; ++i) {
            if (degenerate[i]) continue;
            b.extend({tris[i].v0[0], tris[i].v0[1], tris[i].v0[2]});
            b.extend({tris[i].v1[0], tris[i].v1[1], tris[i].v1[2]});
            b.extend({tris[i].v2[0], tris[i].v2[1], tris[i].v2[2]});
        }
    });
    Aabb box;
    for (const Aabb& b : partial) {
        if (b.empty()) continue;
        box.extend(b.lo);
        box.extend(b.hi);
    }
    if (tight != nullptr) *tight = box;
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

void order_triangles(KdTree& tree, TreeArray<uint32_t>&& refs, const Mesh& mesh,
                     std::span<const uint8_t> degenerate, TreeArray<TriVerts>&& buffer) {
    // Numbering the triangles is one pass in reference order on one thread: the passes it takes
    // to number them in parallel chunks (a parallel least-position pass, a count, the slots, the
    // references) each read the big id arrays at random, and together cost more than the one
    // serial pass (tests/bench/README.md). The ids are written once, into an array that is not
    // zero-filled first; the references are rewritten in place, so their array (the flattened
    // build's) becomes tree.leaf_refs instead of a second fresh one of the same size.
    const auto n = static_cast<uint32_t>(mesh.triangle_count());
    if (buffer.size() != n || degenerate.size() != n)
        throw std::invalid_argument("order_triangles: the buffer and the degenerate flags need " +
                                    std::to_string(n) + " triangles, the mesh's count");
    const size_t m = refs.size();
    constexpr uint32_t kUnplaced = ~0u;
    tree.tri_slots.assign(n, kUnplaced);
    tree.tri_ids = uninitialized_tree_array<uint32_t>(n);
    tree.leaf_refs = std::move(refs);
    uint32_t next = 0;
    for (size_t i = 0; i < m; ++i) {
        uint32_t& ref = tree.leaf_refs[i];
        uint32_t& slot = tree.tri_slots[ref];
        if (slot == kUnplaced) {
            slot = next;
            tree.tri_ids[next++] = ref;
        }
        ref = slot;
    }
    for (uint32_t id = 0; id < n; ++id) {
        if (tree.tri_slots[id] != kUnplaced) continue;
        tree.tri_slots[id] = next;
        tree.tri_ids[next++] = id;
    }
    // The triangles in leaf order, in parallel chunks, made again from the mesh into `buffer`
    // (the build's triangles by id, no longer read): on 64 bunnies a fresh 174 MB array took
    // 0.4-0.7 s to fault in on this machine's virtual memory, the gather itself 20-70 ms.
    tree.tris = std::move(buffer);
    for_triangle_chunks(n, [&](size_t, size_t begin, size_t end) {
        for (size_t slot = begin; slot < end; ++slot) {
            const uint32_t id = tree.tri_ids[slot];
            tree.tris[slot] = mesh_triangle(mesh, id, degenerate[id] != 0);
        }
    });
}

void finish_tree(KdTree& tree, SubTree&& sub, const Mesh& mesh, std::span<const uint8_t> degenerate,
                 TreeArray<TriVerts>&& buffer) {
    // The tree's nodes and references, with the subtrees the parallel build handed over whole
    // copied into place side by side, written once into arrays of their final size that are not
    // written first: the nodes into scratch memory (cluster_nodes reads them once), the references
    // into the tree array that order_triangles rewrites in place as tree.leaf_refs.
    // (flatten_deferred grew the root's own vectors instead: value-initialised, then overwritten,
    // and the references copied once more into a fresh leaf_refs.)
    // Both are tree arrays, so that they take the pages the build's scratch arrays were given
    // (RecycleTreeMappings) where they are big.
    const size_t node_count = sub.node_count();
    TreeArray<std::byte> raw = uninitialized_tree_array<std::byte>(node_count * sizeof(KdNode));
    // KdNode is trivially copyable (an implicit-lifetime type): its objects begin in this storage.
    auto* const nodes = reinterpret_cast<KdNode*>(raw.data());
    TreeArray<uint32_t> refs = uninitialized_tree_array<uint32_t>(sub.ref_count());
    flatten_into(sub, nodes, refs.data(), 0, 1, 0, true);
    sub = SubTree{};  // the build's pieces are not read again
    // The node arrays and the triangles' leaf order touch different members and do not depend on
    // each other, so they are made side by side (on 16 bunnies each was about 0.8% of the
    // build's instructions, on one thread after the parallel build).
    tbb::parallel_invoke(
        [&] {
            tree.nodes = cluster_nodes({nodes, node_count});
            tree.wide_nodes = make_wide_nodes(tree.nodes);
        },
        [&] { order_triangles(tree, std::move(refs), mesh, degenerate, std::move(buffer)); });
    // compute_stats reads the nodes and the arrays' sizes, mark_leaf_runs writes the references'
    // last-reference bits: they run side by side too.
    const double build_ms = tree.stats.build_ms;
    tbb::parallel_invoke([&] { mark_leaf_runs(tree.nodes, tree.leaf_refs); },
                         [&] { tree.stats = compute_stats(tree); });
    tree.stats.build_ms = build_ms;
}

}  // namespace detail

std::vector<TriVerts> triangles_by_id(const KdTree& tree) {
    std::vector<TriVerts> tris(tree.tris.size());
    for (size_t slot = 0; slot < tree.tris.size(); ++slot)
        tris[tree.tri_ids[slot]] = tree.tris[slot];
    return tris;
}

std::vector<TriVerts> make_tri_verts(const Mesh& mesh) {
    TreeArray<TriVerts> by_id;
    detail::prepare_triangles(mesh, by_id);
    return {by_id.begin(), by_id.end()};
}

KdTree detail::build_kdtree_with(const Mesh& mesh, const BuildOptions& options,
                                 const BinnedParams& params) {
    const auto start = std::chrono::steady_clock::now();
    validate_mesh(mesh);
    // The build's freed big arrays serve its later ones (the binned levels' arena's pages become
    // the tree's final arrays). Kept up to twice the build's triangle array (72 bytes a
    // triangle): the arena's blocks (61 bytes a triangle on 64 bunnies: the root's references and
    // its children) and the tree's final arrays (about 45) fit under it.
    const detail::RecycleTreeMappings recycle(2 * mesh.triangle_count() * sizeof(TriVerts));
    KdTree tree;
    tree.options = options;
    TreeArray<TriVerts> by_id;
    const std::vector<uint8_t> degenerate = detail::prepare_triangles(mesh, by_id);
    Aabb tight;
    tree.bounds = detail::root_cell(by_id, degenerate, &tight);
    detail::SubTree sub;
    if (!tree.bounds.empty()) {
        if (options.builder == Builder::kMiddle) {
            detail::build_middle(by_id, degenerate, tree.bounds, options, sub);
        } else {
            detail::build_binned(by_id, degenerate, tree.bounds, tight, options, params, sub);
        }
    }
    tree.stats.build_ms =
        std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - start).count();
    // The triangles by id are not read after the build: their array becomes tree.tris.
    detail::finish_tree(tree, std::move(sub), mesh, degenerate, std::move(by_id));
    return tree;
}

KdTree build_kdtree(const Mesh& mesh, const BuildOptions& options) {
    return detail::build_kdtree_with(mesh, options, detail::BinnedParams{});
}

}  // namespace kdrt
