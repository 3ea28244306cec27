#include "store/mesh_cache.h"

#include <algorithm>
#include <chrono>
#include <filesystem>

#include "core/log.h"
#include "kdrt/proto/mesh_id.h"
#include "kdrt/proto/text.h"

namespace kdrt::server {
namespace {

using proto::Err;
using proto::in_quotes;

double seconds_since(std::chrono::steady_clock::time_point start) {
    return std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
}

/// The bounds of the triangles a tree holds: the summary's bounds (of the referenced vertices).
Aabb tris_bounds(const KdTree& tree) {
    Aabb box;
    bool first = true;
    for (const TriVerts& t : tree.tris)
        for (const float* v : {t.v0, t.v1, t.v2}) {
            const Vec3 p{v[0], v[1], v[2]};
            if (first) {
                box = Aabb{p, p};
                first = false;
            } else {
                box.lo =
                    Vec3{std::min(box.lo.x, p.x), std::min(box.lo.y, p.y), std::min(box.lo.z, p.z)};
                box.hi =
                    Vec3{std::max(box.hi.x, p.x), std::max(box.hi.y, p.y), std::max(box.hi.z, p.z)};
            }
        }
    return box;
}

bool same_box(const Aabb& a, const Aabb& b) {
    return a.lo.x == b.lo.x && a.lo.y == b.lo.y && a.lo.z == b.lo.z && a.hi.x == b.hi.x &&
           a.hi.y == b.hi.y && a.hi.z == b.hi.z;
}

}  // namespace

std::string summary_disagreement(const KdTree& tree, const proto::MeshSummary& summary) {
    if (tree.tris.size() != summary.triangles)
        return "the summary says " + std::to_string(summary.triangles) + " triangles, the tree " +
               std::to_string(tree.tris.size());
    if (!same_box(tris_bounds(tree), summary.bounds))
        return "the summary's bounds are not the bounds of the mesh's triangles";
    return {};
}

uint64_t tree_memory_bytes(const KdTree& tree) noexcept {
    return sizeof(KdTree) + tree.nodes.capacity() * sizeof(KdNode) +
           tree.wide_nodes.capacity() * sizeof(WideNode) +
           tree.leaf_refs.capacity() * sizeof(uint32_t) + tree.tris.capacity() * sizeof(TriVerts) +
           (tree.tri_ids.capacity() + tree.tri_slots.capacity()) * sizeof(uint32_t);
}

uint64_t surface_memory_bytes(const SurfaceIndex& index) noexcept {
    return sizeof(SurfaceIndex) + index.pseudonormals.capacity() * sizeof(float);
}

proto::MeshSummary make_summary(std::string id, const Mesh& mesh, const KdTree& tree) {
    proto::MeshSummary s;
    s.id = std::move(id);
    s.triangles = mesh.triangle_count();
    s.vertices = mesh.vertex_count();
    s.bounds = mesh_bounds(mesh);
    s.tree = tree.stats;
    return s;
}

MeshCache::MeshCache(MeshStore& store, Compute& compute, Metrics& metrics, uint64_t memory_budget)
    : store_(store), compute_(compute), metrics_(metrics), memory_budget_(memory_budget) {}

void MeshCache::note_problem(const char* file, const std::string& reason,
                             const std::string& detail) {
    metrics_.store_problems.add({{"file", file}, {"reason", reason}});
    log_event(LogLevel::kWarn, "store: damaged file",
              {{"file", std::string(file)}, {"reason", reason}, {"error", detail}});
}

std::shared_ptr<MeshCache::Entry> MeshCache::recover(MeshStore::Listed& item, bool may_quarantine) {
    const std::string& id = item.id;
    if (!item.has_summary && !may_quarantine) {
        // Another replica shares the store: these may be its upload, not yet committed.
        log_event(LogLevel::kInfo,
                  "store: uncommitted files left alone (another process shares the store)",
                  {{"mesh", id}});
        return nullptr;
    }
    auto entry = std::make_shared<Entry>();
    entry->id = id;
    bool summary_ok = item.summary.has_value();
    bool mesh_noted = false;
    if (item.summary) {
        auto checked = store_.check_mesh_header(*item.summary);
        if (checked) {
            entry->summary = std::move(item.summary);
            entry->disk_bytes = store_.disk_bytes(id);
            return entry;
        }
        const bool summary_wrong = checked.error().reason == "summary_mismatch";
        note_problem(summary_wrong ? "summary" : "mesh", checked.error().reason,
                     checked.error().detail);
        summary_ok = !summary_wrong;
        mesh_noted = !summary_wrong;
    } else {
        note_problem("summary", item.has_summary ? "corrupt" : "missing", item.summary_error);
        log_event(LogLevel::kWarn, "cache: summary unreadable, recovering from the stored mesh",
                  {{"mesh", id}, {"error", item.summary_error}});
    }

    auto mesh = store_.load_mesh(id);
    auto tree = store_.load_tree(id);
    if (!mesh) {
        if (!mesh_noted && (mesh.error().code != StoreError::Code::kMissing || item.summary))
            note_problem("mesh", mesh.error().reason, mesh.error().detail);
        if (tree) {
            Mesh soup = mesh_from_tree(*tree);
            if (proto::mesh_id(soup) == id) {
                if (auto saved = store_.save_mesh(id, soup); saved) {
                    metrics_.store_repairs.add({{"file", "mesh"}});
                    log_event(LogLevel::kWarn, "store: mesh file rewritten from the tree",
                              {{"mesh", id}, {"error", mesh.error().detail}});
                } else {
                    log_event(LogLevel::kError, "store: cannot rewrite the mesh file",
                              {{"mesh", id}, {"error", saved.error().message}});
                }
                mesh = std::move(soup);
            }
        }
    }
    if (!mesh) {
        const std::string tree_detail =
            tree ? "valid but not of this mesh's triangles" : tree.error().detail;
        const std::string detail =
            "mesh " + id + " is damaged on disk and cannot be served: " + mesh.error().detail +
            "; tree file: " + tree_detail + ". Upload the same mesh again to repair it";
        if (item.summary) {
            // Acknowledged (a readable summary): keep it listed, never serve it, never delete it.
            log_event(LogLevel::kError, "store: mesh damaged beyond repair; kept, not served",
                      {{"mesh", id}, {"error", detail}});
            entry->summary = std::move(item.summary);
            entry->damage = detail;
            entry->disk_bytes = store_.disk_bytes(id);
            return entry;
        }
        auto moved = store_.quarantine(id);
        log_event(LogLevel::kError, "store: unusable files moved to quarantine",
                  {{"mesh", id},
                   {"error", detail},
                   {"quarantine", moved ? moved->string() : "failed: " + moved.error()}});
        return nullptr;
    }

    KdTree built;
    if (!tree) {
        if (tree.error().reason != TreeFileProblem::Reason::kMissing || item.summary)
            note_problem("tree", std::string(reason_label(tree.error().reason)),
                         tree.error().detail);
        const auto start = std::chrono::steady_clock::now();
        built = compute_.build(*mesh);
        metrics_.record_build(seconds_since(start));
        metrics_.cache_rebuilds.add({{"reason", std::string(reason_label(tree.error().reason))}});
        if (auto saved = store_.save_tree(id, built); !saved)
            log_event(LogLevel::kError, "cache: cannot rewrite the tree file",
                      {{"mesh", id}, {"error", saved.error().message}});
    }
    const KdTree& good_tree = tree ? *tree : built;
    if (summary_ok && summary_disagreement(good_tree, *item.summary).empty()) {
        entry->summary = std::move(item.summary);
    } else {
        proto::MeshSummary summary = make_summary(id, *mesh, good_tree);
        if (auto saved = store_.save_summary(summary); saved) {
            metrics_.store_repairs.add({{"file", "summary"}});
            log_event(LogLevel::kWarn, "store: summary rewritten from the stored mesh",
                      {{"mesh", id}});
        } else {
            log_event(LogLevel::kError,
                      "store: cannot rewrite the summary; serving the recovered one from memory",
                      {{"mesh", id}, {"error", saved.error().message}});
        }
        entry->summary = std::move(summary);
    }
    entry->disk_bytes = store_.disk_bytes(id);
    return entry;
}

proto::Result<void, std::string> MeshCache::open() {
    std::vector<std::string> removed;
    auto listed = store_.open(removed);
    for (const std::string& line : removed)
        log_event(LogLevel::kWarn, "cache: removed leftover", {{"what", line}});
    if (!listed) return Err{std::move(listed).error()};
    // Checked after the listing: a process writing any listed file was alive when it was taken.
    const bool may_quarantine = !store_.shared_with_live_process();
    for (MeshStore::Listed& item : *listed) {
        std::shared_ptr<Entry> entry;
        try {
            entry = recover(item, may_quarantine);
        } catch (const std::exception& e) {
            log_event(LogLevel::kError, "cache: cannot recover a stored mesh; left in place",
                      {{"mesh", item.id}, {"error", std::string(e.what())}});
        }
        if (!entry) continue;
        std::lock_guard lock(mutex_);
        disk_bytes_ += entry->disk_bytes;
        entries_[entry->id] = std::move(entry);
    }
    return {};
}

proto::Result<MeshCache::Added, CacheError> MeshCache::add(const Mesh& mesh) {
    const std::string id = proto::mesh_id(mesh);
    std::optional<proto::MeshSummary> previous;  // set when repairing a damaged mesh
    adopt(id);                                   // another replica may have stored it already
    std::unique_lock lock(mutex_);
    for (;;) {
        const auto it = entries_.find(id);
        if (it == entries_.end()) break;
        const std::shared_ptr<Entry> entry = it->second;
        if (entry->summary && !entry->damage.empty() && !entry->flight.valid()) {
            // Stored but damaged: these triangles (verified by their id) replace the files.
            log_event(LogLevel::kInfo, "cache: repairing a damaged mesh from a new upload",
                      {{"mesh", id}});
            previous = entry->summary;
            drop(*entry);
            break;
        }
        if (entry->summary) {
            metrics_.uploads_deduplicated.fetch_add(1);
            return Added{with_runtime(*entry), false};
        }
        // Another upload of the same triangles is building it: wait for that build, then look
        // again (it is either stored now, or failed and was removed).
        const Flight flight = entry->flight;
        lock.unlock();
        flight.wait();
        lock.lock();
    }
    auto entry = std::make_shared<Entry>();
    entry->id = id;
    std::promise<TreeResult> promise;
    entry->flight = promise.get_future().share();
    entries_[id] = entry;
    lock.unlock();

    proto::Result<Added, CacheError> outcome = Err{CacheError{}};
    std::shared_ptr<const KdTree> tree;
    uint64_t disk_bytes = 0;
    try {
        const auto start = std::chrono::steady_clock::now();
        auto built = std::make_shared<KdTree>(compute_.build(mesh));
        metrics_.record_build(seconds_since(start));
        proto::MeshSummary summary = make_summary(id, mesh, *built);
        auto saved = store_.save(summary, mesh, *built, previous.has_value());
        if (saved) {
            disk_bytes = saved->disk_bytes;
            if (!saved->created) {
                // Another replica committed the same mesh meanwhile: its summary is the record.
                metrics_.uploads_deduplicated.fetch_add(1);
                if (auto stored = store_.read_summary(id)) summary = std::move(*stored);
            }
            tree = std::move(built);
            outcome = Added{std::move(summary), saved->created};
        } else {
            log_event(LogLevel::kError, "cache: cannot store mesh",
                      {{"mesh", id}, {"error", saved.error().message}});
            // Never acknowledged: its files go. A damaged mesh being repaired keeps its files
            // (whatever was rewritten is valid); it is checked again on its next use.
            if (!previous) store_.remove(id);
            outcome = Err{CacheError{
                saved.error().no_space ? CacheError::Code::kNoSpace : CacheError::Code::kStorage,
                "cannot store the mesh (nothing was stored): " + saved.error().message}};
        }
    } catch (const MeshError& e) {
        outcome = Err{CacheError{CacheError::Code::kInvalidMesh, e.what()}};
    } catch (const std::exception& e) {
        outcome = Err{CacheError{CacheError::Code::kInternal,
                                 std::string("building the tree failed: ") + e.what()}};
    }

    lock.lock();
    entry->flight = Flight();
    if (outcome) {
        entry->summary = outcome->summary;
        entry->disk_bytes = disk_bytes;
        disk_bytes_ += disk_bytes;
        make_resident(*entry, tree);
        outcome->summary = with_runtime(*entry);
    } else if (is_current(entry)) {
        if (previous) {
            // Back to the acknowledged (damaged) entry, to be checked again when next used.
            entry->summary = std::move(previous);
            entry->disk_bytes = store_.disk_bytes(id);
            disk_bytes_ += entry->disk_bytes;
        } else {
            entries_.erase(id);
        }
    }
    lock.unlock();
    promise.set_value(outcome ? TreeResult(tree) : TreeResult(Err{outcome.error()}));
    return outcome;
}

std::shared_ptr<MeshCache::Entry> MeshCache::committed(const std::string& id) {
    std::unique_lock lock(mutex_);
    bool adopted = false;
    for (;;) {
        const auto it = entries_.find(id);
        if (it != entries_.end() && it->second->summary) return it->second;
        if (it != entries_.end() && it->second->flight.valid()) {
            // Being uploaded, or adopted from the store: wait for that, then look again.
            const Flight flight = it->second->flight;
            lock.unlock();
            flight.wait();
            lock.lock();
            continue;
        }
        if (adopted) return nullptr;
        lock.unlock();
        adopt(id);
        adopted = true;
        lock.lock();
    }
}

void MeshCache::adopt(const std::string& id) {
    if (!proto::is_mesh_id(id)) return;
    std::unique_lock lock(mutex_);
    if (entries_.count(id)) return;
    auto placeholder = std::make_shared<Entry>();
    placeholder->id = id;
    std::promise<TreeResult> promise;
    placeholder->flight = promise.get_future().share();
    entries_[id] = placeholder;
    lock.unlock();

    std::shared_ptr<Entry> found;
    try {
        if (auto item = store_.list_one(id); item && item->summary) {
            found = recover(*item, false);
            if (found) log_event(LogLevel::kInfo, "cache: mesh found in the store", {{"mesh", id}});
        }
    } catch (const std::exception& e) {
        log_event(LogLevel::kError, "cache: cannot read a stored mesh",
                  {{"mesh", id}, {"error", std::string(e.what())}});
    }

    lock.lock();
    placeholder->flight = Flight();
    if (is_current(placeholder)) {
        if (found) {
            placeholder->summary = std::move(found->summary);
            placeholder->damage = std::move(found->damage);
            placeholder->disk_bytes = found->disk_bytes;
            disk_bytes_ += placeholder->disk_bytes;
        } else {
            entries_.erase(id);
        }
    }
    lock.unlock();
    promise.set_value(Err{CacheError{CacheError::Code::kUnknownMesh, "no mesh with id " + id}});
}

bool MeshCache::deleted_elsewhere(const std::string& id) {
    // One or two stat calls, next to a request that uses a tree: a replica that still holds the
    // tree of a mesh deleted through another replica must not go on answering for it. A stat
    // that fails for another reason than absence keeps the mesh.
    std::error_code ec;
    if (std::filesystem::exists(store_.summary_path(id), ec) || ec) return false;
    if (std::filesystem::exists(store_.mesh_path(id), ec) || ec) return false;
    std::lock_guard lock(mutex_);
    const auto it = entries_.find(id);
    if (it != entries_.end() && it->second->summary && !it->second->flight.valid()) {
        log_event(LogLevel::kInfo, "cache: mesh deleted from the store elsewhere", {{"mesh", id}});
        drop(*it->second);
    }
    return true;
}

proto::Result<std::shared_ptr<const KdTree>, CacheError> MeshCache::acquire(const std::string& id) {
    std::shared_ptr<Entry> entry = committed(id);
    if (entry && deleted_elsewhere(id)) entry = nullptr;
    if (!entry) return Err{CacheError{CacheError::Code::kUnknownMesh, "no mesh with id " + id}};
    std::unique_lock lock(mutex_);
    if (!is_current(entry))
        return Err{
            CacheError{CacheError::Code::kUnknownMesh, "no mesh with id " + id + " (deleted)"}};
    if (!entry->damage.empty()) return Err{CacheError{CacheError::Code::kDamaged, entry->damage}};
    if (entry->tree) {
        metrics_.cache_hits.fetch_add(1, std::memory_order_relaxed);
        lru_.splice(lru_.begin(), lru_, entry->lru_position);
        return entry->tree;
    }
    if (entry->flight.valid()) {
        const Flight flight = entry->flight;
        lock.unlock();
        return flight.get();
    }
    metrics_.cache_misses.fetch_add(1);
    std::promise<TreeResult> promise;
    entry->flight = promise.get_future().share();
    const proto::MeshSummary summary = *entry->summary;
    lock.unlock();

    TreeResult outcome = Err{CacheError{}};
    std::optional<proto::MeshSummary> repaired;
    try {
        auto loaded = load(id, summary);
        if (loaded) {
            outcome = std::move(loaded->tree);
            repaired = std::move(loaded->repaired_summary);
        } else {
            outcome = Err{std::move(loaded).error()};
        }
    } catch (const std::exception& e) {
        outcome = Err{CacheError{CacheError::Code::kInternal,
                                 std::string("loading the tree failed: ") + e.what()}};
    }

    lock.lock();
    entry->flight = Flight();
    if (is_current(entry)) {
        if (repaired) entry->summary = std::move(repaired);
        if (outcome)
            make_resident(*entry, *outcome);
        else if (outcome.error().code == CacheError::Code::kDamaged)
            entry->damage = outcome.error().detail;
    } else if (!outcome) {
        outcome =
            Err{CacheError{CacheError::Code::kUnknownMesh, "no mesh with id " + id + " (deleted)"}};
    }
    lock.unlock();
    promise.set_value(outcome);
    return outcome;
}

proto::Result<MeshCache::Loaded, CacheError> MeshCache::load(const std::string& id,
                                                             const proto::MeshSummary& summary) {
    auto tree = store_.load_tree(id);
    if (tree) {
        auto shared = std::make_shared<const KdTree>(std::move(*tree));
        const std::string disagreement = summary_disagreement(*shared, summary);
        if (disagreement.empty()) return Loaded{std::move(shared), std::nullopt};
        // The tree is this mesh's (bound to the id): the summary is what is wrong.
        note_problem("summary", "summary_mismatch",
                     in_quotes(store_.summary_path(id).string()) + ": " + disagreement);
        proto::MeshSummary fixed = summary;
        fixed.triangles = shared->tris.size();
        fixed.bounds = tris_bounds(*shared);
        fixed.tree = shared->stats;
        if (auto mesh = store_.load_mesh(id); mesh) fixed.vertices = mesh->vertex_count();
        if (auto saved = store_.save_summary(fixed); saved) {
            metrics_.store_repairs.add({{"file", "summary"}});
            log_event(LogLevel::kWarn, "store: summary rewritten from the tree", {{"mesh", id}});
        } else {
            log_event(LogLevel::kError, "store: cannot rewrite the summary",
                      {{"mesh", id}, {"error", saved.error().message}});
        }
        return Loaded{std::move(shared), std::move(fixed)};
    }
    const TreeFileProblem& problem = tree.error();
    const std::string reason(reason_label(problem.reason));
    note_problem("tree", reason, problem.detail);
    log_event(LogLevel::kWarn,
              "cache: tree file failed validation; rebuilding from the stored mesh",
              {{"mesh", id}, {"reason", reason}, {"error", problem.detail}});
    auto mesh = store_.load_mesh(id);
    if (!mesh) {
        note_problem("mesh", mesh.error().reason, mesh.error().detail);
        const std::string detail =
            "mesh " + id + " is damaged on disk and cannot be served: " + mesh.error().detail +
            "; tree file: " + problem.detail + ". Upload the same mesh again to repair it";
        log_event(LogLevel::kError, "store: mesh damaged beyond repair; kept, not served",
                  {{"mesh", id}, {"error", detail}});
        return Err{CacheError{CacheError::Code::kDamaged, detail}};
    }
    const auto start = std::chrono::steady_clock::now();
    auto built = std::make_shared<KdTree>(compute_.build(*mesh));
    metrics_.record_build(seconds_since(start));
    metrics_.cache_rebuilds.add({{"reason", reason}});
    if (auto saved = store_.save_tree(id, *built); !saved)
        log_event(LogLevel::kError, "cache: cannot rewrite the tree file",
                  {{"mesh", id}, {"error", saved.error().message}});
    else
        log_event(LogLevel::kInfo, "cache: tree rebuilt",
                  {{"mesh", id}, {"reason", reason}, {"build_ms", built->stats.build_ms}});
    std::optional<proto::MeshSummary> fixed;
    const proto::MeshSummary fresh = make_summary(id, *mesh, *built);
    if (fresh.triangles != summary.triangles || fresh.vertices != summary.vertices ||
        !same_box(fresh.bounds, summary.bounds)) {
        note_problem("summary", "summary_mismatch",
                     in_quotes(store_.summary_path(id).string()) + " disagrees with the mesh file");
        fixed = fresh;
        if (auto saved = store_.save_summary(fresh); saved)
            metrics_.store_repairs.add({{"file", "summary"}});
    }
    return Loaded{std::shared_ptr<const KdTree>(std::move(built)), std::move(fixed)};
}

std::optional<proto::MeshSummary> MeshCache::find(const std::string& id) {
    const std::shared_ptr<Entry> entry = committed(id);
    if (!entry || deleted_elsewhere(id)) return std::nullopt;
    std::lock_guard lock(mutex_);
    if (!entry->summary) return std::nullopt;
    return with_runtime(*entry);
}

std::vector<proto::MeshSummary> MeshCache::list() {
    // The store is the index: meshes other replicas committed are adopted, and meshes they
    // deleted (no summary and no mesh file left) are forgotten.
    if (auto ids = store_.committed_ids(); ids) {
        std::vector<std::string> unknown, gone;
        {
            std::lock_guard lock(mutex_);
            for (const std::string& id : *ids)
                if (!entries_.count(id)) unknown.push_back(id);
            for (const auto& [id, entry] : entries_)
                if (entry->summary && !entry->flight.valid() &&
                    !std::binary_search(ids->begin(), ids->end(), id))
                    gone.push_back(id);
        }
        for (const std::string& id : unknown) adopt(id);
        for (const std::string& id : gone) deleted_elsewhere(id);
    } else {
        log_event(LogLevel::kError, "cache: cannot list the store", {{"error", ids.error()}});
    }
    std::vector<proto::MeshSummary> out;
    {
        std::lock_guard lock(mutex_);
        out.reserve(entries_.size());
        for (const auto& [id, entry] : entries_)
            if (entry->summary) out.push_back(with_runtime(*entry));
    }
    std::sort(out.begin(), out.end(), [](const auto& a, const auto& b) { return a.id < b.id; });
    return out;
}

bool MeshCache::remove(const std::string& id) {
    if (!committed(id)) return false;  // adopts it from the store if another replica stored it
    std::unique_lock lock(mutex_);
    for (;;) {
        const auto it = entries_.find(id);
        if (it == entries_.end()) return false;
        const std::shared_ptr<Entry> entry = it->second;
        if (entry->summary) {
            drop(*entry);
            break;
        }
        const Flight flight = entry->flight;  // being built: let the upload finish first
        lock.unlock();
        flight.wait();
        lock.lock();
    }
    lock.unlock();
    store_.remove(id);
    return true;
}

uint64_t MeshCache::memory_bytes() const {
    std::lock_guard lock(mutex_);
    return memory_bytes_;
}

uint64_t MeshCache::disk_bytes() const {
    std::lock_guard lock(mutex_);
    return disk_bytes_;
}

size_t MeshCache::mesh_count() const {
    std::lock_guard lock(mutex_);
    size_t n = 0;
    for (const auto& [id, entry] : entries_) n += entry->summary.has_value();
    return n;
}

size_t MeshCache::damaged_count() const {
    std::lock_guard lock(mutex_);
    size_t n = 0;
    for (const auto& [id, entry] : entries_) n += !entry->damage.empty();
    return n;
}

size_t MeshCache::resident_count() const {
    std::lock_guard lock(mutex_);
    return lru_.size();
}

proto::MeshSummary MeshCache::with_runtime(const Entry& entry) const {
    proto::MeshSummary s = *entry.summary;
    s.in_memory = entry.tree != nullptr;
    return s;
}

void MeshCache::make_resident(Entry& entry, std::shared_ptr<const KdTree> tree) {
    if (entry.in_lru) return;  // another caller made it resident first
    entry.tree = std::move(tree);
    entry.tree_bytes = tree_memory_bytes(*entry.tree);
    memory_bytes_ += entry.tree_bytes;
    lru_.push_front(&entry);
    entry.lru_position = lru_.begin();
    entry.in_lru = true;
    evict_over_budget();
}

void MeshCache::evict_over_budget() {
    while (memory_bytes_ > memory_budget_ && lru_.size() > 1) {
        Entry* victim = lru_.back();
        lru_.pop_back();
        victim->in_lru = false;
        release_memory(*victim);
        metrics_.cache_evictions.fetch_add(1);
        log_event(LogLevel::kDebug, "cache: evicted", {{"mesh", victim->id}});
    }
}

void MeshCache::release_memory(Entry& entry) {
    memory_bytes_ -= entry.tree_bytes + entry.surface.bytes + entry.clearance.bytes;
    entry.tree_bytes = 0;
    entry.tree.reset();
    entry.surface = {};
    entry.clearance = {};
}

std::shared_ptr<const void> MeshCache::derived(const std::string& id,
                                               const std::shared_ptr<const KdTree>& tree,
                                               Derived Entry::*slot,
                                               const std::function<Made()>& make) {
    const auto resident = [&]() -> Entry* {  // mutex_ held
        const auto it = entries_.find(id);
        if (it == entries_.end() || !it->second->in_lru || it->second->tree != tree) return nullptr;
        return it->second.get();
    };
    {
        std::lock_guard lock(mutex_);
        if (Entry* entry = resident(); entry && (entry->*slot).data) {
            lru_.splice(lru_.begin(), lru_, entry->lru_position);
            return (entry->*slot).data;
        }
    }
    Made made = make();
    std::lock_guard lock(mutex_);
    Entry* entry = resident();
    if (!entry) return made.data;  // evicted or deleted meanwhile: this request's alone
    lru_.splice(lru_.begin(), lru_, entry->lru_position);
    Derived& kept = entry->*slot;
    if (kept.data) return kept.data;  // another first use won
    kept = {std::move(made.data), made.bytes};
    memory_bytes_ += kept.bytes;
    evict_over_budget();
    return kept.data;
}

std::shared_ptr<const SurfaceIndex> MeshCache::surface_index(
    const std::string& id, const std::shared_ptr<const KdTree>& tree) {
    return std::static_pointer_cast<const SurfaceIndex>(derived(id, tree, &Entry::surface, [&] {
        auto index = std::make_shared<const SurfaceIndex>(build_surface_index(*tree));
        const uint64_t bytes = surface_memory_bytes(*index);
        return Made{std::move(index), bytes};
    }));
}

std::shared_ptr<const HitClearance> MeshCache::hit_clearance(
    const std::string& id, const std::shared_ptr<const KdTree>& tree) {
    return std::static_pointer_cast<const HitClearance>(derived(id, tree, &Entry::clearance, [&] {
        // On the compute arena (its parallel parts use the calling thread's arena).
        auto clearance = std::make_shared<const HitClearance>(
            compute_.run([&] { return build_hit_clearance(*tree); }));
        const uint64_t bytes = clearance->bytes();
        return Made{std::move(clearance), bytes};
    }));
}

void MeshCache::drop(Entry& entry) {
    if (entry.in_lru) {
        lru_.erase(entry.lru_position);
        entry.in_lru = false;
        release_memory(entry);
    }
    disk_bytes_ -= entry.disk_bytes;
    const std::string id = entry.id;  // erase() must not read a key owned by the erased node
    entries_.erase(id);               // `entry` may be destroyed here: callers hold a shared_ptr
}

bool MeshCache::is_current(const std::shared_ptr<Entry>& entry) const {
    const auto it = entries_.find(entry->id);
    return it != entries_.end() && it->second == entry;
}

}  // namespace kdrt::server
