// The `kdrt` binary against a real kdrt-server on an ephemeral loopback port: every subcommand,
// its output (human and --json), its errors and exit codes (1 server said no, 2 usage, 3 cannot
// connect, 130 interrupted).

#include <gtest/gtest.h>

#include <nlohmann/json.hpp>
#include <optional>
#include <sstream>
#include <thread>

#include "cli_runner.h"
#include "client_test_util.h"
#include "fake_server.h"
#include "kdrt/proto/mesh_id.h"
#include "kdrt/proto/multi_hit.h"
#include "kdrt/proto/problem.h"
#include "kdrt/proto/ray_batch.h"
#include "kdrt/query.h"
#include "kdrt/raygen.h"
#include "kdrt/trace.h"

namespace kdrt::test {
namespace {

const char* const kCommands[] = {"upload", "meshes",   "info", "rm",     "render",  "trace",
                                 "hits",   "distance", "rays", "health", "metrics", "bench-remote"};

std::vector<std::string> lines_of(const std::string& text) {
    std::vector<std::string> lines;
    std::istringstream in(text);
    for (std::string line; std::getline(in, line);) lines.push_back(line);
    return lines;
}

class Cli : public ::testing::Test {
protected:
    static void SetUpTestSuite() {
        dir_ = new TempDir();
        server_ =
            new ServerProcess({.cache_dir = dir_->path() / "cache", .args = {"--max-jobs", "4"}});
        Rng rng(test_seed() + 40);
        mesh_ = new Mesh(random_soup(rng, 2000));
        tree_ = new KdTree(build_kdtree(*mesh_));
        mesh_file_ = (dir_->path() / "soup.ply").string();
        const std::vector<std::byte> ply = proto::write_mesh(*mesh_, proto::MeshFormat::kPly);
        ASSERT_TRUE(proto::write_file_bytes(mesh_file_, ply));
        id_ = proto::mesh_id(*mesh_);
    }
    static void TearDownTestSuite() {
        delete server_;
        delete dir_;
        delete mesh_;
        delete tree_;
    }
    void SetUp() override { ASSERT_GT(server_->port(), 0); }

    /// Runs kdrt with --server pointing at the suite's server.
    static CliRun kdrt(const std::vector<std::string>& args, CliOptions options = {}) {
        options.env.push_back("KDRT_SERVER=" + server_url(*server_));
        return run_cli(args, options);
    }
    static std::string path(const std::string& name) { return (dir_->path() / name).string(); }
    static void upload_suite_mesh() {
        const CliRun run = kdrt({"upload", mesh_file_});
        ASSERT_EQ(run.exit_code, 0) << run.err;
    }

