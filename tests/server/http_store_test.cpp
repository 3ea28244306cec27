// The store never answers wrong, through the real binary: every kind of stored file flipped,
// truncated, deleted or swapped between meshes; a tree of another mesh; trees of an older format;
// the --check-store scrub; a full disk (a small tmpfs when this process may mount one, and a file
// size limit always).

#include <gtest/gtest.h>
#include <sys/mount.h>

#include <cstdio>
#include <filesystem>
#include <fstream>

#include "http_test_util.h"
#include "kdrt/proto/mesh_id.h"
#include "kdrt/proto/ray_batch.h"

namespace kdrt::test {
namespace {

namespace fs = std::filesystem;

/// Traces `rays` and expects exactly the engine's answer for `mesh`.
void expect_right_answer(httplib::Client& cli, const std::string& id, const Mesh& mesh) {
    const std::vector<Ray> rays = random_rays(mesh_bounds(mesh), 400, 9);
    auto res = trace(cli, id, rays);
    ASSERT_TRUE(res);
    ASSERT_EQ(res->status, 200) << res->body;
    EXPECT_EQ(res->body, engine_hits(mesh, rays));
}

std::string read_all(const fs::path& path) {
    std::ifstream in(path, std::ios::binary);
    return {std::istreambuf_iterator<char>(in), std::istreambuf_iterator<char>()};
}

void write_all(const fs::path& path, const std::string& bytes) {
    std::ofstream(path, std::ios::binary | std::ios::trunc) << bytes;
}

void flip_byte(const fs::path& path, size_t offset) {
    std::string bytes = read_all(path);
    ASSERT_LT(offset, bytes.size()) << path;
    bytes[offset] = static_cast<char>(bytes[offset] ^ 0x5a);
    write_all(path, bytes);
}

void swap_files(const fs::path& a, const fs::path& b) {
    const std::string x = read_all(a), y = read_all(b);
    write_all(a, y);
    write_all(b, x);
}

/// Runs `kdrt-server --check-store` on `cache`; returns the exit code and stdout.
std::pair<int, std::string> check_store(const fs::path& cache) {
    const std::string command = std::string(KDRT_SERVER_BINARY) + " --check-store --cache-dir '" +
                                cache.string() + "' 2>&1";
    FILE* pipe = ::popen(command.c_str(), "r");
    if (!pipe) return {-1, {}};
    std::string out;
    char buf[4096];
    while (size_t n = std::fread(buf, 1, sizeof buf, pipe)) out.append(buf, n);
    const int status = ::pclose(pipe);
    return {WIFEXITED(status) ? WEXITSTATUS(status) : -1, out};
}

/// A cache directory holding meshes a and b (same triangle count, distinct ids), server stopped.
struct Stored {
    TempDir dir;
    Mesh a = small_mesh(301, 1500), b = small_mesh(302, 1500);
    std::string id_a, id_b;
    Stored() {
        ServerProcess server({.cache_dir = cache()});
        auto cli = server.client();
        id_a = upload_id(*cli, a);
        id_b = upload_id(*cli, b);
    }
    [[nodiscard]] fs::path cache() const { return dir.path() / "cache"; }
    [[nodiscard]] fs::path file(const std::string& id, const char* ext) const {
        return cache() / "meshes" / (id + ext);
    }
};

double rebuilds(const ServerProcess& server, const char* reason) {
    return server.metric(std::string("kdrt_cache_rebuilds_total{reason=\"") + reason + "\"}")
        .value_or(-1);
}

TEST(HttpStore, TreeOfAnotherMeshIsRefusedAndRebuilt) {
    Stored s;
    // b's tree is valid (its checksum is right) and has as many triangles as a's.
    fs::copy_file(s.file(s.id_b, ".tree"), s.file(s.id_a, ".tree"),
                  fs::copy_options::overwrite_existing);
    ServerProcess server({.cache_dir = s.cache()});
    auto cli = server.client();
    expect_right_answer(*cli, s.id_a, s.a);
    expect_right_answer(*cli, s.id_b, s.b);
    EXPECT_EQ(rebuilds(server, "other_mesh"), 1.0);
    EXPECT_EQ(server.metric("kdrt_store_problems_total{file=\"tree\",reason=\"other_mesh\"}"), 1.0);
    EXPECT_NE(server.log().find("the tree of mesh " + s.id_b), std::string::npos) << server.log();
    // The rewritten tree is a's: a restart serves it without another rebuild.
    server.stop();
    ServerProcess again({.cache_dir = s.cache()});
    expect_right_answer(*again.client(), s.id_a, s.a);
    EXPECT_EQ(again.metric("kdrt_tree_builds_total"), 0.0);
}

TEST(HttpStore, TreesOfAnOlderFormatAreRebuilt) {
    Stored s;
    // a: the bare engine blob an older server wrote (no container naming the mesh).
    const std::string file = read_all(s.file(s.id_a, ".tree"));
    write_all(s.file(s.id_a, ".tree"), file.substr(96));
    // b: a container holding an engine blob of another format version.
    std::string other = read_all(s.file(s.id_b, ".tree"));
    other[96 + 8] = static_cast<char>(other[96 + 8] + 7);
    write_all(s.file(s.id_b, ".tree"), other);
    ServerProcess server({.cache_dir = s.cache()});
    auto cli = server.client();
    expect_right_answer(*cli, s.id_a, s.a);
    expect_right_answer(*cli, s.id_b, s.b);
    EXPECT_EQ(rebuilds(server, "format_version"), 2.0);
    EXPECT_NE(server.log().find("bare engine tree blob"), std::string::npos) << server.log();
    EXPECT_NE(server.log().find("engine tree format version"), std::string::npos) << server.log();
}

TEST(HttpStore, TruncatedFlippedAndDeletedTreesAreRebuilt) {
    Stored s;
    const Mesh c = small_mesh(303, 1500);
    std::string id_c;
    {
        ServerProcess server({.cache_dir = s.cache()});
        id_c = upload_id(*server.client(), c);
    }
    const std::string tree = read_all(s.file(s.id_a, ".tree"));
    write_all(s.file(s.id_a, ".tree"), tree.substr(0, tree.size() - 100));
    flip_byte(s.file(s.id_b, ".tree"), fs::file_size(s.file(s.id_b, ".tree")) / 2);
    fs::remove(s.file(id_c, ".tree"));
    ServerProcess server({.cache_dir = s.cache()});
    auto cli = server.client();
    expect_right_answer(*cli, s.id_a, s.a);
    expect_right_answer(*cli, s.id_b, s.b);
    expect_right_answer(*cli, id_c, c);
    EXPECT_EQ(rebuilds(server, "truncated"), 1.0);
    EXPECT_EQ(rebuilds(server, "corrupt"), 1.0);
    EXPECT_EQ(rebuilds(server, "missing"), 1.0);
    EXPECT_EQ(server.metric("kdrt_store_damaged_meshes"), 0.0);
}

TEST(HttpStore, DamagedMeshFileIsFoundByTheScrubAndNotNeededWhileTheTreeIsGood) {
    Stored s;
    EXPECT_EQ(check_store(s.cache()).first, 0);
    flip_byte(s.file(s.id_a, ".mesh"), 20);  // a vertex coordinate: the content hash changes
    auto [code, out] = check_store(s.cache());
    EXPECT_EQ(code, 1) << out;
    EXPECT_NE(out.find("damaged " + s.id_a + " (repairable from what remains)"), std::string::npos)
        << out;
    EXPECT_NE(out.find("content hash is"), std::string::npos) << out;
    EXPECT_NE(out.find("ok " + s.id_b), std::string::npos) << out;
    EXPECT_NE(out.find("checked 2 meshes"), std::string::npos) << out;
    // The tree is a's own (bound to its id): the answers are right.
    ServerProcess server({.cache_dir = s.cache()});
    expect_right_answer(*server.client(), s.id_a, s.a);
}

TEST(HttpStore, MeshAndTreeBothDamagedIsAPreciseErrorNeverAWrongAnswer) {
    Stored s;
    flip_byte(s.file(s.id_a, ".tree"), 200);
    flip_byte(s.file(s.id_a, ".mesh"), 20);
    ServerProcess server({.cache_dir = s.cache()});
    auto cli = server.client();
    for (int i = 0; i < 2; ++i) {  // the second request is answered from the damage record
        auto p = expect_problem(trace(*cli, s.id_a, random_rays(mesh_bounds(s.a), 10, 1)), 500);
        EXPECT_EQ(p.kind, proto::ProblemKind::kStoredMeshDamaged);
        EXPECT_NE(p.detail.find(s.id_a + ".mesh\": content hash is"), std::string::npos)
            << p.detail;
        EXPECT_NE(p.detail.find(s.id_a + ".tree\""), std::string::npos) << p.detail;
    }
    EXPECT_EQ(server.metric("kdrt_store_problems_total{file=\"mesh\",reason=\"hash_mismatch\"}"),
              1.0);
    EXPECT_EQ(server.metric("kdrt_store_damaged_meshes"), 1.0);
    EXPECT_NE(server.log().find("mesh damaged beyond repair; kept, not served"), std::string::npos);
    // Still listed, its files kept; the other mesh is unaffected.
    EXPECT_EQ(cli->Get("/v1/meshes/" + s.id_a)->status, 200);
    EXPECT_TRUE(fs::exists(s.file(s.id_a, ".mesh")));
    EXPECT_TRUE(fs::exists(s.file(s.id_a, ".json")));
    expect_right_answer(*cli, s.id_b, s.b);
    // The scrub says it cannot be repaired from what remains.
    auto [code, out] = check_store(s.cache());
    EXPECT_EQ(code, 1);
    EXPECT_NE(out.find("damaged " + s.id_a + " (not repairable"), std::string::npos) << out;
    // Uploading the same triangles repairs it.
    auto res = upload(*cli, s.a);
    ASSERT_TRUE(res);
    EXPECT_EQ(res->status, 201) << res->body;
    expect_right_answer(*cli, s.id_a, s.a);
    EXPECT_EQ(server.metric("kdrt_store_damaged_meshes"), 0.0);
    EXPECT_EQ(check_store(s.cache()).first, 0);
}

TEST(HttpStore, MissingOrTruncatedMeshFileIsRewrittenFromTheTree) {
    Stored s;
    fs::remove(s.file(s.id_a, ".mesh"));
    const std::string mesh_b = read_all(s.file(s.id_b, ".mesh"));
    write_all(s.file(s.id_b, ".mesh"), mesh_b.substr(0, mesh_b.size() / 2));
    {
        ServerProcess server({.cache_dir = s.cache()});
        auto cli = server.client();
        EXPECT_EQ(server.metric("kdrt_store_repairs_total{file=\"mesh\"}"), 2.0);
        EXPECT_EQ(server.metric("kdrt_store_problems_total{file=\"mesh\",reason=\"missing\"}"),
                  1.0);
        EXPECT_EQ(server.metric("kdrt_store_problems_total{file=\"mesh\",reason=\"truncated\"}"),
                  1.0);
        expect_right_answer(*cli, s.id_a, s.a);
        expect_right_answer(*cli, s.id_b, s.b);
    }
    // The rewritten mesh files verify against their ids; losing the trees now is harmless.
    EXPECT_EQ(check_store(s.cache()).first, 0) << check_store(s.cache()).second;
    fs::remove(s.file(s.id_a, ".tree"));
    ServerProcess server({.cache_dir = s.cache()});
    expect_right_answer(*server.client(), s.id_a, s.a);
    EXPECT_EQ(rebuilds(server, "missing"), 1.0);
}

TEST(HttpStore, DeletedOrWrongSummariesAreRebuilt) {
    Stored s;
    const Mesh c = small_mesh(304, 1500);
    std::string id_c;
    {
        ServerProcess server({.cache_dir = s.cache()});
        id_c = upload_id(*server.client(), c);
    }
    fs::remove(s.file(s.id_a, ".json"));  // a deleted summary used to make an intact mesh a 404
    auto summary_b = proto::decode_mesh_summary(read_all(s.file(s.id_b, ".json")));
    ASSERT_TRUE(summary_b);
    summary_b->triangles += 1;
    write_all(s.file(s.id_b, ".json"), proto::encode_mesh_summary(*summary_b));
    auto summary_c = proto::decode_mesh_summary(read_all(s.file(id_c, ".json")));
    ASSERT_TRUE(summary_c);
    summary_c->bounds.hi.x += 10;  // only a trace (or the scrub) reads enough to see this
    write_all(s.file(id_c, ".json"), proto::encode_mesh_summary(*summary_c));
    EXPECT_EQ(check_store(s.cache()).first, 1);

    ServerProcess server({.cache_dir = s.cache()});
    auto cli = server.client();
    for (const auto& [id, mesh] : {std::pair{s.id_a, &s.a}, {s.id_b, &s.b}}) {
        auto res = cli->Get("/v1/meshes/" + id);
        ASSERT_EQ(res->status, 200) << res->body;
        auto got = proto::decode_mesh_summary(res->body);
        ASSERT_TRUE(got);
        EXPECT_EQ(got->triangles, mesh->triangle_count());
        EXPECT_EQ(got->bounds, mesh_bounds(*mesh));
    }
    expect_right_answer(*cli, id_c, c);
    auto got_c = proto::decode_mesh_summary(cli->Get("/v1/meshes/" + id_c)->body);
    ASSERT_TRUE(got_c);
    EXPECT_EQ(got_c->bounds, mesh_bounds(c));
    EXPECT_EQ(server.metric("kdrt_store_repairs_total{file=\"summary\"}"), 3.0);
    EXPECT_EQ(server.metric("kdrt_tree_builds_total"), 0.0);  // the trees were fine
    server.stop();
    EXPECT_EQ(check_store(s.cache()).first, 0) << check_store(s.cache()).second;
}

TEST(HttpStore, SwappedFilesOfEveryKindNeverGiveAWrongAnswer) {
    Stored s;
    swap_files(s.file(s.id_a, ".mesh"), s.file(s.id_b, ".mesh"));
    swap_files(s.file(s.id_a, ".json"), s.file(s.id_b, ".json"));
    {
        ServerProcess server({.cache_dir = s.cache()});
        auto cli = server.client();
        EXPECT_EQ(cli->Get("/v1/meshes/" + s.id_a)->status, 200);
        expect_right_answer(*cli, s.id_a, s.a);
        expect_right_answer(*cli, s.id_b, s.b);
    }
    EXPECT_EQ(check_store(s.cache()).first, 0) << check_store(s.cache()).second;
    swap_files(s.file(s.id_a, ".tree"), s.file(s.id_b, ".tree"));
    ServerProcess server({.cache_dir = s.cache()});
    auto cli = server.client();
    expect_right_answer(*cli, s.id_a, s.a);
    expect_right_answer(*cli, s.id_b, s.b);
    EXPECT_EQ(rebuilds(server, "other_mesh"), 2.0);
}

TEST(HttpStore, StartUpNeverDeletesAnAcknowledgedMesh) {
    Stored s;
    // a: summary and tree deleted, mesh file intact: recovered (not deleted as "uncommitted").
    fs::remove(s.file(s.id_a, ".json"));
    fs::remove(s.file(s.id_a, ".tree"));
    // b: mesh and tree gone, only the summary (the acknowledgement) left: kept, listed, damaged.
    fs::remove(s.file(s.id_b, ".mesh"));
    fs::remove(s.file(s.id_b, ".tree"));
    // An id with only a damaged mesh file and no summary: moved to quarantine, never deleted.
    const std::string orphan(64, 'c');
    write_all(s.file(orphan, ".mesh"), "not a mesh");
    ServerProcess server({.cache_dir = s.cache()});
    auto cli = server.client();
    expect_right_answer(*cli, s.id_a, s.a);
    EXPECT_EQ(cli->Get("/v1/meshes/" + s.id_b)->status, 200);
    auto p = expect_problem(trace(*cli, s.id_b, random_rays(mesh_bounds(s.b), 5, 2)), 500);
    EXPECT_NE(p.detail.find("does not exist"), std::string::npos) << p.detail;
    EXPECT_TRUE(fs::exists(s.file(s.id_b, ".json")));
    EXPECT_EQ(cli->Get("/v1/meshes/" + orphan)->status, 404);
    bool quarantined = false;
    for (const auto& d : fs::directory_iterator(s.cache() / "quarantine"))
        if (d.path().filename().string().rfind(orphan, 0) == 0)
            quarantined = read_all(d.path() / (orphan + ".mesh")) == "not a mesh";
    EXPECT_TRUE(quarantined);
    EXPECT_NE(server.log().find("unusable files moved to quarantine"), std::string::npos);
}

// ---- a full disk ----------------------------------------------------------------------------

/// Checks a server whose disk is full: uploads answer 507 problem+json, nothing unstored is
/// acknowledged or left behind, and stored meshes are still served.
void expect_full_disk_behaviour(ServerProcess& server, const fs::path& cache, const Mesh& stored,
                                const std::string& stored_id, const Mesh& big) {
    auto cli = server.client();
    auto p = expect_problem(upload(*cli, big), 507);
    EXPECT_EQ(p.kind, proto::ProblemKind::kInsufficientStorage);
    EXPECT_NE(p.detail.find("nothing was stored"), std::string::npos) << p.detail;
    const std::string big_id = proto::mesh_id(big);
    EXPECT_EQ(cli->Get("/v1/meshes/" + big_id)->status, 404);
    for (const char* ext : {".mesh", ".tree", ".json"})
        EXPECT_FALSE(fs::exists(cache / "meshes" / (big_id + ext))) << ext;
    auto list = proto::decode_mesh_list(cli->Get("/v1/meshes")->body);
    ASSERT_TRUE(list);
    EXPECT_EQ(list->size(), 1u);
    expect_right_answer(*cli, stored_id, stored);
}

TEST(HttpStore, FileSizeLimitAnswers507AndStoresNothing) {
    TempDir dir;
    const fs::path cache = dir.path() / "cache";
    const Mesh small = small_mesh(305, 300), big = small_mesh(306, 40000);  // ~14 KB, ~1.9 MB
    ServerProcess server({.cache_dir = cache, .file_size_limit = 1u << 20});
    const std::string id = upload_id(*server.client(), small);
    expect_full_disk_behaviour(server, cache, small, id, big);
    // A spooled upload that cannot be spooled is 507 too.
    server.stop();
    ServerProcess spooling(
        {.cache_dir = cache, .args = {"--upload-memory-bytes", "4K"}, .file_size_limit = 1u << 20});
    auto p = expect_problem(
        spooling.client()->Post("/v1/meshes", mesh_body(big, proto::MeshFormat::kRaw),
                                "application/x-kdrt-mesh"),
        507);
    EXPECT_NE(p.detail.find("spool"), std::string::npos) << p.detail;
}

/// A tmpfs of `bytes` mounted at `path` for the object's lifetime; mounted() is false where this
/// process may not mount (not root, no CAP_SYS_ADMIN).
class Tmpfs {
public:
    Tmpfs(const fs::path& path, size_t bytes) : path_(path) {
        fs::create_directories(path);
        const std::string options = "size=" + std::to_string(bytes);
        mounted_ = ::mount("tmpfs", path.c_str(), "tmpfs", 0, options.c_str()) == 0;
    }
    ~Tmpfs() {
        if (mounted_) ::umount2(path_.c_str(), MNT_DETACH);
    }
    Tmpfs(const Tmpfs&) = delete;
    Tmpfs& operator=(const Tmpfs&) = delete;
    [[nodiscard]] bool mounted() const noexcept { return mounted_; }

private:
    fs::path path_;
    bool mounted_ = false;
};

/// Writes zeros to `path` until the file system refuses.
void fill_disk(const fs::path& path) {
    std::FILE* f = std::fopen(path.c_str(), "wb");
    ASSERT_TRUE(f);
    const std::vector<char> block(64 << 10, 0);
    while (std::fwrite(block.data(), 1, block.size(), f) == block.size()) {
    }
    std::fclose(f);
}

TEST(HttpStore, FullTmpfsAnswers507AndARestartOnItStillServes) {
    TempDir dir;
    const fs::path disk = dir.path() / "disk";  // the cache itself: logs stay outside the tmpfs
    Tmpfs tmpfs(disk, 16u << 20);
    if (!tmpfs.mounted())
        GTEST_SKIP() << "cannot mount a tmpfs here (needs CAP_SYS_ADMIN); "
                        "FileSizeLimitAnswers507AndStoresNothing covers 507";
    const Mesh small = small_mesh(307, 300), big = small_mesh(308, 40000);
    std::string id;
    {
        ServerProcess server({.cache_dir = disk});
        id = upload_id(*server.client(), small);
        fill_disk(disk / "filler");
        expect_full_disk_behaviour(server, disk, small, id, big);
    }
    // A restart on the full disk with an unreadable summary: starts, recovers it in memory.
    write_all(disk / "meshes" / (id + ".json"), "");
    fill_disk(disk / "filler2");
    {
        ServerProcess server({.cache_dir = disk});
        ASSERT_TRUE(server.running());
        auto res = server.client()->Get("/v1/meshes/" + id);
        ASSERT_TRUE(res);
        EXPECT_EQ(res->status, 200) << res->body;
        expect_right_answer(*server.client(), id, small);
        EXPECT_NE(server.log().find("serving the recovered one from memory"), std::string::npos)
            << server.log();
    }
    // Space again: the same upload succeeds.
    fs::remove(disk / "filler");
    fs::remove(disk / "filler2");
    ServerProcess server({.cache_dir = disk});
    EXPECT_EQ(upload(*server.client(), big)->status, 201);
}

}  // namespace
}  // namespace kdrt::test
