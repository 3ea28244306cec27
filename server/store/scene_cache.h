#pragma once
/// Scenes in memory, in front of the SceneStore: every operation on a scene (create, read a
/// revision, pose update, instance edit, delete, list) goes through here, which checks the
/// limits, resolves the instances' meshes through the MeshCache (their trees are shared, never
/// copied or rebuilt for a scene), builds the engine's two-level kdrt::Scene and keeps it.
///
/// - A pose update builds the next revision from the current one with Scene::with_transforms
///   (only the top level is rebuilt), writes it to the store (the store's compare-and-set
///   commit decides a race, in one process or across replicas) and answers once it is durable.
/// - A revision's instances get their meshes' HitClearance at its first single-return scan
///   (scan_ready: MeshCache::hit_clearance builds it once per mesh tree, keeps it with the tree
///   and counts it in the mesh cache's budget), not when the scene is made: a scene that is never
///   scanned pays nothing for it. The revision is kept in that form, and the revisions its pose
///   updates make carry it too, so a scan after a pose update builds nothing for it.
/// - Built scenes are kept by (id, revision) in LRU order within `memory_budget` bytes
///   (kdrt::SceneStats::bytes plus the document); a revision older than the store's kept ones
///   (which get() refuses) leaves as soon as a newer one is kept; a scene asked for again after
///   eviction, or written by another replica, is read from the store and built again, its meshes'
///   trees coming through the MeshCache (loaded from the shared store when this replica never saw
///   them).
/// - Another replica's newer revision or deletion is noticed on the next request for the scene
///   (one stat of the store).
///
/// Deleting a mesh that the current revision of a scene uses is refused (mesh_users names the
/// scenes; the route answers 409). Older kept revisions are not checked: querying one whose
/// mesh was deleted answers 409 naming the instance and the mesh.
///
/// Thread-safe.

#include <condition_variable>
#include <cstdint>
#include <functional>
#include <future>
#include <list>
#include <map>
#include <memory>
#include <mutex>
#include <optional>
#include <span>
#include <string>
#include <vector>

#include "core/compute.h"
#include "core/metrics.h"
#include "kdrt/proto/result.h"
#include "kdrt/proto/scene.h"
#include "kdrt/scene.h"
#include "store/mesh_cache.h"
#include "store/scene_store.h"

namespace kdrt::server {

/// Why a scene operation was refused. The route maps it to problem+json (problems.h).
struct SceneProblem {
    enum class Code {
        kUnknownScene,      ///< 404 no such scene
        kUnknownRevision,   ///< 404 the revision was never written or is no longer kept
        kInvalid,           ///< 400 a field is wrong (field, index)
        kUnknownReference,  ///< 422 a mesh id, geometry id or name names nothing (field, index)
        kTooLarge,          ///< 413 max_instances or max_scenes (field, limit)
        kStale,             ///< 412 If-Match names an older revision
        kMeshGone,          ///< 409 a kept revision's mesh was deleted (field, index)
        kNoSpace,           ///< 507
        kDamaged,           ///< 500 a stored revision is damaged (detail names the file)
        kInternal,          ///< 500
    };
    Code code = Code::kInternal;
    std::string detail;
    std::string field;              ///< as the request spells it: "instances[3].transform"
    std::optional<uint32_t> index;  ///< the instance or pose entry
    std::optional<uint64_t> limit;
};

/// A scene revision: its document and its engine scene.
struct SceneEntry {
    proto::SceneDocument doc;
    Scene scene;
    uint64_t bytes = 0;  ///< what it counts in the budget
    /// Made by scan_ready: every clearance that could be attached is (an instance whose mesh was
    /// deleted since has none), so scan_ready returns it as it is, without trying again.
    bool scan_ready = false;
};

struct SceneCacheOptions {
    uint32_t max_instances = 65536;
    uint32_t max_scenes = 10000;
    uint64_t memory_budget = 256ull << 20;
};

class SceneCache {
public:
    SceneCache(SceneStore& store, MeshCache& meshes, Compute& compute, Metrics& metrics,
               SceneCacheOptions options);
    /// Waits for the builds and prunes still running on the arena (`compute` outlives this).
    ~SceneCache();
    SceneCache(const SceneCache&) = delete;
    SceneCache& operator=(const SceneCache&) = delete;

    using EntryPtr = std::shared_ptr<const SceneEntry>;
    template <class T>
    using Result = proto::Result<T, SceneProblem>;

    /// A new scene of `instances` at revision 1: max_scenes (counted in the store), every mesh
    /// known (422 naming the first instance of an unknown one), every transform accepted by the
    /// engine (400 naming the instance and field), then stored durably.
    [[nodiscard]] Result<EntryPtr> create(std::vector<proto::SceneInstanceSpec> instances);

    /// Revision `revision` of scene `id`, or its current revision.
    [[nodiscard]] Result<EntryPtr> get(const std::string& id,
                                       std::optional<uint64_t> revision = std::nullopt);

    /// `entry` (a revision get() gave) with every instance carrying its mesh's HitClearance, for
    /// a single-return scan (the same answers, fewer every-hit windows). The first call for a
    /// mesh tree builds it (MeshCache::hit_clearance: kept with the tree and counted in its
    /// budget; concurrent first calls may both build it, one is kept); the revision is kept in
    /// this form in place of `entry` (Scene::with_clearances: the top level is kept), so later
    /// calls and the revisions later pose updates make from it find it attached. A mesh deleted
    /// meanwhile leaves its instances without one, and the revision remembers that it tried
    /// (SceneEntry::scan_ready): its later scans do not try again. Returns `entry` itself when it
    /// has them or has tried.
    [[nodiscard]] EntryPtr scan_ready(const EntryPtr& entry);

