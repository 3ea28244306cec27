#include "mesh_store.h"

#include <set>
#include <system_error>

#include "durable_file.h"
#include "kdrt/proto/file_io.h"
#include "kdrt/proto/mesh_id.h"
#include "kdrt/proto/mesh_io.h"
#include "kdrt/proto/text.h"
#include "kdrt/serialize.h"

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
    return StoreError{exists ? StoreError::Code::kIo : StoreError::Code::kMissing,
                      std::move(detail)};
}

}  // namespace

MeshStore::MeshStore(fs::path root)
    : root_(std::move(root)), meshes_dir_(root_ / "meshes"), tmp_dir_(root_ / "tmp") {}

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
    std::set<std::string> summaries, data;
    for (const auto& file : fs::directory_iterator(meshes_dir_, ec)) {
        const std::string stem = file.path().stem().string();
        const std::string ext = file.path().extension().string();
        if (!proto::is_mesh_id(stem)) continue;  // not ours: leave it alone
        if (ext == ".json") summaries.insert(stem);
        if (ext == ".mesh" || ext == ".tree") data.insert(stem);
    }
    if (ec) return Err{"cannot list " + in_quotes(meshes_dir_.string()) + ": " + ec.message()};

    std::vector<Listed> listed;
    for (const std::string& id : summaries) {
        if (!fs::exists(mesh_path(id), ec)) {
            removed.push_back("summary without a mesh file " + summary_path(id).string());
            fs::remove(summary_path(id), ec);
            fs::remove(tree_path(id), ec);
            continue;
        }
        Listed entry;
        entry.id = id;
        auto bytes = proto::read_file_bytes(summary_path(id), 1u << 20);
        if (!bytes) {
            entry.summary_error = bytes.error();
        } else {
            const std::string text(reinterpret_cast<const char*>(bytes->data()), bytes->size());
            auto summary = proto::decode_mesh_summary(text);
            if (!summary)
                entry.summary_error = summary.error();
            else if (summary->id != id)
                entry.summary_error = "summary names mesh " + summary->id;
            else
                entry.summary = std::move(*summary);
        }
        entry.disk_bytes = disk_bytes(id);
        listed.push_back(std::move(entry));
    }
    for (const std::string& id : data) {
        if (summaries.count(id)) continue;
        removed.push_back("uncommitted upload " + id);
        fs::remove(mesh_path(id), ec);
        fs::remove(tree_path(id), ec);
    }
    auto synced = sync_directory(meshes_dir_);
    if (!synced) return Err{std::move(synced).error()};
    return listed;
}

proto::Result<uint64_t, std::string> MeshStore::save(const proto::MeshSummary& summary,
                                                     const Mesh& mesh, const KdTree& tree) {
    {
        const std::vector<std::byte> raw = proto::write_mesh(mesh, proto::MeshFormat::kRaw);
        auto written = write_file_durably(mesh_path(summary.id), tmp_dir_, raw);
        if (!written) return Err{std::move(written).error()};
    }
    auto tree_written = save_tree(summary.id, tree);
    if (!tree_written) return Err{std::move(tree_written).error()};
    // The data must be durable before the commit record names it.
    auto synced = sync_directory(meshes_dir_);
    if (!synced) return Err{std::move(synced).error()};
    auto committed = save_summary(summary);
    if (!committed) return Err{std::move(committed).error()};
    return disk_bytes(summary.id);
}

proto::Result<void, std::string> MeshStore::save_tree(const std::string& id, const KdTree& tree) {
    const std::vector<std::byte> blob = serialize_tree(tree);
    return write_file_durably(tree_path(id), tmp_dir_, blob);
}

proto::Result<void, std::string> MeshStore::save_summary(const proto::MeshSummary& summary) {
    proto::MeshSummary stored = summary;
    stored.in_memory.reset();
    auto written = write_file_durably(summary_path(summary.id), tmp_dir_,
                                      text_bytes(proto::encode_mesh_summary(stored)));
    if (!written) return written;
    return sync_directory(meshes_dir_);
}

proto::Result<KdTree, StoreError> MeshStore::load_tree(const std::string& id) const {
    const fs::path path = tree_path(id);
    auto bytes = proto::read_file_bytes(path);
    if (!bytes) return Err{read_error(path, std::move(bytes).error())};
    try {
        return deserialize_tree(*bytes);
    } catch (const TreeFormatError& e) {
        return Err{
            StoreError{StoreError::Code::kCorrupt, in_quotes(path.string()) + ": " + e.what()}};
    }
}

proto::Result<Mesh, StoreError> MeshStore::load_mesh(const std::string& id) const {
    const fs::path path = mesh_path(id);
    auto bytes = proto::read_file_bytes(path);
    if (!bytes) return Err{read_error(path, std::move(bytes).error())};
    auto mesh = proto::parse_mesh(*bytes, proto::MeshFormat::kRaw);
    if (!mesh)
        return Err{StoreError{StoreError::Code::kCorrupt,
                              in_quotes(path.string()) + ": " + mesh.error().message}};
    const std::string actual = proto::mesh_id(*mesh);
    if (actual != id)
        return Err{StoreError{
            StoreError::Code::kCorrupt,
            in_quotes(path.string()) + ": content hash is " + actual + ", not the mesh id"}};
    return std::move(*mesh);
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

}  // namespace kdrt::server
