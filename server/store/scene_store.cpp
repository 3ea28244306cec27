#include "store/scene_store.h"

#include <fcntl.h>
#include <sys/file.h>
#include <sys/stat.h>
#include <unistd.h>

#include <algorithm>
#include <cerrno>
#include <cstdint>
#include <cstdio>
#include <random>
#include <system_error>

#include "kdrt/proto/file_io.h"

namespace kdrt::server {
namespace fs = std::filesystem;

namespace {

constexpr size_t kRevisionDigits = 20;
/// scenes/.create-lock: flocked by create() around the count and the rename.
constexpr const char* kCreateLockName = ".create-lock";
/// scenes/<id>/revisions.kdrs: the scene's revision log.
constexpr const char* kLogName = "revisions.kdrs";

bool flock_unsupported(int err) { return err == ENOLCK || err == EOPNOTSUPP || err == EINVAL; }

/// The file system is full or a size limit refused a write.
bool no_space(int err) { return err == ENOSPC || err == EDQUOT || err == EFBIG; }

WriteError os_error(const std::string& what, const fs::path& path, const std::error_code& ec) {
    const int err = ec.value();
    return WriteError{what + " \"" + path.string() + "\": " + ec.message(), no_space(err)};
}

/// The revision number of a file name "<20 digits>.json"; nullopt for any other name.
std::optional<uint64_t> revision_of(const std::string& name) {
    if (name.size() != kRevisionDigits + 5 || name.substr(kRevisionDigits) != ".json")
        return std::nullopt;
    uint64_t value = 0;
    for (size_t i = 0; i < kRevisionDigits; ++i) {
        const char c = name[i];
        if (c < '0' || c > '9') return std::nullopt;
        if (value > (UINT64_MAX - static_cast<uint64_t>(c - '0')) / 10) return std::nullopt;
        value = value * 10 + static_cast<uint64_t>(c - '0');
    }
    return value == 0 ? std::nullopt : std::optional<uint64_t>(value);
}

SceneStoreError damaged(const fs::path& path, const std::string& why) {
    std::string detail = "\"";
    detail += path.string();
    detail += "\" is damaged: ";
    detail += why;
    return SceneStoreError{SceneStoreError::Code::kCorrupt, std::move(detail)};
}

/// An exclusive flock on a scene's directory (released when destroyed). Every process sharing
/// the store takes it before changing an existing scene, so a commit, an If-Match comparison
/// and a deletion of one scene never interleave. The lock is taken on the directory that was
/// at `dir` when it was opened; a deletion renames that directory away while holding the lock,
/// so after locking, the directory is checked to still be the one at `dir`.
class SceneDirLock {
public:
    /// `create_file`: `dir` is a lock file, created when missing (the create lock). `shared`:
    /// a shared lock (a reader that must not see a commit in progress).
    explicit SceneDirLock(const fs::path& dir, bool create_file = false, bool shared = false) {
        fd_ = create_file ? ::open(dir.c_str(), O_RDONLY | O_CREAT | O_CLOEXEC, 0644)
                          : ::open(dir.c_str(), O_RDONLY | O_DIRECTORY | O_CLOEXEC);
        if (fd_ < 0) {
            error_ = errno;
            return;
        }
        int rc = 0;
        do {
            rc = ::flock(fd_, shared ? LOCK_SH : LOCK_EX);
        } while (rc != 0 && errno == EINTR);
        // A file system without flock: the store uses revision files there, whose link is the
        // compare-and-set (scene_store.h).
        if (rc != 0 && !flock_unsupported(errno)) {
            error_ = errno;
            return;
        }
        struct stat held {};
        struct stat now {};
        if (::fstat(fd_, &held) != 0 || ::stat(dir.c_str(), &now) != 0 ||
            held.st_dev != now.st_dev || held.st_ino != now.st_ino)
            error_ = ENOENT;  // deleted (renamed away) while this waited for the lock
    }
    ~SceneDirLock() {
        if (fd_ >= 0) ::close(fd_);
    }
    SceneDirLock(const SceneDirLock&) = delete;
    SceneDirLock& operator=(const SceneDirLock&) = delete;

