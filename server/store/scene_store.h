#pragma once
/// Durable storage of scenes under the cache directory:
///
///   scenes/<id>/revisions.kdrs    the scene's revision log: its revisions as KDRS records
///                                 (proto::encode_scene_file) back to back, oldest first, each
///                                 numbered one more than the one before (FORMATS.md "Scene
///                                 revision log").
///
/// The current revision is the last whole record; zeros may follow the records. A commit writes
/// one record where the last one ends, over those zeros when they hold it (the file keeps its
/// size, so the flush writes only data), else followed by kPaddingBytes of new zeros (the file
/// grows), and flushes it with a single fdatasync before the caller acknowledges it (unless
/// set_flush_commits(false): then no flush, and a power loss may drop the newest), holding an
/// exclusive flock on the scene's directory that every process sharing the store takes: under
/// it the commit compares its revision with the log's last (the compare-and-set of optimistic
/// concurrency: of two writers, threads or replicas, that both read revision N and write N + 1,
/// exactly one succeeds and the other learns it is stale). A record is read only when it is
/// whole: its header gives its size, and the checksums are checked from the last record back
/// until one matches, so after a crash or a power loss in the middle of an append the torn
/// record (without flushes, the torn records) is ignored by readers and cut off by the next
/// commit (reported through the notice callback). No acknowledged revision is lost,
/// and no reader sees a partly written one. A process that reloads its view of a log changed by
/// another one (a walk of the records' headers) takes the directory's flock shared, so it never
/// sees a record before it is durable.
///
/// The log keeps the newest `revisions_kept` revisions for pinned queries; older ones are no
/// longer served (kMissing) and are dropped when the log is compacted: a commit that finds
/// kCompactRecords such records (or kCompactBytes of them) writes the kept records and its own
/// into a new log under tmp_dir, flushes it, renames it over the old one and syncs the directory
/// (two flushes instead of one, once every kCompactRecords commits).
///
/// Stores written before the log keep one immutable file per revision,
///
///   scenes/<id>/<revision>.json   20 decimal digits, zero-padded; KDRS, or the scene JSON of
///                                 proto::encode_scene_json in stores older still,
///
/// the current revision being the highest-numbered file. Such a scene is read as it is; its next
/// commit moves its kept revisions into a new log (written, flushed and renamed in, under the
/// scene's lock), removes the files and reports it through the notice callback. A log, once
/// there, is the scene's only form: revision files beside it (left by an interrupted move) are
/// ignored and removed by the next compaction. Where the file system refuses flock (ENOLCK,
/// EOPNOTSUPP), which the log's compare-and-set needs, the store keeps the per-revision files
/// for every scene: a revision enters the directory only by a link of a complete, flushed file
/// that fails when the name exists (the commit and the compare-and-set at once), followed by an
/// fsync of the directory; prune() deletes the revisions older than the kept ones.
///
/// A scene is created whole: its directory and revision 1 are written under this process's tmp/
/// and renamed into scenes/ (atomic), so scenes/ never holds an empty or half-made scene. It is
/// deleted by renaming its directory into tmp/ (atomic: it disappears at once for every reader)
/// and then removing the files; an If-Match deletion compares the current revision under the
/// scene's lock, so a delete and a pose update that both name revision N cannot both succeed.
///
/// Thread-safe; any number of processes may share one store (each passes its own tmp_dir, the
/// MeshStore's locked tmp/<process>/). What this process knows of each log (its records'
/// revisions and offsets) is cached and checked against one stat of the log per request.

