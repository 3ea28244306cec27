// `kdrt distance` against a real kdrt-server: CSV and KDRD files equal what proto writes for the
// engine's answers (from KDRP and from XYZ / CSV text points), the summary's counts, and every
// usage error and refusal with its exit code.

#include <gtest/gtest.h>

#include <charconv>
#include <nlohmann/json.hpp>

#include "cli_runner.h"
#include "client_test_util.h"
#include "kdrt/distance.h"
#include "kdrt/proto/distance.h"
#include "kdrt/proto/mesh_id.h"
#include "scenes.h"

namespace kdrt::test {
namespace {

std::string shortest(float value) {
    char buffer[32];
    const auto [end, ec] = std::to_chars(buffer, buffer + sizeof buffer, value);
    return std::string(buffer, end);
}

class CliDistance : public ::testing::Test {
protected:
    static void SetUpTestSuite() {
        dir_ = new TempDir();
        server_ = new ServerProcess({.cache_dir = dir_->path() / "cache"});
        box_ = new Mesh(box_mesh(0.0f, 1.0f));
        box_tree_ = new KdTree(build_kdtree(*box_));
        box_file_ = (dir_->path() / "box.ply").string();
        ASSERT_TRUE(
            proto::write_file_bytes(box_file_, proto::write_mesh(*box_, proto::MeshFormat::kPly)));
        box_id_ = proto::mesh_id(*box_);
        Rng rng(test_seed() + 71);
        points_ = new std::vector<Vec3>();
        for (int i = 0; i < 500; ++i)
            points_->push_back(rng.in_box({{-0.5f, -0.5f, -0.5f}, {1.5f, 1.5f, 1.5f}}));
    }
    static void TearDownTestSuite() {
        delete server_;
        delete dir_;
        delete box_;
        delete box_tree_;
        delete points_;
    }
    void SetUp() override { ASSERT_GT(server_->port(), 0); }

    static CliRun kdrt(const std::vector<std::string>& args) {
        CliOptions options;
        options.env.push_back("KDRT_SERVER=" + server_url(*server_));
        return run_cli(args, options);
    }
    static std::string path(const std::string& name) { return (dir_->path() / name).string(); }
    static void upload_box() {
        const CliRun run = kdrt({"upload", box_file_});
        ASSERT_EQ(run.exit_code, 0) << run.err;
    }
    static std::vector<ClosestPoint> engine(std::span<const Vec3> points,
                                            const DistanceOptions& options) {
        const SurfaceIndex index = build_surface_index(*box_tree_);
        std::vector<ClosestPoint> want(points.size());
        closest_points(*box_tree_, index, points, want, options);
        return want;
    }
    static std::string read_text(const std::string& file) {
        const std::vector<std::byte> bytes = read_bytes(file);
        return std::string(reinterpret_cast<const char*>(bytes.data()), bytes.size());
    }

