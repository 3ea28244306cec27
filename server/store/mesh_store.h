#pragma once
/// Durable storage of acknowledged meshes under the cache directory:
///
///   meshes/<id>.mesh   the mesh as parsed, in the raw format (proto/FORMATS.md); its content hash
///                      is the id, so it verifies itself
///   meshes/<id>.tree   its kD-tree: the engine blob in a container naming the mesh (tree_file.h)
///   meshes/<id>.json   its summary (proto::MeshSummary) - the commit record, written last
///   tmp/<process>/     spooled uploads and writes in progress of one server process, which
///                      holds an flock on tmp/<process>.lock while it runs; a directory whose
///                      lock is free (its process is gone) is removed by the next open()
///   quarantine/        files of a mesh that could be neither served nor repaired, moved aside
///                      at start-up (never deleted), one directory per mesh and time
///
/// Every file is written to tmp/, fsync'd and renamed into meshes/, and the directory is synced
/// before the summary (the commit record) is renamed in, so after a crash a mesh is either
/// complete or its files are complete but uncommitted (no summary). The store itself never
/// deletes a file in meshes/ except on remove(): start-up decisions (repair, quarantine) are the
/// cache's. Thread-safe for distinct ids; the cache serialises work per id.
///
/// Shared stores: any number of server processes (replicas, on one machine or on a shared file
/// system such as NFS or CephFS) may use one store directory at once. Each has its own tmp/
/// subdirectory; meshes/ files are content-addressed (the id is the mesh's hash) and only ever
/// enter it by an atomic link or rename of a complete, fsync'd file, never by writing in place.
/// There is no index file: the directory listing is the index, so two writers cannot lose each
/// other's entries. save() never replaces an existing file (write_file_once): when two replicas
/// store the same mesh at once, the first file in wins and both answer with the same id.

#include <cstdint>
#include <filesystem>
#include <optional>
#include <string>
#include <vector>

#include "kdrt/kdtree.h"
#include "kdrt/mesh.h"
#include "kdrt/proto/json_api.h"
#include "kdrt/proto/result.h"
#include "store/durable_file.h"
#include "store/tree_file.h"

namespace kdrt::server {

/// Why a stored mesh or summary file could not be used.
struct StoreError {
    enum class Code {
        kMissing,  ///< the file does not exist
        kCorrupt,  ///< it exists but fails validation (format, size, or content hash != id)
        kIo,       ///< the operating system refused (permissions, ...)
    };
    Code code = Code::kIo;
    /// Metric label: "missing", "unreadable", "truncated", "corrupt", "hash_mismatch",
    /// "summary_mismatch".
    std::string reason;
    std::string detail;  ///< names the file and what is wrong with it
};

class MeshStore {
public:
    explicit MeshStore(std::filesystem::path root);
    ~MeshStore();
    MeshStore(const MeshStore&) = delete;
    MeshStore& operator=(const MeshStore&) = delete;

    /// Every mesh id with at least one file in meshes/.
    struct Listed {
        std::string id;
        std::optional<proto::MeshSummary> summary;  ///< nullopt: missing or unreadable
        std::string summary_error;                  ///< why, when summary is nullopt
        bool has_mesh = false, has_tree = false, has_summary = false;
    };

    /// Creates the directories and this process's tmp/ directory (locked while the store
    /// lives), removes the tmp/ directories of processes that are gone and loose files in tmp/
    /// (`removed` receives a line per deleted file, for the log) and lists every id found in
    /// meshes/. Deletes nothing in meshes/.
    [[nodiscard]] proto::Result<std::vector<Listed>, std::string> open(
        std::vector<std::string>& removed);
    /// The listing part of open() alone: reads, never writes (for --check-store).
    [[nodiscard]] proto::Result<std::vector<Listed>, std::string> list() const;
    /// One id as list() would list it; nullopt when meshes/ holds no file of it.
    [[nodiscard]] std::optional<Listed> list_one(const std::string& id) const;
    /// The ids with a summary file (committed meshes), from the directory listing alone
    /// (reads no file), sorted.
    [[nodiscard]] proto::Result<std::vector<std::string>, std::string> committed_ids() const;
    /// True when another live process has the store open (holds a tmp/ lock). Files of a mesh
    /// without a summary may then be another process's write in progress.
    [[nodiscard]] bool shared_with_live_process() const;

    struct Saved {
        uint64_t disk_bytes = 0;
        bool created = false;  ///< false: the summary was already there (another process)
    };
    /// Stores mesh, tree and summary durably (in that order). With `replace` false (a new
    /// upload) existing files are kept, never rewritten (write_file_once); with `replace` true
    /// (repairing a damaged mesh) they are replaced atomically.
    [[nodiscard]] proto::Result<Saved, WriteError> save(const proto::MeshSummary& summary,
                                                        const Mesh& mesh, const KdTree& tree,
                                                        bool replace = false);
    /// Reads one summary file (checked to name `id`).
    [[nodiscard]] proto::Result<proto::MeshSummary, std::string> read_summary(
        const std::string& id) const;
    /// Replaces one file (after a rebuild or a repair).
    [[nodiscard]] proto::Result<void, WriteError> save_mesh(const std::string& id,
                                                            const Mesh& mesh);
    [[nodiscard]] proto::Result<void, WriteError> save_tree(const std::string& id,
                                                            const KdTree& tree);
    [[nodiscard]] proto::Result<void, WriteError> save_summary(const proto::MeshSummary& summary);

    /// Loads the tree file and checks that it is the tree of mesh `id`.
    [[nodiscard]] proto::Result<KdTree, TreeFileProblem> load_tree(const std::string& id) const;
    /// Loads the mesh file and checks that its content hash is `id`.
    [[nodiscard]] proto::Result<Mesh, StoreError> load_mesh(const std::string& id) const;
    /// The cheap start-up check of the mesh file against a summary: it exists, its header's
    /// counts match the file size, and its triangle count is the summary's (reason
    /// "summary_mismatch" when only that differs). Reads 8 bytes.
    [[nodiscard]] proto::Result<void, StoreError> check_mesh_header(
        const proto::MeshSummary& summary) const;

    /// Moves the mesh's files to quarantine/<id>.<unix seconds>/ (nothing is deleted). Returns
    /// that directory.
    [[nodiscard]] proto::Result<std::filesystem::path, std::string> quarantine(
        const std::string& id);

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
    std::filesystem::path root_, meshes_dir_, tmp_root_, tmp_dir_, quarantine_dir_;
    std::string process_name_;  ///< this process's tmp/ subdirectory and lock file name
    int lock_fd_ = -1;          ///< flock'd tmp/<process_name_>.lock while open
};

/// The mesh a tree was built from, as an unindexed triangle soup (the tree keeps every
/// triangle's corners in triangle order, so the soup has the same canonical triangles and id).
[[nodiscard]] Mesh mesh_from_tree(const KdTree& tree);

}  // namespace kdrt::server