#include <cstddef>
#include <cstdint>
#include <filesystem>
#include <functional>
#include <memory>
#include <mutex>
#include <optional>
#include <span>
#include <string>
#include <unordered_map>
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

    /// Creates scenes/ when missing, and finds whether its file system takes flock (the log
    /// needs it; uses_log()).
    [[nodiscard]] proto::Result<void, std::string> open();

    /// True when scenes are kept in revision logs; false where the file system refuses flock
    /// (per-revision files). Set by open().
    [[nodiscard]] bool uses_log() const noexcept { return uses_log_; }
    /// Forces the per-revision files (tests; as a file system without flock would).
    void use_revision_files() noexcept { uses_log_ = false; }

    /// Whether a commit to a log flushes its record (fdatasync) before it returns (the default,
    /// config scene_sync "commit"): an acknowledged revision survives a power loss. Without
    /// (scene_sync "none") it is in the page cache when acknowledged: it survives the server
    /// being killed or crashing, and a power loss may drop the newest revisions (the log stays
    /// valid: its torn end is ignored and cut off). Creation, compaction and deletion flush
    /// either way. Set before use.
    void set_flush_commits(bool flush) noexcept { flush_commits_ = flush; }

    /// Called (from the thread that did it) when the store repairs or converts a scene: a torn
    /// record cut off the end of a log, revision files moved into a log. `scene` is the id,
    /// `what` says what was done. Set before use; not thread-safe to change.
    using Notice = std::function<void(const std::string& scene, const std::string& what)>;
    void set_notice(Notice notice) { notice_ = std::move(notice); }

    /// The scenes still in per-revision files (each moved into a log on its next commit when
    /// uses_log()); one stat per scene.
    [[nodiscard]] size_t revision_file_scenes() const;

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
    /// encodes `scene` (with per-revision files: also writes it durably under tmp_dir, nothing
    /// visible, removed when the StagedRevision goes unused); commit(staged) appends it to the
    /// log and flushes it (or links the file in and syncs the directory), under the scene's
    /// lock, with commit()'s answers.
    struct StagedRevision {
        std::string id;
        uint64_t revision = 0;
        std::vector<std::byte> bytes;  ///< the KDRS (the log's record)
        StagedFile file;               ///< per-revision files only
    };
    [[nodiscard]] proto::Result<StagedRevision, WriteError> stage(
        const proto::SceneDocument& scene) const;
    /// stage() of revision `revision` of `id` that the caller encoded as KDRS
    /// (proto::encode_scene_file, e.g. from the base revision and the changed poses, so that no
    /// document is made for it): `bytes` are written as they are, and read back by read().
    [[nodiscard]] proto::Result<StagedRevision, WriteError> stage(
        const std::string& id, uint64_t revision, std::vector<std::byte> bytes) const;
    [[nodiscard]] proto::Result<bool, WriteError> commit(StagedRevision staged);
    /// Per-revision files: deletes the revisions of `id` older than the newest revisions_kept,
    /// `newest` being the newest (best effort: a file that cannot be removed stays until the
    /// next prune). Nothing for a scene in a log (compacted by its commits).
    void prune(const std::string& id, uint64_t newest) const;

    /// The newest revision of scene `id` (a directory listing); kMissing when there is no such
    /// scene.
    [[nodiscard]] proto::Result<uint64_t, SceneStoreError> latest(const std::string& id) const;
    /// True when revision `revision` of `id` is stored and kept (one stat).
    [[nodiscard]] bool has_revision(const std::string& id, uint64_t revision) const;
    /// True when `revision` is the current revision of `id` (one or two stats).
    [[nodiscard]] bool is_current(const std::string& id, uint64_t revision) const;
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

    /// Bytes of the scene's files (its log, or its revision files).
    [[nodiscard]] uint64_t disk_bytes(const std::string& id) const;

    [[nodiscard]] std::filesystem::path scene_dir(const std::string& id) const {
        return scenes_dir_ / id;
    }
    /// The per-revision file of `revision` (stores written before the log).
    [[nodiscard]] std::filesystem::path revision_path(const std::string& id,
                                                      uint64_t revision) const;
    [[nodiscard]] std::filesystem::path log_path(const std::string& id) const;
    [[nodiscard]] uint32_t revisions_kept() const noexcept { return revisions_kept_; }

    /// A log compacts when it holds this many revisions older than the kept ones ...
    static constexpr size_t kCompactRecords = 64;
    /// ... or this many bytes of them.
    static constexpr uint64_t kCompactBytes = 64ull << 20;
    /// The zeros a log keeps after its records for the next commits (at least this many, or
    /// kPaddingRecords of the record that grew it, in whole 4 KiB pages): a record written over
    /// zeros already on the disk changes no metadata, so its flush writes only its data (an
    /// append also commits the file's new size and blocks through the file system's journal).
    static constexpr uint64_t kPaddingBytes = 1ull << 20;
    static constexpr uint64_t kPaddingRecords = 8;

