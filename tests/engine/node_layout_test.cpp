// The cache-line layout of the nodes (engine/src/node_layout.cpp): the same tree, children after
// their parents, pairs inside lines, and most descents staying within a line.

#include "node_layout.h"

#include <gtest/gtest.h>

#include <cstdint>
#include <string>
#include <vector>

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
