#pragma once
/// The figures that describe a built kD-tree (TreeStats): a value type (no function here needs
/// kdrt_engine). kdrt/kdtree.h builds trees and computes them.

#include <cstdint>

namespace kdrt {

/// Figures that describe a built tree. Filled by the builders (build_ms included) and kept with
/// the tree through serialisation.
struct TreeStats {
    uint64_t triangles = 0;  ///< triangles in the mesh
    uint64_t nodes = 0;
    uint64_t leaves = 0;
    uint64_t empty_leaves = 0;
    uint64_t refs = 0;       ///< triangle references in all leaves
    uint32_t max_depth = 0;  ///< deepest leaf (root = 0)
    double mean_leaf_depth = 0;
    double mean_tris_per_leaf = 0;  ///< over non-empty leaves
    double sah_cost = 0;            ///< expected cost of a random ray through the root cell
    uint64_t bytes = 0;             ///< nodes + refs + triangle data
    double bytes_per_triangle = 0;
    double build_ms = 0;
};

}  // namespace kdrt