private:
    /// What this process knows of one log: the file it read (device, inode, size, times), its
    /// whole records in order and where the last one ends (a torn record may follow it).
    struct LogIndex {
        struct Record {
            uint64_t revision = 0;
            uint64_t offset = 0;
            uint64_t size = 0;
        };
        uint64_t dev = 0, ino = 0, size = 0;
        int64_t mtime_ns = 0, ctime_ns = 0;
        std::vector<Record> records;
        uint64_t end = 0;
        /// True when the bytes from `end` to `size` are known to be zeros (this process wrote
        /// them, or a commit read them): the next record is written there in place.
        bool zero_tail = false;
        [[nodiscard]] uint64_t latest() const noexcept {
            return records.empty() ? 0 : records.back().revision;
        }
        [[nodiscard]] const Record* find(uint64_t revision) const noexcept;
    };
    using IndexPtr = std::shared_ptr<const LogIndex>;
    /// The log of `id` as it is now (one stat; a walk of its headers under a shared lock of the
    /// scene's directory when it changed since this process last read it). kMissing: no log
    /// (no such scene, or a scene in revision files: `revision_files` is set then).
    [[nodiscard]] proto::Result<IndexPtr, SceneStoreError> index(
        const std::string& id, bool* revision_files = nullptr) const;
    /// The log open as `fd` (a caller holding the scene's lock), from the cache or walked.
    [[nodiscard]] proto::Result<IndexPtr, SceneStoreError> index_of(const std::string& id,
                                                                    int fd) const;
    /// Reads one revision file (revision files' form).
    [[nodiscard]] proto::Result<proto::SceneDocument, SceneStoreError> read_revision_file(
        const std::string& id, uint64_t revision) const;
    /// Appends (or compacts into a new log) under the scene's lock; commit(staged)'s log form.
    [[nodiscard]] proto::Result<bool, WriteError> commit_to_log(StagedRevision& staged);
    /// Writes `records` (whole KDRS each) and then `last` as a new log of `id`, flushed and
    /// renamed in over any old one, the directory (open as `dir_fd`) synced.
    [[nodiscard]] proto::Result<IndexPtr, WriteError> write_log(
        const std::string& id, int dir_fd, const std::vector<std::vector<std::byte>>& records,
        std::span<const std::byte> last) const;
    void remember(const std::string& id, IndexPtr index) const;
    void forget(const std::string& id) const;
    void notice(const std::string& id, const std::string& what) const {
        if (notice_) notice_(id, what);
    }

    /// The revisions of `id` on disk, ascending; kMissing for no such scene directory.
    [[nodiscard]] proto::Result<std::vector<uint64_t>, SceneStoreError> revisions(
        const std::string& id) const;

    std::filesystem::path scenes_dir_, tmp_dir_;
    uint32_t revisions_kept_;
    bool uses_log_ = true;
    bool flush_commits_ = true;
    Notice notice_;
    /// The cached LogIndex of each log this process has read (behind a pointer: the store moves).
    struct Indexes {
        std::mutex mutex;
        std::unordered_map<std::string, IndexPtr> by_id;
    };
    std::unique_ptr<Indexes> indexes_ = std::make_unique<Indexes>();
};

}  // namespace kdrt::server
