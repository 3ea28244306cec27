// Cache-line clustering of the nodes (issue 11, "nodes clustered into cache lines"): the builders
// emit nodes depth first, so the child pair of a node's right child is far from it, and every
// traversal step of an incoherent ray may be a cache miss. Here each 64-byte line holds four
// child pairs: a pair and, breadth first, the pairs below it (two levels more). A descent crosses
// a line boundary once per two or three levels instead of on nearly every step.
//
// Line 0 holds the root, an unused slot (so that pairs start at even indices and never straddle a
// line) and the first three pairs. The pairs that do not fit in their parent's line start lines
// of their own, taken depth first so that a subtree's lines stay close; a line whose subtree runs
// out is filled with the next pending pairs rather than left with holes.

#include "node_layout.h"

#include <cstdint>
#include <deque>
#include <limits>
#include <memory>
#include <stdexcept>
#include <utility>
#include <vector>

#include <tbb/blocked_range.h>
#include <tbb/parallel_for.h>
#include <tbb/parallel_invoke.h>

namespace kdrt::detail {

NodeArray cluster_nodes(std::span<const KdNode> nodes) {
    NodeArray out;
    if (nodes.empty()) return out;
    if (nodes[0].is_leaf()) {
        out.assign(nodes.begin(), nodes.begin() + 1);
        return out;
    }
    // The layout has no holes: line 0's unused slot, then every pair, so nodes.size() + 1 nodes.
    // The output is sized (value-initialised: each page's first touch, on 64 bunnies tens of
    // milliseconds of fresh huge pages) by one task while the other walks the tree.
    const size_t out_size = nodes.size() + 1;
    // new_first[f]: the new index of the child pair that starts at old index f. Not zero-filled:
    // it is read only at first children, and every pair gets its index before the copy below.
    // A tree array: a big one takes pages a build has freed (RecycleTreeMappings).
    TreeArray<uint32_t> new_first = uninitialized_tree_array<uint32_t>(nodes.size());
    std::vector<uint32_t> order;  // old first indices, in their new order (pair i at 2 + 2 i)
    uint32_t slot = 2;  // the next free node index: line 0 starts with the root and an unused slot
    const auto walk = [&] {
        order.reserve(nodes.size() / 2);
        std::vector<uint32_t> pending{nodes[0].first_child()};  // line roots, depth first (a stack)
        std::deque<uint32_t> line;
        while (!pending.empty()) {
            // One line: breadth first from a pending pair, topped up from the stack when it runs
            // out.
            const uint32_t line_end = (slot / kNodesPerLine + 1) * kNodesPerLine;
            line.clear();
            line.push_back(pending.back());
            pending.pop_back();
            while (slot < line_end) {
                if (line.empty()) {
                    if (pending.empty()) break;
                    line.push_back(pending.back());
                    pending.pop_back();
                }
                const uint32_t first = line.front();
                line.pop_front();
                new_first[first] = slot;
                order.push_back(first);
                slot += 2;
                for (uint32_t c = first; c < first + 2; ++c)
                    if (!nodes[c].is_leaf()) line.push_back(nodes[c].first_child());
            }
            // What did not fit starts lines of its own, the first of them next.
            pending.insert(pending.end(), line.rbegin(), line.rend());
        }
    };
    tbb::parallel_invoke([&] { out = NodeArray(out_size); }, walk);
    if (slot != out.size()) out.resize(slot);  // (never: the layout has no holes)
    out[0] = KdNode::inner(nodes[0].axis(), nodes[0].split(), new_first[nodes[0].first_child()]);
    // The pairs in parallel chunks: pair i goes to 2 + 2 i, whatever thread writes it.
    constexpr size_t kPairsPerChunk = size_t{1} << 14;
    tbb::parallel_for(
        tbb::blocked_range<size_t>(0, order.size(), kPairsPerChunk),
        [&](const tbb::blocked_range<size_t>& range) {
            for (size_t i = range.begin(); i < range.end(); ++i) {
                const uint32_t first = order[i];
                const size_t at = 2 + 2 * i;
                for (uint32_t c = 0; c < 2; ++c) {
                    const KdNode n = nodes[first + c];
                    out[at + c] = n.is_leaf() ? n
                                              : KdNode::inner(n.axis(), n.split(),
                                                              new_first[n.first_child()]);
                }
            }
        },
        tbb::simple_partitioner());
    return out;
}

}  // namespace kdrt::detail

