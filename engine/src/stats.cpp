#include <algorithm>
#include <vector>

#include "geometry.h"
#include "kdrt/kdtree.h"

namespace kdrt {

using detail::half_area;

TreeStats compute_stats(const KdTree& tree) {
    TreeStats s;
    s.triangles = tree.tris.size();
    // s.nodes counts the nodes reachable from the root (the cache-line layout leaves slot 1
    // unused); s.bytes counts the array as allocated.
    s.refs = tree.leaf_refs.size();
    s.bytes = tree.nodes.size() * sizeof(KdNode) + tree.wide_nodes.size() * sizeof(WideNode) +
              tree.leaf_refs.size() * sizeof(uint32_t) + tree.tris.size() * sizeof(TriVerts) +
              (tree.tri_ids.size() + tree.tri_slots.size()) * sizeof(uint32_t);
    s.bytes_per_triangle =
        s.triangles ? static_cast<double>(s.bytes) / static_cast<double>(s.triangles) : 0.0;
    if (tree.nodes.empty()) return s;

    struct Item {
        uint32_t node;
        uint32_t depth;
        Aabb cell;
    };
    const double root_area = half_area(tree.bounds);
    double depth_sum = 0, cost = 0;
    uint64_t nonempty = 0, nonempty_refs = 0;
    std::vector<Item> stack{{0, 0, tree.bounds}};
    while (!stack.empty()) {
        const Item item = stack.back();
        stack.pop_back();
        const KdNode node = tree.nodes[item.node];
        const double p = root_area > 0 ? half_area(item.cell) / root_area : 1.0;
        ++s.nodes;
        if (node.is_leaf()) {
            ++s.leaves;
            depth_sum += item.depth;
            s.max_depth = std::max(s.max_depth, item.depth);
            if (node.prim_count() == 0) {
                ++s.empty_leaves;
            } else {
                ++nonempty;
                nonempty_refs += node.prim_count();
            }
            cost += p * tree.options.intersection_cost * node.prim_count();
            continue;
        }
        cost += p * tree.options.traversal_cost;
        Aabb left = item.cell, right = item.cell;
        left.hi[node.axis()] = node.split();
        right.lo[node.axis()] = node.split();
        stack.push_back({node.first_child() + 1, item.depth + 1, right});
        stack.push_back({node.first_child(), item.depth + 1, left});
    }
    s.mean_leaf_depth = s.leaves ? depth_sum / static_cast<double>(s.leaves) : 0.0;
    s.mean_tris_per_leaf =
        nonempty ? static_cast<double>(nonempty_refs) / static_cast<double>(nonempty) : 0.0;
    s.sah_cost = cost;
    return s;
}

}  // namespace kdrt
