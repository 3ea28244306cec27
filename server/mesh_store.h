#pragma once
/// Durable storage of acknowledged meshes under the cache directory:
///
///   meshes/<id>.mesh   the mesh as parsed, in the raw format (proto/FORMATS.md)
///   meshes/<id>.tree   its serialised kD-tree (engine blob, with checksum)
///   meshes/<id>.json   its summary (proto::MeshSummary) - the commit record, written last
///   tmp/               spooled uploads and writes in progress; emptied at start-up
///
/// Every file is written to tmp/, fsync'd and renamed into meshes/, and the directory is synced
/// before the summary (the commit record) is renamed in, so after a crash a mesh is either
/// complete or absent. Thread-safe for distinct ids; the cache serialises work per id.

#include <cstdint>
#include <filesystem>
#include <optional>
#include <string>
#include <vector>

#include "kdrt/kdtree.h"
#include "kdrt/mesh.h"
#include "kdrt/proto/json_api.h"
#include "kdrt/proto/result.h"

namespace kdrt::server {

/// Why a stored file could not be used.
struct StoreError {
    enum class Code {
        kMissing,  ///< the file does not exist
        kCorrupt,  ///< it exists but fails validation (checksum, format, or content hash != id)
        kIo,       ///< the operating system refused (permissions, disk full, ...)
    };
    Code code = Code::kIo;
    std::string detail;
};

class MeshStore {
public:
    explicit MeshStore(std::filesystem::path root);

    /// A committed mesh found by open().
    struct Listed {
        std::string id;
        std::optional<proto::MeshSummary> summary;  ///< nullopt: the summary file is unreadable
        std::string summary_error;                  ///< why, when summary is nullopt
        uint64_t disk_bytes = 0;
    };

    /// Creates the directories, empties tmp/, deletes files of uncommitted meshes (no summary)
    /// and summaries without a mesh file, and lists the committed meshes. `removed` receives a
    /// line per deleted leftover, for the log.
    [[nodiscard]] proto::Result<std::vector<Listed>, std::string> open(
        std::vector<std::string>& removed);

    /// Stores mesh, tree and summary durably (in that order). Returns the bytes on disk.
    [[nodiscard]] proto::Result<uint64_t, std::string> save(const proto::MeshSummary& summary,
                                                            const Mesh& mesh, const KdTree& tree);
    /// Replaces the tree file (after a rebuild) or the summary file (after recovery).
    [[nodiscard]] proto::Result<void, std::string> save_tree(const std::string& id,
                                                             const KdTree& tree);
    [[nodiscard]] proto::Result<void, std::string> save_summary(const proto::MeshSummary& summary);

    /// Loads and validates the tree file.
    [[nodiscard]] proto::Result<KdTree, StoreError> load_tree(const std::string& id) const;
    /// Loads the mesh file and checks that its content hash is `id`.
    [[nodiscard]] proto::Result<Mesh, StoreError> load_mesh(const std::string& id) const;

    /// Deletes the mesh's files (summary first, so a crash never leaves a summary without data).
    void remove(const std::string& id);

    /// Total size of the mesh's files.
    [[nodiscard]] uint64_t disk_bytes(const std::string& id) const;

    [[nodiscard]] const std::filesystem::path& tmp_dir() const noexcept { return tmp_dir_; }
    [[nodiscard]] std::filesystem::path mesh_path(const std::string& id) const {
        return meshes_dir_ / (id + ".mesh");
    }
    [[nodiscard]] std::filesystem::path tree_path(const std::string& id) const {
        return meshes_dir_ / (id + ".tree");
    }
    [[nodiscard]] std::filesystem::path summary_path(const std::string& id) const {
        return meshes_dir_ / (id + ".json");
    }

private:
    std::filesystem::path root_, meshes_dir_, tmp_dir_;
};

}  // namespace kdrt::server
