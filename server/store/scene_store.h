#pragma once
/// Durable storage of scenes under the cache directory:
///
///   scenes/<id>/<revision>.json   one file per revision (20 decimal digits, zero-padded, so the
///                                 names sort as the numbers), KDRS (proto::encode_scene_file);
///                                 immutable once written. Stores written before KDRS hold the
///                                 scene JSON of proto::encode_scene_json under the same name
///                                 and are read as such (proto::decode_stored_scene). The name
///                                 stays ".json" so that every kdrt-server version sharing a
///                                 store takes the same name for revision N (the link is the
///                                 compare-and-set).
///
/// The current revision is the highest-numbered file: there is no pointer file to update.
/// A revision enters the directory only by write_file_once (an atomic link of a complete,
/// fsync'd file that fails when the name exists), followed by an fsync of the directory before
/// the caller acknowledges it. That link is the commit and the compare-and-set of optimistic
/// concurrency at once: of two writers (threads or replicas sharing the store) that both read
/// revision N and write N + 1, exactly one succeeds and the other learns it is stale. After a
/// crash a revision is either wholly there or absent; no acknowledged revision is lost, and no
/// reader ever sees a partly written one.
///
/// Every change to an existing scene (a commit, a deletion) holds an exclusive flock on the
/// scene's directory, taken by every process sharing the store: an If-Match deletion compares
/// the current revision and renames the directory away with no commit in between (so a delete
/// and a pose update that both name revision N cannot both succeed), and where the file system
/// has no hard links (write_file_once's rename fallback) the existence check and the rename of a
/// revision are not interleaved with another writer's. When the file system refuses flock
/// (ENOLCK, EOPNOTSUPP), the link alone stays the compare-and-set of commits.
///
/// A scene is created whole: its directory and revision 1 are written under this process's tmp/
/// and renamed into scenes/ (atomic), so scenes/ never holds an empty or half-made scene. It is
/// deleted by renaming its directory into tmp/ (atomic: it disappears at once for every reader)
/// and then removing the files. After a commit, prune() deletes the revisions older than the newest
/// `revisions_kept` (pinned queries may use the kept ones); the server calls it after the answer.
///
/// Thread-safe; any number of processes may share one store (each passes its own tmp_dir, the
/// MeshStore's locked tmp/<process>/).

#include <cstddef>
#include <cstdint>
#include <filesystem>
#include <optional>
#include <span>
#include <string>
#include <vector>

#include "kdrt/proto/result.h"
#include "kdrt/proto/scene.h"
#include "store/durable_file.h"

namespace kdrt::server {

/// Why a scene or revision could not be read.
struct SceneStoreError {
    enum class Code {
        kMissing,  ///< no such scene, or no such revision (never written, or no longer kept)
        kCorrupt,  ///< the revision file exists but does not decode, or names another scene
        kIo,       ///< the operating system refused
    };
    Code code = Code::kIo;
    std::string detail;  ///< names the file and what is wrong
};

class SceneStore {
public:
    /// `root` is the cache directory; `tmp_dir` this process's private temp directory on the
    /// same file system. `revisions_kept` >= 1.
    SceneStore(std::filesystem::path root, std::filesystem::path tmp_dir, uint32_t revisions_kept);

    /// Creates scenes/ when missing.
    [[nodiscard]] proto::Result<void, std::string> open();

    /// A new scene id: 32 lower-case hex digits from 128 random bits.
    [[nodiscard]] static std::string new_id();

    /// What create() did.
    struct Creation {
        bool created = false;  ///< false: the store held max_scenes scenes already
        size_t scenes = 0;     ///< when refused: how many it held
    };
    /// Stores `scene` as revision 1 of a new scene (scene.id must be a fresh id, revision 1),
    /// unless the store holds `max_scenes` scenes already. The count and the rename into scenes/
    /// happen under an exclusive flock of scenes/.create-lock that every process sharing the
    /// store takes, so concurrent creates (threads, or replicas on one store) never pass
    /// max_scenes. (Where the file system refuses flock the count is taken unlocked, and two
    /// creates at the same moment may each pass it by one.) Durable when it returns created.
    [[nodiscard]] proto::Result<Creation, WriteError> create(const proto::SceneDocument& scene,
                                                             size_t max_scenes = SIZE_MAX);