    static TempDir* dir_;
    static ServerProcess* server_;
    static Mesh* mesh_;
    static KdTree* tree_;
    static std::string mesh_file_;
    static std::string id_;
};
TempDir* Cli::dir_ = nullptr;
ServerProcess* Cli::server_ = nullptr;
Mesh* Cli::mesh_ = nullptr;
KdTree* Cli::tree_ = nullptr;
std::string Cli::mesh_file_;
std::string Cli::id_;

// ---- help and usage ----------------------------------------------------------------------------

TEST_F(Cli, HelpForTheToolAndEverySubcommand) {
    for (const std::vector<std::string>& args :
         {std::vector<std::string>{"--help"}, {"-h"}, {"help"}}) {
        const CliRun run = run_cli(args);
        EXPECT_EQ(run.exit_code, 0);
        EXPECT_EQ(run.out.rfind("usage: kdrt ", 0), 0u) << run.out;
        for (const char* command : kCommands)
            EXPECT_TRUE(contains(run.out, "\n  " + std::string(command) + " "));
        EXPECT_TRUE(contains(run.out, "Exit status: 0 success; 1 the server refused"));
        EXPECT_TRUE(run.err.empty());
    }
    for (const char* command : kCommands) {
        SCOPED_TRACE(command);
        const std::string usage = "usage: kdrt " + std::string(command);
        for (const std::vector<std::string>& args : {std::vector<std::string>{command, "--help"},
                                                     {command, "-h"},
                                                     {"help", command},
                                                     {"--server", "x:1", command, "--help"}}) {
            const CliRun run = run_cli(args);
            EXPECT_EQ(run.exit_code, 0) << run.err;
            EXPECT_EQ(run.out.rfind(usage, 0), 0u) << run.out;
        }
    }
    const CliRun version = run_cli({"--version"});
    EXPECT_EQ(version.exit_code, 0);
    EXPECT_EQ(version.out.rfind("kdrt 0.", 0), 0u) << version.out;
}

TEST_F(Cli, UsageErrorsExitTwoWithAMessage) {
    struct Case {
        std::vector<std::string> args;
        std::string message;
    };
    const std::vector<Case> cases = {
        {{}, "kdrt: missing command"},
        {{"frobnicate"}, "kdrt: unknown command \"frobnicate\""},
        {{"--frob", "meshes"}, "kdrt: unknown option \"--frob\" before the command"},
        {{"help", "frobnicate"}, "kdrt help: unknown command \"frobnicate\""},
        {{"meshes", "--frob"}, "kdrt meshes: unknown option \"--frob\" for kdrt meshes"},
        {{"meshes", "extra"}, "kdrt meshes: unexpected argument \"extra\""},
        {{"upload"}, "kdrt upload: missing FILE"},
        {{"upload", "--format", "fbx", "x.obj"},
         "kdrt upload: --format: \"fbx\" is not obj, ply, off, stl or raw"},
        {{"info"}, "kdrt info: missing ID"},
        {{"info", "a", "b"}, "kdrt info: unexpected argument \"b\""},
        {{"rm"}, "kdrt rm: missing ID"},
        {{"render", "abcd"}, "kdrt render: missing -o FILE"},
        {{"render", "abcd", "-o", "x.bmp"},
         "cannot tell the image format of \"x.bmp\" from its extension"},
        {{"render", "-o", "x.png"}, "kdrt render: missing ID"},
        {{"render", "abcd", "-o"}, "kdrt render: option -o needs a value"},
        {{"trace", "abcd"}, "kdrt trace: missing ID and RAYS"},
        {{"trace", "abcd", "r.kdrr"}, "kdrt trace: missing -o FILE"},
        {{"trace", "abcd", "r.kdrr", "-o", "h", "--connections", "0"},
         "--connections: \"0\" is not in 1 .. 64"},
        {{"trace", "abcd", "r.kdrr", "-o", "h", "--split", "0"},
         "--split: \"0\" is not in 1 .. 64"},
        {{"hits", "abcd", "r.kdrr", "-o", "h"}, "kdrt hits needs --all"},
        {{"hits", "abcd", "--all"}, "kdrt hits: missing ID and RAYS"},
        {{"hits", "abcd", "r.kdrr", "--all"}, "kdrt hits: missing -o FILE"},
        {{"hits", "abcd", "r.kdrr", "--all", "-o", "h", "--max-hits", "0"}, "--max-hits: \"0\""},
        {{"hits", "abcd", "r.kdrr", "--all", "-o", "h", "--fields", "uv"},
         "--fields: \"uv\" is not full, t or t_prim"},
        {{"hits", "abcd", "r.kdrr", "--all", "-o", "h.ply", "--count-only"},
         "--count-only writes KDRC counts"},
        {{"rays", "m.obj"}, "kdrt rays: missing -o FILE"},
        {{"rays"}, "kdrt rays: missing MESH"},
        {{"rays", "m.obj", "-o", "r", "--kind", "sideways"},
         "--kind: \"sideways\" is not primary, shadow, diffuse or random"},
        {{"rays", "m.obj", "-o", "r", "--res", "0"}, "--res: \"0\" is not in 1 .. 8192"},
        {{"health", "--server", "ftp://x"}, "unknown scheme \"ftp\""},
        {{"health", "--timeout", "-1"}, "--timeout: \"-1\" is not a positive number of seconds"},
        {{"health", "--retries", "many"}, "--retries: \"many\" is not a whole number"},
        {{"bench-remote"}, "kdrt bench-remote: missing ID"},
        {{"bench-remote", "abcd", "--mesh", "m", "--rays", "r"}, "give --mesh or --rays, not both"},
        {{"bench-remote", "abcd", "--reps", "0"}, "--reps: \"0\" is not in 1 .. 100"},
        {{"json", "--json=yes"}, "kdrt: unknown command \"json\""},
        {{"meshes", "--json=yes"}, "option --json takes no value"},
    };
    for (const Case& c : cases) {
        std::string joined;
        for (const auto& a : c.args) joined += a + " ";
        SCOPED_TRACE(joined);
        const CliRun run = kdrt(c.args);
        EXPECT_EQ(run.exit_code, 2) << run.err;
        EXPECT_TRUE(contains(run.err, c.message)) << run.err;
        EXPECT_TRUE(run.out.empty()) << run.out;
    }
}

TEST_F(Cli, RenderOptionsAreCheckedBeforeAnyRequest) {
    upload_suite_mesh();
    struct Case {
        std::vector<std::string> args;
        std::string message;
    };
    const std::vector<Case> cases = {
        {{"--size", "100"}, "--size: \"100\" is not WIDTHxHEIGHT"},
        {{"--size", "0x10"}, "--size: \"0x10\" is not WIDTHxHEIGHT"},
        {{"--eye", "1,2"}, "--eye: \"1,2\" is not three numbers x,y,z"},
        {{"--look-at", "a,b,c"}, "--look-at: \"a,b,c\" is not three numbers"},
        {{"--fov", "180"}, "--fov: \"180\" is not a number of degrees in (0, 180)"},
        {{"--ortho", "-1"}, "--ortho: \"-1\" is not a positive number"},
        {{"--shading", "toon"},
         "--shading: \"toon\" is not normals, eyelight, ao, diffuse, depth, primid or geomid"},
        {{"--spp", "0"}, "--spp: \"0\" is not in 1 .. 65536"},
        {{"--seed", "-3"}, "--seed: \"-3\" is not a whole number"},
        {{"--tile", "1,2,3"}, "--tile: \"1,2,3\" is not x,y,w,h"},
        {{"--ao-samples", "0"}, "--ao-samples: \"0\" is not in 1 .. 4096"},
        {{"--ao-distance", "0"}, "--ao-distance: \"0\" is not a number > 0"},
        {{"--light", "0,0,0"}, "--light: the direction must not be the zero vector"},
        {{"--light", "1,2"}, "--light: \"1,2\" is not three numbers x,y,z"},
        {{"--light-intensity", "-1"}, "--light-intensity: \"-1\" is not a number >= 0"},
        {{"--bounces", "65"}, "--bounces: \"65\" is not in 0 .. 64"},
        {{"--sky", "nan"}, "--sky: \"nan\" is not a number >= 0"},
        {{"--background", "1,x,0"}, "--background: \"1,x,0\" is not three numbers x,y,z"},
    };
    for (const Case& c : cases) {
        SCOPED_TRACE(c.args[0]);
        std::vector<std::string> args = {"render", id_, "-o", path("never.png")};
        args.insert(args.end(), c.args.begin(), c.args.end());
        const CliRun run = kdrt(args);
        EXPECT_EQ(run.exit_code, 2) << run.err;
        EXPECT_TRUE(contains(run.err, c.message)) << run.err;
        EXPECT_FALSE(std::filesystem::exists(path("never.png")));
    }
}

// ---- meshes ------------------------------------------------------------------------------------

TEST_F(Cli, UploadPrintsIdTrianglesAndBuildTimePerFile) {
    const std::string off = data_path("diplodocus.off");
    const CliRun run = kdrt({"upload", mesh_file_, off});
    ASSERT_EQ(run.exit_code, 0) << run.err;
    const auto lines = lines_of(run.out);
    ASSERT_EQ(lines.size(), 2u) << run.out;
    EXPECT_EQ(lines[0].rfind(id_ + "  2000 triangles  ", 0), 0u) << lines[0];
    EXPECT_TRUE(lines[0].ends_with(" ms  " + mesh_file_)) << lines[0];
    const std::string dino = proto::mesh_id(load_mesh(off));
    EXPECT_EQ(
        lines[1].rfind(
            dino + "  " + std::to_string(load_mesh(off).triangle_count()) + " triangles  ", 0),
        0u);

    const CliRun json = kdrt({"upload", "--json", mesh_file_, off});
    ASSERT_EQ(json.exit_code, 0) << json.err;
    const auto json_lines = lines_of(json.out);
    ASSERT_EQ(json_lines.size(), 2u);
    const auto first = nlohmann::json::parse(json_lines[0]);
    EXPECT_EQ(first["file"], mesh_file_);
    EXPECT_EQ(first["id"], id_);
    EXPECT_EQ(first["triangles"], 2000);
    EXPECT_EQ(first["vertices"], mesh_->vertex_count());
    for (const char* key : {"bounds", "build_ms", "tree", "in_memory"})
        EXPECT_TRUE(first.contains(key)) << key;
    EXPECT_EQ(nlohmann::json::parse(json_lines[1])["id"], dino);

    // --format overrides the extension.
    const std::string renamed = path("soup.data");
    std::filesystem::copy_file(mesh_file_, renamed,
                               std::filesystem::copy_options::overwrite_existing);
    const CliRun formatted = kdrt({"upload", renamed, "--format", "ply"});
    EXPECT_EQ(formatted.exit_code, 0) << formatted.err;
    EXPECT_EQ(formatted.out.rfind(id_, 0), 0u);
}

TEST_F(Cli, UploadErrorsNameTheFileAndKeepGoing) {
    const std::string bad = path("bad.obj");
    write_text(bad, "v 0 0 0\nv 1 0 0\nf 1 2 3\n");
    const CliRun run = kdrt({"upload", bad, mesh_file_});
    EXPECT_EQ(run.exit_code, 1);
    EXPECT_TRUE(contains(run.err, "kdrt upload: " + bad + ": 422 Mesh parse error: line 3:"))
        << run.err;
    EXPECT_EQ(run.out.rfind(id_, 0), 0u) << run.out;  // the good file was still uploaded

    const CliRun missing = kdrt({"upload", path("nope.obj"), mesh_file_});
    EXPECT_EQ(missing.exit_code, 2);
    EXPECT_TRUE(contains(missing.err, "cannot upload: cannot open \"" + path("nope.obj") +
                                          "\" for reading: No such file or directory"))
        << missing.err;
    EXPECT_EQ(missing.out.rfind(id_, 0), 0u);

    const CliRun unknown = kdrt({"upload", path("x.fbx")});
    EXPECT_EQ(unknown.exit_code, 2);
    EXPECT_TRUE(contains(unknown.err, "cannot tell the mesh format of \"" + path("x.fbx") + "\""))
        << unknown.err;

    const CliRun empty = kdrt({"upload", "--format", "obj", "/dev/null"});
    EXPECT_EQ(empty.exit_code, 1) << empty.err;
    EXPECT_TRUE(contains(empty.err, "422 Invalid mesh: the obj mesh has no triangles"))
        << empty.err;
}

TEST_F(Cli, MeshesInfoAndRm) {
    upload_suite_mesh();
    const CliRun list = kdrt({"meshes"});
    ASSERT_EQ(list.exit_code, 0) << list.err;
    EXPECT_EQ(list.out.rfind("ID ", 0), 0u);
    EXPECT_TRUE(contains(list.out, "\n" + id_ + " ")) << list.out;
    const CliRun json = kdrt({"meshes", "--json"});
    ASSERT_EQ(json.exit_code, 0);
    bool found = false;
    for (const std::string& line : lines_of(json.out))
        found |= nlohmann::json::parse(line)["id"] == id_;
    EXPECT_TRUE(found) << json.out;

    const CliRun info = kdrt({"info", id_});
    ASSERT_EQ(info.exit_code, 0) << info.err;
    EXPECT_TRUE(contains(info.out, "id          " + id_ + "\ntriangles   2000\n")) << info.out;
    EXPECT_TRUE(contains(info.out, "\ntree        ")) << info.out;
    const CliRun by_prefix = kdrt({"info", id_.substr(0, 12), "--json"});
    ASSERT_EQ(by_prefix.exit_code, 0) << by_prefix.err;
    EXPECT_EQ(nlohmann::json::parse(by_prefix.out)["id"], id_);
    const CliRun upper =
        kdrt({"info", "--json",
              std::string(1, static_cast<char>(std::toupper(id_[0]))) + id_.substr(1, 7)});
    EXPECT_EQ(upper.exit_code, 0) << upper.err;

    // Two meshes whose ids share a prefix cannot exist on demand; an unknown prefix can.
    std::string absent = id_.substr(0, 8);
    absent[0] = absent[0] == 'f' ? '0' : 'f';
    const CliRun no_match = kdrt({"info", absent});
    EXPECT_EQ(no_match.exit_code, 1);
    EXPECT_TRUE(
        contains(no_match.err, "kdrt info: no stored mesh has an id starting with " + absent))
        << no_match.err;

    const CliRun rm = kdrt({"rm", id_});
    ASSERT_EQ(rm.exit_code, 0) << rm.err;
    EXPECT_EQ(rm.out, "removed " + id_ + "\n");
    const CliRun gone = kdrt({"info", id_});
    EXPECT_EQ(gone.exit_code, 1);
    EXPECT_TRUE(contains(gone.err, "kdrt info: 404 Unknown mesh: no mesh with id " + id_))
        << gone.err;
    const CliRun rm_again = kdrt({"rm", id_});
    EXPECT_EQ(rm_again.exit_code, 1);
    EXPECT_TRUE(contains(rm_again.err, "404 Unknown mesh")) << rm_again.err;
    const CliRun not_an_id = kdrt({"info", "hello"});
    EXPECT_EQ(not_an_id.exit_code, 1);
    EXPECT_TRUE(contains(not_an_id.err, "404 Unknown mesh: \"hello\" is not a mesh id"))
        << not_an_id.err;
}

TEST_F(Cli, AmbiguousIdPrefixIsAUsageError) {
    // Upload meshes until two ids share their first 4 hex digits (about 300 random meshes on
    // average for one collision among 65536 prefixes; bounded).
    std::map<std::string, std::string> by_prefix;
    std::string prefix;
    Client c(server_url(*server_), fast_options());
    for (uint64_t seed = 1; seed <= 2000 && prefix.empty(); ++seed) {
        Mesh tiny;
        add_triangle(tiny, {0, 0, 0}, {1, 0, 0}, {0, static_cast<float>(seed), 0});
        const std::string id = proto::mesh_id(tiny);
        if (by_prefix.count(id.substr(0, 4))) {
            ASSERT_TRUE(c.upload(tiny));
            Mesh other;
            add_triangle(other, {0, 0, 0}, {1, 0, 0},
                         {0, std::stof(by_prefix[id.substr(0, 4)]), 0});
            ASSERT_TRUE(c.upload(other));
            prefix = id.substr(0, 4);
        }
        by_prefix[id.substr(0, 4)] = std::to_string(seed);
    }
    ASSERT_FALSE(prefix.empty());
    const CliRun run = kdrt({"info", prefix});
    EXPECT_EQ(run.exit_code, 2);
    EXPECT_TRUE(contains(run.err, "mesh id prefix " + prefix + " is ambiguous: ")) << run.err;
    EXPECT_TRUE(contains(run.err, " stored meshes start with it; give more digits")) << run.err;
}

// ---- render ------------------------------------------------------------------------------------

TEST_F(Cli, RenderWritesTheFormatOfTheExtension) {
    upload_suite_mesh();
    Client c(server_url(*server_), fast_options());
    struct Case {
        const char* file;
        const char* format;
        std::string magic;
    };
    for (const Case& k : {Case{"out.png", "png", std::string("\x89PNG\r\n\x1a\n", 8)},
                          Case{"out.JPG", "jpg", std::string("\xff\xd8\xff", 3)},
                          Case{"out.jpeg", "jpg", std::string("\xff\xd8\xff", 3)},
                          Case{"out.exr", "exr", std::string("\x76\x2f\x31\x01", 4)}}) {
        SCOPED_TRACE(k.file);
        const CliRun run =
            kdrt({"render", id_, "-o", path(k.file), "--size", "80x60", "--shading", "normals"});
        ASSERT_EQ(run.exit_code, 0) << run.err;
        EXPECT_TRUE(contains(run.err, "wrote " + path(k.file) + " (")) << run.err;
        EXPECT_TRUE(contains(run.err, "80x60 normals, 1 spp)")) << run.err;
        const std::vector<std::byte> bytes = read_bytes(path(k.file));
        ASSERT_GE(bytes.size(), k.magic.size());
        EXPECT_EQ(std::memcmp(bytes.data(), k.magic.data(), k.magic.size()), 0);
        RenderRequest same = small_render(id_, Shading::kNormals, k.format);
        same.settings.width = 80;
        same.settings.height = 60;
        auto expected = c.render(same);
        ASSERT_TRUE(expected) << expected.error().to_string();
        expect_same_image(bytes, *expected, k.format);
    }
}

TEST_F(Cli, RenderShadingSettingsReachTheServer) {
    upload_suite_mesh();
    // Every setting flag, each away from its default, gives the bytes of the same request made
    // through the client library.
    const CliRun diffuse =
        kdrt({"render", id_, "-o", path("sun.png"), "--size", "48x40", "--shading", "diffuse",
              "--light", "-1,2,0.5", "--light-intensity", "0.6", "--bounces", "1", "--sky", "0.25",
              "--background", "0.1,0.2,0.3"});
    ASSERT_EQ(diffuse.exit_code, 0) << diffuse.err;
    RenderRequest sun = small_render(id_, Shading::kDiffuse);
    sun.settings.width = 48;
    sun.settings.height = 40;
    sun.settings.light.direction = {-1.0f, 2.0f, 0.5f};
    sun.settings.light.intensity = 0.6f;
    sun.settings.bounces = 1;
    sun.settings.sky = 0.25f;
    sun.settings.background = {0.1f, 0.2f, 0.3f};
    auto expected = Client(server_url(*server_), fast_options()).render(sun);
    ASSERT_TRUE(expected) << expected.error().to_string();
    EXPECT_EQ(read_bytes(path("sun.png")), *expected);
    RenderRequest plain = small_render(id_, Shading::kDiffuse);
    plain.settings.width = 48;
    plain.settings.height = 40;
    auto defaults = Client(server_url(*server_), fast_options()).render(plain);
    ASSERT_TRUE(defaults) << defaults.error().to_string();
    EXPECT_NE(*defaults, *expected) << "the settings changed the picture";

    const CliRun ao = kdrt({"render", id_, "-o", path("ao.png"), "--size", "40x40", "--shading",
                            "ao", "--ao-samples", "5", "--ao-distance", "0.5"});
    ASSERT_EQ(ao.exit_code, 0) << ao.err;
    RenderRequest occ = small_render(id_, Shading::kAo);
    occ.settings.width = 40;
    occ.settings.height = 40;
    occ.settings.ao_samples = 5;
    occ.settings.ao_distance = 0.5f;
    auto expected_ao = Client(server_url(*server_), fast_options()).render(occ);
    ASSERT_TRUE(expected_ao) << expected_ao.error().to_string();
    EXPECT_EQ(read_bytes(path("ao.png")), *expected_ao);
}

TEST_F(Cli, RenderCameraOptionsOverrideTheDefaultView) {
    upload_suite_mesh();
    const CliRun run = kdrt({"render",    id_,           "-o",        path("cam.png"),
                             "--size",    "64x48",       "--eye",     "0.5,0.5,3",
                             "--look-at", "0.5,0.5,0.5", "--up",      "0,1,0",
                             "--fov",     "30",          "--spp",     "2",
                             "--seed",    "7",           "--shading", "depth",
                             "--tile",    "8,8,16,16"});
    ASSERT_EQ(run.exit_code, 0) << run.err;
    RenderRequest same = small_render(id_, Shading::kDepth);
    same.settings.width = 64;
    same.settings.height = 48;
    same.settings.spp = 2;
    same.settings.seed = 7;
    same.settings.region = PixelRegion{8, 8, 16, 16};
    same.settings.camera = CameraSpec{
        {0.5f, 0.5f, 3}, {0.5f, 0.5f, 0.5f}, {0, 1, 0}, 30.0f, 1.0f, Projection::kPerspective};
    auto expected = Client(server_url(*server_), fast_options()).render(same);
    ASSERT_TRUE(expected) << expected.error().to_string();
    EXPECT_EQ(read_bytes(path("cam.png")), *expected);

    // Only --ortho: the rest of the camera is the default view of the bounds.
    const CliRun ortho =
        kdrt({"render", id_, "-o", path("ortho.png"), "--ortho", "2", "--size", "32x32"});
    ASSERT_EQ(ortho.exit_code, 0) << ortho.err;
    RenderRequest ortho_request = small_render(id_);
    ortho_request.settings.width = ortho_request.settings.height = 32;
    auto info = Client(server_url(*server_), fast_options()).mesh(id_);
    ASSERT_TRUE(info);
    CameraSpec spec = default_camera(info->bounds, 1.0f);
    spec.projection = Projection::kOrthographic;
    spec.ortho_height = 2;
    ortho_request.settings.camera = spec;
    auto ortho_expected = Client(server_url(*server_), fast_options()).render(ortho_request);
    ASSERT_TRUE(ortho_expected);
    EXPECT_EQ(read_bytes(path("ortho.png")), *ortho_expected);
}

TEST_F(Cli, RenderProgressIsPlainLinesWithoutATerminal) {
    upload_suite_mesh();
    const CliRun run =
        kdrt({"render", id_, "-o", path("progress.png"), "--size", "512x512", "--shading", "ao"});
    ASSERT_EQ(run.exit_code, 0) << run.err;
    EXPECT_EQ(run.err.find('\r'), std::string::npos);
    const auto lines = lines_of(run.err);
    ASSERT_FALSE(lines.empty());
    // Progress lines, then the summary (stderr too: stdout stays empty).
    ASSERT_GE(lines.size(), 2u);
    for (size_t i = 0; i + 1 < lines.size(); ++i)
        EXPECT_EQ(lines[i].rfind("render: ", 0), 0u) << lines[i];
    EXPECT_EQ(lines[lines.size() - 2].rfind("render: done in ", 0), 0u) << run.err;
    EXPECT_EQ(lines.back().rfind("wrote " + path("progress.png") + " (", 0), 0u) << run.err;
    EXPECT_EQ(run.out, "");
    const CliRun quiet =
        kdrt({"render", id_, "-o", path("quiet.png"), "--size", "64x64", "--quiet"});
    ASSERT_EQ(quiet.exit_code, 0);
    EXPECT_TRUE(quiet.err.empty()) << quiet.err;
}

TEST_F(Cli, RenderProgressIsABarOnATerminal) {
    upload_suite_mesh();
    const CliRun run =
        kdrt({"render", id_, "-o", path("bar.png"), "--size", "512x512", "--shading", "ao"},
             {.stderr_tty = true});
    ASSERT_EQ(run.exit_code, 0) << run.err;
    EXPECT_TRUE(contains(run.err, "\rrender: [")) << run.err;
    EXPECT_TRUE(contains(run.err, "] 100% done")) << run.err;
    EXPECT_TRUE(contains(run.err, "render: done in ")) << run.err;
}

TEST_F(Cli, InterruptCancelsTheRenderJob) {
    upload_suite_mesh();
    const CliRun run = kdrt({"render", id_, "-o", path("never.exr"), "--size", "2048x2048",
                             "--shading", "ao", "--spp", "256"},
                            {.interrupt_when = "render: "});
    EXPECT_EQ(run.exit_code, 130) << run.err;
    const std::string marker = "interrupted; job ";
    const size_t at = run.err.find(marker);
    ASSERT_NE(at, std::string::npos) << run.err;
    const std::string job_id = run.err.substr(at + marker.size(), 32);
    EXPECT_TRUE(contains(run.err, marker + job_id + " cancelled"));
    EXPECT_FALSE(std::filesystem::exists(path("never.exr")));
    Client c(server_url(*server_), fast_options());
    Job job;
    job.id = job_id;
    auto status = c.job(job_id);
    ASSERT_TRUE(status) << status.error().to_string();
    EXPECT_TRUE(status->cancel_requested || status->state == proto::JobState::kCancelled);
}

TEST_F(Cli, RenderErrors) {
    const std::string unknown(64, 'e');
    const CliRun run = kdrt({"render", unknown, "-o", path("x.png")});
    EXPECT_EQ(run.exit_code, 1);
    EXPECT_TRUE(contains(run.err, "kdrt render: 404 Unknown mesh: no mesh with id " + unknown))
        << run.err;
    upload_suite_mesh();
    const CliRun too_big = kdrt({"render", id_, "-o", path("x.png"), "--spp", "5000"});
    EXPECT_EQ(too_big.exit_code, 1);
    EXPECT_TRUE(contains(too_big.err, "kdrt render: 400 Bad request: ")) << too_big.err;
    const CliRun unwritable =
        kdrt({"render", id_, "-o", path("no/such/dir/x.png"), "--size", "8x8"});
    EXPECT_EQ(unwritable.exit_code, 2);
    EXPECT_TRUE(contains(unwritable.err, "cannot write the image: ")) << unwritable.err;
}

/// Images the suite's server has rendered (kdrt_renders_total: counted before the answer is
/// sent, unlike the per-request counters, which follow it).
double renders(const ServerProcess& server) {
    return server.metric("kdrt_renders_total").value_or(-1);
}

TEST_F(Cli, SplitRenderWritesTheBytesOfTheUnsplitRender) {
    upload_suite_mesh();
    Client c(server_url(*server_), fast_options());
    struct Case {
        const char* file;
        const char* format;
        std::vector<std::string> args;
        unsigned parts;
        Shading shading;
        std::optional<PixelRegion> tile;
    };
    const std::vector<Case> cases = {
        {"split.png", "png", {"--shading", "normals", "--split", "6"}, 6, Shading::kNormals, {}},
        {"split.jpg", "jpg", {"--shading", "normals", "--split", "6"}, 6, Shading::kNormals, {}},
        {"split.exr", "exr", {"--shading", "normals", "--split", "6"}, 6, Shading::kNormals, {}},
        // Random sampling (ao, 2 spp): every pixel's samples are the same in any band.
        {"ao.png", "png", {"--shading", "ao", "--spp", "2", "--split", "5"}, 5, Shading::kAo, {}},
        {"one.png", "png", {"--split", "1"}, 1, Shading::kEyelight, {}},
        {"rows.png", "png", {"--split", "64"}, 64, Shading::kEyelight, {}},
        // A tile in one band per row.
        {"tile.png",
         "png",
         {"--tile", "10,5,50,33", "--split", "33"},
         33,
         Shading::kEyelight,
         PixelRegion{10, 5, 50, 33}},
    };
    for (const Case& k : cases) {
        SCOPED_TRACE(k.file);
        std::vector<std::string> args = {
            "render", id_, "-o", path(k.file), "--size", "96x64", "--connections", "3"};
        args.insert(args.end(), k.args.begin(), k.args.end());
        const double before = renders(*server_);
        const CliRun run = kdrt(args);
        ASSERT_EQ(run.exit_code, 0) << run.err;
        const uint32_t width = k.tile ? k.tile->width : 96, height = k.tile ? k.tile->height : 64;
        EXPECT_TRUE(contains(run.err, "wrote " + path(k.file) + " (")) << run.err;
        EXPECT_TRUE(contains(run.err, std::to_string(width) + "x" + std::to_string(height) + " " +
                                          std::string(shading_name(k.shading)) + ", " +
                                          (k.shading == Shading::kAo ? "2" : "1") + " spp, " +
                                          std::to_string(k.parts) +
                                          (k.parts == 1 ? " part)" : " parts)")))
            << run.out;
        // One synchronous render per band.
        EXPECT_EQ(renders(*server_) - before, k.parts);
        RenderRequest same = small_render(id_, k.shading, k.format);
        if (k.shading == Shading::kAo) same.settings.spp = 2;
        same.settings.region = k.tile;
        auto expected = c.render(same);
        ASSERT_TRUE(expected) << expected.error().to_string();
        expect_same_image(read_bytes(path(k.file)), *expected, k.format);
    }
}

TEST_F(Cli, SplitRenderUsageErrors) {
    upload_suite_mesh();
    struct Case {
        std::vector<std::string> args;
        std::string message;
    };
    const std::vector<Case> cases = {
        {{"--split", "0"},
         "kdrt render: --split: \"0\" is not in 1 .. 16384 (bands of rows, at most one per row of "
         "the frame or tile)"},
        {{"--split", "16385"}, "--split: \"16385\" is not in 1 .. 16384"},
        {{"--split", "two"}, "--split: \"two\" is not a whole number"},
        {{"--size", "96x64", "--split", "65"},
         "kdrt render: --split: 65 bands, but the frame has only 64 rows (at most one band per "
         "row)"},
        {{"--tile", "0,0,8,4", "--split", "5"},
         "--split: 5 bands, but the tile has only 4 rows (at most one band per row)"},
        {{"--connections", "2"}, "kdrt render: --connections applies to --split renders only"},
        {{"--split", "2", "--connections", "0"}, "--connections: \"0\" is not in 1 .. 64"},
        {{"--split", "2", "--connections", "65"}, "--connections: \"65\" is not in 1 .. 64"},
    };
    const double before = renders(*server_);
    for (const Case& c : cases) {
        std::string joined;
        for (const auto& a : c.args) joined += a + " ";
        SCOPED_TRACE(joined);
        std::vector<std::string> args = {"render", id_, "-o", path("never.png")};
        args.insert(args.end(), c.args.begin(), c.args.end());
        const CliRun run = kdrt(args);
        // 2: a usage error, found here (a server's refusal exits 1).
        EXPECT_EQ(run.exit_code, 2) << run.err;
        EXPECT_TRUE(contains(run.err, c.message)) << run.err;
        EXPECT_TRUE(run.out.empty()) << run.out;
        EXPECT_FALSE(std::filesystem::exists(path("never.png")));
    }
    EXPECT_EQ(renders(*server_), before);
}

// ---- rays, trace -------------------------------------------------------------------------------

TEST_F(Cli, RaysWritesTheEngineRaySets) {
    for (const char* kind : {"primary", "shadow", "diffuse", "random"}) {
        SCOPED_TRACE(kind);
        const std::string out = path(std::string(kind) + ".kdrr");
        // No server needed: a bad KDRT_SERVER does not matter.
        const CliRun run =
            run_cli({"rays", mesh_file_, "-o", out, "--kind", kind, "--res", "64", "--seed", "5"},
                    {.env = {"KDRT_SERVER=ftp://nowhere"}});
        ASSERT_EQ(run.exit_code, 0) << run.err;
        const auto parsed = parse_ray_kind(kind);
        const std::vector<Ray> want =
            generate_rays(*tree_, {.kind = *parsed, .res = 64, .seed = 5});
        EXPECT_EQ(read_bytes(out), proto::encode_rays(want, *parsed == RayKind::kShadow));
        EXPECT_TRUE(
            contains(run.err, "wrote " + std::to_string(want.size()) + " " + kind + " rays"))
            << run.err;
    }
    const CliRun json =
        run_cli({"rays", mesh_file_, "-o", path("j.kdrr"), "--res", "16", "--json"});
    ASSERT_EQ(json.exit_code, 0) << json.err;
    const auto line = nlohmann::json::parse(json.out);
    EXPECT_EQ(line["command"], "rays");
    EXPECT_EQ(line["kind"], "primary");
    EXPECT_EQ(line["rays"], 256);
    EXPECT_EQ(line["bytes"], 16 + 256 * 32);
    EXPECT_EQ(line["occlusion"], false);
}

TEST_F(Cli, RaysErrors) {
    const std::string bad = path("broken.off");
    write_text(bad, "OFF\n3 1 0\n0 0 0\n1 0 0\n");
    const CliRun run = run_cli({"rays", bad, "-o", path("r.kdrr")});
    EXPECT_EQ(run.exit_code, 2);
    EXPECT_TRUE(contains(run.err, "kdrt rays: cannot read the mesh: " + bad + ": line 5:"))
        << run.err;
    const CliRun missing = run_cli({"rays", path("absent.obj"), "-o", path("r.kdrr")});
    EXPECT_EQ(missing.exit_code, 2);
    EXPECT_TRUE(contains(missing.err, "No such file or directory")) << missing.err;
    const CliRun unwritable =
        run_cli({"rays", mesh_file_, "-o", path("no/dir/r.kdrr"), "--res", "4"});
    EXPECT_EQ(unwritable.exit_code, 2);
    EXPECT_TRUE(contains(unwritable.err, "kdrt rays: cannot write the rays: ")) << unwritable.err;
}

TEST_F(Cli, TraceWritesTheEngineAnswers) {
    upload_suite_mesh();
    for (const char* kind : {"primary", "shadow"}) {
        SCOPED_TRACE(kind);
        const std::string rays = path(std::string("t_") + kind + ".kdrr");
        const std::string out = path(std::string("t_") + kind + ".out");
        ASSERT_EQ(
            run_cli({"rays", mesh_file_, "-o", rays, "--kind", kind, "--res", "300"}).exit_code, 0);
        const CliRun run =
            kdrt({"trace", id_, rays, "-o", out, "--connections", "2", "--chunk-rays", "7000"});
        ASSERT_EQ(run.exit_code, 0) << run.err;
        auto batch = proto::decode_rays(read_bytes(rays));
        ASSERT_TRUE(batch);
        // Split into 5 routed parts (docs/scale-out.md): the same answers, byte for byte.
        const std::string split_out = path(std::string("t_") + kind + ".split.out");
        const CliRun split = kdrt({"trace", id_, rays, "-o", split_out, "--split", "5"});
        ASSERT_EQ(split.exit_code, 0) << split.err;
        EXPECT_EQ(read_bytes(split_out), read_bytes(out));
        if (batch->occlusion) {
            std::vector<uint8_t> want(batch->rays.size());
            occluded(*tree_, batch->rays, want);
            EXPECT_EQ(read_bytes(out), proto::encode_occlusion(want));
            EXPECT_TRUE(contains(run.err, " occluded -> " + out)) << run.err;
        } else {
            std::vector<Hit> want(batch->rays.size());
            intersect(*tree_, batch->rays, want);
            EXPECT_EQ(read_bytes(out), proto::encode_hits(want));
            const auto hits =
                std::count_if(want.begin(), want.end(), [](const Hit& h) { return h.is_hit(); });
            EXPECT_TRUE(contains(run.err,
                                 "over 2 connections: " + std::to_string(hits) + " hits -> " + out))
                << run.err;
        }
        EXPECT_EQ(run.err.rfind("traced " + std::to_string(batch->rays.size()) + " rays (", 0), 0u)
            << run.err;
    }
    const CliRun json =
        kdrt({"trace", id_.substr(0, 10), path("t_primary.kdrr"), "-o", path("j.kdrh"), "--json"});
    ASSERT_EQ(json.exit_code, 0) << json.err;
    const auto line = nlohmann::json::parse(json.out);
    EXPECT_EQ(line["mesh"], id_);
    EXPECT_EQ(line["rays"], 90000);
    EXPECT_EQ(line["connections"], 4);
    EXPECT_GT(line["mrays_per_s"].get<double>(), 0.0);
}

TEST_F(Cli, HitsAllWritesTheEngineAnswers) {
    upload_suite_mesh();
    const std::string rays = path("all.kdrr");
    ASSERT_EQ(
        run_cli({"rays", mesh_file_, "-o", rays, "--kind", "random", "--res", "60"}).exit_code, 0);
    auto batch = proto::decode_rays(read_bytes(rays));
    ASSERT_TRUE(batch);
    // KDRM in two chunks, joined: the engine's answer.
    const std::string out = path("all.kdrm");
    CliRun run = kdrt({"hits", id_, rays, "--all", "-o", out, "--max-hits", "3", "--merge",
                       "--normal", "--chunk-rays", "2000"});
    ASSERT_EQ(run.exit_code, 0) << run.err;
    const AllHits want = intersect_all(*tree_, batch->rays, AllHitsOptions{3, true});
    std::vector<Vec3> normals(want.hits.size());
    hit_attributes(*tree_, want.hits, normals, {});
    proto::MultiHitsView view;
    view.layout.normal = true;
    view.merged = true;
    view.max_hits = 3;
    view.offsets = want.offsets;
    view.counts = want.counts;
    view.hits = want.hits;
    view.normals = normals;
    EXPECT_EQ(read_bytes(out), proto::encode_multi_hits(view));
    uint64_t total = 0;
    for (uint32_t c : want.counts) total += c;
    EXPECT_TRUE(contains(run.err, ": " + std::to_string(total) + " hits, " +
                                      std::to_string(want.hits.size()) + " kept -> " + out))
        << run.err;
    // Counts only.
    run = kdrt({"hits", id_, rays, "--all", "--count-only", "-o", path("all.kdrc")});
    ASSERT_EQ(run.exit_code, 0) << run.err;
    std::vector<uint32_t> counts(batch->rays.size());
    count_intersections(*tree_, batch->rays, false, counts);
    EXPECT_EQ(read_bytes(path("all.kdrc")), proto::encode_hit_counts(counts));
    // A PLY point cloud of the hit points.
    run = kdrt({"hits", id_, rays, "--all", "-o", path("all.ply"), "--max-hits", "2"});
    ASSERT_EQ(run.exit_code, 0) << run.err;
    const std::vector<std::byte> ply = read_bytes(path("all.ply"));
    const std::string head(reinterpret_cast<const char*>(ply.data()),
                           std::min<size_t>(ply.size(), 400));
    EXPECT_EQ(head.rfind("ply\nformat binary_little_endian 1.0\n", 0), 0u) << head;
    const AllHits two = intersect_all(*tree_, batch->rays, AllHitsOptions{2, false});
    EXPECT_TRUE(contains(head, "element vertex " + std::to_string(two.hits.size()) + "\n")) << head;
}

TEST_F(Cli, TraceErrors) {
    upload_suite_mesh();
    const std::string junk = path("junk.kdrr");
    write_text(junk, "ABCDxxxxxxxxxxxxxxxx");
    const CliRun bad = kdrt({"trace", id_, junk, "-o", path("h.kdrh")});
    EXPECT_EQ(bad.exit_code, 2);
    EXPECT_TRUE(contains(bad.err, "kdrt trace: cannot read the rays: " + junk +
                                      " is not a KDRR ray batch: bad_magic: bad magic \"ABCD\""))
        << bad.err;
    const CliRun missing = kdrt({"trace", id_, path("none.kdrr"), "-o", path("h.kdrh")});
    EXPECT_EQ(missing.exit_code, 2);
    EXPECT_TRUE(contains(missing.err, "No such file or directory")) << missing.err;

    const std::string rays = path("few.kdrr");
    std::vector<Ray> few(10, Ray{0, 0, -5, 0, 0, 0, 1, INFINITY});
    ASSERT_TRUE(proto::write_file_bytes(rays, proto::encode_rays(few, false)));
    const CliRun unknown = kdrt({"trace", std::string(64, 'd'), rays, "-o", path("h.kdrh")});
    EXPECT_EQ(unknown.exit_code, 1);
    EXPECT_TRUE(contains(unknown.err, "kdrt trace: 404 Unknown mesh")) << unknown.err;
    few[4].dz = NAN;
    ASSERT_TRUE(proto::write_file_bytes(rays, proto::encode_rays(few, false)));
    const CliRun nan = kdrt({"trace", id_, rays, "-o", path("h.kdrh")});
    EXPECT_EQ(nan.exit_code, 1);
    EXPECT_TRUE(
        contains(nan.err, "400 Malformed ray batch: malformed KDRR batch: ray 4: field dz is NaN"))
        << nan.err;
    EXPECT_FALSE(std::filesystem::exists(path("h.kdrh")));
}

// ---- operations --------------------------------------------------------------------------------

TEST_F(Cli, HealthAndMetrics) {
    const CliRun health = kdrt({"health"});
    EXPECT_EQ(health.exit_code, 0) << health.err;
    EXPECT_EQ(health.out, "ok: " + server_url(*server_) + " is alive and ready\n");
    const CliRun metrics = kdrt({"metrics"});
    EXPECT_EQ(metrics.exit_code, 0) << metrics.err;
    EXPECT_TRUE(contains(metrics.out, "# TYPE kdrt_http_requests_total counter\n")) << metrics.out;
    // --server beats KDRT_SERVER.
    const CliRun flag = run_cli({"health", "--server", server_url(*server_)},
                                {.env = {"KDRT_SERVER=http://127.0.0.1:1"}});
    EXPECT_EQ(flag.exit_code, 0) << flag.err;
}

TEST_F(Cli, HealthReportsAServerThatIsNotReady) {
    FakeServer fake([](httplib::Server& http) {
        http.Get("/healthz", [](const httplib::Request&, httplib::Response& res) {
            res.set_content("{\"status\":\"ok\"}", "application/json");
        });
        http.Get("/readyz", [](const httplib::Request&, httplib::Response& res) {
            proto::Problem p;
            p.kind = proto::ProblemKind::kNotReady;
            p.detail = "the server is shutting down";
            res.status = 503;
            res.set_content(proto::encode_problem(p), std::string(proto::kProblemMediaType));
        });
    });
    const CliRun run = run_cli({"health", "--server", fake.url()});
    EXPECT_EQ(run.exit_code, 1);
    EXPECT_EQ(run.out, fake.url() + " is alive but not ready\n");
    EXPECT_TRUE(contains(run.err, "kdrt health: 503 Not ready: the server is shutting down"))
        << run.err;
}

TEST_F(Cli, ServerDownExitsThreeWithAClearMessage) {
    const std::string down = "http://127.0.0.1:" + std::to_string(unused_port());
    for (const std::vector<std::string>& args : {std::vector<std::string>{"health"},
                                                 {"meshes"},
                                                 {"upload", mesh_file_},
                                                 {"info", id_},
                                                 {"rm", id_},
                                                 {"metrics"},
                                                 {"render", id_, "-o", path("d.png")},
                                                 {"bench-remote", id_}}) {
        SCOPED_TRACE(args[0]);
        std::vector<std::string> with_server = args;
        with_server.insert(with_server.end(), {"--server", down, "--retries", "1"});
        const CliRun run = run_cli(with_server);
        EXPECT_EQ(run.exit_code, 3) << run.err;
        EXPECT_TRUE(contains(run.err, "kdrt " + args[0] + ": ")) << run.err;
        EXPECT_TRUE(contains(
            run.err, "cannot connect: " + down + ": could not connect: Connection refused ("))
            << run.err;
        EXPECT_TRUE(contains(run.err, "2 attempts)")) << run.err;
        EXPECT_TRUE(contains(
            run.err,
            "is kdrt-server running there? Set the address with --server URL or KDRT_SERVER."))
            << run.err;
    }
    // The default retries (4, with backoff) still end in well under a minute.
    const CliRun defaults = run_cli({"health"}, {.env = {"KDRT_SERVER=" + down}});
    EXPECT_EQ(defaults.exit_code, 3);
    EXPECT_TRUE(contains(defaults.err, "5 attempts)")) << defaults.err;
}

TEST_F(Cli, Injected503sAreRetriedByTheCli) {
    FaultyProxy proxy(server_->port(), 2, 0);
    const CliRun run = run_cli({"upload", mesh_file_, "--server", proxy.url()});
    EXPECT_EQ(run.exit_code, 0) << run.err;
    EXPECT_EQ(run.out.rfind(id_, 0), 0u);
    EXPECT_EQ(proxy.requests(), 3);
    FaultyProxy always(server_->port(), 1000, 0);
    const CliRun busy = run_cli({"meshes", "--server", always.url(), "--retries", "2"});
    EXPECT_EQ(busy.exit_code, 1);
    EXPECT_TRUE(contains(busy.err, "kdrt meshes: 503 Over capacity: injected 503 number 3"))
        << busy.err;
    EXPECT_EQ(always.requests(), 3);
}

TEST(CliSplit, BandsOverTheServersRawLimitAreRefusedAndMoreBandsFit) {
    TempDir dir;
    // 4 KiB: a 32 x 16 band (32 + 6144 bytes raw) is refused, a 32 x 8 band (32 + 3072) fits.
    ServerProcess server(
        {.cache_dir = dir.path() / "cache", .args = {"--max-raw-render-bytes", "4K"}});
    const std::string url = server_url(server);
    Client c(url, fast_options());
    Rng rng(test_seed() + 41);
    auto mesh = c.upload(random_soup(rng, 300));
    ASSERT_TRUE(mesh) << mesh.error().to_string();
    const std::string out = (dir.path() / "x.png").string();
    const CliRun refused = run_cli(
        {"render", mesh->id, "-o", out, "--size", "32x32", "--split", "2", "--server", url});
    EXPECT_EQ(refused.exit_code, 1) << refused.err;
    EXPECT_TRUE(contains(refused.err,
                         "kdrt render: 400 Bad request: raw render answer of 6176 bytes (32 x 16 "
                         "tile x 3 floats + a 32-byte header) exceeds max_raw_render_bytes 4096"))
        << refused.err;
    EXPECT_FALSE(std::filesystem::exists(out));
    const CliRun fits = run_cli(
        {"render", mesh->id, "-o", out, "--size", "32x32", "--split", "4", "--server", url});
    ASSERT_EQ(fits.exit_code, 0) << fits.err;
    RenderRequest same = small_render(mesh->id);
    same.settings.width = 32;
    same.settings.height = 32;
    auto expected = c.render(same);
    ASSERT_TRUE(expected) << expected.error().to_string();
    EXPECT_EQ(read_bytes(out), *expected);
}

TEST(CliAuth, TokenFromFlagOrEnvironment) {
    TempDir dir;
    ServerProcess server({.cache_dir = dir.path() / "cache", .args = {"--token", "t0ken"}});
    const std::string url = server_url(server);
    const CliRun refused = run_cli({"meshes", "--server", url});
    EXPECT_EQ(refused.exit_code, 1);
    EXPECT_TRUE(contains(refused.err, "kdrt meshes: 401 Unauthorized: ")) << refused.err;
    EXPECT_TRUE(
        contains(refused.err, "set the server's bearer token with --token TOKEN or KDRT_TOKEN."))
        << refused.err;
    EXPECT_EQ(run_cli({"meshes", "--server", url, "--token", "t0ken"}).exit_code, 0);
    EXPECT_EQ(run_cli({"meshes", "--server", url}, {.env = {"KDRT_TOKEN=t0ken"}}).exit_code, 0);
    EXPECT_EQ(
        run_cli({"meshes", "--server", url, "--token", "wrong"}, {.env = {"KDRT_TOKEN=t0ken"}})
            .exit_code,
        1);
}

TEST(CliAuth, AReadOnlyTokenIsRefusedUploadsAndDeletionsWithTheRoleNamed) {
    TempDir dir;
    const std::filesystem::path tokens = dir.path() / "tokens";
    // Tokens of at least 16 characters (kMinTokenChars).
    const std::string viewer = "viewer-0123456789", admin = "admin-0123456789ab";
    const std::string lines = "read " + viewer + "\nread,write " + admin + "\n";
    ASSERT_TRUE(proto::write_file_bytes(tokens, std::as_bytes(std::span(lines))));
    ServerProcess server(
        {.cache_dir = dir.path() / "cache", .args = {"--tokens-file", tokens.string()}});
    const std::string url = server_url(server);
    Rng rng(test_seed() + 41);
    const std::string file = (dir.path() / "soup.ply").string();
    ASSERT_TRUE(proto::write_file_bytes(
        file, proto::write_mesh(random_soup(rng, 50), proto::MeshFormat::kPly)));
    const CliRun refused = run_cli({"upload", file, "--server", url, "--token", viewer});
    EXPECT_EQ(refused.exit_code, 1);
    EXPECT_TRUE(contains(refused.err, "kdrt upload: " + file +
                                          ": 403 Forbidden: POST /v1/meshes needs a token with "
                                          "the role write; this token has the role read"))
        << refused.err;
    const CliRun uploaded = run_cli({"upload", file, "--server", url, "--token", admin});
    ASSERT_EQ(uploaded.exit_code, 0) << uploaded.err;
    const std::string id = uploaded.out.substr(0, 64);
    EXPECT_EQ(run_cli({"meshes", "--server", url, "--token", viewer}).exit_code, 0);
    const CliRun kept = run_cli({"rm", id, "--server", url, "--token", viewer});
    EXPECT_EQ(kept.exit_code, 1);
    EXPECT_TRUE(contains(kept.err,
                         "403 Forbidden: DELETE /v1/meshes/{id} needs a token with the "
                         "role write"))
        << kept.err;
    EXPECT_EQ(run_cli({"rm", id, "--server", url, "--token", admin}).exit_code, 0);
}

// ---- bench-remote ------------------------------------------------------------------------------

TEST_F(Cli, BenchRemoteMeasuresEveryRaySource) {
    upload_suite_mesh();
    // Primary rays from the server's bounds: needs only the id.
    const CliRun bounds =
        kdrt({"bench-remote", id_, "--res", "64", "--reps", "2", "--connections", "2", "--json"});
    ASSERT_EQ(bounds.exit_code, 0) << bounds.err;
    const auto b = nlohmann::json::parse(bounds.out);
    EXPECT_EQ(b["command"], "bench-remote");
    EXPECT_EQ(b["mesh"], id_);
    EXPECT_EQ(b["kind"], "primary");
    EXPECT_EQ(b["source"], "bounds");
    EXPECT_EQ(b["rays"], 64 * 64);
    EXPECT_EQ(b["connections"], 2);
    EXPECT_EQ(b["reps"], 2);
    EXPECT_GT(b["mrays_per_s"].get<double>(), 0.0);
    EXPECT_LE(b["seconds_min"].get<double>(), b["seconds"].get<double>());
    EXPECT_GT(b["hits"].get<uint64_t>(), 0u);

    // Diffuse rays from the uploaded file: exactly generate_rays' set.
    const CliRun diffuse = kdrt(
        {"bench-remote", id_, "--kind", "diffuse", "--mesh", mesh_file_, "--res", "64", "--json"});
    ASSERT_EQ(diffuse.exit_code, 0) << diffuse.err;
    const auto d = nlohmann::json::parse(diffuse.out);
    EXPECT_EQ(d["source"], "mesh");
    EXPECT_EQ(d["rays"], generate_rays(*tree_, {.kind = RayKind::kDiffuse, .res = 64}).size());
    EXPECT_EQ(d["occlusion"], false);

    const std::string shadow = path("bench_shadow.kdrr");
    ASSERT_EQ(
        run_cli({"rays", mesh_file_, "-o", shadow, "--kind", "shadow", "--res", "64"}).exit_code,
        0);
    const CliRun file = kdrt({"bench-remote", id_, "--rays", shadow});
    ASSERT_EQ(file.exit_code, 0) << file.err;
    EXPECT_EQ(file.out.rfind("file rays (rays): ", 0), 0u) << file.out;
    EXPECT_TRUE(contains(file.out, " Mrays/s, ")) << file.out;
    EXPECT_TRUE(contains(file.out, " occluded\n")) << file.out;
}

TEST_F(Cli, BenchRemoteErrors) {
    upload_suite_mesh();
    const CliRun needs_mesh = kdrt({"bench-remote", id_, "--kind", "diffuse"});
    EXPECT_EQ(needs_mesh.exit_code, 2);
    EXPECT_TRUE(
        contains(needs_mesh.err, "--kind diffuse needs the mesh's triangles: add --mesh FILE"))
        << needs_mesh.err;
    const CliRun wrong_mesh =
        kdrt({"bench-remote", id_, "--mesh", data_path("diplodocus.off"), "--res", "8"});
    EXPECT_EQ(wrong_mesh.exit_code, 2);
    EXPECT_TRUE(contains(wrong_mesh.err, "is not mesh " + id_ + " (its id is ")) << wrong_mesh.err;
    const CliRun unknown = kdrt({"bench-remote", std::string(64, '9')});
    EXPECT_EQ(unknown.exit_code, 1);
    EXPECT_TRUE(contains(unknown.err, "404 Unknown mesh")) << unknown.err;
}

// ---- output conventions: -o -, --json, --quiet
// ---------------------------------------------------

/// Parses one JSON object per line; fails the test on anything else.
std::vector<nlohmann::json> json_lines(const std::string& text) {
    std::vector<nlohmann::json> out;
    for (const std::string& line : lines_of(text)) {
        auto j = nlohmann::json::parse(line, nullptr, false);
        EXPECT_TRUE(j.is_object()) << line;
        out.push_back(j);
    }
    return out;
}

TEST_F(Cli, DashOutputWritesTheDataToStdoutAndEveryHumanLineToStderr) {
    upload_suite_mesh();
    const std::string rays = path("dash.kdrr"), hits = path("dash.kdrh");
    // kdrt rays -o -: the KDRR bytes on stdout, the summary on stderr.
    const CliRun gen = run_cli({"rays", mesh_file_, "-o", "-", "--res", "40"});
    ASSERT_EQ(gen.exit_code, 0) << gen.err;
    ASSERT_EQ(run_cli({"rays", mesh_file_, "-o", rays, "--res", "40"}).exit_code, 0);
    EXPECT_EQ(gen.out, as_string(read_bytes(rays)));
    EXPECT_TRUE(contains(gen.err, "wrote 1600 primary rays to - (")) << gen.err;
    EXPECT_FALSE(std::filesystem::exists("-"));
    // kdrt trace: to a file, stdout stays empty; to -, stdout is exactly the file's bytes.
    const CliRun file = kdrt({"trace", id_, rays, "-o", hits});
    ASSERT_EQ(file.exit_code, 0) << file.err;
    EXPECT_EQ(file.out, "");
    EXPECT_TRUE(contains(file.err, "traced 1600 rays (closest hits)")) << file.err;
    const CliRun dash = kdrt({"trace", id_, rays, "-o", "-"});
    ASSERT_EQ(dash.exit_code, 0) << dash.err;
    EXPECT_EQ(dash.out, as_string(read_bytes(hits)));
    EXPECT_TRUE(contains(dash.err, "traced 1600 rays (closest hits)")) << dash.err;
    // --json with -o -: the JSON summary goes to stderr, the data alone to stdout.
    const CliRun json = kdrt({"trace", id_, rays, "-o", "-", "--json"});
    ASSERT_EQ(json.exit_code, 0) << json.err;
    EXPECT_EQ(json.out, as_string(read_bytes(hits)));
    const auto summary = json_lines(json.err);
    ASSERT_EQ(summary.size(), 1u) << json.err;
    EXPECT_EQ(summary[0]["rays"], 1600);
    EXPECT_EQ(summary[0]["out"], "-");
    // --quiet: nothing on stderr.
    const CliRun quiet = kdrt({"trace", id_, rays, "-o", "-", "-q"});
    ASSERT_EQ(quiet.exit_code, 0) << quiet.err;
    EXPECT_EQ(quiet.out, as_string(read_bytes(hits)));
    EXPECT_EQ(quiet.err, "");
    // Commands whose format comes from the extension take --format with -o -.
    const CliRun png = kdrt({"render", id_, "-o", path("dash.png"), "--size", "40x30", "-q"});
    ASSERT_EQ(png.exit_code, 0) << png.err;
    const CliRun png_dash =
        kdrt({"render", id_, "-o", "-", "--format", "png", "--size", "40x30", "-q"});
    ASSERT_EQ(png_dash.exit_code, 0) << png_dash.err;
    EXPECT_EQ(png_dash.out, as_string(read_bytes(path("dash.png"))));
    EXPECT_EQ(png_dash.err, "");
    const CliRun no_format = kdrt({"render", id_, "-o", "-"});
    EXPECT_EQ(no_format.exit_code, 2);
    EXPECT_TRUE(contains(no_format.err, "or --format")) << no_format.err;
    const CliRun bad_format = kdrt({"render", id_, "-o", "-", "--format", "gif"});
    EXPECT_EQ(bad_format.exit_code, 2);
    EXPECT_TRUE(contains(bad_format.err, "--format: \"gif\" is not png, jpg or exr"))
        << bad_format.err;
    const CliRun bad_hits = kdrt({"hits", id_, rays, "--all", "-o", "-", "--format", "csv"});
    EXPECT_EQ(bad_hits.exit_code, 2);
    EXPECT_TRUE(contains(bad_hits.err, "--format: \"csv\" is not ply, kdrm or kdrc"))
        << bad_hits.err;
    const CliRun split = kdrt(
        {"render", id_, "-o", "-", "--format", "png", "--size", "40x30", "--split", "3", "-q"});
    ASSERT_EQ(split.exit_code, 0) << split.err;
    EXPECT_EQ(split.out, as_string(read_bytes(path("dash.png"))));
    const CliRun kdrz = kdrt({"scan", id_, "--pinhole", "-o", path("dash.kdrz"), "--eye", "0,0,5",
                              "--look-at", "0,0,0", "--size", "20x10"});
    ASSERT_EQ(kdrz.exit_code, 0) << kdrz.err;
    EXPECT_EQ(kdrz.out, "");
    const CliRun kdrz_dash = kdrt({"scan", id_, "--pinhole", "-o", "-", "--format", "kdrz", "--eye",
                                   "0,0,5", "--look-at", "0,0,0", "--size", "20x10"});
    ASSERT_EQ(kdrz_dash.exit_code, 0) << kdrz_dash.err;
    EXPECT_EQ(kdrz_dash.out, as_string(read_bytes(path("dash.kdrz"))));
    EXPECT_TRUE(contains(kdrz_dash.err, "wrote - (")) << kdrz_dash.err;
}

TEST_F(Cli, JsonReportsOfEveryCommand) {
    upload_suite_mesh();
    // --json before the command, like --server.
    const CliRun health = kdrt({"--json", "health"});
    ASSERT_EQ(health.exit_code, 0) << health.err;
    auto h = json_lines(health.out);
    ASSERT_EQ(h.size(), 1u);
    EXPECT_EQ(h[0]["url"], server_url(*server_));
    EXPECT_EQ(h[0]["alive"], true);
    EXPECT_EQ(h[0]["ready"], true);
    // metrics: one object per sample of the text format, labels unescaped, non-finite values
    // as words (a fixed text from a fake server, so the answer is known).
    FakeServer fake([](httplib::Server& http) {
        http.Get("/metrics", [](const httplib::Request&, httplib::Response& res) {
            res.set_content(
                "# HELP a_total A.\n# TYPE a_total counter\na_total 3\n"
                "b_seconds_bucket{route=\"/v1/x\",le=\"+Inf\"} 7\n"
                "c{path=\"q\\\"uote\\\\back\\nline\"} 0.25\n"
                "d +Inf\ne NaN\n",
                "text/plain; version=0.0.4");
        });
    });
    const CliRun metrics = run_cli({"metrics", "--json", "--server", fake.url()});
    ASSERT_EQ(metrics.exit_code, 0) << metrics.err;
    EXPECT_EQ(metrics.out,
              "{\"name\":\"a_total\",\"labels\":{},\"value\":3}\n"
              "{\"name\":\"b_seconds_bucket\",\"labels\":{\"route\":\"/v1/x\",\"le\":\"+Inf\"},"
              "\"value\":7}\n"
              "{\"name\":\"c\",\"labels\":{\"path\":\"q\\\"uote\\\\back\\nline\"},\"value\":0.25}\n"
              "{\"name\":\"d\",\"labels\":{},\"value\":\"+Inf\"}\n"
              "{\"name\":\"e\",\"labels\":{},\"value\":\"NaN\"}\n");
    // And the real server's: every line parses.
    const CliRun real = kdrt({"metrics", "--json"});
    ASSERT_EQ(real.exit_code, 0) << real.err;
    EXPECT_GT(json_lines(real.out).size(), 10u);
    // render and scan: the summary as JSON on stdout, nothing human anywhere.
    const CliRun render =
        kdrt({"render", id_, "-o", path("json.png"), "--size", "40x30", "--json"});
    ASSERT_EQ(render.exit_code, 0) << render.err;
    auto r = json_lines(render.out);
    ASSERT_EQ(r.size(), 1u) << render.out;
    EXPECT_EQ(r[0]["out"], path("json.png"));
    EXPECT_EQ(r[0]["width"], 40);
    EXPECT_EQ(r[0]["bytes"], std::filesystem::file_size(path("json.png")));
    EXPECT_FALSE(contains(render.err, "wrote")) << render.err;
    const CliRun scan = kdrt({"scan", id_, "--pinhole", "-o", path("json.kdrz"), "--eye", "0,0,5",
                              "--look-at", "0,0,0", "--size", "20x10", "--json"});
    ASSERT_EQ(scan.exit_code, 0) << scan.err;
    auto sc = json_lines(scan.out);
    ASSERT_EQ(sc.size(), 1u) << scan.out;
    EXPECT_EQ(sc[0]["sensor"], "pinhole");
    EXPECT_EQ(scan.err, "");
    // rm: {"removed": ID}.
    const CliRun rm = kdrt({"rm", id_, "--json"});
    ASSERT_EQ(rm.exit_code, 0) << rm.err;
    auto gone = json_lines(rm.out);
    ASSERT_EQ(gone.size(), 1u);
    EXPECT_EQ(gone[0]["removed"], id_);
}

TEST_F(Cli, QuietPrintsOnlyDataAndErrors) {
    const CliRun upload = kdrt({"upload", mesh_file_, "-q"});
    ASSERT_EQ(upload.exit_code, 0) << upload.err;
    EXPECT_EQ(upload.out, id_ + "\n");
    const CliRun meshes = kdrt({"--quiet", "meshes"});
    ASSERT_EQ(meshes.exit_code, 0) << meshes.err;
    EXPECT_TRUE(contains("\n" + meshes.out, "\n" + id_ + "\n")) << meshes.out;
    for (const std::string& line : lines_of(meshes.out)) EXPECT_EQ(line.size(), 64u) << line;
    const CliRun info = kdrt({"info", id_.substr(0, 12), "-q"});
    ASSERT_EQ(info.exit_code, 0) << info.err;
    EXPECT_EQ(info.out, id_ + "\n");
    const CliRun health = kdrt({"health", "-q"});
    EXPECT_EQ(health.exit_code, 0) << health.err;
    EXPECT_EQ(health.out + health.err, "");
    const CliRun rays = run_cli({"rays", mesh_file_, "-o", path("q.kdrr"), "--res", "8", "-q"});
    EXPECT_EQ(rays.exit_code, 0) << rays.err;
    EXPECT_EQ(rays.out + rays.err, "");
    // Errors still print.
    const CliRun down =
        run_cli({"health", "-q", "--server", "http://127.0.0.1:9", "--retries", "0"});
    EXPECT_EQ(down.exit_code, 3);
    EXPECT_TRUE(contains(down.err, "kdrt health: ")) << down.err;
    const CliRun rm = kdrt({"rm", id_, "-q"});
    EXPECT_EQ(rm.exit_code, 0) << rm.err;
    EXPECT_EQ(rm.out + rm.err, "");
}

}  // namespace
}  // namespace kdrt::test
