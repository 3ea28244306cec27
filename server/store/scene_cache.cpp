#include "store/scene_cache.h"

#include <algorithm>
#include <atomic>
#include <cstring>
#include <future>
#include <new>
#include <unordered_map>
#include <unordered_set>

namespace kdrt::server {

namespace {

using Code = SceneProblem::Code;

SceneProblem problem(Code code, std::string detail, std::string field = {},
                     std::optional<uint32_t> index = std::nullopt) {
    SceneProblem p;
    p.code = code;
    p.detail = std::move(detail);
    p.field = std::move(field);
    p.index = index;
    return p;
}

SceneProblem store_problem(const SceneStoreError& e, const std::string& id,
                           std::optional<uint64_t> revision) {
    switch (e.code) {
        case SceneStoreError::Code::kMissing:
            if (revision)
                return problem(Code::kUnknownRevision,
                               "scene " + id + " has no revision " + std::to_string(*revision) +
                                   " (never written, or older than the kept revisions)");
            return problem(Code::kUnknownScene, "no scene with id " + id);
        case SceneStoreError::Code::kCorrupt:
            return problem(Code::kDamaged, e.detail);
        case SceneStoreError::Code::kIo:
            break;
    }
    return problem(Code::kInternal, e.detail);
}

SceneProblem write_problem(const WriteError& e) {
    return problem(e.no_space ? Code::kNoSpace : Code::kInternal, e.message);
}

Affine3x4 affine(const proto::Transform& t) {
    Affine3x4 a;
    static_assert(sizeof a.m == sizeof t.m);
    std::memcpy(a.m, t.m.data(), sizeof a.m);
    return a;
}

/// The engine's SceneError as a problem about entry `index` of `array_name`.
SceneProblem scene_error_problem(const SceneError& e, const std::string& array_name,
                                 std::optional<uint32_t> index) {
    const bool over = e.field() == "instances";
    std::string field = array_name;
    if (!over && index) {
        field += "[" + std::to_string(*index) + "]";
        if (!e.field().empty() && e.field() != "geom") field += "." + e.field();
    }
    return problem(over ? Code::kTooLarge : Code::kInvalid, e.what(), field,
                   over ? std::nullopt : index);
}

uint64_t entry_bytes(const SceneEntry& e) {
    uint64_t doc = sizeof(SceneEntry);
    for (const auto& inst : e.doc.instances)
        doc += sizeof inst + inst.mesh.capacity() + inst.name.capacity();
    return doc + e.scene.stats().bytes;
}

}  // namespace

SceneCache::SceneCache(SceneStore& store, MeshCache& meshes, Compute& compute, Metrics& metrics,
                       SceneCacheOptions options)
    : store_(store), meshes_(meshes), compute_(compute), metrics_(metrics), options_(options) {}

SceneCache::Result<SceneCache::EntryPtr> SceneCache::build(proto::SceneDocument doc,
                                                           const char* array_name, bool stored) {
    if (doc.instances.size() > options_.max_instances) {
        SceneProblem p = problem(Code::kTooLarge,
                                 "the scene would have " + std::to_string(doc.instances.size()) +
                                     " instances, more than max_instances (" +
                                     std::to_string(options_.max_instances) + ")",
                                 array_name);
        p.limit = options_.max_instances;
        return proto::Err{std::move(p)};
    }
    try {
        std::unordered_map<std::string, std::shared_ptr<const KdTree>> trees;
        std::vector<SceneInstance> instances(doc.instances.size());
        for (size_t i = 0; i < doc.instances.size(); ++i) {
            const std::string& mesh = doc.instances[i].mesh;
            auto it = trees.find(mesh);
            if (it == trees.end()) {
                auto tree = meshes_.acquire(mesh);
                if (!tree) {
                    const auto index = static_cast<uint32_t>(i);
                    const std::string field =
                        std::string(array_name) + "[" + std::to_string(i) + "].mesh";
                    switch (tree.error().code) {
                        case CacheError::Code::kUnknownMesh:
                            return proto::Err{problem(
                                stored ? Code::kMeshGone : Code::kUnknownReference,
                                "instance " + std::to_string(i) + ": no mesh with id " + mesh +
                                    (stored ? " (it was deleted after this revision was written)"
                                            : ""),
                                field, index)};
                        case CacheError::Code::kDamaged:
                            return proto::Err{problem(
                                Code::kDamaged,
                                "instance " + std::to_string(i) + ": " + tree.error().detail, field,
                                index)};
                        default:
                            return proto::Err{
                                problem(Code::kInternal, tree.error().detail, field, index)};
                    }
                }
                it = trees.emplace(mesh, std::move(tree).value()).first;
            }
            instances[i].tree = it->second;
            instances[i].transform = affine(doc.instances[i].transform);
        }
        SceneBuildOptions build_options;
        build_options.max_instances = options_.max_instances;
        auto entry = std::make_shared<SceneEntry>();
        // Without the meshes' HitClearance: a revision gets it at its first single-return scan
        // (scan_ready).
        entry->scene =
            compute_.run([&] { return build_scene(std::move(instances), build_options); });
        entry->doc = std::move(doc);
        entry->bytes = entry_bytes(*entry);
        return EntryPtr(std::move(entry));
    } catch (const SceneError& e) {
        return proto::Err{scene_error_problem(e, array_name, e.instance_index())};
    } catch (const std::bad_alloc&) {
        return proto::Err{problem(Code::kInternal, "out of memory building the scene")};
    }
}

SceneCache::EntryPtr SceneCache::scan_ready(const EntryPtr& entry) {
    const Scene& scene = entry->scene;
    const uint32_t n = scene.size();
    bool missing = false;
    for (uint32_t g = 0; g < n && !missing; ++g) missing = !scene.instance(g).clearance;
    // Tried already: what is missing belongs to meshes deleted since (their every-hit windows
    // give the same answers), so a scan of such a revision does not rebuild it each time.
    if (!missing || entry->scan_ready) return entry;
    // Per distinct tree (the instances of one mesh share it): the mesh cache's clearance of it,
    // built at its first use there.
    std::unordered_map<const KdTree*, std::shared_ptr<const HitClearance>> clearances;
    std::vector<std::shared_ptr<const HitClearance>> per_instance(n);
    try {
        for (uint32_t g = 0; g < n; ++g) {
            const SceneInstance& inst = scene.instance(g);
            if (inst.clearance) {
                per_instance[g] = inst.clearance;
                continue;
            }
            const auto [it, added] = clearances.try_emplace(inst.tree.get());
            // A mesh deleted since: no clearance (every window, the same answers).
            if (added && meshes_.find(entry->doc.instances[g].mesh))
                it->second = meshes_.hit_clearance(entry->doc.instances[g].mesh, inst.tree);
            per_instance[g] = it->second;
        }
        auto ready = std::make_shared<SceneEntry>();
        ready->doc = entry->doc;
        ready->scene = scene.with_clearances(per_instance);
        ready->bytes = entry_bytes(*ready);
        ready->scan_ready = true;
        // Kept in place of `entry` (unless it was evicted or replaced meanwhile), so the next
        // scan and the next pose update's base find it.
        std::lock_guard lock(mutex_);
        const auto it = by_key_.find({entry->doc.id, entry->doc.revision});
        if (it != by_key_.end() && *it->second == entry) {
            bytes_ += ready->bytes;
            bytes_ -= entry->bytes;
            *it->second = ready;
        }
        return ready;
    } catch (const std::bad_alloc&) {
        return entry;  // scanned without it: the same answers
    } catch (const SceneError&) {
        return entry;  // (a clearance of another tree; cannot happen: built from the same one)
    }
}

namespace {
SceneProblem too_many_scenes(size_t scenes, uint32_t max_scenes) {
    SceneProblem p =
        problem(Code::kTooLarge,
                "the store holds " + std::to_string(scenes) + " scenes, max_scenes is " +
                    std::to_string(max_scenes) + "; delete one first",
                "");
    p.limit = max_scenes;
    return p;
}
}  // namespace

SceneCache::Result<SceneCache::EntryPtr> SceneCache::create(
    std::vector<proto::SceneInstanceSpec> instances) {
    // Counted before any work, and again under the store's create lock (SceneStore::create).
    if (auto ids = store_.ids(); ids && ids->size() >= options_.max_scenes)
        return proto::Err{too_many_scenes(ids->size(), options_.max_scenes)};
    proto::SceneDocument doc;
    doc.id = SceneStore::new_id();
    doc.revision = 1;
    doc.instances = std::move(instances);
    // Built before it is stored: nothing is acknowledged that cannot be queried.
    auto entry = build(std::move(doc), "instances", false);
    if (!entry) return entry;
    auto created = store_.create((*entry)->doc, options_.max_scenes);
    if (!created) return proto::Err{write_problem(created.error())};
    if (!created->created) return proto::Err{too_many_scenes(created->scenes, options_.max_scenes)};
    metrics_.scene_revisions.fetch_add(1);
    keep(*entry);
    return entry;
}

SceneCache::EntryPtr SceneCache::find(const std::string& id, uint64_t revision) {
    std::shared_future<EntryPtr> building;
    {
        std::lock_guard lock(mutex_);
        const auto it = by_key_.find({id, revision});
        if (it != by_key_.end()) {
            lru_.splice(lru_.begin(), lru_, it->second);
            return *it->second;
        }
        const auto b = building_.find({id, revision});
        if (b == building_.end()) return nullptr;
        building = b->second;
    }
    // Committed and answered, its scene still building on the arena: wait for it (nullptr when
    // the build failed: the caller then builds it from the store).
    EntryPtr entry = building.get();
    if (entry) keep(entry);
    std::lock_guard lock(mutex_);
    const auto b = building_.find({id, revision});
    if (b != building_.end()) building_.erase(b);
    return entry;
}

void SceneCache::prune_later(const std::string& id, uint64_t revision) {
    // A log drops old revisions in its commits; revision files are deleted here.
    if (store_.uses_log() || revision <= store_.revisions_kept()) return;
    if (compute_.threads() <= 1) {  // no arena worker to run it later
        store_.prune(id, revision);
        return;
    }
    in_flight_add();
    compute_.enqueue([this, id, revision] {
        store_.prune(id, revision);
        in_flight_done();
    });
}

void SceneCache::in_flight_add() {
    std::lock_guard lock(in_flight_mutex_);
    ++in_flight_;
}

void SceneCache::in_flight_done() {
    std::lock_guard lock(in_flight_mutex_);
    if (--in_flight_ == 0) in_flight_cv_.notify_all();
}

SceneCache::~SceneCache() {
    std::unique_lock lock(in_flight_mutex_);
    in_flight_cv_.wait(lock, [&] { return in_flight_ == 0; });
}

SceneCache::Result<SceneCache::EntryPtr> SceneCache::load(const std::string& id,
                                                          uint64_t revision) {
    auto doc = store_.read(id, revision);
    if (!doc) return proto::Err{store_problem(doc.error(), id, revision)};
    auto entry = build(std::move(doc).value(), "instances", true);
    if (!entry) {
        // A stored revision's refusal is the store's damage or a deleted mesh, not the caller's.
        if (entry.error().code == Code::kInvalid || entry.error().code == Code::kTooLarge)
            entry.error().code = Code::kDamaged;
        return entry;
    }
    keep(*entry);
    return entry;
}

SceneCache::Result<SceneCache::EntryPtr> SceneCache::current(const std::string& id) {
    if (!proto::is_scene_id(id))
        return proto::Err{problem(Code::kUnknownScene, "no scene with id " + id)};
    uint64_t known = 0;
    {
        std::lock_guard lock(mutex_);
        if (const auto it = latest_.find(id); it != latest_.end()) known = it->second;
    }
    if (known > 0 && store_.is_current(id, known))
        if (EntryPtr hit = find(id, known)) return hit;
    auto latest = store_.latest(id);
    if (!latest) {
        if (latest.error().code == SceneStoreError::Code::kMissing) forget(id);
        return proto::Err{store_problem(latest.error(), id, std::nullopt)};
    }
    if (EntryPtr hit = find(id, *latest)) {
        std::lock_guard lock(mutex_);
        latest_[id] = std::max(latest_[id], *latest);
        return hit;
    }
    return load(id, *latest);
}

SceneCache::Result<SceneCache::EntryPtr> SceneCache::get(const std::string& id,
                                                         std::optional<uint64_t> revision) {
    if (!revision) return current(id);
    if (!proto::is_scene_id(id))
        return proto::Err{problem(Code::kUnknownScene, "no scene with id " + id)};
    {
        // Older than the kept revisions: refused even while its file waits for the prune that
        // follows a commit (prune_later), so what is served does not depend on that timing.
        std::lock_guard lock(mutex_);
        const auto it = latest_.find(id);
        if (it != latest_.end() && *revision + store_.revisions_kept() <= it->second)
            return proto::Err{
                store_problem(SceneStoreError{SceneStoreError::Code::kMissing, ""}, id, revision)};
    }
    if (EntryPtr hit = find(id, *revision); hit && store_.has_revision(id, *revision)) {
        // A kept revision may name a mesh deleted since (deleting is refused only while the
        // current revision uses it): answer as a revision loaded now would.
        std::unordered_set<std::string_view> checked;
        for (size_t i = 0; i < hit->doc.instances.size(); ++i) {
            const std::string& mesh = hit->doc.instances[i].mesh;
            if (!checked.insert(mesh).second || meshes_.find(mesh)) continue;
            return proto::Err{
                problem(Code::kMeshGone,
                        "instance " + std::to_string(i) + ": no mesh with id " + mesh +
                            " (it was deleted after this revision was written)",
                        "instances[" + std::to_string(i) + "].mesh", static_cast<uint32_t>(i))};
        }
        return hit;
    }
    if (!store_.has_revision(id, *revision)) {
        auto latest = store_.latest(id);
        if (!latest) return proto::Err{store_problem(latest.error(), id, std::nullopt)};
        return proto::Err{
            store_problem(SceneStoreError{SceneStoreError::Code::kMissing, ""}, id, revision)};
    }
    return load(id, *revision);
}

namespace {
SceneProblem stale(Metrics& metrics, const std::string& id, uint64_t if_match, uint64_t current) {
    metrics.scene_conflicts.fetch_add(1);
    return problem(Code::kStale,
                   "If-Match names revision " + std::to_string(if_match) + " of scene " + id +
                       ", but the current revision is " + std::to_string(current),
                   "If-Match");
}
}  // namespace

SceneCache::Result<SceneCache::Committed> SceneCache::update(
    const std::string& id, std::optional<uint64_t> if_match, const char* what,
    const std::function<Result<Next>(const EntryPtr& base)>& next) {
    for (int attempt = 0; attempt < 16; ++attempt) {
        auto base = current(id);
        if (!base) return proto::Err{std::move(base).error()};
        const EntryPtr& b = *base;
        if (if_match && *if_match != b->doc.revision)
            return proto::Err{stale(metrics_, id, *if_match, b->doc.revision)};
        auto n = next(b);
        if (!n) return proto::Err{std::move(n).error()};
        if (!n->build) {  // built already (an instance edit)
            auto committed = store_.commit(n->doc);
            if (!committed) return proto::Err{write_problem(committed.error())};
            if (*committed) {
                metrics_.scene_revisions.fetch_add(1);
                auto entry = std::make_shared<SceneEntry>();
                entry->doc = std::move(n->doc);
                entry->scene = std::move(n->scene);
                entry->bytes = entry_bytes(*entry);
                keep(entry);
                prune_later(id, entry->doc.revision);
                const proto::SceneListItem summary{id, entry->doc.revision,
                                                   entry->doc.instances.size()};
                return Committed{summary, EntryPtr(std::move(entry))};
            }
        } else {
            // The revision's document and scene are made on an arena worker while this thread
            // commits the record encoded from the base (SceneStore::commit), and the answer does
            // not wait for them: the revision is registered as
            // building, and whoever asks for it next (a query, the next update) waits for it
            // (find()). Until then nothing but the task touches the entry.
            const proto::SceneListItem summary = n->summary;
            auto entry = std::make_shared<SceneEntry>();
            auto done = std::make_shared<std::promise<EntryPtr>>();
            std::shared_future<EntryPtr> built = done->get_future().share();
            auto task = [this, entry, done, build = std::move(n->build)]() mutable {
                EntryPtr result;
                try {
                    build(*entry);
                    entry->bytes = entry_bytes(*entry);
                    result = entry;
                } catch (...) {  // std::bad_alloc: a later request builds it from the store
                }
                done->set_value(std::move(result));
                build = nullptr;  // nothing of the scene outlives this cache in the task
                entry.reset();
                done.reset();
                in_flight_done();
            };
            // With revision files the check (what the build would refuse) runs on an arena worker
            // as well, while this thread stages the revision (writes and flushes it under tmp/);
            // the commit waits for it. Whichever comes first runs it: when the workers are busy
            // (a long query holds the arena), this thread checks after the write instead of
            // waiting for one. A log's stage writes nothing: this thread checks (beside the
            // build), which spares the commit a hand-off from a worker that has to be woken.
            struct Check {
                std::atomic<bool> claimed{false};
                std::function<std::optional<SceneProblem>()> run;
                std::promise<std::optional<SceneProblem>> done;
                std::optional<SceneProblem> operator()() {
                    try {
                        return run ? run() : std::nullopt;
                    } catch (const std::bad_alloc&) {
                        return problem(Code::kInternal, "out of memory updating the scene");
                    }
                }
            };
            auto check = std::make_shared<Check>();
            check->run = std::move(n->check);
            std::future<std::optional<SceneProblem>> checked = check->done.get_future();
            // With one thread the arena has no worker to run an enqueued task: checked before
            // the write, built after the commit.
            const bool overlap = compute_.threads() > 1;
            const bool check_beside = overlap && !store_.uses_log();
            if (check_beside) {
                in_flight_add();
                compute_.enqueue([this, check]() mutable {
                    if (!check->claimed.exchange(true)) check->done.set_value((*check)());
                    check.reset();
                    in_flight_done();
                });
            }
            if (overlap) {
                in_flight_add();
                compute_.enqueue(task);
            }
            std::optional<SceneProblem> refused;
            if (!check_beside && (refused = (*check)())) return proto::Err{std::move(*refused)};
            auto staged = store_.stage(id, summary.revision, std::move(n->file));
            if (check_beside) refused = check->claimed.exchange(true) ? checked.get() : (*check)();
            if (refused) return proto::Err{std::move(*refused)};
            if (!staged) return proto::Err{write_problem(staged.error())};
            auto committed = store_.commit(std::move(staged).value());
            if (!overlap) {
                in_flight_add();
                compute_.run(task);
            }
            if (!committed) return proto::Err{write_problem(committed.error())};
            if (*committed) {
                metrics_.scene_revisions.fetch_add(1);
                {
                    std::lock_guard lock(mutex_);
                    building_[{id, summary.revision}] = built;
                    uint64_t& latest = latest_[id];
                    latest = std::max(latest, summary.revision);
                }
                prune_later(id, summary.revision);
                return Committed{summary, nullptr};  // the entry may be building
            }
        }
        if (if_match) {  // someone else committed base + 1 first
            auto now = store_.latest(id);
            if (!now) return proto::Err{store_problem(now.error(), id, std::nullopt)};
            return proto::Err{stale(metrics_, id, *if_match, *now)};
        }
    }
    return proto::Err{problem(
        Code::kInternal, "scene " + id + " changed 16 times while this " + what + " was applied")};
}

SceneCache::Result<proto::SceneListItem> SceneCache::set_poses(
    const std::string& id, std::optional<uint64_t> if_match,
    std::span<const proto::PoseEntry> poses) {
    // Without If-Match a lost race is retried on the newer revision (the poses are absolute).
    auto updated = update(id, if_match, "update", [&](const EntryPtr& b) -> Result<Next> {
        auto resolved = proto::resolve_poses(b->doc, poses);
        if (!resolved) {
            const auto& e = resolved.error();
            return proto::Err{problem(Code::kUnknownReference, e.detail, e.field, e.index)};
        }
        auto poses_in =
            std::make_shared<const std::vector<proto::ResolvedPose>>(std::move(resolved).value());
        auto engine_poses = std::make_shared<std::vector<InstancePose>>(poses_in->size());
        for (size_t k = 0; k < poses_in->size(); ++k)
            (*engine_poses)[k] = {(*poses_in)[k].geometry_id, affine((*poses_in)[k].transform)};
        Next n;
        n.summary = {id, b->doc.revision + 1, b->doc.instances.size()};
        // The revision's file straight from the base and the poses; its document (a copy of the
        // base's, ~0.35 ms for 1,000 instances) is made by the build, off the request's path.
        n.file = proto::encode_scene_file(b->doc, n.summary.revision, *poses_in);
        // What the build would refuse, checked before the commit (so nothing is stored that it
        // refuses; update() says on which thread); the build overlaps the write.
        n.check = [scene = b->scene, engine_poses, poses_in]() -> std::optional<SceneProblem> {
            try {
                scene.check_transforms(*engine_poses);
            } catch (const SceneError& e) {
                // The last pose entry of the instance: what the engine's error refers to.
                std::optional<uint32_t> k;
                for (size_t j = poses_in->size(); e.instance_index() && j-- > 0;) {
                    if ((*poses_in)[j].geometry_id == *e.instance_index()) {
                        k = static_cast<uint32_t>(j);
                        break;
                    }
                }
                SceneProblem p = scene_error_problem(e, "poses", k);
                p.detail = "geometry id " +
                           (e.instance_index() ? std::to_string(*e.instance_index()) : "?") + ": " +
                           e.what();
                return p;
            }
            return std::nullopt;
        };
        n.build = [b, engine_poses, poses_in](SceneEntry& entry) {
            entry.doc = b->doc;
            entry.doc.revision = b->doc.revision + 1;
            for (const proto::ResolvedPose& p : *poses_in)
                entry.doc.instances[p.geometry_id].transform = p.transform;
            entry.scene = b->scene.with_transforms(*engine_poses);
        };
        return n;
    });
    if (!updated) return proto::Err{std::move(updated).error()};
    return std::move(updated).value().summary;
}

SceneCache::Result<SceneCache::EntryPtr> SceneCache::edit(const std::string& id,
                                                          std::optional<uint64_t> if_match,
                                                          const proto::InstanceEdit& edit) {
    auto edited = update(id, if_match, "edit", [&](const EntryPtr& b) -> Result<Next> {
        proto::SceneLimits limits;
        limits.max_instances = options_.max_instances;
        auto doc = proto::apply_instance_edit(b->doc, edit, limits);
        if (!doc) {
            const auto& e = doc.error();
            SceneProblem p = problem(e.unknown_reference ? Code::kUnknownReference
                                     : e.over_limit      ? Code::kTooLarge
                                                         : Code::kInvalid,
                                     e.detail, e.field, e.index);
            if (e.over_limit) p.limit = options_.max_instances;
            return proto::Err{std::move(p)};
        }
        doc->revision = b->doc.revision + 1;
        // The added instances are checked against their place in "add".
        const size_t kept = doc->instances.size() - edit.add.size();
        auto next = build(std::move(doc).value(), "instances", true);
        if (!next) {
            SceneProblem p = std::move(next).error();
            if (p.index && *p.index >= kept) {
                const uint32_t k = *p.index - static_cast<uint32_t>(kept);
                const std::string old_prefix = "instances[" + std::to_string(*p.index) + "]";
                if (p.field.rfind(old_prefix, 0) == 0)
                    p.field = "add[" + std::to_string(k) + "]" + p.field.substr(old_prefix.size());
                p.index = k;
                if (p.code == Code::kMeshGone) p.code = Code::kUnknownReference;
            }
            return proto::Err{std::move(p)};
        }
        Next n;
        n.doc = (*next)->doc;
        n.scene = (*next)->scene;
        return n;
    });
    if (!edited) return proto::Err{std::move(edited).error()};
    return std::move(edited).value().entry;
}

SceneCache::Result<bool> SceneCache::remove(const std::string& id,
                                            std::optional<uint64_t> if_match) {
    if (!proto::is_scene_id(id)) return false;
    // The store compares If-Match and deletes under the scene's lock: a revision committed
    // meanwhile (here or by another replica) makes this stale, never silently deleted.
    auto removed = store_.remove(id, if_match);
    if (!removed) return proto::Err{write_problem(removed.error())};
    switch (removed->outcome) {
        case SceneStore::Removal::Outcome::kStale:
            return proto::Err{stale(metrics_, id, *if_match, removed->current)};
        case SceneStore::Removal::Outcome::kMissing:
            forget(id);
            return false;
        case SceneStore::Removal::Outcome::kRemoved:
            break;
    }
    forget(id);
    return true;
}

std::vector<SceneCache::EntryPtr> SceneCache::list(std::vector<std::string>* damaged) {
    std::vector<EntryPtr> out;
    auto ids = store_.ids();
    if (!ids) return out;
    for (const std::string& id : *ids) {
        // The document is enough for a listing: no need to build scenes that are not resident.
        auto latest = store_.latest(id);
        if (!latest) continue;  // deleted meanwhile
        if (EntryPtr hit = find(id, *latest)) {
            out.push_back(hit);
            continue;
        }
        auto doc = store_.read(id, *latest);
        if (!doc) {
            if (damaged && doc.error().code != SceneStoreError::Code::kMissing)
                damaged->push_back(doc.error().detail);
            continue;
        }
        auto entry = std::make_shared<SceneEntry>();
        entry->doc = std::move(doc).value();
        out.push_back(std::move(entry));
    }
    return out;
}

std::vector<std::string> SceneCache::mesh_users(const std::string& mesh_id) {
    std::vector<std::string> users;
    auto ids = store_.ids();
    if (!ids) return users;
    for (const std::string& id : *ids) {
        auto latest = store_.latest(id);
        if (!latest) continue;
        EntryPtr hit = find(id, *latest);
        proto::SceneDocument doc;
        if (hit) {
            doc = hit->doc;
        } else if (auto read = store_.read(id, *latest)) {
            doc = std::move(read).value();
        } else {
            continue;
        }
        for (const auto& inst : doc.instances)
            if (inst.mesh == mesh_id) {
                users.push_back(id);
                break;
            }
    }
    return users;
}

void SceneCache::keep(const EntryPtr& entry) {
    std::vector<EntryPtr> dropped;  // freed after the lock is let go
    std::lock_guard lock(mutex_);
    const Key key{entry->doc.id, entry->doc.revision};
    uint64_t& latest = latest_[entry->doc.id];
    latest = std::max(latest, entry->doc.revision);
    // The revisions this scene's newest has left behind, which get() refuses (older than the
    // kept ones), go now: a moving sensor's pose updates filled the whole budget with them,
    // each new revision on memory never used before (page faults) while they waited for the
    // LRU to reach them.
    const uint64_t kept = store_.revisions_kept();
    for (auto it = by_key_.lower_bound({entry->doc.id, 0}); it != by_key_.end() &&
                                                            it->first.first == entry->doc.id &&
                                                            it->first.second + kept <= latest;) {
        bytes_ -= (*it->second)->bytes;
        dropped.push_back(std::move(*it->second));
        lru_.erase(it->second);
        it = by_key_.erase(it);
    }
    if (by_key_.count(key) || key.second + kept <= latest) return;
    lru_.push_front(entry);
    by_key_[key] = lru_.begin();
    bytes_ += entry->bytes;
    // Evict least recently used beyond the budget, always keeping the newest entry.
    while (bytes_ > options_.memory_budget && lru_.size() > 1) {
        const EntryPtr& victim = lru_.back();
        bytes_ -= victim->bytes;
        by_key_.erase({victim->doc.id, victim->doc.revision});
        lru_.pop_back();
        metrics_.scene_evictions.fetch_add(1);
    }
}

void SceneCache::forget(const std::string& id) {
    std::lock_guard lock(mutex_);
    latest_.erase(id);
    for (auto it = building_.lower_bound({id, 0}); it != building_.end() && it->first.first == id;)
        it = building_.erase(it);
    for (auto it = by_key_.lower_bound({id, 0}); it != by_key_.end() && it->first.first == id;) {
        bytes_ -= (*it->second)->bytes;
        lru_.erase(it->second);
        it = by_key_.erase(it);
    }
}

uint64_t SceneCache::memory_bytes() const {
    std::lock_guard lock(mutex_);
    return bytes_;
}

size_t SceneCache::resident_count() const {
    std::lock_guard lock(mutex_);
    return lru_.size();
}

size_t SceneCache::scene_count() const {
    auto ids = store_.ids();
    return ids ? ids->size() : 0;
}

}  // namespace kdrt::server
