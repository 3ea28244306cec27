#pragma once
/// The mesh cache: an index of every stored mesh (summaries always in memory), kD-trees in
/// memory under a byte budget with LRU eviction, and the disk store behind it.
///
/// - add(): the same triangles uploaded concurrently are built once; the other uploads wait for
///   that build and get `created = false`.
/// - acquire(): a resident tree is returned at once (a short mutex for the lookup, then the
///   caller traces lock-free on an immutable shared tree). An evicted tree is reloaded from disk
///   by one caller while others asking for the same mesh wait; requests for other meshes never
///   wait on it, nor on any build.
/// - A tree file that fails validation is rebuilt from the stored mesh (logged, counted in
///   kdrt_cache_rebuilds_total); a stored mesh whose content hash no longer matches its id is
///   dropped (logged) and never served.
/// - Eviction drops the cache's reference only: traces in flight keep their tree alive. The
///   most recently used tree stays resident even if it alone exceeds the budget.
/// All member functions are thread-safe.

#include <cstdint>
#include <future>
#include <list>
#include <memory>
#include <mutex>
#include <optional>
#include <string>
#include <unordered_map>
#include <vector>

#include "compute.h"
#include "kdrt/kdtree.h"
#include "kdrt/mesh.h"
#include "kdrt/proto/json_api.h"
#include "kdrt/proto/result.h"
#include "mesh_store.h"
#include "metrics.h"

namespace kdrt::server {

struct CacheError {
    enum class Code {
        kUnknownMesh,  ///< no acknowledged mesh with that id
        kInvalidMesh,  ///< the engine refused the mesh (MeshError)
        kStorage,      ///< the disk refused a write
        kLost,         ///< the stored copy is corrupt beyond repair; the mesh was dropped
        kInternal,     ///< an unexpected exception (e.g. out of memory)
    };
    Code code = Code::kInternal;
    std::string detail;
};

class MeshCache {
public:
    MeshCache(MeshStore& store, Compute& compute, Metrics& metrics, uint64_t memory_budget);

    /// Loads the index from the store; summaries that cannot be read are recovered from the
    /// stored mesh and tree. Call once before anything else.
    [[nodiscard]] proto::Result<void, std::string> open();

    struct Added {
        proto::MeshSummary summary;
        bool created = false;  ///< false: the mesh was already stored (not rebuilt)
    };
    /// Stores `mesh` (parsed and non-empty) under its content id, building its tree unless it is
    /// already stored. Durable when it returns success.
    [[nodiscard]] proto::Result<Added, CacheError> add(const Mesh& mesh);

    /// The tree of mesh `id`, loading or rebuilding it if it is not in memory.
    [[nodiscard]] proto::Result<std::shared_ptr<const KdTree>, CacheError> acquire(
        const std::string& id);

    [[nodiscard]] std::optional<proto::MeshSummary> find(const std::string& id) const;
    /// Every acknowledged mesh, sorted by id.
    [[nodiscard]] std::vector<proto::MeshSummary> list() const;
    /// Forgets the mesh and deletes its files. False if there is no such mesh.
    bool remove(const std::string& id);

    [[nodiscard]] uint64_t memory_bytes() const;
    [[nodiscard]] uint64_t disk_bytes() const;
    [[nodiscard]] size_t mesh_count() const;
    [[nodiscard]] size_t resident_count() const;

private:
    using TreeResult = proto::Result<std::shared_ptr<const KdTree>, CacheError>;
    using Flight = std::shared_future<TreeResult>;

    struct Entry {
        std::string id;
        std::optional<proto::MeshSummary> summary;  ///< set once acknowledged (stored)
        std::shared_ptr<const KdTree> tree;         ///< set while resident
        uint64_t tree_bytes = 0;
        uint64_t disk_bytes = 0;
        std::list<Entry*>::iterator lru_position;
        bool in_lru = false;
        Flight flight;  ///< the build (no summary yet) or disk load in progress, if any
    };

    TreeResult load(const std::string& id, const proto::MeshSummary& summary);
    proto::MeshSummary with_runtime(const Entry& entry) const;
    void make_resident(Entry& entry, std::shared_ptr<const KdTree> tree);  // mutex_ held
    void drop(Entry& entry);                                               // mutex_ held
    bool is_current(const std::shared_ptr<Entry>& entry) const;            // mutex_ held

    MeshStore& store_;
    Compute& compute_;
    Metrics& metrics_;
    const uint64_t memory_budget_;

    mutable std::mutex mutex_;
    std::unordered_map<std::string, std::shared_ptr<Entry>> entries_;
    std::list<Entry*> lru_;  ///< resident entries, most recently used first
    uint64_t memory_bytes_ = 0;
    uint64_t disk_bytes_ = 0;
};

/// Memory held by a tree's arrays.
[[nodiscard]] uint64_t tree_memory_bytes(const KdTree& tree) noexcept;

/// The summary of a mesh and its tree.
[[nodiscard]] proto::MeshSummary make_summary(std::string id, const Mesh& mesh, const KdTree& tree);

}  // namespace kdrt::server
