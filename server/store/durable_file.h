#pragma once
/// Crash-safe file replacement and read-only file mappings (POSIX).

#include <cstddef>
#include <filesystem>
#include <span>
#include <string>
#include <utility>

#include "kdrt/proto/result.h"

namespace kdrt::server {

/// A failed write: the message names the path and the OS reason; `no_space` is set when the
/// file system is full or a size limit refused the write (ENOSPC, EDQUOT, EFBIG).
struct WriteError {
    std::string message;
    bool no_space = false;
};

/// Writes `bytes` to a new file in `tmp_dir`, fsyncs it and renames it over `path` (same file
/// system). When the call returns success the content is durable once the directory holding
/// `path` is synced (sync_directory). On failure the temp file is removed and the error names
/// the path and the OS reason.
[[nodiscard]] proto::Result<void, WriteError> write_file_durably(
    const std::filesystem::path& path, const std::filesystem::path& tmp_dir,
    std::span<const std::byte> bytes);

/// Like write_file_durably, but never replaces an existing `path`: the temp file is hard-linked
/// to `path` (atomic, fails if it exists) and then unlinked. For content-addressed files that
/// several processes sharing one directory may write at once: the first one in wins, the others'
/// (equal) content is discarded. Returns true when this call created `path`, false when it was
/// already there. Where the file system has no hard links it falls back to rename() after an
/// existence check (a narrow race in which an equal file may be replaced by an equal one).
[[nodiscard]] proto::Result<bool, WriteError> write_file_once(const std::filesystem::path& path,
                                                              const std::filesystem::path& tmp_dir,
                                                              std::span<const std::byte> bytes);

/// write_file_once in two steps, so that a caller can do other work between them: stage_file
/// writes `bytes` to a new temp file in `tmp_dir` and flushes it (fdatasync: the data and the
/// size, which is all a reader needs of a file that is never changed again); publish_once then
/// links it to its name unless that exists. Until then nothing is visible outside tmp_dir. The
/// temp file is removed when the StagedFile is destroyed. Move-only.
class StagedFile {
public:
    StagedFile() = default;
    explicit StagedFile(std::filesystem::path tmp) : tmp_(std::move(tmp)) {}
    StagedFile(StagedFile&& other) noexcept : tmp_(std::exchange(other.tmp_, {})) {}
    StagedFile& operator=(StagedFile&& other) noexcept;
    StagedFile(const StagedFile&) = delete;
    StagedFile& operator=(const StagedFile&) = delete;
    ~StagedFile();

    [[nodiscard]] const std::filesystem::path& tmp_path() const noexcept { return tmp_; }
    /// Forgets the temp name (it was renamed away): nothing is removed.
    void release() noexcept { tmp_.clear(); }

private:
    std::filesystem::path tmp_;
};

/// Writes and flushes `bytes` to a temp file in `tmp_dir` named after `path`.
[[nodiscard]] proto::Result<StagedFile, WriteError> stage_file(const std::filesystem::path& path,
                                                               const std::filesystem::path& tmp_dir,
                                                               std::span<const std::byte> bytes);
/// Links the staged file to `path` as write_file_once does (true: created; false: `path` was
/// there already) and removes the temp name. The content is durable once the directory holding
/// `path` is synced.
[[nodiscard]] proto::Result<bool, WriteError> publish_once(StagedFile staged,
                                                           const std::filesystem::path& path);

/// fsync of a directory, making renames and unlinks in it durable.
[[nodiscard]] proto::Result<void, WriteError> sync_directory(const std::filesystem::path& dir);
/// The same through an open descriptor of it (`dir` names it in an error).
[[nodiscard]] proto::Result<void, WriteError> sync_directory(int fd,
                                                             const std::filesystem::path& dir);

/// A whole file mapped read-only (empty files give an empty span). Move-only.
class MappedFile {
public:
    MappedFile() = default;
    MappedFile(MappedFile&& other) noexcept;
    MappedFile& operator=(MappedFile&& other) noexcept;
    MappedFile(const MappedFile&) = delete;
    MappedFile& operator=(const MappedFile&) = delete;
    ~MappedFile();

    /// Maps the open descriptor `fd` (not closed by this class) of `size` bytes.
    [[nodiscard]] static proto::Result<MappedFile, std::string> map(int fd, size_t size);

    [[nodiscard]] std::span<const std::byte> bytes() const noexcept { return {data_, size_}; }

private:
    const std::byte* data_ = nullptr;
    size_t size_ = 0;
};

}  // namespace kdrt::server