    /// Stores `scene` as revision scene.revision (>= 2) of an existing scene. Returns false,
    /// writing nothing, when that revision exists already (another writer committed it first:
    /// the caller's base revision is stale) or the scene was deleted. Durable on true. Deletes
    /// no old revision: prune() does, after the answer.
    [[nodiscard]] proto::Result<bool, WriteError> commit(const proto::SceneDocument& scene);

    /// commit() in two steps, so that a caller can overlap other work with the write: stage()
    /// encodes `scene` and writes it durably under tmp_dir (nothing visible; removed when the
    /// StagedRevision goes unused); commit(staged) links it in under the scene's lock and syncs
    /// the directory, with commit()'s answers.
    struct StagedRevision {
        std::string id;
        uint64_t revision = 0;
        StagedFile file;
    };
    [[nodiscard]] proto::Result<StagedRevision, WriteError> stage(
        const proto::SceneDocument& scene) const;
    /// stage() of revision `revision` of `id` that the caller encoded as KDRS
    /// (proto::encode_scene_file, e.g. from the base revision and the changed poses, so that no
    /// document is made for it): `bytes` are written as they are, and read back by read().
    [[nodiscard]] proto::Result<StagedRevision, WriteError> stage(
        const std::string& id, uint64_t revision, std::span<const std::byte> bytes) const;
    [[nodiscard]] proto::Result<bool, WriteError> commit(StagedRevision staged);
    /// Deletes the revisions of `id` older than the newest revisions_kept, `newest` being the
    /// newest (best effort: a file that cannot be removed stays until the next prune).
    void prune(const std::string& id, uint64_t newest) const;

    /// The newest revision of scene `id` (a directory listing); kMissing when there is no such
    /// scene.
    [[nodiscard]] proto::Result<uint64_t, SceneStoreError> latest(const std::string& id) const;
    /// True when revision `revision` of `id` is on disk (one stat).
    [[nodiscard]] bool has_revision(const std::string& id, uint64_t revision) const;
    /// Reads and decodes one revision, checking that it names `id` and `revision`.
    [[nodiscard]] proto::Result<proto::SceneDocument, SceneStoreError> read(
        const std::string& id, uint64_t revision) const;

    /// Every scene id in scenes/, sorted (a directory listing; reads no revision).
    [[nodiscard]] proto::Result<std::vector<std::string>, std::string> ids() const;

    /// What remove() did.
    struct Removal {
        enum class Outcome {
            kRemoved,  ///< the scene and all its revisions are gone
            kMissing,  ///< there was no such scene
            kStale,    ///< `if_revision` was not the current revision: nothing was deleted
        };
        Outcome outcome = Outcome::kMissing;
        uint64_t current = 0;  ///< kStale: the current revision
    };
    /// Deletes the scene with all its revisions; with `if_revision`, only when that is its
    /// current revision at the moment of the deletion (no commit can come in between, in this
    /// process or another sharing the store).
    [[nodiscard]] proto::Result<Removal, WriteError> remove(
        const std::string& id, std::optional<uint64_t> if_revision = std::nullopt);

    /// Bytes of the scene's revision files.
    [[nodiscard]] uint64_t disk_bytes(const std::string& id) const;

    [[nodiscard]] std::filesystem::path scene_dir(const std::string& id) const {
        return scenes_dir_ / id;
    }
    [[nodiscard]] std::filesystem::path revision_path(const std::string& id,
                                                      uint64_t revision) const;
    [[nodiscard]] uint32_t revisions_kept() const noexcept { return revisions_kept_; }

private:
    /// The revisions of `id` on disk, ascending; kMissing for no such scene directory.
    [[nodiscard]] proto::Result<std::vector<uint64_t>, SceneStoreError> revisions(
        const std::string& id) const;

    std::filesystem::path scenes_dir_, tmp_dir_;
    uint32_t revisions_kept_;
};

}  // namespace kdrt::server
