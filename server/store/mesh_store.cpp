#include "store/mesh_store.h"

#include <fcntl.h>
#include <sys/file.h>
#include <unistd.h>

#include <algorithm>
#include <cctype>
#include <chrono>
#include <cstring>
#include <fstream>
#include <random>
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

/// A name no other process sharing the store uses: host, pid and 64 random bits.
std::string unique_process_name() {
    char host[256] = {};
    if (::gethostname(host, sizeof host - 1) != 0 || host[0] == 0) std::strcpy(host, "host");
    std::string name;
    for (const char* c = host; *c; ++c)
        name.push_back(std::isalnum(static_cast<unsigned char>(*c)) || *c == '-' ? *c : '_');
    std::random_device random;
    const uint64_t nonce = (uint64_t{random()} << 32) ^ random();
    static constexpr char kHex[] = "0123456789abcdef";
    name += "." + std::to_string(::getpid()) + ".";
    for (int i = 0; i < 16; ++i) name.push_back(kHex[(nonce >> (4 * i)) & 15]);
    return name;
}

/// True when the lock file at `path` is flock'd by a live process (or cannot be checked).
bool lock_held(const fs::path& path) {
    const int fd = ::open(path.c_str(), O_RDWR | O_CLOEXEC);
    if (fd < 0) return errno != ENOENT;
    const bool held = ::flock(fd, LOCK_EX | LOCK_NB) != 0;
    ::close(fd);
    return held;
}

}  // namespace

MeshStore::MeshStore(fs::path root)
    : root_(std::move(root)),
      meshes_dir_(root_ / "meshes"),
      tmp_root_(root_ / "tmp"),
      quarantine_dir_(root_ / "quarantine"),
      process_name_(unique_process_name()) {
    tmp_dir_ = tmp_root_ / process_name_;
}

MeshStore::~MeshStore() {
    if (lock_fd_ < 0) return;
    std::error_code ec;
    fs::remove_all(tmp_dir_, ec);
    fs::remove(tmp_root_ / (process_name_ + ".lock"), ec);
    ::close(lock_fd_);
}

proto::Result<std::vector<MeshStore::Listed>, std::string> MeshStore::open(
    std::vector<std::string>& removed) {
    std::error_code ec;
    for (const fs::path& dir : {root_, meshes_dir_, tmp_root_}) {
        fs::create_directories(dir, ec);
        if (ec) return Err{"cannot create " + in_quotes(dir.string()) + ": " + ec.message()};
    }
    if (lock_fd_ < 0) {
        // The lock first, then the directory: a directory is never seen without its lock held.
        const fs::path lock_path = tmp_root_ / (process_name_ + ".lock");
        lock_fd_ = ::open(lock_path.c_str(), O_RDWR | O_CREAT | O_CLOEXEC, 0644);
        if (lock_fd_ < 0 || ::flock(lock_fd_, LOCK_EX | LOCK_NB) != 0)
            return Err{"cannot lock " + in_quotes(lock_path.string()) + ": " +
                       std::generic_category().message(errno)};
        fs::create_directories(tmp_dir_, ec);
        if (ec) return Err{"cannot create " + in_quotes(tmp_dir_.string()) + ": " + ec.message()};
    }
    // Leftovers: tmp/ directories of processes that are gone (their lock is free), and loose
    // files (written by versions before tmp/ was per process).
    std::vector<fs::path> entries;
    for (const auto& file : fs::directory_iterator(tmp_root_, ec)) entries.push_back(file.path());
    for (const fs::path& path : entries) {
        const std::string name = path.filename().string();
        if (name == process_name_ || name == process_name_ + ".lock") continue;
        if (path.extension() == ".lock") {
            const fs::path dir = tmp_root_ / path.stem();
            if (lock_held(path)) continue;
            for (const auto& file : fs::recursive_directory_iterator(dir, ec))
                if (!file.is_directory(ec))
                    removed.push_back("temporary file " + file.path().string());
            fs::remove_all(dir, ec);
            fs::remove(path, ec);
        } else if (fs::is_directory(path, ec)) {
            if (fs::exists(tmp_root_ / (name + ".lock"), ec)) continue;  // judged by its lock
            // A directory without a lock file: its process is gone (the lock is made first).
            for (const auto& file : fs::recursive_directory_iterator(path, ec))
                if (!file.is_directory(ec))
                    removed.push_back("temporary file " + file.path().string());
            fs::remove_all(path, ec);
        } else {
            fs::remove(path, ec);
            removed.push_back("temporary file " + path.string());
        }
    }
    return list();
}

