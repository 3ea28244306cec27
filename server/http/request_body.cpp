#include "http/request_body.h"

#include <fcntl.h>
#include <unistd.h>

#include <algorithm>
#include <cerrno>
#include <cstring>
#include <system_error>

namespace kdrt::server {

RequestBody::RequestBody(uint64_t max_bytes, uint64_t memory_bytes, std::filesystem::path spool_dir,
                         uint64_t expected_bytes, std::vector<std::byte> buffer)
    : max_bytes_(max_bytes),
      memory_bytes_(memory_bytes),
      spool_dir_(std::move(spool_dir)),
      memory_(std::move(buffer)) {
    memory_.clear();
    if (expected_bytes > 0 && expected_bytes <= std::min(max_bytes_, memory_bytes_))
        memory_.reserve(static_cast<size_t>(expected_bytes));
}

RequestBody::~RequestBody() {
    if (fd_ >= 0) ::close(fd_);
}

bool RequestBody::spill() {
    // O_TMPFILE: the file has no name, so nothing is left behind whatever happens to the process.
    fd_ = ::open(spool_dir_.c_str(), O_TMPFILE | O_RDWR | O_CLOEXEC, 0600);
    if (fd_ < 0) {
        // File systems without O_TMPFILE (older overlayfs): a named file, unlinked at once.
        std::string name = (spool_dir_ / "upload-XXXXXX").string();
        fd_ = ::mkostemp(name.data(), O_CLOEXEC);
        if (fd_ >= 0) ::unlink(name.c_str());
    }
    if (fd_ < 0) {
        error_ = "cannot create a spool file in \"" + spool_dir_.string() +
                 "\": " + std::generic_category().message(errno);
        return false;
    }
    const std::vector<std::byte> pending = std::move(memory_);
    memory_ = {};
    size_t done = 0;
    while (done < pending.size()) {
        const ssize_t n = ::write(fd_, pending.data() + done, pending.size() - done);
        if (n < 0 && errno == EINTR) continue;
        if (n < 0) {
            set_write_error(errno);
            return false;
        }
        done += static_cast<size_t>(n);
    }
    return true;
}

void RequestBody::set_write_error(int err) {
    error_ = "cannot write the spool file: " + std::generic_category().message(err);
    no_space_ = err == ENOSPC || err == EDQUOT || err == EFBIG;
}

bool RequestBody::append(const char* data, size_t size) {
    if (too_large_ || !error_.empty()) return false;
    if (size_ + size > max_bytes_) {
        too_large_ = true;
        return false;
    }
    if (fd_ < 0 && size_ + size > memory_bytes_ && !spill()) return false;
    if (fd_ >= 0) {
        size_t done = 0;
        while (done < size) {
            const ssize_t n = ::write(fd_, data + done, size - done);
            if (n < 0 && errno == EINTR) continue;
            if (n < 0) {
                set_write_error(errno);
                return false;
            }
            done += static_cast<size_t>(n);
        }
    } else {
        const auto* bytes = reinterpret_cast<const std::byte*>(data);
        memory_.insert(memory_.end(), bytes, bytes + size);
    }
    size_ += size;
    return true;
}

proto::Result<void, std::string> RequestBody::finish() {
    if (!error_.empty()) return proto::Err{error_};
    if (fd_ < 0) return {};
    auto mapped = MappedFile::map(fd_, static_cast<size_t>(size_));
    if (!mapped) return proto::Err{"cannot map the spool file: " + mapped.error()};
    mapping_ = std::move(*mapped);
    return {};
}

std::span<const std::byte> RequestBody::bytes() const noexcept {
    return fd_ >= 0 ? mapping_.bytes() : std::span<const std::byte>(memory_);
}

}  // namespace kdrt::server
