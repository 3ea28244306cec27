#pragma once
/// Whole-file reads and writes for ray/hit batches, meshes and images on disk.

#include <cstddef>
#include <cstdint>
#include <filesystem>
#include <limits>
#include <span>
#include <string>
#include <vector>

#include "kdrt/proto/result.h"

namespace kdrt::proto {

/// Reads the whole file (regular file, pipe or device) into memory. On failure the error names
/// the path and the operating system's reason, e.g.
/// `cannot open "rays.kdrr" for reading: No such file or directory`. A file larger than
/// `max_bytes` is refused without reading it all. Thread-safe.
[[nodiscard]] Result<std::vector<std::byte>, std::string> read_file_bytes(
    const std::filesystem::path& path, uint64_t max_bytes = std::numeric_limits<uint64_t>::max());

/// Creates or truncates `path` and writes `bytes` to it (mode 0644 before umask). Not atomic: a
/// failed write can leave a partial file. The error names the path and the reason. Thread-safe
/// for distinct paths.
[[nodiscard]] Result<void, std::string> write_file_bytes(const std::filesystem::path& path,
                                                         std::span<const std::byte> bytes);

}  // namespace kdrt::proto
