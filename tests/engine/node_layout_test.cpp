// The cache-line layout of the nodes (engine/src/node_layout.cpp): the same tree, children after
// their parents, pairs inside lines, and most descents staying within a line.

#include "node_layout.h"

#include <gtest/gtest.h>

#include <cstdint>
#include <deque>
#include <string>
#include <vector>

#include <tbb/task_arena.h>

#include "kdrt/kdtree.h"
#include "kdrt/proto/mesh_io.h"
#include "test_util.h"

namespace kdrt::test {
namespace {

/// A depth-first node array as the builders make it, of a tree with `depth` full levels.
std::vector<KdNode> full_tree(int depth) {
    std::vector<KdNode> nodes{KdNode{}};
    uint32_t next_ref = 0;
    struct Item {
        uint32_t slot;
        int level;
    };
    std::vector<Item> stack{{0, 0}};
    while (!stack.empty()) {
        const Item it = stack.back();
        stack.pop_back();
        if (it.level == depth) {
            nodes[it.slot] = KdNode::leaf(1, next_ref++);
            continue;
        }
        const auto first = static_cast<uint32_t>(nodes.size());
        nodes.emplace_back();
        nodes.emplace_back();
        nodes[it.slot] = KdNode::inner(it.level % 3, static_cast<float>(it.slot), first);
        stack.push_back({first + 1, it.level + 1});
        stack.push_back({first, it.level + 1});
    }
    return nodes;
}

void expect_valid_layout(std::span<const KdNode> dfs, const NodeArray& lines) {
    EXPECT_EQ(tree_shape(dfs), tree_shape(lines)) << "the same tree";
    EXPECT_EQ(reinterpret_cast<uintptr_t>(lines.data()) % 64, 0u) << "the array starts a line";
    if (dfs.size() > 1) {
        EXPECT_EQ(lines.size(), dfs.size() + 1) << "one unused slot, no holes";
    }
    for (uint32_t i = 0; i < lines.size(); ++i) {
        const KdNode n = lines[i];
        if (n.is_leaf()) continue;
        EXPECT_GT(n.first_child(), i) << "children after their parent, node " << i;
        EXPECT_EQ(n.first_child() % 2, 0u) << "a pair never straddles a line, node " << i;
        EXPECT_LT(n.first_child() + 1, lines.size());
    }
}

/// A depth-first node array of a random tree: each node from level 6 to `depth` splits with
/// probability 3/4, so subtrees are ragged and lines run out and are topped up anywhere.
std::vector<KdNode> random_tree(Rng& rng, int depth) {
    std::vector<KdNode> nodes{KdNode{}};
    struct Item {
        uint32_t slot;
        int level;
    };
    std::vector<Item> stack{{0, 0}};
    uint32_t next_ref = 0;
    while (!stack.empty()) {
        const Item it = stack.back();
        stack.pop_back();
        if (it.level == depth || (it.level > 5 && rng.below(4) == 0)) {
            nodes[it.slot] = KdNode::leaf(rng.below(3), next_ref++);
            continue;
        }
        const auto first = static_cast<uint32_t>(nodes.size());
        nodes.emplace_back();
        nodes.emplace_back();
        nodes[it.slot] = KdNode::inner(static_cast<int>(rng.below(3)), rng.uniform(-1, 1), first);
        stack.push_back({first + 1, it.level + 1});
        stack.push_back({first, it.level + 1});
    }
    return nodes;
}

/// The layout as one serial pass writes it (cluster_nodes before it sized and wrote its output in
/// parallel): the oracle for the parallel one.
std::vector<KdNode> serial_layout(std::span<const KdNode> nodes) {
    if (nodes[0].is_leaf()) return {nodes[0]};
    std::vector<uint32_t> new_first(nodes.size(), 0), order;
    std::vector<uint32_t> pending{nodes[0].first_child()};
    uint32_t slot = 2;
    std::deque<uint32_t> line;
    while (!pending.empty()) {
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
        pending.insert(pending.end(), line.rbegin(), line.rend());
    }
    std::vector<KdNode> out(slot);
    out[0] = KdNode::inner(nodes[0].axis(), nodes[0].split(), new_first[nodes[0].first_child()]);
    for (const uint32_t first : order) {
        for (uint32_t c = 0; c < 2; ++c) {
            const KdNode n = nodes[first + c];
            out[new_first[first] + c] =
                n.is_leaf() ? n : KdNode::inner(n.axis(), n.split(), new_first[n.first_child()]);
        }
    }
    return out;
}

// cluster_nodes sizes its output while it walks the tree and writes the pairs in parallel chunks:
// at any thread count it must give, node for node, what the serial pass gives. The big trees have
// many chunks of pairs; the small ones fit in one.
TEST(NodeLayout, ParallelLayoutIsTheSerialOneAtAnyThreadCount) {
    Rng rng(test_seed() + 77);
    for (const int depth : {0, 1, 5, 12, 24}) {
        SCOPED_TRACE(testing::Message() << "depth " << depth);
        const std::vector<KdNode> dfs = random_tree(rng, depth);
        const std::vector<KdNode> want = serial_layout(dfs);
        if (depth == 24) {
            ASSERT_GT(dfs.size(), 100'000u) << "the big tree spans many chunks of pairs";
        }
        for (const int threads : {1, 2, 4}) {
            SCOPED_TRACE(threads);
            NodeArray got;
            tbb::task_arena arena(threads);
            arena.execute([&] { got = detail::cluster_nodes(dfs); });
            ASSERT_EQ(got.size(), want.size());
            for (size_t i = 0; i < want.size(); ++i) ASSERT_EQ(got[i], want[i]) << "node " << i;
            expect_valid_layout(dfs, got);
        }
    }
}

TEST(NodeLayout, FullTreesKeepTheirShapeAndDescendWithinLines) {
    for (int depth : {0, 1, 2, 3, 4, 9}) {
        SCOPED_TRACE(testing::Message() << "depth " << depth);
        const std::vector<KdNode> dfs = full_tree(depth);
        const NodeArray lines = detail::cluster_nodes(dfs);
        expect_valid_layout(dfs, lines);
        if (depth == 0) {
            EXPECT_EQ(lines.size(), 1u) << "a lone leaf stays alone";
        }
        if (depth >= 3) {
            // Line 0: the root, the unused slot, its child pair and both grandchild pairs.
            const KdNode root = lines[0];
            ASSERT_EQ(root.first_child(), 2u);
            EXPECT_EQ(lines[2].first_child() / kNodesPerLine, 0u);
            EXPECT_EQ(lines[3].first_child() / kNodesPerLine, 0u);
        }
    }
}

TEST(NodeLayout, BunnyTreeDescendsWithinALineMostSteps) {
    auto mesh = proto::load_mesh_file(std::string(KDRT_TEST_DATA_DIR) + "/bunny00.off");
    ASSERT_TRUE(mesh.ok());
    const KdTree tree = build_kdtree(*mesh);
    const NodeArray& nodes = tree.nodes;
    // Rebuild the depth-first order from the layout to check the transform round trip.
    size_t inner = 0, same_line = 0;
    for (uint32_t i = 0; i < nodes.size(); ++i) {
        const KdNode n = nodes[i];
        if (n.is_leaf()) continue;
        ++inner;
        for (uint32_t c = n.first_child(); c < n.first_child() + 2; ++c) {
            if (nodes[c].is_leaf()) continue;
            // A step from child c to its own children stays in c's line?
            same_line += nodes[c].first_child() / kNodesPerLine == c / kNodesPerLine ? 1 : 0;
        }
    }
    ASSERT_GT(inner, 1000u);
    // Each line holds a pair and the pairs of its children: at least half of all
    // pair-to-children steps stay in the line (two of every three in a full tree).
    EXPECT_GT(static_cast<double>(same_line), 0.5 * static_cast<double>(inner)) << same_line;
    for (uint32_t i = 0; i < nodes.size(); ++i) {
        if (nodes[i].is_leaf()) continue;
        ASSERT_GT(nodes[i].first_child(), i);
        ASSERT_EQ(nodes[i].first_child() % 2, 0u);
    }
}

}  // namespace
}  // namespace kdrt::test
