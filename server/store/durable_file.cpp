#include "store/durable_file.h"

#include <fcntl.h>
#include <sys/mman.h>
#include <unistd.h>

#include <atomic>
#include <cerrno>
#include <system_error>

namespace kdrt::server {
namespace {

WriteError os_error(const std::string& what, const std::filesystem::path& path, int err) {
    return WriteError{what + " \"" + path.string() + "\": " + std::generic_category().message(err),
                      err == ENOSPC || err == EDQUOT || err == EFBIG};
}

}  // namespace

namespace {

/// Writes and flushes `bytes` to a fresh temp file in `tmp_dir`; returns its path. `data_only`:
/// fdatasync (the data and the size), else fsync.
proto::Result<std::filesystem::path, WriteError> write_temp(const std::filesystem::path& path,
                                                            const std::filesystem::path& tmp_dir,
                                                            std::span<const std::byte> bytes,
                                                            bool data_only = false) {
    static std::atomic<uint64_t> counter{0};
    const std::filesystem::path tmp =
        tmp_dir / (path.filename().string() + "." + std::to_string(::getpid()) + "." +
                   std::to_string(counter.fetch_add(1)) + ".tmp");
    const int fd = ::open(tmp.c_str(), O_WRONLY | O_CREAT | O_EXCL | O_CLOEXEC, 0644);
    if (fd < 0) return proto::Err{os_error("cannot create", tmp, errno)};
    const auto fail =
        [&](const std::string& what) -> proto::Result<std::filesystem::path, WriteError> {
        const int err = errno;
        ::close(fd);
        ::unlink(tmp.c_str());
        return proto::Err{os_error(what, tmp, err)};
    };
    size_t done = 0;
    while (done < bytes.size()) {
        const ssize_t n = ::write(fd, bytes.data() + done, bytes.size() - done);
        if (n < 0) {
            if (errno == EINTR) continue;
            return fail("cannot write");
        }
        done += static_cast<size_t>(n);
    }
    if ((data_only ? ::fdatasync(fd) : ::fsync(fd)) != 0)
        return fail(data_only ? "cannot fdatasync" : "cannot fsync");
    if (::close(fd) != 0) {
        const int err = errno;
        ::unlink(tmp.c_str());
        return proto::Err{os_error("cannot close", tmp, err)};
    }
    return tmp;
}

}  // namespace

proto::Result<void, WriteError> write_file_durably(const std::filesystem::path& path,
                                                   const std::filesystem::path& tmp_dir,
                                                   std::span<const std::byte> bytes) {
    auto tmp = write_temp(path, tmp_dir, bytes);
    if (!tmp) return proto::Err{std::move(tmp).error()};
    if (::rename(tmp->c_str(), path.c_str()) != 0) {
        const int err = errno;
        ::unlink(tmp->c_str());
        return proto::Err{os_error("cannot rename into", path, err)};
    }
    return {};
}

proto::Result<bool, WriteError> write_file_once(const std::filesystem::path& path,
                                                const std::filesystem::path& tmp_dir,
                                                std::span<const std::byte> bytes) {
    std::error_code ec;
    if (std::filesystem::exists(path, ec)) return false;  // already there: nothing to write
    auto staged = stage_file(path, tmp_dir, bytes);
    if (!staged) return proto::Err{std::move(staged).error()};
    return publish_once(std::move(staged).value(), path);
}

StagedFile& StagedFile::operator=(StagedFile&& other) noexcept {
    if (this != &other) {
        if (!tmp_.empty()) ::unlink(tmp_.c_str());
        tmp_ = std::exchange(other.tmp_, {});
    }
    return *this;
}

StagedFile::~StagedFile() {
    if (!tmp_.empty()) ::unlink(tmp_.c_str());
}

proto::Result<StagedFile, WriteError> stage_file(const std::filesystem::path& path,
                                                 const std::filesystem::path& tmp_dir,
                                                 std::span<const std::byte> bytes) {
    auto tmp = write_temp(path, tmp_dir, bytes, true);
    if (!tmp) return proto::Err{std::move(tmp).error()};
    return StagedFile(std::move(tmp).value());
}

proto::Result<bool, WriteError> publish_once(StagedFile staged, const std::filesystem::path& path) {
    const std::filesystem::path& tmp = staged.tmp_path();  // unlinked when `staged` goes
    if (::link(tmp.c_str(), path.c_str()) == 0) return true;
    const int err = errno;
    if (err == EEXIST) return false;
    if (err != EPERM && err != EOPNOTSUPP && err != ENOSYS)
        return proto::Err{os_error("cannot link into", path, err)};
    // No hard links on this file system: an existence check, then the rename (a narrow race in
    // which an equal file may be replaced by an equal one; a scene's flock closes it there).
    std::error_code ec;
    if (std::filesystem::exists(path, ec)) return false;
    if (::rename(tmp.c_str(), path.c_str()) != 0)
        return proto::Err{os_error("cannot rename into", path, errno)};
    staged.release();  // renamed: the temp name is gone
    return true;
}

proto::Result<void, WriteError> sync_directory(const std::filesystem::path& dir) {
    const int fd = ::open(dir.c_str(), O_RDONLY | O_DIRECTORY | O_CLOEXEC);
    if (fd < 0) return proto::Err{os_error("cannot open directory", dir, errno)};
    auto synced = sync_directory(fd, dir);
    ::close(fd);
    return synced;
}

proto::Result<void, WriteError> sync_directory(int fd, const std::filesystem::path& dir) {
    if (::fsync(fd) != 0) return proto::Err{os_error("cannot fsync directory", dir, errno)};
    return {};
}

MappedFile::MappedFile(MappedFile&& other) noexcept : data_(other.data_), size_(other.size_) {
    other.data_ = nullptr;
    other.size_ = 0;
}

MappedFile& MappedFile::operator=(MappedFile&& other) noexcept {
    if (this != &other) {
        this->~MappedFile();
        data_ = other.data_;
        size_ = other.size_;
        other.data_ = nullptr;
        other.size_ = 0;
    }
    return *this;
}

MappedFile::~MappedFile() {
    if (data_) ::munmap(const_cast<std::byte*>(data_), size_);
}

proto::Result<MappedFile, std::string> MappedFile::map(int fd, size_t size) {
    MappedFile m;
    if (size == 0) return m;
    void* p = ::mmap(nullptr, size, PROT_READ, MAP_PRIVATE, fd, 0);
    if (p == MAP_FAILED)
        return proto::Err{"cannot map " + std::to_string(size) +
                          " bytes: " + std::generic_category().message(errno)};
    ::madvise(p, size, MADV_SEQUENTIAL);
    m.data_ = static_cast<const std::byte*>(p);
    m.size_ = size;
    return m;
}

}  // namespace kdrt::server
