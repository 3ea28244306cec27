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
/// - A tree file that is refused (missing, truncated, corrupt, of another format version, or the
///   tree of another mesh: tree_file.h) is rebuilt from the stored mesh, which is checked against
///   its id first (logged with the reason, counted in kdrt_cache_rebuilds_total{reason} and
///   kdrt_store_problems_total{file,reason}). A summary that disagrees with the tree or the mesh
///   file is rewritten from them; a missing or damaged mesh file is rewritten from a valid tree.
/// - A mesh with neither a valid mesh file nor a valid tree is never served and never deleted:
///   it stays listed, marked damaged, and every trace answers 500 stored-mesh-damaged naming the
///   files and what is wrong with each; uploading the same triangles again repairs it. At
///   start-up, files that are not even backed by a readable summary are moved to quarantine/.
/// - Nothing is acknowledged before it is durable; a full disk is kNoSpace (507).
/// - Eviction drops the cache's reference only: traces in flight keep their tree alive. The
///   most recently used tree stays resident even if it alone exceeds the budget.
/// - The budget counts each resident tree's arrays and the data derived from the tree that is
///   kept with it once asked for: its SurfaceIndex (kdrt/distance.h: pseudonormals, about 84
///   bytes a triangle; a distance query asks) and its HitClearance (kdrt/hit_clearance.h: 52
///   bytes a triangle; a scene scan asks). Both are evicted and deleted with the tree, so
///   memory_budget bounds all three.
/// - Shared stores (mesh_store.h): other replicas add and delete meshes in the same store. A
///   mesh this cache does not know is looked up in the store (its summary file) when asked for,
///   registered, and its tree loaded (or rebuilt) by one caller while the others wait (adopt());
///   list() lists the store's committed meshes and forgets those another replica deleted.
///   At start-up, files without a summary are quarantined only when no other live process has
///   the store open (else they may be its upload in progress).
/// All member functions are thread-safe.

#include <cstdint>
#include <functional>
#include <future>
#include <list>
#include <memory>
#include <mutex>
#include <optional>
#include <string>
#include <unordered_map>
#include <vector>

#include "core/compute.h"
#include "core/metrics.h"
#include "kdrt/distance.h"
#include "kdrt/hit_clearance.h"
#include "kdrt/kdtree.h"
#include "kdrt/mesh.h"
#include "kdrt/proto/json_api.h"
#include "kdrt/proto/result.h"
#include "store/mesh_store.h"

namespace kdrt::server {

struct CacheError {
    enum class Code {
        kUnknownMesh,  ///< no acknowledged mesh with that id
        kInvalidMesh,  ///< the engine refused the mesh (MeshError)
        kStorage,      ///< the disk refused a write
        kNoSpace,      ///< the disk (or a file size limit) is full; nothing was stored
        kDamaged,      ///< the stored mesh and tree are both damaged; detail says how
        kInternal,     ///< an unexpected exception (e.g. out of memory)
    };
    Code code = Code::kInternal;
    std::string detail;
};

class MeshCache {
public:
    MeshCache(MeshStore& store, Compute& compute, Metrics& metrics, uint64_t memory_budget);

    /// Loads the index from the store, repairing what it can (summaries from the mesh file or the
    /// tree, a mesh file from the tree) and quarantining ids with no usable data; never deletes
    /// data in meshes/ and never fails because a repair could not be written (e.g. a full disk:
    /// the repaired summary is then used from memory). Call once before anything else.
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

    /// The SurfaceIndex of `tree`, the tree acquire(id) returned, built on its first use (outside
    /// the lock; concurrent first uses may build it twice, the first kept wins) and kept with the
    /// tree: its bytes count towards memory_budget (evicting least recently used entries as a
    /// tree does, the asking entry becoming the most recent) and it is evicted and deleted with
    /// the tree. When `tree` is no longer the resident tree of `id` (evicted or deleted
    /// meanwhile), the index is built for the caller only and not kept. Throws std::bad_alloc.
    [[nodiscard]] std::shared_ptr<const SurfaceIndex> surface_index(
        const std::string& id, const std::shared_ptr<const KdTree>& tree);
    /// The HitClearance of `tree` (what a scene's single-return scans skip windows with), kept
    /// and counted exactly as surface_index() keeps and counts the SurfaceIndex.
    [[nodiscard]] std::shared_ptr<const HitClearance> hit_clearance(
        const std::string& id, const std::shared_ptr<const KdTree>& tree);

