#include "kdrt/proto/file_io.h"

#include <fcntl.h>
#include <sys/stat.h>
#include <unistd.h>

#include <algorithm>
#include <cerrno>
#include <system_error>

namespace kdrt::proto {
namespace {

std::string os_reason(int err) { return std::generic_category().message(err); }

std::string quoted(const std::filesystem::path& path) {
    // Appended piecewise: GCC 12 warns (-Wrestrict, a false positive) on "\"" + str + "\"".
    std::string s(1, '"');
    s += path.string();
    s += '"';
    return s;
}

/// Closes the descriptor on every path out of a function.
class FileDescriptor {
public:
    explicit FileDescriptor(int fd) noexcept : fd_(fd) {}
    FileDescriptor(const FileDescriptor&) = delete;
    FileDescriptor& operator=(const FileDescriptor&) = delete;
    ~FileDescriptor() {
        if (fd_ >= 0) ::close(fd_);
    }
    [[nodiscard]] int get() const noexcept { return fd_; }
    /// Closes now and reports close()'s errno (0 on success); the destructor then does nothing.
    int close_checked() noexcept {
        const int rc = ::close(fd_);
        fd_ = -1;
        return rc == 0 ? 0 : errno;
    }

private:
    int fd_;
};

}  // namespace

Result<std::vector<std::byte>, std::string> read_file_bytes(const std::filesystem::path& path,
                                                            uint64_t max_bytes) {
    FileDescriptor fd(::open(path.c_str(), O_RDONLY | O_CLOEXEC));
    if (fd.get() < 0)
        return Err{"cannot open " + quoted(path) + " for reading: " + os_reason(errno)};
    struct stat st {};
    if (::fstat(fd.get(), &st) != 0)
        return Err{"cannot stat " + quoted(path) + ": " + os_reason(errno)};
    if (S_ISDIR(st.st_mode)) return Err{"cannot read " + quoted(path) + ": " + os_reason(EISDIR)};

    std::vector<std::byte> bytes;
    if (S_ISREG(st.st_mode)) {
        const auto size = static_cast<uint64_t>(st.st_size);
        if (size > max_bytes) {
            return Err{"cannot read " + quoted(path) + ": file has " + std::to_string(size) +
                       " bytes, limit is " + std::to_string(max_bytes)};
        }
        // One spare byte: reading it means the file grew, and the loop below carries on.
        bytes.resize(static_cast<size_t>(size) + 1);
    }
    // Read until EOF even for regular files: the size may change, and pipes have none.
    constexpr size_t kMinChunk = size_t{1} << 16;
    size_t used = 0;
    for (;;) {
        if (used == bytes.size()) bytes.resize(used + std::max(kMinChunk, used / 2));
        const ssize_t n = ::read(fd.get(), bytes.data() + used, bytes.size() - used);
        if (n < 0) {
            if (errno == EINTR) continue;
            return Err{"cannot read " + quoted(path) + ": " + os_reason(errno)};
        }
        if (n == 0) break;
        used += static_cast<size_t>(n);
        if (used > max_bytes) {
            return Err{"cannot read " + quoted(path) + ": more than " + std::to_string(max_bytes) +
                       " bytes (the limit)"};
        }
    }
    bytes.resize(used);
    return bytes;
}

Result<void, std::string> write_file_bytes(const std::filesystem::path& path,
                                           std::span<const std::byte> bytes) {
    FileDescriptor fd(::open(path.c_str(), O_WRONLY | O_CREAT | O_TRUNC | O_CLOEXEC, 0644));
    if (fd.get() < 0)
        return Err{"cannot open " + quoted(path) + " for writing: " + os_reason(errno)};
    size_t done = 0;
    while (done < bytes.size()) {
        const ssize_t n = ::write(fd.get(), bytes.data() + done, bytes.size() - done);
        if (n < 0) {
            if (errno == EINTR) continue;
            return Err{"cannot write " + quoted(path) + ": " + os_reason(errno)};
        }
        done += static_cast<size_t>(n);
    }
    if (const int err = fd.close_checked(); err != 0) {
        return Err{"cannot write " + quoted(path) + ": " + os_reason(err)};
    }
    return {};
}

}  // namespace kdrt::proto