bool MeshStore::shared_with_live_process() const {
    std::error_code ec;
    for (const auto& file : fs::directory_iterator(tmp_root_, ec)) {
        const fs::path& path = file.path();
        if (path.extension() != ".lock" || path.stem().string() == process_name_) continue;
        if (lock_held(path)) return true;
    }
    return false;
}

proto::Result<proto::MeshSummary, std::string> MeshStore::read_summary(
    const std::string& id) const {
    auto bytes = proto::read_file_bytes(summary_path(id), 1u << 20);
    if (!bytes) return Err{bytes.error()};
    const std::string text(reinterpret_cast<const char*>(bytes->data()), bytes->size());
    auto summary = proto::decode_mesh_summary(text);
    if (!summary) return Err{in_quotes(summary_path(id).string()) + ": " + summary.error()};
    if (summary->id != id)
        return Err{in_quotes(summary_path(id).string()) + " names mesh " + summary->id};
    return std::move(*summary);
}

std::optional<MeshStore::Listed> MeshStore::list_one(const std::string& id) const {
    if (!proto::is_mesh_id(id)) return std::nullopt;
    std::error_code ec;
    Listed entry;
    entry.id = id;
    entry.has_mesh = fs::exists(mesh_path(id), ec);
    entry.has_tree = fs::exists(tree_path(id), ec);
    entry.has_summary = fs::exists(summary_path(id), ec);
    if (!entry.has_mesh && !entry.has_tree && !entry.has_summary) return std::nullopt;
    if (!entry.has_summary) {
        entry.summary_error = "no summary file";
    } else if (auto summary = read_summary(id); !summary) {
        entry.summary_error = summary.error();
    } else {
        entry.summary = std::move(*summary);
    }
    return entry;
}

proto::Result<std::vector<std::string>, std::string> MeshStore::committed_ids() const {
    std::error_code ec;
    std::vector<std::string> ids;
    for (const auto& file : fs::directory_iterator(meshes_dir_, ec)) {
        const std::string stem = file.path().stem().string();
        if (file.path().extension() == ".json" && proto::is_mesh_id(stem)) ids.push_back(stem);
    }
    if (ec) return Err{"cannot list " + in_quotes(meshes_dir_.string()) + ": " + ec.message()};
    std::sort(ids.begin(), ids.end());
    return ids;
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
    for (const std::string& id : ids)
        if (auto entry = list_one(id)) listed.push_back(std::move(*entry));
    return listed;
}

proto::Result<MeshStore::Saved, WriteError> MeshStore::save(const proto::MeshSummary& summary,
                                                            const Mesh& mesh, const KdTree& tree,
                                                            bool replace) {
    const std::string& id = summary.id;
    if (replace) {
        if (auto written = save_mesh(id, mesh); !written) return Err{written.error()};
        if (auto written = save_tree(id, tree); !written) return Err{written.error()};
        // The data must be durable before the commit record names it.
        if (auto synced = sync_directory(meshes_dir_); !synced) return Err{synced.error()};
        if (auto committed = save_summary(summary); !committed) return Err{committed.error()};
        return Saved{disk_bytes(id), true};
    }
    // A file already there is another process's equal write, or a leftover that is checked
    // (against the id it is named by) and replaced when it does not hold up.
    const std::vector<std::byte> raw = proto::write_mesh(mesh, proto::MeshFormat::kRaw);
    auto mesh_written = write_file_once(mesh_path(id), tmp_dir_, raw);
    if (!mesh_written) return Err{mesh_written.error()};
    if (!*mesh_written && !load_mesh(id))
        if (auto written = save_mesh(id, mesh); !written) return Err{written.error()};
    auto tree_written = write_file_once(tree_path(id), tmp_dir_, encode_tree_file(id, tree));
    if (!tree_written) return Err{tree_written.error()};
    if (!*tree_written && !load_tree(id))
        if (auto written = save_tree(id, tree); !written) return Err{written.error()};
    if (auto synced = sync_directory(meshes_dir_); !synced) return Err{synced.error()};
    proto::MeshSummary stored = summary;
    stored.in_memory.reset();
    auto committed =
        write_file_once(summary_path(id), tmp_dir_, text_bytes(proto::encode_mesh_summary(stored)));
    if (!committed) return Err{committed.error()};
    if (auto synced = sync_directory(meshes_dir_); !synced) return Err{synced.error()};
    return Saved{disk_bytes(id), *committed};
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
