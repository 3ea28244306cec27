// The "hack" kD-tree of Stoll 2005: split the largest extent in the middle, stop at a fixed
// triangle count or depth. It exists only as the baseline the benchmark compares the SAH tree to.

#include <algorithm>
#include <vector>

#include <tbb/parallel_invoke.h>

#include "build_internal.h"

namespace kdrt::detail {
namespace {

struct MiddleBuilder {
    std::span<const TriVerts> tris;
    std::vector<Aabb> boxes;  // per triangle vertex bounds
    uint32_t leaf_size;
    uint32_t max_depth;

    void build(SubTree& out, uint32_t slot, const Aabb& cell, std::vector<uint32_t>&& prims,
               uint32_t depth) {
        const Vec3 ext = cell.extent();
        const int axis = ext.x >= ext.y && ext.x >= ext.z ? 0 : (ext.y >= ext.z ? 1 : 2);
        const float mid = cell.lo[axis] + 0.5f * ext[axis];
        if (prims.size() <= leaf_size || depth >= max_depth ||
            !(mid > cell.lo[axis] && mid < cell.hi[axis])) {
            make_leaf(out, slot, prims);
            out.max_depth = std::max(out.max_depth, depth);
            return;
        }
        std::vector<uint32_t> left, right;
        for (uint32_t prim : prims) {
            if (boxes[prim].lo[axis] <= mid) left.push_back(prim);
            if (boxes[prim].hi[axis] >= mid) right.push_back(prim);
        }
        prims = {};
        Aabb left_cell = cell, right_cell = cell;
        left_cell.hi[axis] = mid;
        right_cell.lo[axis] = mid;
        if (left.size() + right.size() >= 4096) {
            SubTree left_tree, right_tree;
            tbb::parallel_invoke(
                [&] { build(left_tree, 0, left_cell, std::move(left), depth + 1); },
                [&] { build(right_tree, 0, right_cell, std::move(right), depth + 1); });
            const uint32_t first = add_child_pair(out, slot, axis, mid);
            splice(out, first, left_tree);
            splice(out, first + 1, right_tree);
        } else {
            const uint32_t first = add_child_pair(out, slot, axis, mid);
            build(out, first, left_cell, std::move(left), depth + 1);
            build(out, first + 1, right_cell, std::move(right), depth + 1);
        }
    }
};

}  // namespace

void build_middle(std::span<const TriVerts> tris, const std::vector<uint8_t>& degenerate,
                  const Aabb& root, const BuildOptions& options, SubTree& out) {
    MiddleBuilder builder{
        tris, std::vector<Aabb>(tris.size()), std::max(options.middle_leaf_size, 1u),
        static_cast<uint32_t>(std::clamp(options.middle_max_depth, 0, kMaxDepth))};
    std::vector<uint32_t> prims;
    for (uint32_t prim = 0; prim < tris.size(); ++prim) {
        if (degenerate[prim]) continue;
        const TriVerts& t = tris[prim];
        for (int a = 0; a < 3; ++a) {
            builder.boxes[prim].lo[a] = std::min({t.v0[a], t.v1[a], t.v2[a]});
            builder.boxes[prim].hi[a] = std::max({t.v0[a], t.v1[a], t.v2[a]});
        }
        prims.push_back(prim);
    }
    builder.build(out, 0, root, std::move(prims), 0);
}

}  // namespace kdrt::detail
