#include <gtest/gtest.h>

#include <bit>
#include <cstring>

#include "kdrt/kdtree.h"

namespace kdrt {
namespace {

// The bit layout documented in kdtree.h, pinned word by word.
TEST(KdNode, IsEightBytes) {
    static_assert(sizeof(KdNode) == 8);
    static_assert(alignof(KdNode) == 4);
    EXPECT_EQ(sizeof(KdNode), 8u);
}

TEST(KdNode, InnerLayout) {
    const KdNode n = KdNode::inner(2, 1.5f, 12345);
    EXPECT_FALSE(n.is_leaf());
    EXPECT_EQ(n.axis(), 2);
    EXPECT_EQ(n.first_child(), 12345u);
    EXPECT_EQ(n.split(), 1.5f);
    EXPECT_EQ(n.word0(), (12345u << 2) | 2u);
    EXPECT_EQ(n.word1(), std::bit_cast<uint32_t>(1.5f));
    uint32_t raw[2];
    std::memcpy(raw, &n, sizeof raw);
    EXPECT_EQ(raw[0], n.word0());
    EXPECT_EQ(raw[1], n.word1());
}

TEST(KdNode, LeafLayout) {
    const KdNode n = KdNode::leaf(7, 99);
    EXPECT_TRUE(n.is_leaf());
    EXPECT_EQ(n.prim_count(), 7u);
    EXPECT_EQ(n.first_ref(), 99u);
    EXPECT_EQ(n.word0(), (7u << 2) | 3u);
    EXPECT_EQ(n.word1(), 99u);
}

TEST(KdNode, ThirtyBitFieldsRoundTrip) {
    const uint32_t max = KdNode::kMaxField;
    EXPECT_EQ(KdNode::inner(0, -0.0f, max).first_child(), max);
    EXPECT_EQ(KdNode::leaf(max, 0xFFFFFFFFu).prim_count(), max);
    EXPECT_EQ(KdNode::leaf(max, 0xFFFFFFFFu).first_ref(), 0xFFFFFFFFu);
    for (int axis = 0; axis < 3; ++axis) EXPECT_EQ(KdNode::inner(axis, 0.0f, max).axis(), axis);
    EXPECT_TRUE(KdNode{}.is_leaf());
    EXPECT_EQ(KdNode{}.prim_count(), 0u);
}

}  // namespace
}  // namespace kdrt
