#include <algorithm>
#include <vector>

#include <tbb/parallel_for.h>

#include "geometry.h"
#include "kdrt/kdtree.h"

namespace kdrt {
namespace {

using detail::half_area;

/// Trees of more nodes than this walk their subtrees below kSplitDepth in parallel; smaller trees
/// are walked by one thread in one pass.
constexpr size_t kParallelNodes = size_t{1} << 16;
/// The depth whose inner nodes root the parallel walks (at most 2^10 of them). It depends on the
/// tree alone, never on the thread count, and so does the order of every sum.
constexpr uint32_t kSplitDepth = 10;

struct Item {
    uint32_t node;
    uint32_t depth;
    Aabb cell;
};

/// One term of sah_cost in walk order: a node's own term, or the sum of a deferred subtree.
struct Term {
    static constexpr uint32_t kOwn = ~0u;
    double value;
    uint32_t subtree;  ///< index into the deferred subtrees, or kOwn
};

/// The figures of one walk. The counts are exact at any grouping; `cost` is a sum of doubles,
/// so its grouping is fixed (see compute_stats).
struct Walk {
    uint64_t nodes = 0, leaves = 0, empty_leaves = 0, nonempty = 0, nonempty_refs = 0;
    uint64_t depth_sum = 0;
    uint32_t max_depth = 0;
    double cost = 0;

    void add_counts(const Walk& w) noexcept {
        nodes += w.nodes;
        leaves += w.leaves;
        empty_leaves += w.empty_leaves;
        nonempty += w.nonempty;
        nonempty_refs += w.nonempty_refs;
        depth_sum += w.depth_sum;
        max_depth = std::max(max_depth, w.max_depth);
    }
};

/// Walks the subtree of `root` depth first, left child first, adding each node's SAH term to
/// w.cost in that order. An inner node at depth `defer_depth` is not entered: it goes to
/// `deferred` and gets its place in `order` between the terms around it.
/// Without deferral (order == nullptr) the terms are summed straight into w.cost.
void walk(const KdTree& tree, const Item& root, double root_area, uint32_t defer_depth, Walk& w,
          std::vector<Item>* deferred, std::vector<Term>* order) {
    std::vector<Item> stack{root};
    while (!stack.empty()) {
        const Item item = stack.back();
        stack.pop_back();
        const KdNode node = tree.nodes[item.node];
        if (deferred && !node.is_leaf() && item.depth == defer_depth) {
            order->push_back({0.0, static_cast<uint32_t>(deferred->size())});
            deferred->push_back(item);
            continue;
        }
        const double p = root_area > 0 ? half_area(item.cell) / root_area : 1.0;
        double term;
        ++w.nodes;
        if (node.is_leaf()) {
            ++w.leaves;
            w.depth_sum += item.depth;
            w.max_depth = std::max(w.max_depth, item.depth);
            if (node.prim_count() == 0) {
                ++w.empty_leaves;
            } else {
                ++w.nonempty;
                w.nonempty_refs += node.prim_count();
            }
            term = p * tree.options.intersection_cost * node.prim_count();
        } else {
            term = p * tree.options.traversal_cost;
            Aabb left = item.cell, right = item.cell;
            left.hi[node.axis()] = node.split();
            right.lo[node.axis()] = node.split();
            stack.push_back({node.first_child() + 1, item.depth + 1, right});
            stack.push_back({node.first_child(), item.depth + 1, left});
        }
        if (order) {
            order->push_back({term, Term::kOwn});
        } else {
            w.cost += term;
        }
    }
}

}  // namespace

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

    const double root_area = half_area(tree.bounds);
    const Item root{0, 0, tree.bounds};
    Walk total;
    if (tree.nodes.size() <= kParallelNodes) {
        walk(tree, root, root_area, 0, total, nullptr, nullptr);
    } else {
        // The nodes above kSplitDepth are walked first, keeping their terms in walk order; the
        // subtrees below are walked in parallel, each summing its own terms; then the terms are
        // summed in walk order with each subtree's sum in its subtree's place. The grouping, and
        // so every bit of sah_cost, depends on the tree only.
        std::vector<Item> deferred;
        std::vector<Term> order;
        walk(tree, root, root_area, kSplitDepth, total, &deferred, &order);
        std::vector<Walk> below(deferred.size());
        tbb::parallel_for(size_t{0}, deferred.size(), [&](size_t i) {
            walk(tree, deferred[i], root_area, 0, below[i], nullptr, nullptr);
        });
        for (const Walk& w : below) total.add_counts(w);
        for (const Term& term : order)
            total.cost += term.subtree == Term::kOwn ? term.value : below[term.subtree].cost;
    }
    s.nodes = total.nodes;
    s.leaves = total.leaves;
    s.empty_leaves = total.empty_leaves;
    s.max_depth = total.max_depth;
    s.mean_leaf_depth =
        s.leaves ? static_cast<double>(total.depth_sum) / static_cast<double>(s.leaves) : 0.0;
    s.mean_tris_per_leaf = total.nonempty ? static_cast<double>(total.nonempty_refs) /
                                                static_cast<double>(total.nonempty)
                                          : 0.0;
    s.sah_cost = total.cost;
    return s;
}

}  // namespace kdrt
