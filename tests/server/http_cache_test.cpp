// The mesh cache through the real binary: durability across restarts, corrupt cache files,
// eviction and reload under a tiny memory budget, concurrent identical uploads.

#include <gtest/gtest.h>

#include <filesystem>
#include <fstream>
#include <thread>

#include "http_test_util.h"
#include "kdrt/proto/mesh_id.h"
#include "kdrt/proto/mesh_io.h"
#include "kdrt/proto/ray_batch.h"

namespace kdrt::test {
namespace {

namespace fs = std::filesystem;

void flip_tree_byte(const fs::path& path, size_t offset) {
    std::fstream f(path, std::ios::in | std::ios::out | std::ios::binary);
    ASSERT_TRUE(f) << path;
    f.seekg(static_cast<std::streamoff>(offset));
    char c = 0;
    f.get(c);
    f.seekp(static_cast<std::streamoff>(offset));
    f.put(static_cast<char>(c ^ 0x5a));
}

TEST(HttpCache, RestartKeepsEveryMesh) {
    TempDir dir;
    const Mesh a = small_mesh(11), b = small_mesh(12);
    const std::vector<Ray> rays = random_rays(mesh_bounds(a), 300, 5);
    std::string id_a, id_b;
    {
        ServerProcess server({.cache_dir = dir.path() / "cache"});
        auto cli = server.client();
        id_a = upload_id(*cli, a);
        id_b = upload_id(*cli, b);
        EXPECT_EQ(server.stop(), 0) << server.log();
        EXPECT_NE(server.log().find("shutting down signal=SIGTERM"), std::string::npos);
    }
    ServerProcess server({.cache_dir = dir.path() / "cache"});
    auto cli = server.client();
    auto list = proto::decode_mesh_list(cli->Get("/v1/meshes")->body);
    ASSERT_TRUE(list);
    ASSERT_EQ(list->size(), 2u);
    EXPECT_FALSE((*list)[0].in_memory.value_or(true));  // loaded lazily
    auto res = trace(*cli, id_a, rays);
    ASSERT_TRUE(res);
    ASSERT_EQ(res->status, 200) << res->body;
    EXPECT_EQ(res->body, engine_hits(a, rays));
    // The tree came from disk, not from a rebuild; an upload of the same mesh is not rebuilt.
    EXPECT_EQ(server.metric("kdrt_tree_builds_total"), 0.0);
    EXPECT_EQ(server.metric("kdrt_cache_misses_total"), 1.0);
    EXPECT_EQ(upload(*cli, b)->status, 200);
    EXPECT_EQ(server.metric("kdrt_tree_builds_total"), 0.0);
}

TEST(HttpCache, CorruptTreeFileIsRebuiltNotServed) {
    TempDir dir;
    const Mesh mesh = small_mesh(21, 2000);
    const std::vector<Ray> rays = random_rays(mesh_bounds(mesh), 500, 6);
    std::string id;
    {
        ServerProcess server({.cache_dir = dir.path() / "cache"});
        id = upload_id(*server.client(), mesh);
    }
    const fs::path tree_file = dir.path() / "cache" / "meshes" / (id + ".tree");
    ASSERT_TRUE(fs::exists(tree_file));
    flip_tree_byte(tree_file, fs::file_size(tree_file) / 2);

    ServerProcess server({.cache_dir = dir.path() / "cache"});
    auto cli = server.client();
    auto res = trace(*cli, id, rays);
    ASSERT_TRUE(res);
    ASSERT_EQ(res->status, 200) << res->body;
    EXPECT_EQ(res->body, engine_hits(mesh, rays));
    EXPECT_EQ(server.metric("kdrt_cache_rebuilds_total{reason=\"corrupt\"}"), 1.0);
    EXPECT_EQ(server.metric("kdrt_tree_builds_total"), 1.0);
    EXPECT_NE(server.log().find("tree file failed validation; rebuilding from the stored mesh"),
              std::string::npos)
        << server.log();
    // The rewritten file is good: a restart loads it without another rebuild.
    server.stop();
    ServerProcess again({.cache_dir = dir.path() / "cache"});
    auto res2 = trace(*again.client(), id, rays);
    ASSERT_TRUE(res2);
    EXPECT_EQ(res2->body, engine_hits(mesh, rays));
    EXPECT_EQ(again.metric("kdrt_cache_rebuilds_total{reason=\"corrupt\"}"), 0.0);
}

TEST(HttpCache, TreeOfAnOlderFormatIsRebuilt) {
    // A cache written by kdrt 0.1: its tree blob is format version 1 (tests/data/store-v1).
    const fs::path old_store = fs::path(KDRT_TEST_DATA_DIR) / "store-v1";
    const std::string id = "02b48668aa10941dfd1a5be5dab0ab8f116513d9e97666413d4e35c9b878230a";
    auto mesh = proto::load_mesh_file((old_store / "sphere.obj").string());
    ASSERT_TRUE(mesh.ok());
    ASSERT_EQ(proto::mesh_id(*mesh), id);
    TempDir dir;
    fs::create_directories(dir.path() / "cache" / "meshes");
    fs::copy(old_store / "meshes", dir.path() / "cache" / "meshes",
             fs::copy_options::recursive | fs::copy_options::overwrite_existing);
    const fs::path tree_file = dir.path() / "cache" / "meshes" / (id + ".tree");
    {
        std::ifstream f(tree_file, std::ios::binary);
        char head[12] = {};
        f.read(head, sizeof head);
        ASSERT_EQ(std::string(head, 8), "KDRTTREE");
        ASSERT_EQ(head[8], 1) << "the checked-in blob must stay format version 1";
    }
    const std::vector<Ray> rays = random_rays(mesh_bounds(*mesh), 500, 7);
    ServerProcess server({.cache_dir = dir.path() / "cache"});
    auto cli = server.client();
    auto res = trace(*cli, id, rays);
    ASSERT_TRUE(res);
    ASSERT_EQ(res->status, 200) << res->body;
    EXPECT_EQ(res->body, engine_hits(*mesh, rays));
    EXPECT_EQ(server.metric("kdrt_cache_rebuilds_total{reason=\"format_version\"}"), 1.0);
    EXPECT_NE(
        server.log().find("rebuilding from the stored mesh mesh=" + id + " reason=format_version"),
        std::string::npos)
        << server.log();
    // The tree file is rewritten in the current format: a restart loads it as it is.
    server.stop();
    ServerProcess again({.cache_dir = dir.path() / "cache"});
    auto res2 = trace(*again.client(), id, rays);
    ASSERT_TRUE(res2);
    EXPECT_EQ(res2->body, engine_hits(*mesh, rays));
    EXPECT_EQ(again.metric("kdrt_cache_rebuilds_total{reason=\"format_version\"}"), 0.0);
}

TEST(HttpCache, UnreadableSummaryIsRecoveredAtStartUp) {
    TempDir dir;
    const Mesh mesh = small_mesh(41);
    std::string id;
    {
        ServerProcess server({.cache_dir = dir.path() / "cache"});
        id = upload_id(*server.client(), mesh);
    }
    const fs::path meshes = dir.path() / "cache" / "meshes";
    std::ofstream(meshes / (id + ".json"), std::ios::trunc) << "{not json";
    // Leftovers of an upload that never committed, and a stray temp file, are cleaned up.
    const std::string orphan(64, 'b');
    std::ofstream(meshes / (orphan + ".mesh")) << "partial";
    std::ofstream(dir.path() / "cache" / "tmp" / "x.tmp") << "partial";

    ServerProcess server({.cache_dir = dir.path() / "cache"});
    auto cli = server.client();
    auto res = cli->Get("/v1/meshes/" + id);
    ASSERT_TRUE(res);
    ASSERT_EQ(res->status, 200);
    auto summary = proto::decode_mesh_summary(res->body);
    ASSERT_TRUE(summary);
    EXPECT_EQ(summary->triangles, mesh.triangle_count());
    EXPECT_FALSE(fs::exists(meshes / (orphan + ".mesh")));  // quarantined (http_store_test)
    EXPECT_FALSE(fs::exists(dir.path() / "cache" / "tmp" / "x.tmp"));
    EXPECT_NE(server.log().find("summary unreadable, recovering from the stored mesh"),
              std::string::npos);
}

TEST(HttpCache, TinyBudgetEvictsAndReloadsWithoutRebuilding) {
    TempDir dir;
    ServerProcess server({.cache_dir = dir.path() / "cache", .args = {"--memory-budget", "1"}});
    auto cli = server.client();
    const Mesh a = small_mesh(51), b = small_mesh(52), c = small_mesh(53);
    const std::string ids[3] = {upload_id(*cli, a), upload_id(*cli, b), upload_id(*cli, c)};
    const Mesh* meshes[3] = {&a, &b, &c};
    EXPECT_EQ(server.metric("kdrt_cache_evictions_total"), 2.0);
    for (int round = 0; round < 2; ++round) {
        for (int i = 0; i < 3; ++i) {
            const auto rays = random_rays(mesh_bounds(*meshes[i]), 100, static_cast<uint64_t>(i));
            auto res = trace(*cli, ids[i], rays);
            ASSERT_TRUE(res);
            ASSERT_EQ(res->status, 200) << res->body;
            EXPECT_EQ(res->body, engine_hits(*meshes[i], rays));
        }
    }
    // Only the most recently used tree stays resident; every other access reloaded from disk.
    EXPECT_EQ(server.metric("kdrt_tree_builds_total"), 3.0);
    EXPECT_EQ(server.metric("kdrt_cache_misses_total"), 6.0);
    EXPECT_EQ(server.metric("kdrt_cache_meshes{state=\"resident\"}"), 1.0);
    EXPECT_GT(server.metric("kdrt_cache_bytes{where=\"disk\"}").value_or(0), 0.0);
}

TEST(HttpCache, ConcurrentIdenticalUploadsBuildOnce) {
    TempDir dir;
    ServerProcess server({.cache_dir = dir.path() / "cache"});
    const Mesh mesh = small_mesh(61, 20000);
    const std::string body = mesh_body(mesh, proto::MeshFormat::kRaw);
    constexpr int kClients = 6;
    std::vector<int> statuses(kClients, 0);
    std::vector<std::string> ids(kClients);
    std::vector<std::thread> threads;
    threads.reserve(kClients);
    for (int i = 0; i < kClients; ++i) {
        threads.emplace_back([&, i] {
            auto cli = server.client();
            auto res = cli->Post("/v1/meshes", body, "application/x-kdrt-mesh");
            if (!res) return;
            statuses[i] = res->status;
            if (auto s = proto::decode_mesh_summary(res->body)) ids[i] = s->id;
        });
    }
    for (auto& t : threads) t.join();
    EXPECT_EQ(std::count(statuses.begin(), statuses.end(), 201), 1);
    EXPECT_EQ(std::count(statuses.begin(), statuses.end(), 200), kClients - 1);
    for (const std::string& id : ids) EXPECT_EQ(id, proto::mesh_id(mesh));
    EXPECT_EQ(server.metric("kdrt_tree_builds_total"), 1.0);
}

TEST(HttpCache, LargeUploadsAreSpooledToDisk) {
    TempDir dir;
    ServerProcess server(
        {.cache_dir = dir.path() / "cache", .args = {"--upload-memory-bytes", "4K"}});
    const Mesh mesh = small_mesh(71, 3000);
    auto res = server.client()->Post("/v1/meshes", mesh_body(mesh, proto::MeshFormat::kPly, false),
                                     "application/ply");
    ASSERT_TRUE(res);
    ASSERT_EQ(res->status, 201) << res->body;
    EXPECT_EQ(proto::decode_mesh_summary(res->body)->id, proto::mesh_id(mesh));
    // Nothing is left behind in the spool directory (tmp/<process>/, beside its lock file).
    size_t process_dirs = 0;
    for (const auto& entry : fs::directory_iterator(dir.path() / "cache" / "tmp")) {
        if (entry.path().extension() == ".lock") continue;
        ASSERT_TRUE(entry.is_directory()) << entry.path();
        EXPECT_TRUE(fs::is_empty(entry.path())) << entry.path();
        ++process_dirs;
    }
    EXPECT_EQ(process_dirs, 1u);
}

}  // namespace
}  // namespace kdrt::test