namespace kdrt {

// Wide nodes (issue 23): each binary inner node that starts a treelet is collapsed with the two
// levels below it. Treelets are numbered depth first, so a subtree's wide nodes are close together.
namespace {

/// The number of wide nodes make_wide_nodes makes of `nodes`: the treelet roots, i.e. the root
/// and every inner node three levels below a treelet root. One pass over the inner nodes, so the
/// array is allocated once at its final size (grown by emplace_back, each doubling was a fresh
/// 2 MiB-aligned allocation to fault in and copy: on 64 bunnies most of make_wide_nodes' wall
/// time).
size_t count_wide_nodes(std::span<const KdNode> nodes) {
    size_t count = 1;
    std::vector<uint32_t> roots{0u};
    while (!roots.empty()) {
        const uint32_t root = roots.back();
        roots.pop_back();
        for (uint32_t c1 = nodes[root].first_child(); c1 < nodes[root].first_child() + 2; ++c1) {
            if (nodes[c1].is_leaf()) continue;
            for (uint32_t c2 = nodes[c1].first_child(); c2 < nodes[c1].first_child() + 2; ++c2) {
                if (nodes[c2].is_leaf()) continue;
                for (uint32_t c3 = nodes[c2].first_child(); c3 < nodes[c2].first_child() + 2;
                     ++c3) {
                    if (nodes[c3].is_leaf()) continue;
                    ++count;
                    roots.push_back(c3);
                }
            }
        }
    }
    return count;
}

}  // namespace

TreeArray<WideNode> make_wide_nodes(std::span<const KdNode> nodes) {
    if (nodes.empty() || nodes[0].is_leaf()) return {};
    constexpr uint32_t kMaxIndex = KdNode::kMaxField;
    const size_t count = count_wide_nodes(nodes);
    // A wide node's index must fit a slot (the root's is never named by one).
    if (count - 1 > kMaxIndex) throw std::length_error("too many wide nodes");
    // Every element is written below (out[at] = w, once for each index handed out).
    TreeArray<WideNode> out = uninitialized_tree_array<WideNode>(count);
    // A leaf's slot names its first reference (the kernel reads its run from there); an empty
    // leaf's names its node (only the counting kernels visit it).
    const auto leaf_slot = [](const KdNode& n, uint32_t index) {
        if (n.prim_count() == 0) return WideNode::make_slot(WideNode::kSlotEmpty, index);
        if (n.first_ref() > kMaxIndex)
            throw std::length_error("a leaf's first reference does not fit a wide node's slot");
        return WideNode::make_slot(WideNode::kSlotLeaf, n.first_ref());
    };
    std::vector<std::pair<uint32_t, uint32_t>> pending{{0u, 0u}};  // (binary root, wide index)
    uint32_t next = 1;  // the next wide index to hand out, in the same order as emplace_back did
    while (!pending.empty()) {
        const auto [root, at] = pending.back();
        pending.pop_back();
        WideNode w{};
        w.axes = 0;
        for (int j = 0; j < WideNode::kPlanes; ++j) w.split[j] = 0.0f;
        for (int s = 0; s < WideNode::kSlots; ++s) w.slot[s] = WideNode::kSlotNone;
        const auto set_plane = [&w](int j, const KdNode& n) {
            w.split[j] = n.split();
            w.axes |= static_cast<uint32_t>(n.axis()) << (2 * j);
        };
        const auto pad_plane = [&w](int j) {
            // +inf on x: every ray keeps its whole interval on the low side (b = 0).
            w.split[j] = std::numeric_limits<float>::infinity();  // axis code 0: x
        };
        set_plane(0, nodes[root]);
        for (uint32_t b0 = 0; b0 < 2; ++b0) {
            const uint32_t c1 = nodes[root].first_child() + b0;
            const int p1 = 1 + static_cast<int>(b0);
            if (nodes[c1].is_leaf()) {
                pad_plane(p1);
                pad_plane(3 + 2 * static_cast<int>(b0));
                w.slot[4 * b0] = leaf_slot(nodes[c1], c1);
                continue;
            }
            set_plane(p1, nodes[c1]);
            for (uint32_t b1 = 0; b1 < 2; ++b1) {
                const uint32_t c2 = nodes[c1].first_child() + b1;
                const int p2 = 3 + static_cast<int>(2 * b0 + b1);
                if (nodes[c2].is_leaf()) {
                    pad_plane(p2);
                    w.slot[4 * b0 + 2 * b1] = leaf_slot(nodes[c2], c2);
                    continue;
                }
                set_plane(p2, nodes[c2]);
                for (uint32_t b2 = 0; b2 < 2; ++b2) {
                    const uint32_t c3 = nodes[c2].first_child() + b2;
                    const uint32_t s = 4 * b0 + 2 * b1 + b2;
                    if (nodes[c3].is_leaf()) {
                        w.slot[s] = leaf_slot(nodes[c3], c3);
                        continue;
                    }
                    const uint32_t child = next++;
                    w.slot[s] = WideNode::make_slot(WideNode::kSlotNode, child);
                    pending.emplace_back(c3, child);
                }
            }
        }
        out[at] = w;
    }
    return out;
}

void mark_leaf_runs(std::span<const KdNode> nodes, std::span<uint32_t> refs) noexcept {
    for (uint32_t& ref : refs) ref &= ~KdTree::kLastRef;
    for (const KdNode& node : nodes) {
        if (node.is_leaf() && node.prim_count() > 0)
            refs[node.first_ref() + node.prim_count() - 1] |= KdTree::kLastRef;
    }
}

}  // namespace kdrt