    /// The open directory (valid when error() is 0).
    [[nodiscard]] int fd() const noexcept { return fd_; }
    /// 0 when held; ENOENT or ENOTDIR when the scene is not (or no longer) there.
    [[nodiscard]] int error() const noexcept { return error_; }
    [[nodiscard]] bool missing() const noexcept { return error_ == ENOENT || error_ == ENOTDIR; }

private:
    int fd_ = -1;
    int error_ = 0;
};

/// Reads exactly `n` bytes at `offset`. False on an error (errno set) or a short read (errno 0).
bool read_at(int fd, std::byte* out, size_t n, uint64_t offset) {
    size_t done = 0;
    while (done < n) {
        const ssize_t r = ::pread(fd, out + done, n - done, static_cast<off_t>(offset + done));
        if (r < 0) {
            if (errno == EINTR) continue;
            return false;
        }
        if (r == 0) {
            errno = 0;
            return false;
        }
        done += static_cast<size_t>(r);
    }
    return true;
}

/// Writes all of `bytes` at `offset`; false (errno set) on an error.
bool write_at(int fd, std::span<const std::byte> bytes, uint64_t offset) {
    size_t done = 0;
    while (done < bytes.size()) {
        const ssize_t w = ::pwrite(fd, bytes.data() + done, bytes.size() - done,
                                   static_cast<off_t>(offset + done));
        if (w < 0) {
            if (errno == EINTR) continue;
            return false;
        }
        done += static_cast<size_t>(w);
    }
    return true;
}

int64_t nanoseconds(const struct timespec& t) {
    return static_cast<int64_t>(t.tv_sec) * 1'000'000'000 + t.tv_nsec;
}

/// Closes a descriptor when it goes.
struct FdCloser {
    int fd = -1;
    ~FdCloser() {
        if (fd >= 0) ::close(fd);
    }
};

SceneStoreError io_error(const std::string& what, const fs::path& path, int err) {
    return SceneStoreError{SceneStoreError::Code::kIo, what + " \"" + path.string() + "\": " +
                                                           std::generic_category().message(err)};
}

}  // namespace

SceneStore::SceneStore(fs::path root, fs::path tmp_dir, uint32_t revisions_kept)
    : scenes_dir_(std::move(root) / "scenes"),
      tmp_dir_(std::move(tmp_dir)),
      revisions_kept_(std::max<uint32_t>(1, revisions_kept)) {}

proto::Result<void, std::string> SceneStore::open() {
    std::error_code ec;
    fs::create_directories(scenes_dir_, ec);
    if (ec) return proto::Err{"cannot create \"" + scenes_dir_.string() + "\": " + ec.message()};
    // The log's compare-and-set is its flock: without flock, revision files (linked, not
    // appended) stay the form of every scene.
    const fs::path lock_path = scenes_dir_ / kCreateLockName;
    const int fd = ::open(lock_path.c_str(), O_RDONLY | O_CREAT | O_CLOEXEC, 0644);
    if (fd < 0)
        return proto::Err{"cannot open \"" + lock_path.string() +
                          "\": " + std::generic_category().message(errno)};
    int rc = 0;
    do {
        rc = ::flock(fd, LOCK_SH);
    } while (rc != 0 && errno == EINTR);
    const int err = rc == 0 ? 0 : errno;
    ::close(fd);
    if (err != 0 && !flock_unsupported(err))
        return proto::Err{"cannot lock \"" + lock_path.string() +
                          "\": " + std::generic_category().message(err)};
    if (err != 0) uses_log_ = false;
    return {};
}

size_t SceneStore::revision_file_scenes() const {
    size_t n = 0;
    if (auto all = ids()) {
        std::error_code ec;
        for (const std::string& id : *all) n += !fs::exists(log_path(id), ec) && !ec;
    }
    return n;
}

fs::path SceneStore::log_path(const std::string& id) const { return scene_dir(id) / kLogName; }

const SceneStore::LogIndex::Record* SceneStore::LogIndex::find(uint64_t revision) const noexcept {
    // Consecutive revisions: the record's place follows from the first one's.
    if (records.empty() || revision < records.front().revision || revision > latest())
        return nullptr;
    return &records[revision - records.front().revision];
}

std::string SceneStore::new_id() {
    std::random_device device;
    std::string id;
    id.reserve(proto::kSceneIdLength);
    static constexpr char kHex[] = "0123456789abcdef";
    for (size_t i = 0; i < proto::kSceneIdLength / 8; ++i) {
        const uint32_t word = device();
        for (int k = 0; k < 8; ++k) id.push_back(kHex[(word >> (4 * k)) & 0xF]);
    }
    return id;
}

fs::path SceneStore::revision_path(const std::string& id, uint64_t revision) const {
    char name[kRevisionDigits + 6];
    std::snprintf(name, sizeof name, "%020llu.json", static_cast<unsigned long long>(revision));
    return scene_dir(id) / name;
}

proto::Result<SceneStore::Creation, WriteError> SceneStore::create(
    const proto::SceneDocument& scene, size_t max_scenes) {
    // Build the whole scene directory in tmp/, then rename it into scenes/ (atomic).
    const fs::path staging = tmp_dir_ / ("scene-" + scene.id);
    std::error_code ec;
    fs::remove_all(staging, ec);
    fs::create_directory(staging, ec);
    if (ec) return proto::Err{os_error("cannot create", staging, ec)};
    const auto cleanup = [&] {
        std::error_code ignored;
        fs::remove_all(staging, ignored);
    };
    const std::vector<std::byte> bytes = proto::encode_scene_file(scene);
    const fs::path file =
        staging /
        (uses_log_ ? fs::path(kLogName) : revision_path(scene.id, scene.revision).filename());
    if (auto w = write_file_durably(file, tmp_dir_, bytes); !w) {
        cleanup();
        return proto::Err{std::move(w).error()};
    }
    if (auto s = sync_directory(staging); !s) {
        cleanup();
        return proto::Err{std::move(s).error()};
    }
    // The count and the rename under the store's create lock, which every process sharing the
    // store takes: concurrent creates (threads or replicas) never pass max_scenes.
    const fs::path lock_path = scenes_dir_ / kCreateLockName;
    const SceneDirLock lock(lock_path, true);
    if (lock.error() != 0) {
        cleanup();
        return proto::Err{os_error("cannot lock", lock_path,
                                   std::error_code(lock.error(), std::generic_category()))};
    }
    if (max_scenes != SIZE_MAX) {
        auto all = ids();
        if (!all) {
            cleanup();
            return proto::Err{WriteError{all.error()}};
        }
        if (all->size() >= max_scenes) {
            cleanup();
            return Creation{false, all->size()};
        }
    }
    fs::rename(staging, scene_dir(scene.id), ec);
    if (ec) {
        cleanup();
        return proto::Err{os_error("cannot rename into", scene_dir(scene.id), ec)};
    }
    if (auto s = sync_directory(scenes_dir_); !s) return proto::Err{std::move(s).error()};
    return Creation{true, 0};
}

proto::Result<bool, WriteError> SceneStore::commit(const proto::SceneDocument& scene) {
    // Stale or deleted already: nothing to write.
    std::error_code ec;
    if (has_revision(scene.id, scene.revision) || !fs::exists(scene_dir(scene.id), ec))
        return false;
    auto staged = stage(scene);
    if (!staged) return proto::Err{std::move(staged).error()};
    return commit(std::move(staged).value());
}

proto::Result<SceneStore::StagedRevision, WriteError> SceneStore::stage(
    const proto::SceneDocument& scene) const {
    return stage(scene.id, scene.revision, proto::encode_scene_file(scene));
}

proto::Result<SceneStore::StagedRevision, WriteError> SceneStore::stage(
    const std::string& id, uint64_t revision, std::vector<std::byte> bytes) const {
    // A log's record is written by the commit, under the scene's lock.
    if (uses_log_) return StagedRevision{id, revision, std::move(bytes), StagedFile()};
    auto file = stage_file(revision_path(id, revision), tmp_dir_, bytes);
    if (!file) return proto::Err{std::move(file).error()};
    return StagedRevision{id, revision, {}, std::move(file).value()};
}

proto::Result<bool, WriteError> SceneStore::commit(StagedRevision staged) {
    if (uses_log_) return commit_to_log(staged);
    const fs::path dir = scene_dir(staged.id);
    const SceneDirLock lock(dir);
    if (lock.missing()) return false;  // deleted
    if (lock.error() != 0)
        return proto::Err{
            os_error("cannot lock", dir, std::error_code(lock.error(), std::generic_category()))};
    // Held: the directory stays at `dir` (a deletion waits for the lock) until this returns.
    auto created = publish_once(std::move(staged.file), revision_path(staged.id, staged.revision));
    if (!created) return proto::Err{std::move(created).error()};
    if (!*created) return false;
    if (auto s = sync_directory(lock.fd(), dir); !s) return proto::Err{std::move(s).error()};
    return true;
}

void SceneStore::prune(const std::string& id, uint64_t newest) const {
    if (uses_log_ || newest <= revisions_kept_) return;  // a log compacts in its commits
    // No lock: the files removed are never written again, and a deletion of the scene meanwhile
    // only makes these removals miss.
    if (auto all = revisions(id)) {
        std::error_code ec;
        for (const uint64_t r : *all)
            if (r + revisions_kept_ <= newest) fs::remove(revision_path(id, r), ec);
    }
}

proto::Result<std::vector<uint64_t>, SceneStoreError> SceneStore::revisions(
    const std::string& id) const {
    std::vector<uint64_t> out;
    std::error_code ec;
    fs::directory_iterator it(scene_dir(id), ec);
    if (ec) {
        if (ec == std::errc::no_such_file_or_directory || ec == std::errc::not_a_directory)
            return proto::Err{SceneStoreError{SceneStoreError::Code::kMissing, "no scene " + id}};
        return proto::Err{
            SceneStoreError{SceneStoreError::Code::kIo,
                            "cannot list \"" + scene_dir(id).string() + "\": " + ec.message()}};
    }
    for (const auto& entry : it)
        if (const auto r = revision_of(entry.path().filename().string())) out.push_back(*r);
    std::sort(out.begin(), out.end());
    if (out.empty())  // a directory being deleted (its files removed first)
        return proto::Err{SceneStoreError{SceneStoreError::Code::kMissing, "no scene " + id}};
    return out;
}

namespace {

/// The records of the log open as `fd` (`st` its fstat): headers walked from the start while
/// each is whole, fits in the file and numbers one more than the one before; then the
/// checksums from the last record back, dropping each that fails until one matches. A record
/// torn by a crash in its append fails (and, without a flush a commit, so may the few before it
/// after a power loss): those were never flushed. A record before a matching one that fails is
/// damage, reported when it is read.
template <class Index>
proto::Result<Index, SceneStoreError> walk_log(int fd, const struct stat& st,
                                               const fs::path& path) {
    Index out;
    out.dev = static_cast<uint64_t>(st.st_dev);
    out.ino = static_cast<uint64_t>(st.st_ino);
    out.size = static_cast<uint64_t>(st.st_size);
    out.mtime_ns = nanoseconds(st.st_mtim);
    out.ctime_ns = nanoseconds(st.st_ctim);
    std::byte head[proto::kSceneFileHeaderBytes];
    for (uint64_t at = 0; at + sizeof head <= out.size;) {
        if (!read_at(fd, head, sizeof head, at)) {
            if (errno != 0) return proto::Err{io_error("cannot read", path, errno)};
            break;
        }
        const auto header = proto::read_scene_file_header(head);
        if (!header || header->size > out.size - at ||
            (!out.records.empty() && header->revision != out.records.back().revision + 1))
            break;
        out.records.push_back({header->revision, at, header->size});
        at += header->size;
    }
    std::vector<std::byte> bytes;
    while (!out.records.empty()) {
        const auto& last = out.records.back();
        bytes.resize(last.size);
        if (!read_at(fd, bytes.data(), bytes.size(), last.offset))
            return proto::Err{io_error("cannot read", path, errno != 0 ? errno : EIO)};
        if (proto::scene_file_checksum_matches(bytes)) break;
        out.records.pop_back();
    }
    out.end = out.records.empty() ? 0 : out.records.back().offset + out.records.back().size;
    return out;
}

template <class Index>
bool same_file(const Index& index, const struct stat& st) {
    return index.dev == static_cast<uint64_t>(st.st_dev) &&
           index.ino == static_cast<uint64_t>(st.st_ino) &&
           index.size == static_cast<uint64_t>(st.st_size) &&
           index.mtime_ns == nanoseconds(st.st_mtim) && index.ctime_ns == nanoseconds(st.st_ctim);
}

/// False when the log open as `fd` may hold a record after the ones `index` knows: a commit
/// (of any process) writes its record where the last known one ends, into the log's zeros
/// without changing its size, and a time stamp may not tell (on kernels before 6.13 it moves
/// once a clock tick), so the header there is read. A log without zeros after its records
/// grows with each commit: the size tells.
template <class Index>
bool nothing_after(int fd, const Index& index) {
    if (index.end >= index.size) return true;
    std::byte head[proto::kSceneFileHeaderBytes];
    if (index.end + sizeof head > index.size) return true;  // no room for a record
    if (!read_at(fd, head, sizeof head, index.end)) return false;
    const auto header = proto::read_scene_file_header(head);
    return !header || header->revision != index.latest() + 1;
}

/// The zeros written after a record of `record_bytes` that did not fit in a log's zeros.
uint64_t log_padding(uint64_t record_bytes) {
    const uint64_t want =
        std::max(SceneStore::kPaddingBytes, SceneStore::kPaddingRecords * record_bytes);
    return (want + 4095) / 4096 * 4096;
}

/// True when the `n` bytes of `fd` from `offset` are all zero (a read error: false).
bool zeros_at(int fd, uint64_t offset, uint64_t n) {
    std::vector<std::byte> bytes(std::min<uint64_t>(n, 1 << 20));
    for (uint64_t done = 0; done < n;) {
        const size_t step = static_cast<size_t>(std::min<uint64_t>(bytes.size(), n - done));
        if (!read_at(fd, bytes.data(), step, offset + done)) return false;
        for (size_t i = 0; i < step; ++i)
            if (bytes[i] != std::byte{0}) return false;
        done += step;
    }
    return true;
}

}  // namespace

void SceneStore::remember(const std::string& id, IndexPtr index) const {
    std::lock_guard lock(indexes_->mutex);
    indexes_->by_id[id] = std::move(index);
}

void SceneStore::forget(const std::string& id) const {
    std::lock_guard lock(indexes_->mutex);
    indexes_->by_id.erase(id);
}

proto::Result<SceneStore::IndexPtr, SceneStoreError> SceneStore::index_of(const std::string& id,
                                                                          int fd) const {
    const fs::path path = log_path(id);
    struct stat st {};
    if (::fstat(fd, &st) != 0) return proto::Err{io_error("cannot stat", path, errno)};
    IndexPtr cached;
    {
        std::lock_guard lock(indexes_->mutex);
        const auto it = indexes_->by_id.find(id);
        if (it != indexes_->by_id.end() && same_file(*it->second, st)) cached = it->second;
    }
    if (cached && nothing_after(fd, *cached)) return cached;
    auto walked = walk_log<LogIndex>(fd, st, path);
    if (!walked) return proto::Err{std::move(walked).error()};
    auto index = std::make_shared<const LogIndex>(std::move(walked).value());
    remember(id, index);
    return index;
}

proto::Result<SceneStore::IndexPtr, SceneStoreError> SceneStore::index(const std::string& id,
                                                                       bool* revision_files) const {
    if (revision_files) *revision_files = false;
    const fs::path path = log_path(id);
    const auto missing = [&]() -> proto::Result<IndexPtr, SceneStoreError> {
        forget(id);
        std::error_code ec;
        if (revision_files) *revision_files = fs::is_directory(scene_dir(id), ec);
        return proto::Err{SceneStoreError{SceneStoreError::Code::kMissing, "no scene " + id}};
    };
    struct stat st {};
    if (::stat(path.c_str(), &st) != 0) {
        if (errno == ENOENT || errno == ENOTDIR) return missing();
        return proto::Err{io_error("cannot stat", path, errno)};
    }
    {
        IndexPtr cached;
        {
            std::lock_guard lock(indexes_->mutex);
            const auto it = indexes_->by_id.find(id);
            if (it != indexes_->by_id.end() && same_file(*it->second, st)) cached = it->second;
        }
        if (cached && cached->end >= cached->size) return cached;
        if (cached) {  // zeros after its records: a commit there does not change the size
            const FdCloser probe{::open(path.c_str(), O_RDONLY | O_CLOEXEC)};
            if (probe.fd >= 0 && nothing_after(probe.fd, *cached)) return cached;
        }
    }
    // Changed since this process read it (another process committed, or it is new here): walked
    // under a shared lock of the directory, so that a commit in progress (its record appended
    // but not yet flushed) finishes first.
    const SceneDirLock lock(scene_dir(id), false, true);
    if (lock.missing()) return missing();
    if (lock.error() != 0) return proto::Err{io_error("cannot lock", scene_dir(id), lock.error())};
    const FdCloser fd{::open(path.c_str(), O_RDONLY | O_CLOEXEC)};
    if (fd.fd < 0) {
        if (errno == ENOENT) return missing();
        return proto::Err{io_error("cannot open", path, errno)};
    }
    return index_of(id, fd.fd);
}

proto::Result<uint64_t, SceneStoreError> SceneStore::latest(const std::string& id) const {
    bool files = false;
    auto log = index(id, &files);
    if (log) {
        if ((*log)->records.empty())
            return proto::Err{SceneStoreError{SceneStoreError::Code::kMissing, "no scene " + id}};
        return (*log)->latest();
    }
    if (!files) return proto::Err{std::move(log).error()};
    auto all = revisions(id);
    if (!all) return proto::Err{std::move(all).error()};
    return all->back();
}

bool SceneStore::has_revision(const std::string& id, uint64_t revision) const {
    bool files = false;
    auto log = index(id, &files);
    if (log) return (*log)->find(revision) && revision + revisions_kept_ > (*log)->latest();
    std::error_code ec;
    return files && fs::exists(revision_path(id, revision), ec);
}

bool SceneStore::is_current(const std::string& id, uint64_t revision) const {
    bool files = false;
    auto log = index(id, &files);
    if (log) return (*log)->latest() == revision;
    return files && has_revision(id, revision) && !has_revision(id, revision + 1);
}

proto::Result<proto::SceneDocument, SceneStoreError> SceneStore::read(const std::string& id,
                                                                      uint64_t revision) const {
    const auto no_revision = [&] {
        return proto::Err{
            SceneStoreError{SceneStoreError::Code::kMissing,
                            "no revision " + std::to_string(revision) + " of scene " + id}};
    };
    const fs::path path = log_path(id);
    // A compaction may rename a new log in between the index and the open: then again.
    for (int attempt = 0; attempt < 8; ++attempt) {
        bool files = false;
        auto log = index(id, &files);
        if (!log) {
            if (files) break;  // revision files
            if (log.error().code == SceneStoreError::Code::kMissing) return no_revision();
            return proto::Err{std::move(log).error()};
        }
        const LogIndex& in = **log;
        const LogIndex::Record* record = in.find(revision);
        if (!record || revision + revisions_kept_ <= in.latest()) return no_revision();
        const FdCloser fd{::open(path.c_str(), O_RDONLY | O_CLOEXEC)};
        struct stat st {};
        if (fd.fd < 0) {
            if (errno == ENOENT) return no_revision();
            return proto::Err{io_error("cannot open", path, errno)};
        }
        if (::fstat(fd.fd, &st) != 0) return proto::Err{io_error("cannot stat", path, errno)};
        if (static_cast<uint64_t>(st.st_ino) != in.ino ||
            static_cast<uint64_t>(st.st_dev) != in.dev)
            continue;
        std::vector<std::byte> bytes(record->size);
        if (!read_at(fd.fd, bytes.data(), bytes.size(), record->offset))
            return proto::Err{io_error("cannot read", path, errno != 0 ? errno : EIO)};
        auto doc = proto::decode_stored_scene(bytes);
        const std::string where = "revision " + std::to_string(revision) + " at offset " +
                                  std::to_string(record->offset) + ": ";
        if (!doc) return proto::Err{damaged(path, where + doc.error())};
        if (doc->id != id || doc->revision != revision)
            return proto::Err{damaged(path, where + "it holds revision " +
                                                std::to_string(doc->revision) + " of scene " +
                                                doc->id)};
        return std::move(doc).value();
    }
    return read_revision_file(id, revision);
}

proto::Result<proto::SceneDocument, SceneStoreError> SceneStore::read_revision_file(
    const std::string& id, uint64_t revision) const {
    const fs::path path = revision_path(id, revision);
    auto bytes = proto::read_file_bytes(path);
    if (!bytes) {
        std::error_code ec;
        const bool missing = !fs::exists(path, ec);
        return proto::Err{
            SceneStoreError{missing ? SceneStoreError::Code::kMissing : SceneStoreError::Code::kIo,
                            missing ? "no revision " + std::to_string(revision) + " of scene " + id
                                    : bytes.error()}};
    }
    // KDRS, or the JSON of a store written before KDRS; read without the instance limit: a
    // lower max_instances after a restart must not make an acknowledged scene unreadable.
    auto doc = proto::decode_stored_scene(*bytes);
    if (!doc) return proto::Err{damaged(path, doc.error())};
    if (doc->id != id || doc->revision != revision)
        return proto::Err{damaged(
            path, "it holds revision " + std::to_string(doc->revision) + " of scene " + doc->id)};
    return std::move(doc).value();
}

proto::Result<SceneStore::IndexPtr, WriteError> SceneStore::write_log(
    const std::string& id, int dir_fd, const std::vector<std::vector<std::byte>>& records,
    std::span<const std::byte> last) const {
    auto index = std::make_shared<LogIndex>();
    std::vector<std::byte> bytes;
    for (const auto& r : records) {
        index->records.push_back(
            {proto::read_scene_file_header(r)->revision, bytes.size(), r.size()});
        bytes.insert(bytes.end(), r.begin(), r.end());
    }
    index->records.push_back(
        {proto::read_scene_file_header(last)->revision, bytes.size(), last.size()});
    bytes.insert(bytes.end(), last.begin(), last.end());
    index->end = bytes.size();
    bytes.resize(bytes.size() + log_padding(last.size()));  // zeros for the next commits
    index->zero_tail = true;
    const fs::path path = log_path(id);
    auto w = write_file_durably(path, tmp_dir_, bytes);
    if (!w && w.error().no_space) {  // no room for the zeros: the records alone
        bytes.resize(index->end);
        w = write_file_durably(path, tmp_dir_, bytes);
    }
    if (!w) return proto::Err{w.error()};
    if (auto d = sync_directory(dir_fd, scene_dir(id)); !d) return proto::Err{d.error()};
    struct stat st {};
    if (::stat(path.c_str(), &st) == 0) {
        index->dev = static_cast<uint64_t>(st.st_dev);
        index->ino = static_cast<uint64_t>(st.st_ino);
        index->size = static_cast<uint64_t>(st.st_size);
        index->mtime_ns = nanoseconds(st.st_mtim);
        index->ctime_ns = nanoseconds(st.st_ctim);
    }
    return IndexPtr(std::move(index));
}

proto::Result<bool, WriteError> SceneStore::commit_to_log(StagedRevision& staged) {
    const std::string& id = staged.id;
    const fs::path dir = scene_dir(id), path = log_path(id);
    const auto os = [&](const std::string& what, const fs::path& where, int err) {
        return proto::Err{os_error(what, where, std::error_code(err, std::generic_category()))};
    };
    // The record must read back as this revision (a walk trusts its header): refused before
    // anything is written.
    if (const auto header = proto::read_scene_file_header(staged.bytes);
        !header || header->revision != staged.revision || header->size != staged.bytes.size())
        return proto::Err{WriteError{"revision " + std::to_string(staged.revision) + " of scene " +
                                     id + ": the staged bytes are not its KDRS"}};
    const SceneDirLock lock(dir);
    if (lock.missing()) return false;  // deleted
    if (lock.error() != 0) return os("cannot lock", dir, lock.error());
    // Held: the directory stays at `dir` (a deletion waits for the lock) until this returns, and
    // no other writer appends.
    const FdCloser fd{::open(path.c_str(), O_RDWR | O_CLOEXEC)};
    if (fd.fd < 0) {
        if (errno != ENOENT) return os("cannot open", path, errno);
        // A scene in revision files: its kept revisions and this one become its log.
        auto all = revisions(id);
        if (!all) {
            if (all.error().code == SceneStoreError::Code::kMissing) return false;
            return proto::Err{WriteError{all.error().detail}};
        }
        if (all->back() + 1 != staged.revision) return false;  // stale
        // The newest ones, consecutive and readable (a damaged file ends the run: the log's
        // revisions have no gaps).
        std::vector<std::vector<std::byte>> kept;
        for (auto r = all->rbegin(); r != all->rend(); ++r) {
            if (*r + revisions_kept_ <= staged.revision) break;
            if (r != all->rbegin() && *r + 1 != *(r - 1)) break;
            auto doc = read_revision_file(id, *r);
            if (!doc) break;
            kept.push_back(proto::encode_scene_file(*doc));
        }
        std::reverse(kept.begin(), kept.end());
        auto written = write_log(id, lock.fd(), kept, staged.bytes);
        if (!written) return proto::Err{std::move(written).error()};
        remember(id, std::move(written).value());
        std::error_code ec;
        for (const uint64_t r : *all) fs::remove(revision_path(id, r), ec);
        notice(id, "moved " + std::to_string(kept.size()) + " of its " +
                       std::to_string(all->size()) + " revision files into " + kLogName +
                       " (revisions before the newest " + std::to_string(revisions_kept_) +
                       " are not kept)");
        return true;
    }
    auto log = index_of(id, fd.fd);
    if (!log) return proto::Err{WriteError{log.error().detail}};
    const LogIndex& in = **log;
    if (in.latest() + 1 != staged.revision) return false;  // stale
    // Revisions that this commit leaves older than the kept ones: compacted away when many.
    size_t dead = 0;
    uint64_t dead_bytes = 0;
    for (const LogIndex::Record& r : in.records) {
        if (r.revision + revisions_kept_ > staged.revision) break;
        ++dead;
        dead_bytes += r.size;
    }
    if (dead >= kCompactRecords || (dead > 0 && dead_bytes >= kCompactBytes)) {
        std::vector<std::vector<std::byte>> kept;
        for (size_t k = dead; k < in.records.size(); ++k) {
            const LogIndex::Record& r = in.records[k];
            std::vector<std::byte> bytes(r.size);
            if (!read_at(fd.fd, bytes.data(), bytes.size(), r.offset))
                return os("cannot read", path, errno != 0 ? errno : EIO);
            kept.push_back(std::move(bytes));
        }
        auto written = write_log(id, lock.fd(), kept, staged.bytes);
        if (!written) return proto::Err{std::move(written).error()};
        remember(id, std::move(written).value());
        // Revision files left by an interrupted move into the log.
        std::error_code ec;
        for (const auto& entry : fs::directory_iterator(dir, ec))
            if (revision_of(entry.path().filename().string())) fs::remove(entry.path(), ec);
        return true;
    }
    // After the records: the zeros of earlier commits, or what a crash in the middle of a
    // commit left (a torn record, never acknowledged), which is cut off.
    uint64_t size = in.size;
    if (in.end < in.size && !in.zero_tail && !zeros_at(fd.fd, in.end, in.size - in.end)) {
        if (::ftruncate(fd.fd, static_cast<off_t>(in.end)) != 0)
            return os("cannot truncate", path, errno);
        notice(id, "cut a torn record of " + std::to_string(in.size - in.end) +
                       " bytes off the end of " + kLogName + " (never acknowledged)");
        size = in.end;
    }
    // The commit: one record written and one flush, or none. Over the zeros when they hold it
    // (only the data is flushed); else the record and new zeros after it (the flush commits the
    // size and blocks too, once for the next commits).
    const uint64_t end = in.end + staged.bytes.size();
    std::span<const std::byte> bytes = staged.bytes;
    std::vector<std::byte> grown;
    if (end > size) {
        grown.resize(staged.bytes.size() + log_padding(staged.bytes.size()));
        std::copy(staged.bytes.begin(), staged.bytes.end(), grown.begin());
        bytes = grown;
    }
    bool written = write_at(fd.fd, bytes, in.end);
    if (!written && !grown.empty() && no_space(errno)) {
        // No room for the zeros (a full file system, a file size limit): the record alone.
        written = ::ftruncate(fd.fd, static_cast<off_t>(in.end)) == 0 &&
                  write_at(fd.fd, staged.bytes, in.end);
    }
    if (!written || (flush_commits_ && ::fdatasync(fd.fd) != 0)) {
        const int err = errno;
        // Best effort: what was written is cut off again (else the next commit does it).
        if (::ftruncate(fd.fd, static_cast<off_t>(in.end)) == 0) (void)::fdatasync(fd.fd);
        forget(id);
        return os("cannot write to", path, err);
    }
    auto next = std::make_shared<LogIndex>(in);
    next->records.push_back({staged.revision, in.end, staged.bytes.size()});
    next->end = end;
    next->zero_tail = true;
    struct stat st {};
    if (::fstat(fd.fd, &st) == 0) {
        next->size = static_cast<uint64_t>(st.st_size);
        next->mtime_ns = nanoseconds(st.st_mtim);
        next->ctime_ns = nanoseconds(st.st_ctim);
        remember(id, std::move(next));
    } else {
        forget(id);
    }
    return true;
}

proto::Result<std::vector<std::string>, std::string> SceneStore::ids() const {
    std::vector<std::string> out;
    std::error_code ec;
    fs::directory_iterator it(scenes_dir_, ec);
    if (ec) return proto::Err{"cannot list \"" + scenes_dir_.string() + "\": " + ec.message()};
    for (const auto& entry : it) {
        const std::string name = entry.path().filename().string();
        if (proto::is_scene_id(name)) out.push_back(name);
    }
    std::sort(out.begin(), out.end());
    return out;
}

proto::Result<SceneStore::Removal, WriteError> SceneStore::remove(
    const std::string& id, std::optional<uint64_t> if_revision) {
    using Outcome = Removal::Outcome;
    const fs::path dir = scene_dir(id);
    const SceneDirLock lock(dir);
    if (lock.missing()) return Removal{Outcome::kMissing};
    if (lock.error() != 0)
        return proto::Err{
            os_error("cannot lock", dir, std::error_code(lock.error(), std::generic_category()))};
    if (if_revision) {
        // Held: no revision can be committed between this comparison and the rename.
        uint64_t current = 0;
        const FdCloser fd{::open(log_path(id).c_str(), O_RDONLY | O_CLOEXEC)};
        if (fd.fd >= 0) {
            auto log = index_of(id, fd.fd);
            if (!log) return proto::Err{WriteError{log.error().detail}};
            current = (*log)->latest();
        } else {
            auto latest = revisions(id);
            if (!latest) {
                if (latest.error().code == SceneStoreError::Code::kMissing)
                    return Removal{Outcome::kMissing};
                return proto::Err{WriteError{latest.error().detail}};
            }
            current = latest->back();
        }
        if (current != *if_revision) return Removal{Outcome::kStale, current};
    }
    const fs::path doomed = tmp_dir_ / ("deleted-scene-" + id);
    std::error_code ec;
    fs::remove_all(doomed, ec);
    fs::rename(dir, doomed, ec);
    if (ec) {
        if (ec == std::errc::no_such_file_or_directory) return Removal{Outcome::kMissing};
        return proto::Err{os_error("cannot delete", dir, ec)};
    }
    forget(id);
    if (auto s = sync_directory(scenes_dir_); !s) return proto::Err{std::move(s).error()};
    fs::remove_all(doomed, ec);  // best effort: a leftover is swept with tmp/ at start-up
    return Removal{Outcome::kRemoved};
}

uint64_t SceneStore::disk_bytes(const std::string& id) const {
    uint64_t total = 0;
    std::error_code ec;
    for (const auto& entry : fs::directory_iterator(scene_dir(id), ec)) {
        const auto size = entry.file_size(ec);
        if (!ec) total += size;
    }
    return total;
}

}  // namespace kdrt::server
