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
#include <vector>

namespace kdrt::detail {

NodeArray cluster_nodes(std::span<const KdNode> nodes) {
    NodeArray out;
    if (nodes.empty()) return out;
    if (nodes[0].is_leaf()) {
        out.assign(nodes.begin(), nodes.begin() + 1);
        return out;
    }
    // new_first[f]: the new index of the child pair that starts at old index f.
    std::vector<uint32_t> new_first(nodes.size(), 0);
    std::vector<uint32_t> order;  // old first indices, in their new order
    order.reserve(nodes.size() / 2);

    std::vector<uint32_t> pending{nodes[0].first_child()};  // line roots, depth first (a stack)
    uint32_t slot = 2;  // the next free node index: line 0 starts with the root and an unused slot
    std::deque<uint32_t> line;
    while (!pending.empty()) {
        // One line: breadth first from a pending pair, topped up from the stack when it runs out.
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
    out.assign(slot, KdNode{});
    out[0] = KdNode::inner(nodes[0].axis(), nodes[0].split(), new_first[nodes[0].first_child()]);
    for (uint32_t first : order) {
        const uint32_t at = new_first[first];
        for (uint32_t c = 0; c < 2; ++c) {
            const KdNode n = nodes[first + c];
            out[at + c] =
                n.is_leaf() ? n : KdNode::inner(n.axis(), n.split(), new_first[n.first_child()]);
        }
    }
    return out;
}

}  // namespace kdrt::detail
