#include "mesh_store.h"

#include <chrono>
#include <cstring>
#include <fstream>
#include <set>
#include <system_error>

#include "kdrt/proto/file_io.h"
#include "kdrt/proto/mesh_id.h"
#include "kdrt/proto/mesh_io.h"
#include "kdrt/proto/text.h"

namespace kdrt::server {
namespace {

namespace fs = std::filesystem;
using proto::Err;
using proto::in_quotes;

std::span<const std::byte> text_bytes(const std::string& text) {
    return {reinterpret_cast<const std::byte*>(text.data()), text.size()};
}

StoreError read_error(const fs::path& path, std::string detail) {
    std::error_code ec;
    const bool exists = fs::exists(path, ec);
    return exists ? StoreError{StoreError::Code::kIo, "unreadable", std::move(detail)}
                  : StoreError{StoreError::Code::kMissing, "missing",
                               in_quotes(path.string()) + " does not exist"};
}

}  // namespace

MeshStore::MeshStore(fs::path root)
    : root_(std::move(root)),
      meshes_dir_(root_ / "meshes"),
      tmp_dir_(root_ / "tmp"),
      quarantine_dir_(root_ / "quarantine") {}

proto::Result<std::vector<MeshStore::Listed>, std::string> MeshStore::open(
    std::vector<std::string>& removed) {
    std::error_code ec;
    for (const fs::path& dir : {root_, meshes_dir_, tmp_dir_}) {
        fs::create_directories(dir, ec);
        if (ec) return Err{"cannot create " + in_quotes(dir.string()) + ": " + ec.message()};
    }
    for (const auto& file : fs::directory_iterator(tmp_dir_, ec)) {
        fs::remove_all(file.path(), ec);
        removed.push_back("temporary file " + file.path().string());
    }
    return list();
}

proto::Result<std::vector<MeshStore::Listed>, std::string> MeshStore::list() const {
    std::error_code ec;
    std::set<std::string> ids;
    for (const auto& file : fs::directory_iterator(meshes_dir_, ec)) {
        const std::string stem = file.path().stem().string();
        const std::string ext = file.path().extension().string();
        if (!proto::is_mesh_id(stem)) continue;  // not ours: leave it alone
        if (ext == ".json" || ext == ".mesh" || ext == ".tree") ids.insert(stem);
    }
    if (ec) return Err{"cannot list " + in_quotes(meshes_dir_.string()) + ": " + ec.message()};

    std::vector<Listed> listed;
    for (const std::string& id : ids) {
        Listed entry;
        entry.id = id;
        entry.has_mesh = fs::exists(mesh_path(id), ec);
        entry.has_tree = fs::exists(tree_path(id), ec);
        entry.has_summary = fs::exists(summary_path(id), ec);
        if (!entry.has_summary) {
            entry.summary_error = "no summary file";
        } else if (auto bytes = proto::read_file_bytes(summary_path(id), 1u << 20); !bytes) {
            entry.summary_error = bytes.error();
        } else {
            const std::string text(reinterpret_cast<const char*>(bytes->data()), bytes->size());
            auto summary = proto::decode_mesh_summary(text);
            if (!summary)
                entry.summary_error = in_quotes(summary_path(id).string()) + ": " + summary.error();
            else if (summary->id != id)
                entry.summary_error =
                    in_quotes(summary_path(id).string()) + " names mesh " + summary->id;
            else
                entry.summary = std::move(*summary);
        }
        listed.push_back(std::move(entry));
    }
    return listed;
}

proto::Result<uint64_t, WriteError> MeshStore::save(const proto::MeshSummary& summary,
                                                    const Mesh& mesh, const KdTree& tree) {
    if (auto written = save_mesh(summary.id, mesh); !written) return Err{written.error()};
    if (auto written = save_tree(summary.id, tree); !written) return Err{written.error()};
    // The data must be durable before the commit record names it.
    if (auto synced = sync_directory(meshes_dir_); !synced) return Err{synced.error()};
    if (auto committed = save_summary(summary); !committed) return Err{committed.error()};
    return disk_bytes(summary.id);
}

proto::Result<void, WriteError> MeshStore::save_mesh(const std::string& id, const Mesh& mesh) {
    const std::vector<std::byte> raw = proto::write_mesh(mesh, proto::MeshFormat::kRaw);
    return write_file_durably(mesh_path(id), tmp_dir_, raw);
}

proto::Result<void, WriteError> MeshStore::save_tree(const std::string& id, const KdTree& tree) {
    return write_file_durably(tree_path(id), tmp_dir_, encode_tree_file(id, tree));
}

proto::Result<void, WriteError> MeshStore::save_summary(const proto::MeshSummary& summary) {
    proto::MeshSummary stored = summary;
    stored.in_memory.reset();
    auto written = write_file_durably(summary_path(summary.id), tmp_dir_,
                                      text_bytes(proto::encode_mesh_summary(stored)));
    if (!written) return written;
    return sync_directory(meshes_dir_);
}

proto::Result<KdTree, TreeFileProblem> MeshStore::load_tree(const std::string& id) const {
    const fs::path path = tree_path(id);
    auto bytes = proto::read_file_bytes(path);
    if (!bytes) {
        std::error_code ec;
        if (!fs::exists(path, ec))
            return Err{TreeFileProblem{TreeFileProblem::Reason::kMissing,
                                       in_quotes(path.string()) + " does not exist"}};
        return Err{TreeFileProblem{TreeFileProblem::Reason::kUnreadable, bytes.error()}};
    }
    auto tree = decode_tree_file(id, *bytes);
    if (!tree) {
        TreeFileProblem problem = std::move(tree).error();
        problem.detail = in_quotes(path.string()) + ": " + problem.detail;
        return Err{std::move(problem)};
    }
    return std::move(*tree);
}

proto::Result<Mesh, StoreError> MeshStore::load_mesh(const std::string& id) const {
    const fs::path path = mesh_path(id);
    auto bytes = proto::read_file_bytes(path);
    if (!bytes) return Err{read_error(path, std::move(bytes).error())};
    auto mesh = proto::parse_mesh(*bytes, proto::MeshFormat::kRaw);
    if (!mesh)
        return Err{StoreError{StoreError::Code::kCorrupt, "corrupt",
                              in_quotes(path.string()) + ": " + mesh.error().message}};
    const std::string actual = proto::mesh_id(*mesh);
    if (actual != id)
        return Err{StoreError{
            StoreError::Code::kCorrupt, "hash_mismatch",
            in_quotes(path.string()) + ": content hash is " + actual + ", not the mesh id"}};
    return std::move(*mesh);
}

proto::Result<void, StoreError> MeshStore::check_mesh_header(
    const proto::MeshSummary& summary) const {
    const fs::path path = mesh_path(summary.id);
    std::error_code ec;
    const uint64_t size = fs::file_size(path, ec);
    if (ec) return Err{read_error(path, in_quotes(path.string()) + ": " + ec.message())};
    std::ifstream in(path, std::ios::binary);
    unsigned char header[8] = {};
    if (!in.read(reinterpret_cast<char*>(header), sizeof header))
        return Err{StoreError{StoreError::Code::kCorrupt, "truncated",
                              in_quotes(path.string()) + ": " + std::to_string(size) +
                                  " bytes, shorter than the 8-byte header"}};
    const auto u32 = [&](int at) {
        return uint64_t{header[at]} | uint64_t{header[at + 1]} << 8 |
               uint64_t{header[at + 2]} << 16 | uint64_t{header[at + 3]} << 24;
    };
    const uint64_t vertices = u32(0), triangles = u32(4);
    const uint64_t expected = 8 + 12 * vertices + 12 * triangles;
    if (size != expected)
        return Err{StoreError{StoreError::Code::kCorrupt, "truncated",
                              in_quotes(path.string()) + ": " + std::to_string(size) +
                                  " bytes, its header's counts (" + std::to_string(vertices) +
                                  " vertices, " + std::to_string(triangles) + " triangles) need " +
                                  std::to_string(expected)}};
    if (triangles != summary.triangles)
        return Err{StoreError{StoreError::Code::kCorrupt, "summary_mismatch",
                              in_quotes(summary_path(summary.id).string()) + " says " +
                                  std::to_string(summary.triangles) + " triangles, the mesh file " +
                                  std::to_string(triangles)}};
    return {};
}

proto::Result<fs::path, std::string> MeshStore::quarantine(const std::string& id) {
    const auto seconds = std::chrono::duration_cast<std::chrono::seconds>(
                             std::chrono::system_clock::now().time_since_epoch())
                             .count();
    const fs::path dir = quarantine_dir_ / (id + "." + std::to_string(seconds));
    std::error_code ec;
    fs::create_directories(dir, ec);
    if (ec) return Err{"cannot create " + in_quotes(dir.string()) + ": " + ec.message()};
    // The summary first: once it is gone the mesh is no longer committed.
    for (const fs::path& file : {summary_path(id), mesh_path(id), tree_path(id)}) {
        if (!fs::exists(file, ec)) continue;
        fs::rename(file, dir / file.filename(), ec);
        if (ec)
            return Err{"cannot move " + in_quotes(file.string()) + " to " +
                       in_quotes(dir.string()) + ": " + ec.message()};
    }
    (void)sync_directory(meshes_dir_);
    (void)sync_directory(dir);
    return dir;
}

void MeshStore::remove(const std::string& id) {
    std::error_code ec;
    fs::remove(summary_path(id), ec);
    (void)sync_directory(meshes_dir_);
    fs::remove(tree_path(id), ec);
    fs::remove(mesh_path(id), ec);
}

uint64_t MeshStore::disk_bytes(const std::string& id) const {
    uint64_t total = 0;
    std::error_code ec;
    for (const fs::path& p : {mesh_path(id), tree_path(id), summary_path(id)}) {
        const auto size = fs::file_size(p, ec);
        if (!ec) total += size;
    }
    return total;
}

Mesh mesh_from_tree(const KdTree& tree) {
    Mesh mesh;
    mesh.positions.resize(tree.tris.size() * 9);
    mesh.indices.resize(tree.tris.size() * 3);
    for (size_t t = 0; t < tree.tris.size(); ++t) {
        const TriVerts& tri = tree.triangle(static_cast<uint32_t>(t));  // by mesh id
        std::memcpy(&mesh.positions[9 * t], tri.v0, sizeof tri.v0);
        std::memcpy(&mesh.positions[9 * t + 3], tri.v1, sizeof tri.v1);
        std::memcpy(&mesh.positions[9 * t + 6], tri.v2, sizeof tri.v2);
        for (uint32_t c = 0; c < 3; ++c) mesh.indices[3 * t + c] = static_cast<uint32_t>(3 * t + c);
    }
    return mesh;
}

}  // namespace kdrt::server
