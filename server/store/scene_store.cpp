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

WriteError os_error(const std::string& what, const fs::path& path, const std::error_code& ec) {
    const int err = ec.value();
    return WriteError{what + " \"" + path.string() + "\": " + ec.message(),
                      err == ENOSPC || err == EDQUOT || err == EFBIG};
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
    /// `create_file`: `dir` is a lock file, created when missing (the create lock).
    explicit SceneDirLock(const fs::path& dir, bool create_file = false) {
        fd_ = create_file ? ::open(dir.c_str(), O_RDONLY | O_CREAT | O_CLOEXEC, 0644)
                          : ::open(dir.c_str(), O_RDONLY | O_DIRECTORY | O_CLOEXEC);
        if (fd_ < 0) {
            error_ = errno;
            return;
        }
        int rc = 0;
        do {
            rc = ::flock(fd_, LOCK_EX);
        } while (rc != 0 && errno == EINTR);
        // A file system without flock: the link stays the compare-and-set (scene_store.h).
        if (rc != 0 && errno != ENOLCK && errno != EOPNOTSUPP && errno != EINVAL) {
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

}  // namespace

SceneStore::SceneStore(fs::path root, fs::path tmp_dir, uint32_t revisions_kept)
    : scenes_dir_(std::move(root) / "scenes"),
      tmp_dir_(std::move(tmp_dir)),
      revisions_kept_(std::max<uint32_t>(1, revisions_kept)) {}

proto::Result<void, std::string> SceneStore::open() {
    std::error_code ec;
    fs::create_directories(scenes_dir_, ec);
    if (ec) return proto::Err{"cannot create \"" + scenes_dir_.string() + "\": " + ec.message()};
    return {};
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
    const fs::path file = staging / revision_path(scene.id, scene.revision).filename();
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
    if (has_revision(scene.id, scene.revision) || !fs::exists(scene_dir(scene.id))) return false;
    auto staged = stage(scene);
    if (!staged) return proto::Err{std::move(staged).error()};
    return commit(std::move(staged).value());
}

proto::Result<SceneStore::StagedRevision, WriteError> SceneStore::stage(
    const proto::SceneDocument& scene) const {
    return stage(scene.id, scene.revision, proto::encode_scene_file(scene));
}

proto::Result<SceneStore::StagedRevision, WriteError> SceneStore::stage(
    const std::string& id, uint64_t revision, std::span<const std::byte> bytes) const {
    auto file = stage_file(revision_path(id, revision), tmp_dir_, bytes);
    if (!file) return proto::Err{std::move(file).error()};
    return StagedRevision{id, revision, std::move(file).value()};
}

proto::Result<bool, WriteError> SceneStore::commit(StagedRevision staged) {
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
    if (newest <= revisions_kept_) return;
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

proto::Result<uint64_t, SceneStoreError> SceneStore::latest(const std::string& id) const {
    auto all = revisions(id);
    if (!all) return proto::Err{std::move(all).error()};
    return all->back();
}

bool SceneStore::has_revision(const std::string& id, uint64_t revision) const {
    std::error_code ec;
    return fs::exists(revision_path(id, revision), ec);
}

proto::Result<proto::SceneDocument, SceneStoreError> SceneStore::read(const std::string& id,
                                                                      uint64_t revision) const {
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
        auto latest = revisions(id);
        if (!latest) {
            if (latest.error().code == SceneStoreError::Code::kMissing)
                return Removal{Outcome::kMissing};
            return proto::Err{WriteError{latest.error().detail}};
        }
        if (latest->back() != *if_revision) return Removal{Outcome::kStale, latest->back()};
    }
    const fs::path doomed = tmp_dir_ / ("deleted-scene-" + id);
    std::error_code ec;
    fs::remove_all(doomed, ec);
    fs::rename(dir, doomed, ec);
    if (ec) {
        if (ec == std::errc::no_such_file_or_directory) return Removal{Outcome::kMissing};
        return proto::Err{os_error("cannot delete", dir, ec)};
    }
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
