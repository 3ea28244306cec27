#pragma once
/// A request body received in chunks: kept in memory up to a threshold, then spooled to an
/// unlinked temp file and mapped, so a large upload is never held twice in memory (the parser
/// reads the page cache, the parsed mesh is the only anonymous copy). Enforces a size limit as
/// bytes arrive, whatever the Content-Length said (chunked bodies have none).

#include <cstddef>
#include <cstdint>
#include <filesystem>
#include <span>
#include <string>
#include <vector>

#include "kdrt/proto/result.h"
#include "store/durable_file.h"

namespace kdrt::server {

/// A refused body of known size up to this is read and dropped, so the keep-alive connection
/// stays usable and clients that only read the reply after sending everything see it (64 MiB
/// drain in ~30 ms on loopback); a larger or unsized one gets `Connection: close` instead.
inline constexpr uint64_t kDrainBodyBytes = uint64_t{64} << 20;

class RequestBody {
public:
    /// `max_bytes`: larger bodies are refused; `memory_bytes`: spool beyond this; `spool_dir`:
    /// where the temp file goes. `expected_bytes` (Content-Length, if known) pre-sizes the buffer.
    /// `buffer` (optional) is reused as the in-memory storage (its capacity is kept).
    RequestBody(uint64_t max_bytes, uint64_t memory_bytes, std::filesystem::path spool_dir,
                uint64_t expected_bytes = 0, std::vector<std::byte> buffer = {});
    RequestBody(const RequestBody&) = delete;
    RequestBody& operator=(const RequestBody&) = delete;
    ~RequestBody();

    /// Appends a chunk. False (and stays false) once the body exceeds max_bytes or a spool write
    /// fails; too_large()/error() tell which.
    bool append(const char* data, size_t size);

    /// Call after the last chunk; then bytes() is the whole body.
    [[nodiscard]] proto::Result<void, std::string> finish();
    [[nodiscard]] std::span<const std::byte> bytes() const noexcept;

    /// Gives the in-memory storage back (for reuse); bytes() is empty afterwards.
    [[nodiscard]] std::vector<std::byte> release_buffer() noexcept { return std::move(memory_); }

    [[nodiscard]] uint64_t size() const noexcept { return size_; }
    [[nodiscard]] bool too_large() const noexcept { return too_large_; }
    [[nodiscard]] bool spooled() const noexcept { return fd_ >= 0; }
    [[nodiscard]] const std::string& error() const noexcept { return error_; }
    /// The spool write failed because the disk (or a file size limit) is full.
    [[nodiscard]] bool no_space() const noexcept { return no_space_; }

private:
    bool spill();
    void set_write_error(int err);

    uint64_t max_bytes_, memory_bytes_;
    std::filesystem::path spool_dir_;
    std::vector<std::byte> memory_;
    int fd_ = -1;
    uint64_t size_ = 0;
    bool too_large_ = false;
    std::string error_;
    bool no_space_ = false;
    MappedFile mapping_;
};

}  // namespace kdrt::server