    /// The mesh's summary, looking in the store when this cache does not know it.
    [[nodiscard]] std::optional<proto::MeshSummary> find(const std::string& id);
    /// Every acknowledged mesh in the store, sorted by id.
    [[nodiscard]] std::vector<proto::MeshSummary> list();
    /// Forgets the mesh and deletes its files. False if there is no such mesh.
    bool remove(const std::string& id);

    [[nodiscard]] uint64_t memory_bytes() const;
    [[nodiscard]] uint64_t disk_bytes() const;
    [[nodiscard]] size_t mesh_count() const;
    [[nodiscard]] size_t resident_count() const;
    /// Acknowledged meshes that are known to be damaged (neither mesh file nor tree valid).
    [[nodiscard]] size_t damaged_count() const;

private:
    using TreeResult = proto::Result<std::shared_ptr<const KdTree>, CacheError>;
    using Flight = std::shared_future<TreeResult>;

    /// Data derived from a resident tree, kept with it and counted in the budget.
    struct Derived {
        std::shared_ptr<const void> data;
        uint64_t bytes = 0;
    };
    /// What derived() builds: the data and the bytes it holds.
    struct Made {
        std::shared_ptr<const void> data;
        uint64_t bytes = 0;
    };

    struct Entry {
        std::string id;
        std::optional<proto::MeshSummary> summary;  ///< set once acknowledged (stored)
        std::shared_ptr<const KdTree> tree;         ///< set while resident
        uint64_t tree_bytes = 0;
        Derived surface;    ///< its SurfaceIndex, while resident, once asked for
        Derived clearance;  ///< its HitClearance, likewise
        uint64_t disk_bytes = 0;
        std::list<Entry*>::iterator lru_position;
        bool in_lru = false;
        Flight flight;       ///< the build (no summary yet) or disk load in progress, if any
        std::string damage;  ///< non-empty: known damaged (CacheError::kDamaged detail)
    };

    struct Loaded {
        std::shared_ptr<const KdTree> tree;
        std::optional<proto::MeshSummary> repaired_summary;  ///< the stored one was wrong
    };
    proto::Result<Loaded, CacheError> load(const std::string& id,
                                           const proto::MeshSummary& summary);
    /// open()'s decision for one listed id: the entry to register, or nullptr (quarantined).
    /// `may_quarantine`: files without a summary may be moved aside (no other live process
    /// could be writing them); else they are left alone.
    std::shared_ptr<Entry> recover(MeshStore::Listed& item, bool may_quarantine);
    /// Registers mesh `id` from the store if it is committed there and not known here (one
    /// caller per id does the work; others wait for it). Call without mutex_ held.
    void adopt(const std::string& id);
    /// The committed entry of `id` (adopted from the store if need be), or nullptr.
    std::shared_ptr<Entry> committed(const std::string& id);
    void note_problem(const char* file, const std::string& reason, const std::string& detail);
    proto::MeshSummary with_runtime(const Entry& entry) const;
    /// surface_index() and hit_clearance(): the data in `slot` of the resident entry of `id`
    /// whose tree is `tree`, made by `make` (outside the lock) on its first use and kept, counted
    /// and evicted with the tree; for the caller alone when `tree` is no longer resident.
    std::shared_ptr<const void> derived(const std::string& id,
                                        const std::shared_ptr<const KdTree>& tree,
                                        Derived Entry::*slot, const std::function<Made()>& make);
    void make_resident(Entry& entry, std::shared_ptr<const KdTree> tree);  // mutex_ held
    void evict_over_budget();                                              // mutex_ held
    void release_memory(Entry& entry);  // mutex_ held: forget the tree and the index
    void drop(Entry& entry);            // mutex_ held
    /// True when another replica deleted mesh `id` from the shared store (neither its summary nor
    /// its mesh file is left; remove() deletes the summary first), the entry then forgotten here
    /// as list() would forget it. mutex_ not held.
    bool deleted_elsewhere(const std::string& id);
    bool is_current(const std::shared_ptr<Entry>& entry) const;  // mutex_ held

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
/// Memory held by a SurfaceIndex (its pseudonormals: 84 bytes a triangle).
[[nodiscard]] uint64_t surface_memory_bytes(const SurfaceIndex& index) noexcept;

/// What `summary` says that a tree bound to the same mesh contradicts (triangle count, bounds);
/// empty when they agree.
[[nodiscard]] std::string summary_disagreement(const KdTree& tree,
                                               const proto::MeshSummary& summary);

/// The summary of a mesh and its tree.
[[nodiscard]] proto::MeshSummary make_summary(std::string id, const Mesh& mesh, const KdTree& tree);

}  // namespace kdrt::server