    /// The next revision with the poses applied (in order; later entries for one instance
    /// win). `if_match`: refuse with kStale unless it is the current revision. Without it the
    /// update applies to whatever is current (retried when another writer commits first).
    /// Answers once the revision is durable: its scene (Scene::with_transforms, started before
    /// the write) may still be building then, and the next request for the revision (a query,
    /// the next update) waits for it. Returns the new revision's id, number and instances.
    [[nodiscard]] Result<proto::SceneListItem> set_poses(const std::string& id,
                                                         std::optional<uint64_t> if_match,
                                                         std::span<const proto::PoseEntry> poses);
    /// The next revision with instances removed and added (proto::apply_instance_edit).
    [[nodiscard]] Result<EntryPtr> edit(const std::string& id, std::optional<uint64_t> if_match,
                                        const proto::InstanceEdit& edit);

    /// Deletes the scene. `if_match` as above. False when there was no such scene.
    [[nodiscard]] Result<bool> remove(const std::string& id, std::optional<uint64_t> if_match);

    /// Current revision of every stored scene (damaged ones left out and logged by the caller
    /// through `damaged`).
    [[nodiscard]] std::vector<EntryPtr> list(std::vector<std::string>* damaged = nullptr);

    /// The scenes whose current revision uses mesh `mesh_id` (reads every scene's current
    /// revision from the store), sorted.
    [[nodiscard]] std::vector<std::string> mesh_users(const std::string& mesh_id);

    [[nodiscard]] uint64_t memory_bytes() const;
    [[nodiscard]] size_t resident_count() const;
    /// Stored scenes (a directory listing).
    [[nodiscard]] size_t scene_count() const;
    [[nodiscard]] const SceneCacheOptions& options() const noexcept { return options_; }

private:
    /// Builds a revision's scene from its document. `stored`: the instances were accepted
    /// before, so a missing mesh was deleted since (kMeshGone), not unknown (kUnknownReference).
    Result<EntryPtr> build(proto::SceneDocument doc, const char* array_name, bool stored);
    /// Reads and builds revision `revision` of `id` from the store.
    Result<EntryPtr> load(const std::string& id, uint64_t revision);
    /// The current revision (the cached one when the store has nothing newer).
    Result<EntryPtr> current(const std::string& id);
    /// The next revision as update() commits it, in one of two forms:
    /// - built already (an instance edit): `doc` and `scene`, `build` empty;
    /// - a pose update: `summary` (its id, number and instance count) and `file` (its KDRS,
    ///   encoded from the base revision and the poses), written durably while `build` makes its
    ///   document and engine scene on an arena worker (it must not fail but for std::bad_alloc),
    ///   off the request's path. `check`, when set, says whether the revision may be committed
    ///   (what the build would refuse); the commit waits for it (run on the calling thread for a
    ///   log, on an arena worker while the file is written for revision files).
    struct Next {
        proto::SceneDocument doc;
        Scene scene;
        proto::SceneListItem summary;
        std::vector<std::byte> file;
        std::function<void(SceneEntry&)> build;
        std::function<std::optional<SceneProblem>()> check;
    };
    /// What update() committed: `summary` always; `entry` when built already (an instance
    /// edit), null while the revision's scene builds (a pose update; find() waits for it).
    struct Committed {
        proto::SceneListItem summary;
        EntryPtr entry;
    };
    /// The compare-and-set loop of set_poses and edit: `next` makes revision base + 1 from the
    /// current revision `base`, which is committed (SceneStore::commit, with `build` run on an
    /// arena worker meanwhile) and kept; `if_match` refuses a stale base (kStale), and without
    /// it a lost race is retried on the newer revision, up to 16 times (`what` names the update
    /// in that error).
    Result<Committed> update(const std::string& id, std::optional<uint64_t> if_match,
                             const char* what,
                             const std::function<Result<Next>(const EntryPtr& base)>& next);
    /// Into the LRU, evicting beyond the budget and the scene's revisions older than the kept
    /// ones (an entry that old itself is not kept).
    void keep(const EntryPtr& entry);
    /// Deletes the revisions older than the kept ones after a commit of `revision`, on the
    /// arena, after the answer (SceneStore::prune).
    void prune_later(const std::string& id, uint64_t revision);
    void in_flight_add();   ///< a task enqueued on the arena that uses this
    void in_flight_done();  ///< ... finished
    void forget(const std::string& id);
    EntryPtr find(const std::string& id, uint64_t revision);

    SceneStore& store_;
    MeshCache& meshes_;
    Compute& compute_;
    Metrics& metrics_;
    const SceneCacheOptions options_;

    mutable std::mutex mutex_;
    using Key = std::pair<std::string, uint64_t>;
    std::list<EntryPtr> lru_;  ///< most recent first
    std::map<Key, std::list<EntryPtr>::iterator> by_key_;
    std::map<std::string, uint64_t> latest_;  ///< the newest revision seen per scene
    /// Committed revisions whose scene is still building (set_poses); find() waits for them.
    std::map<Key, std::shared_future<EntryPtr>> building_;
    std::mutex in_flight_mutex_;
    std::condition_variable in_flight_cv_;
    size_t in_flight_ = 0;
    uint64_t bytes_ = 0;
};

}  // namespace kdrt::server
