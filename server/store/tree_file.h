#pragma once
/// The store's tree file: the engine's tree blob (kdrt/serialize.h) inside a small server-side
/// container that binds it to the mesh it was built from.
///
/// Layout (little-endian), 96 header bytes then the blob:
///
///   0    8   magic "KDRTSTRE"
///   8    4   u32 container version (kTreeFileVersion)
///   12   4   u32 header bytes (96)
///   16   64  the mesh id (64 lower-case hex characters, the SHA-256 of its canonical triangles)
///   80   8   u64 blob bytes (the file is exactly 96 + this long)
///   88   8   u64 FNV-1a 64 of bytes 0..87
///   96   ..  the engine blob ("KDRTTREE", u32 engine format version, ..., its own checksum)
///
/// The engine blob checksums its own content; the container adds what the blob cannot know: whose
/// tree it is. A blob copied from another mesh (even one with the same triangle count and a valid
/// checksum) carries the other mesh's id and is refused.

#include <cstddef>
#include <span>
#include <string>
#include <string_view>
#include <vector>

#include "kdrt/kdtree.h"
#include "kdrt/proto/result.h"

namespace kdrt::server {

inline constexpr uint32_t kTreeFileVersion = 1;
inline constexpr size_t kTreeFileHeaderBytes = 96;

/// Why a tree file was refused. The reason is also the `reason` label of
/// kdrt_cache_rebuilds_total.
struct TreeFileProblem {
    enum class Reason {
        kMissing,        ///< no tree file
        kUnreadable,     ///< the operating system refused to read it
        kTruncated,      ///< shorter (or longer) than its header says
        kCorrupt,        ///< bad magic, header checksum, or an engine blob that fails validation
        kFormatVersion,  ///< a container or engine blob of another format version
        kOtherMesh,      ///< a valid tree of another mesh
    };
    Reason reason = Reason::kCorrupt;
    std::string detail;
};

/// "missing", "unreadable", "truncated", "corrupt", "format_version", "other_mesh".
[[nodiscard]] std::string_view reason_label(TreeFileProblem::Reason reason) noexcept;

/// The tree file of mesh `id` holding `tree`.
[[nodiscard]] std::vector<std::byte> encode_tree_file(std::string_view id, const KdTree& tree);

/// Validates the container against `id` and deserialises the blob (which validates itself).
[[nodiscard]] proto::Result<KdTree, TreeFileProblem> decode_tree_file(
    std::string_view id, std::span<const std::byte> file);

}  // namespace kdrt::server