    static TempDir* dir_;
    static ServerProcess* server_;
    static Mesh* box_;
    static KdTree* box_tree_;
    static std::string box_file_;
    static std::string box_id_;
    static std::vector<Vec3>* points_;
};
TempDir* CliDistance::dir_ = nullptr;
ServerProcess* CliDistance::server_ = nullptr;
Mesh* CliDistance::box_ = nullptr;
KdTree* CliDistance::box_tree_ = nullptr;
std::string CliDistance::box_file_;
std::string CliDistance::box_id_;
std::vector<Vec3>* CliDistance::points_ = nullptr;

TEST_F(CliDistance, HelpNamesEveryOption) {
    const CliRun run = kdrt({"distance", "--help"});
    EXPECT_EQ(run.exit_code, 0) << run.err;
    EXPECT_EQ(run.out.rfind("usage: kdrt distance ID POINTS -o OUT", 0), 0u) << run.out;
    for (const char* option :
         {"--max-distance", "--signed", "--chunk-points", "--json", ".csv", ".kdrd", "KDRP"})
        EXPECT_TRUE(contains(run.out, option)) << option;
    const CliRun main = kdrt({"--help"});
    EXPECT_TRUE(contains(main.out, "\n  distance ID POINTS -o OUT ")) << main.out;
}

TEST_F(CliDistance, UsageErrorsExitTwoWithAMessage) {
    const std::string points = path("usage.xyz");
    write_text(points, "0 0 0\n");
    struct Case {
        std::vector<std::string> args;
        std::string message;
    };
    const std::vector<Case> cases = {
        {{"distance"}, "kdrt distance: missing ID and POINTS"},
        {{"distance", "abcd"}, "kdrt distance: missing ID and POINTS"},
        {{"distance", "abcd", points}, "kdrt distance: missing -o OUT"},
        {{"distance", "abcd", points, "x", "-o", "a.csv"}, "unexpected argument \"x\""},
        {{"distance", "abcd", points, "-o", "a.ply"},
         "cannot tell the output format of \"a.ply\" from its extension (.csv or .kdrd)"},
        {{"distance", "abcd", points, "-o", "a"}, "cannot tell the output format of \"a\""},
        {{"distance", "abcd", points, "-o", "a.csv", "--max-distance", "-1"},
         "--max-distance: query parameter max_distance is \"-1\""},
        {{"distance", "abcd", points, "-o", "a.csv", "--max-distance", "near"},
         "--max-distance: query parameter max_distance is \"near\""},
        {{"distance", "abcd", points, "-o", "a.csv", "--chunk-points", "0"},
         "--chunk-points: \"0\" is not in 1 .. 4194304"},
        {{"distance", "abcd", points, "-o", "a.csv", "--signed=yes"},
         "option --signed takes no value"},
        {{"distance", "abcd", points, "-o"}, "option -o needs a value"},
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

TEST_F(CliDistance, UnreadablePointsExitTwoNamingWhere) {
    upload_box();
    const std::string out = path("bad.csv");
    // A missing file.
    CliRun run = kdrt({"distance", box_id_, path("none.xyz"), "-o", out});
    EXPECT_EQ(run.exit_code, 2);
    EXPECT_TRUE(contains(run.err, "No such file or directory")) << run.err;
    // Text: the bad line is named.
    const std::string text = path("bad.xyz");
    write_text(text, "x,y,z\n0 0 0\n1 2\n");
    run = kdrt({"distance", box_id_, text, "-o", out});
    EXPECT_EQ(run.exit_code, 2);
    EXPECT_TRUE(contains(run.err, "kdrt distance: cannot read the points: " + text + ": line 3"))
        << run.err;
    // KDRP: a NaN point is named by index and field; a truncated file by its size.
    std::vector<Vec3> points(5, Vec3{0, 0, 0});
    points[3].y = NAN;
    const std::string kdrp = path("bad.kdrp");
    ASSERT_TRUE(proto::write_file_bytes(kdrp, proto::encode_points(points)));
    run = kdrt({"distance", box_id_, kdrp, "-o", out});
    EXPECT_EQ(run.exit_code, 2);
    EXPECT_TRUE(contains(run.err, "is not a usable KDRP point batch")) << run.err;
    EXPECT_TRUE(contains(run.err, "point 3: field y is NaN")) << run.err;
    std::vector<std::byte> bytes = proto::encode_points(std::vector<Vec3>(3, Vec3{0, 0, 0}));
    bytes.resize(bytes.size() - 4);
    ASSERT_TRUE(proto::write_file_bytes(kdrp, bytes));
    run = kdrt({"distance", box_id_, kdrp, "-o", out});
    EXPECT_EQ(run.exit_code, 2);
    EXPECT_TRUE(contains(run.err, "length_mismatch")) << run.err;
    EXPECT_FALSE(std::filesystem::exists(out));
}

TEST_F(CliDistance, ServerRefusalsExitOne) {
    const std::string points = path("few.xyz");
    write_text(points, "0 0 0\n1 1 1\n");
    const CliRun unknown = kdrt({"distance", std::string(64, 'd'), points, "-o", path("u.csv")});
    EXPECT_EQ(unknown.exit_code, 1);
    EXPECT_TRUE(contains(unknown.err, "kdrt distance: 404 Unknown mesh")) << unknown.err;
    EXPECT_FALSE(std::filesystem::exists(path("u.csv")));
}

TEST_F(CliDistance, KdrpInKdrdOutIsTheEnginesAnswer) {
    upload_box();
    const std::string in = path("q.kdrp");
    ASSERT_TRUE(proto::write_file_bytes(in, proto::encode_points(*points_)));
    for (const bool sign : {false, true}) {
        SCOPED_TRACE(sign);
        const std::string out = path(sign ? "signed.kdrd" : "unsigned.kdrd");
        std::vector<std::string> args = {"distance", box_id_.substr(0, 8), in,    "-o",
                                         out,        "--chunk-points",     "128", "--json"};
        if (sign) args.push_back("--signed");
        const CliRun run = kdrt(args);
        ASSERT_EQ(run.exit_code, 0) << run.err;
        const std::vector<ClosestPoint> want = engine(*points_, {.sign = sign});
        EXPECT_TRUE(read_bytes(out) == proto::encode_distances(want, sign));
        const auto summary = nlohmann::json::parse(run.out);
        EXPECT_EQ(summary["command"], "distance");
        EXPECT_EQ(summary["mesh"], box_id_);
        EXPECT_EQ(summary["points"], points_->size());
        EXPECT_EQ(summary["surface"], "closed");
        EXPECT_EQ(summary["closed"], true);
        uint64_t inside = 0, outside = 0;
        for (const ClosestPoint& c : want) {
            inside += c.side == Side::kInside ? 1 : 0;
            outside += c.side == Side::kOutside ? 1 : 0;
        }
        EXPECT_EQ(summary["inside"], inside);
        EXPECT_EQ(summary["outside"], outside);
        EXPECT_EQ(summary["found"], points_->size());
        if (sign) {
            EXPECT_GT(inside, 0u);
        }
    }
}

TEST_F(CliDistance, TextInCsvOutIsTheEnginesAnswer) {
    upload_box();
    // CSV with a header and a comment, and XYZ with an extra column: both read the same points.
    std::string csv = "x,y,z\n# query points\n", xyz;
    for (const Vec3& p : *points_) {
        csv += shortest(p.x) + "," + shortest(p.y) + "," + shortest(p.z) + "\n";
        xyz += shortest(p.x) + " " + shortest(p.y) + "\t" + shortest(p.z) + " 7\n";
    }
    const std::string in_csv = path("q.csv"), in_xyz = path("q.xyz");
    write_text(in_csv, csv);
    write_text(in_xyz, xyz);
    const DistanceOptions options{.max_distance = 0.2f, .sign = true};
    const std::string want = proto::distances_csv(*points_, engine(*points_, options));
    for (const std::string& in : {in_csv, in_xyz}) {
        SCOPED_TRACE(in);
        const std::string out = path("answers.csv");
        const CliRun run =
            kdrt({"distance", box_id_, in, "-o", out, "--max-distance", "0.2", "--signed"});
        ASSERT_EQ(run.exit_code, 0) << run.err;
        EXPECT_EQ(read_text(out), want);
        EXPECT_TRUE(contains(run.err, "queried 500 points in ")) << run.err;
        EXPECT_TRUE(contains(run.err, " inside, ")) << run.err;
    }
    // Some points are farther than 0.2 from the box: their rows have no prim.
    EXPECT_TRUE(contains(want, ",unknown,,")) << want.substr(0, 400);
}

TEST_F(CliDistance, OpenMeshSaysWhySidesAreUnknown) {
    Mesh open = box_mesh(0.0f, 1.0f);
    open.indices.resize(open.indices.size() - 3);  // one triangle less: 3 boundary edges
    const std::string file = path("open.ply");
    ASSERT_TRUE(proto::write_file_bytes(file, proto::write_mesh(open, proto::MeshFormat::kPly)));
    ASSERT_EQ(kdrt({"upload", file}).exit_code, 0);
    const std::string points = path("open.xyz");
    write_text(points, "0.5 0.5 0.5\n2 2 2\n");
    const CliRun run =
        kdrt({"distance", proto::mesh_id(open), points, "-o", path("open.csv"), "--signed"});
    ASSERT_EQ(run.exit_code, 0) << run.err;
    EXPECT_TRUE(contains(run.err,
                         "0 inside, 0 outside (sides unknown: the mesh is not closed: 3 "
                         "boundary edges"))
        << run.out;
}

}  // namespace
}  // namespace kdrt::test
