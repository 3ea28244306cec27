#pragma once
/// Versioned binary form of a KdTree, loadable without rebuilding.

#include <cstddef>
#include <span>
#include <stdexcept>
#include <vector>

#include "kdrt/kdtree.h"

namespace kdrt {

/// Current tree blob format version.
/// Version 2 (kdrt 0.2): nodes in cache lines, triangles in leaf order with their mesh ids. A blob
/// of another version is refused (TreeFormatError); the server then rebuilds the tree from the
/// stored mesh.
inline constexpr uint32_t kTreeFormatVersion = 2;

/// Thrown by deserialize_tree for a blob it refuses; what() names the problem (bad magic,
/// version, truncated section, checksum mismatch, inconsistent content).
class TreeFormatError : public std::runtime_error {
public:
    using std::runtime_error::runtime_error;
};

/// Layout (little-endian): "KDRTTREE", u32 version, u32 header bytes, build options, stats,
/// bounds, array counts, then nodes, refs, triangles, their mesh ids, and a trailing u64 checksum
/// of all bytes before it. See engine/src/serialize.cpp for the exact field list.
[[nodiscard]] std::vector<std::byte> serialize_tree(const KdTree& tree);

/// Loads a blob written by serialize_tree. Validates magic, version, sizes, checksum and the
/// tree's internal references (child and ref indices in range), so a loaded tree is safe to trace.
[[nodiscard]] KdTree deserialize_tree(std::span<const std::byte> blob);

}  // namespace kdrt
