#include "mesh_cache.h"

#include <algorithm>
#include <chrono>

#include "kdrt/proto/mesh_id.h"
#include "log.h"

namespace kdrt::server {
namespace {

using proto::Err;

double seconds_since(std::chrono::steady_clock::time_point start) {
    return std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
}

/// A tree that loaded cleanly must also belong to the summary it is filed under.
bool consistent(const KdTree& tree, const proto::MeshSummary& summary) {
    return tree.stats.triangles == summary.triangles && tree.tris.size() == summary.triangles;
}

}  // namespace

uint64_t tree_memory_bytes(const KdTree& tree) noexcept {
    return sizeof(KdTree) + tree.nodes.capacity() * sizeof(KdNode) +
           tree.leaf_refs.capacity() * sizeof(uint32_t) + tree.tris.capacity() * sizeof(TriVerts) +
           (tree.tri_ids.capacity() + tree.tri_slots.capacity()) * sizeof(uint32_t);
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

proto::Result<void, std::string> MeshCache::open() {
    std::vector<std::string> removed;
    auto listed = store_.open(removed);
    for (const std::string& line : removed)
        log_event(LogLevel::kWarn, "cache: removed leftover", {{"what", line}});
    if (!listed) return Err{std::move(listed).error()};
    for (MeshStore::Listed& item : *listed) {
        if (!item.summary) {
            log_event(LogLevel::kWarn, "cache: summary unreadable, recovering from the stored mesh",
                      {{"mesh", item.id}, {"error", item.summary_error}});
            auto mesh = store_.load_mesh(item.id);
            if (!mesh) {
                log_event(LogLevel::kError, "cache: stored mesh is corrupt; dropped",
                          {{"mesh", item.id}, {"error", mesh.error().detail}});
                store_.remove(item.id);
                continue;
            }
            auto tree = store_.load_tree(item.id);
            KdTree built;
            if (!tree) {
                const auto start = std::chrono::steady_clock::now();
                built = compute_.build(*mesh);
                metrics_.record_build(seconds_since(start));
                metrics_.cache_rebuilds.fetch_add(1);
                if (auto saved = store_.save_tree(item.id, built); !saved)
                    return Err{std::move(saved).error()};
            }
            proto::MeshSummary summary = make_summary(item.id, *mesh, tree ? *tree : built);
            if (auto saved = store_.save_summary(summary); !saved)
                return Err{std::move(saved).error()};
            item.summary = std::move(summary);
            item.disk_bytes = store_.disk_bytes(item.id);
        }
        auto entry = std::make_shared<Entry>();
        entry->id = item.id;
        entry->summary = std::move(item.summary);
        entry->disk_bytes = item.disk_bytes;
        std::lock_guard lock(mutex_);
        disk_bytes_ += entry->disk_bytes;
        entries_[entry->id] = std::move(entry);
    }
    return {};
}

proto::Result<MeshCache::Added, CacheError> MeshCache::add(const Mesh& mesh) {
    const std::string id = proto::mesh_id(mesh);
    std::unique_lock lock(mutex_);
    for (;;) {
        const auto it = entries_.find(id);
        if (it == entries_.end()) break;
        const std::shared_ptr<Entry> entry = it->second;
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
        auto saved = store_.save(summary, mesh, *built);
        if (saved) {
            disk_bytes = *saved;
            tree = std::move(built);
            outcome = Added{std::move(summary), true};
        } else {
            log_event(LogLevel::kError, "cache: cannot store mesh",
                      {{"mesh", id}, {"error", saved.error()}});
            store_.remove(id);
            outcome = Err{
                CacheError{CacheError::Code::kStorage, "cannot store the mesh: " + saved.error()}};
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
        entries_.erase(id);
    }
    lock.unlock();
    promise.set_value(outcome ? TreeResult(tree) : TreeResult(Err{outcome.error()}));
    return outcome;
}

proto::Result<std::shared_ptr<const KdTree>, CacheError> MeshCache::acquire(const std::string& id) {
    std::unique_lock lock(mutex_);
    const auto it = entries_.find(id);
    if (it == entries_.end() || !it->second->summary)
        return Err{CacheError{CacheError::Code::kUnknownMesh, "no mesh with id " + id}};
    const std::shared_ptr<Entry> entry = it->second;
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
    try {
        outcome = load(id, summary);
    } catch (const std::exception& e) {
        outcome = Err{CacheError{CacheError::Code::kInternal,
                                 std::string("loading the tree failed: ") + e.what()}};
    }

    lock.lock();
    entry->flight = Flight();
    if (is_current(entry)) {
        if (outcome)
            make_resident(*entry, *outcome);
        else if (outcome.error().code == CacheError::Code::kLost)
            drop(*entry);
    } else if (!outcome) {
        outcome =
            Err{CacheError{CacheError::Code::kUnknownMesh, "no mesh with id " + id + " (deleted)"}};
    }
    lock.unlock();
    promise.set_value(outcome);
    return outcome;
}

MeshCache::TreeResult MeshCache::load(const std::string& id, const proto::MeshSummary& summary) {
    auto tree = store_.load_tree(id);
    if (tree && consistent(*tree, summary))
        return std::shared_ptr<const KdTree>(std::make_shared<KdTree>(std::move(*tree)));
    const std::string why = tree ? "tree does not match the mesh summary" : tree.error().detail;
    log_event(LogLevel::kWarn,
              "cache: tree file failed validation; rebuilding from the stored mesh",
              {{"mesh", id}, {"error", why}});
    auto mesh = store_.load_mesh(id);
    if (!mesh) {
        log_event(LogLevel::kError, "cache: stored mesh is corrupt; dropped",
                  {{"mesh", id}, {"error", mesh.error().detail}});
        store_.remove(id);
        return Err{CacheError{CacheError::Code::kLost,
                              "mesh " + id + " was dropped: its stored copy is corrupt (" +
                                  mesh.error().detail + ")"}};
    }
    const auto start = std::chrono::steady_clock::now();
    auto built = std::make_shared<KdTree>(compute_.build(*mesh));
    metrics_.record_build(seconds_since(start));
    metrics_.cache_rebuilds.fetch_add(1);
    if (auto saved = store_.save_tree(id, *built); !saved)
        log_event(LogLevel::kError, "cache: cannot rewrite the tree file",
                  {{"mesh", id}, {"error", saved.error()}});
    else
        log_event(LogLevel::kInfo, "cache: tree rebuilt",
                  {{"mesh", id}, {"build_ms", built->stats.build_ms}});
    return std::shared_ptr<const KdTree>(std::move(built));
}

std::optional<proto::MeshSummary> MeshCache::find(const std::string& id) const {
    std::lock_guard lock(mutex_);
    const auto it = entries_.find(id);
    if (it == entries_.end() || !it->second->summary) return std::nullopt;
    return with_runtime(*it->second);
}

std::vector<proto::MeshSummary> MeshCache::list() const {
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
    while (memory_bytes_ > memory_budget_ && lru_.size() > 1) {
        Entry* victim = lru_.back();
        lru_.pop_back();
        victim->in_lru = false;
        memory_bytes_ -= victim->tree_bytes;
        victim->tree_bytes = 0;
        victim->tree.reset();
        metrics_.cache_evictions.fetch_add(1);
        log_event(LogLevel::kDebug, "cache: evicted", {{"mesh", victim->id}});
    }
}

void MeshCache::drop(Entry& entry) {
    if (entry.in_lru) {
        lru_.erase(entry.lru_position);
        entry.in_lru = false;
        memory_bytes_ -= entry.tree_bytes;
        entry.tree.reset();
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
