// POST /v1/render and the async jobs, against the in-process renderer.

#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <cstring>
#include <map>
#include <optional>
#include <thread>

#include "http_test_util.h"
#include "kdrt/proto/image_io.h"
#include "kdrt/proto/raw_image.h"
#include "kdrt/render.h"

namespace kdrt::test {
namespace {

using proto::ProblemKind;

class HttpRender : public ::testing::Test {
protected:
    static void SetUpTestSuite() {
        dir_ = new TempDir();
        server_ =
            new ServerProcess({.cache_dir = dir_->path() / "cache", .args = {"--max-jobs", "2"}});
        mesh_ = new Mesh(small_mesh(77, 4000));  // renders like the bunny, builds in milliseconds
        tree_ = new KdTree(build_kdtree(*mesh_));
        id_ = upload_id(*server_->client(), *mesh_);
    }
    static void TearDownTestSuite() {
        delete server_;
        delete dir_;
        delete mesh_;
        delete tree_;
    }
    static httplib::Result post_render(httplib::Client& cli, const std::string& json,
                                       bool async = false) {
        httplib::Headers headers;
        if (async) headers.emplace("Prefer", "respond-async");
        return cli.Post("/v1/render", headers, json, "application/json");
    }
    /// The server's png_compression default (config/kdrt.json).
    static constexpr int kDefaultPngCompression = 1;
    /// The image the server should send for `request`.
    static std::string expected_image(const proto::RenderRequest& request) {
        const Image image = render(*tree_, request.settings);
        proto::ImageEncodeOptions options;
        options.png_compression = request.compression.value_or(kDefaultPngCompression);
        // 8-bit files: the light modes through the sRGB curve, the data modes (ao's fraction,
        // normals, depth, false colours) as round(255 x value) (openapi.yaml).
        const Shading mode = request.settings.shading;
        options.transfer = mode == Shading::kEyelight || mode == Shading::kDiffuse
                               ? proto::EightBitTransfer::kSrgb
                               : proto::EightBitTransfer::kData;
        auto bytes =
            proto::encode_image(image, *proto::image_format_from_name(request.format), options);
        EXPECT_TRUE(bytes) << bytes.error();
        return bytes ? bytes_to_string(*bytes) : std::string();
    }
    static proto::RenderRequest request(const std::string& json) {
        auto r = proto::decode_render_request(json);
        EXPECT_TRUE(r) << r.error().detail;
        return r ? *r : proto::RenderRequest{};
    }

    static TempDir* dir_;
    static ServerProcess* server_;
    static Mesh* mesh_;
    static KdTree* tree_;
    static std::string id_;
};
TempDir* HttpRender::dir_ = nullptr;
ServerProcess* HttpRender::server_ = nullptr;
Mesh* HttpRender::mesh_ = nullptr;
KdTree* HttpRender::tree_ = nullptr;
std::string HttpRender::id_;

TEST_F(HttpRender, EveryShadingModeMatchesTheEngine) {
    auto cli = server_->client();
    for (const char* shading : {"normals", "eyelight", "ao", "diffuse", "depth", "primid"}) {
        SCOPED_TRACE(shading);
        const std::string json =
            "{\"mesh\":\"" + id_ + "\",\"shading\":\"" + shading + "\",\"width\":96,\"height\":64}";
        auto res = post_render(*cli, json);
        ASSERT_TRUE(res);
        ASSERT_EQ(res->status, 200) << res->body;
        EXPECT_EQ(res->get_header_value("Content-Type"), "image/png");
        auto decoded = proto::decode_image(string_to_bytes(res->body));
        ASSERT_TRUE(decoded) << decoded.error();
        EXPECT_EQ(decoded->width, 96u);
        EXPECT_EQ(decoded->height, 64u);
        EXPECT_EQ(res->body, expected_image(request(json)));
    }
}

TEST_F(HttpRender, DefaultsExrTilesAndExplicitCameras) {
    auto cli = server_->client();
    // Only "mesh": 512 x 512 eyelight PNG of the default view.
    auto res = post_render(*cli, "{\"mesh\":\"" + id_ + "\"}");
    ASSERT_TRUE(res);
    ASSERT_EQ(res->status, 200) << res->body;
    auto decoded = proto::decode_image(string_to_bytes(res->body));
    ASSERT_TRUE(decoded);
    EXPECT_EQ(decoded->width, 512u);
    EXPECT_EQ(decoded->height, 512u);

    // EXR keeps linear values: compare the decoded pixels with the engine's (as half floats).
    const std::string exr =
        "{\"mesh\":\"" + id_ +
        "\",\"format\":\"exr\",\"shading\":\"depth\",\"width\":40,\"height\":30}";
    res = post_render(*cli, exr);
    ASSERT_TRUE(res);
    ASSERT_EQ(res->status, 200) << res->body;
    EXPECT_EQ(res->get_header_value("Content-Type"), "image/x-exr");
    auto exr_image = proto::decode_image(string_to_bytes(res->body));
    ASSERT_TRUE(exr_image) << exr_image.error();
    auto want = proto::decode_image(string_to_bytes(expected_image(request(exr))));
    ASSERT_TRUE(want);
    EXPECT_EQ(exr_image->pixels, want->pixels);

    // A tile of a frame is exactly that part of the full frame.
    const std::string camera =
        R"("camera":{"eye":[0,0.1,1.5],"look_at":[0,0,0],"up":[0,1,0],"fov":35})";
    const std::string full =
        "{\"mesh\":\"" + id_ + "\"," + camera + ",\"width\":64,\"height\":48,\"format\":\"exr\"}";
    const std::string tile = "{\"mesh\":\"" + id_ + "\"," + camera +
                             ",\"width\":64,\"height\":48,\"format\":\"exr\",\"tile\":{\"x\":16,"
                             "\"y\":8,\"w\":32,\"h\":24}}";
    auto full_image = proto::decode_image(string_to_bytes(post_render(*cli, full)->body));
    auto tile_res = post_render(*cli, tile);
    ASSERT_EQ(tile_res->status, 200) << tile_res->body;
    auto tile_image = proto::decode_image(string_to_bytes(tile_res->body));
    ASSERT_TRUE(full_image && tile_image);
    ASSERT_EQ(tile_image->width, 32u);
    ASSERT_EQ(tile_image->height, 24u);
    const uint32_t c = full_image->channels;
    for (uint32_t y = 0; y < 24; ++y)
        for (uint32_t x = 0; x < 32 * c; ++x)
            ASSERT_EQ(tile_image->pixels[y * 32 * c + x],
                      full_image->pixels[(y + 8) * 64 * c + 16 * c + x]);

    // Orthographic projection and JPEG.
    res = post_render(
        *cli, "{\"mesh\":\"" + id_ +
                  "\",\"format\":\"jpg\",\"width\":32,\"height\":32,\"camera\":{\"eye\":[0,0,2],"
                  "\"look_at\":[0,0,0],\"projection\":\"orthographic\",\"ortho_height\":1.2}}");
    ASSERT_TRUE(res);
    ASSERT_EQ(res->status, 200) << res->body;
    EXPECT_EQ(res->get_header_value("Content-Type"), "image/jpeg");
}

TEST_F(HttpRender, ShadingSettingsReachTheEngine) {
    auto cli = server_->client();
    const std::string mesh = "{\"mesh\":\"" + id_ + "\",\"width\":48,\"height\":40,";
    for (const std::string& settings : {
             std::string(R"("shading":"ao","ao_samples":3,"ao_distance":0.5)"),
             std::string(
                 R"("shading":"diffuse","light":{"direction":[-1,0.5,0.25],"intensity":0.5},)"
                 R"("bounces":1,)"
                 R"("sky":0.5,"spp":2)"),
             std::string(R"("shading":"eyelight","background":[0.25,0.5,0.125])"),
         }) {
        SCOPED_TRACE(settings);
        const std::string json = mesh + settings + ",\"format\":\"exr\"}";
        auto res = post_render(*cli, json);
        ASSERT_TRUE(res);
        ASSERT_EQ(res->status, 200) << res->body;
        // EXR headers carry the time (capDate): compare the pixels.
        auto got = proto::decode_image(string_to_bytes(res->body));
        auto want = proto::decode_image(string_to_bytes(expected_image(request(json))));
        ASSERT_TRUE(got && want);
        EXPECT_EQ(got->pixels, want->pixels);
        // Not the image of the defaults: the members changed something.
        const std::string plain =
            mesh + settings.substr(0, settings.find(',')) + ",\"format\":\"exr\"}";
        auto defaults = proto::decode_image(string_to_bytes(expected_image(request(plain))));
        ASSERT_TRUE(defaults);
        EXPECT_NE(got->pixels, defaults->pixels);
    }
}

TEST_F(HttpRender, AoPngLevelsAreTheUnoccludedShare) {
    // The display transform of ao: PNG level = round(255 x unoccluded share), no sRGB curve
    // (which would show a half-occluded crease as the light level 188 instead of 128).
    auto cli = server_->client();
    const std::string json = "{\"mesh\":\"" + id_ +
                             R"(","width":40,"height":32,"shading":"ao","ao_samples":8,)"
                             R"("background":[0.25,0.25,0.25]})";
    auto res = post_render(*cli, json);
    ASSERT_TRUE(res);
    ASSERT_EQ(res->status, 200) << res->body;
    auto png = proto::decode_image(string_to_bytes(res->body));
    ASSERT_TRUE(png) << png.error();
    const Image engine = render(*tree_, request(json).settings);
    ASSERT_EQ(png->pixels.size(), engine.pixels.size());
    size_t partly_occluded = 0;
    for (size_t i = 0; i < engine.pixels.size(); ++i) {
        const float v = engine.pixels[i];
        const int level = proto::linear_to_srgb8(png->pixels[i]);  // the file's 8-bit level
        ASSERT_EQ(level, std::lround(std::clamp(v, 0.0f, 1.0f) * 255.0f)) << "value " << v;
        partly_occluded += v > 0.3f && v < 0.7f && v != 0.25f;
    }
    EXPECT_GT(partly_occluded, 0u);
}

TEST_F(HttpRender, PngCompressionLevelsDecodeToTheSamePixels) {
    auto cli = server_->client();
    const std::string base =
        "{\"mesh\":\"" + id_ + "\",\"width\":160,\"height\":120,\"shading\":\"diffuse\"";
    std::optional<Image> first;
    std::map<std::string, size_t> sizes;
    for (const std::string level : {"", "0", "1", "3", "6", "9"}) {
        SCOPED_TRACE("compression " + (level.empty() ? std::string("default") : level));
        std::string json = base;
        if (!level.empty()) json += ",\"compression\":" + level;
        json += "}";
        auto res = post_render(*cli, json);
        ASSERT_TRUE(res);
        ASSERT_EQ(res->status, 200) << res->body;
        EXPECT_EQ(res->get_header_value("Content-Type"), "image/png");
        EXPECT_FALSE(res->get_header_value("X-Encode-Ms").empty());
        EXPECT_EQ(res->body, expected_image(request(json)));
        sizes[level] = res->body.size();
        auto decoded = proto::decode_image(string_to_bytes(res->body));
        ASSERT_TRUE(decoded) << decoded.error();
        if (!first) {
            first = std::move(*decoded);
            continue;
        }
        EXPECT_EQ(decoded->width, first->width);
        EXPECT_EQ(decoded->height, first->height);
        EXPECT_EQ(decoded->channels, first->channels);
        EXPECT_TRUE(decoded->pixels == first->pixels)
            << "the pixels differ from the default level's";
    }
    EXPECT_EQ(sizes[""], sizes["1"]);  // the server's default
    EXPECT_GT(sizes["0"], sizes["1"]);
    EXPECT_GE(sizes["1"], sizes["9"]);
    // An async job encodes at the requested level too.
    auto queued = post_render(*cli, base + ",\"compression\":0}", true);
    ASSERT_TRUE(queued);
    ASSERT_EQ(queued->status, 202) << queued->body;
    const std::string location = queued->get_header_value("Location");
    for (int i = 0; i < 3000; ++i) {
        auto result = cli->Get(location + "/result");
        ASSERT_TRUE(result);
        if (result->status == 200) {
            EXPECT_EQ(result->body.size(), sizes["0"]);
            return;
        }
        std::this_thread::sleep_for(std::chrono::milliseconds(10));
    }
    FAIL() << "the job did not finish";
}

TEST_F(HttpRender, RawAnswersAreTheEnginePixelsOfTheTileAndSayWhereItLies) {
    auto cli = server_->client();
    for (const char* shading : {"diffuse", "normals"}) {
        for (const std::string tile : {"", ",\"tile\":{\"x\":7,\"y\":11,\"w\":40,\"h\":9}"}) {
            SCOPED_TRACE(std::string(shading) + (tile.empty() ? " frame" : " tile"));
            const std::string json = "{\"mesh\":\"" + id_ + "\",\"shading\":\"" + shading +
                                     "\",\"width\":96,\"height\":64,\"format\":\"raw\"" + tile +
                                     "}";
            auto res = post_render(*cli, json);
            ASSERT_TRUE(res);
            ASSERT_EQ(res->status, 200) << res->body;
            EXPECT_EQ(res->get_header_value("Content-Type"), "application/x-kdrt-image");
            EXPECT_EQ(res->get_header_value("X-Kdrt-Png-Compression"),
                      std::to_string(kDefaultPngCompression));
            auto raw = proto::decode_raw_image(string_to_bytes(res->body));
            ASSERT_TRUE(raw) << raw.error();
            const proto::RenderRequest r = request(json);
            EXPECT_EQ(raw->region, r.settings.region.value_or(PixelRegion{0, 0, 96, 64}));
            EXPECT_EQ(raw->frame_width, 96u);
            EXPECT_EQ(raw->frame_height, 64u);
            const Image engine = render(*tree_, r.settings);
            EXPECT_EQ(raw->image.width, engine.width);
            EXPECT_EQ(raw->image.height, engine.height);
            EXPECT_EQ(raw->image.channels, engine.channels);
            ASSERT_EQ(raw->image.pixels.size(), engine.pixels.size());
            EXPECT_EQ(std::memcmp(raw->image.pixels.data(), engine.pixels.data(),
                                  engine.pixels.size() * sizeof(float)),
                      0);
        }
    }
    // The header names the request's own level when it has one; raw takes no compression.
    auto p = expect_problem(
        post_render(*cli, "{\"mesh\":\"" + id_ + "\",\"format\":\"raw\",\"compression\":3}"), 400);
    EXPECT_NE(p.detail.find("\"compression\" applies to png only, not \"raw\""), std::string::npos)
        << p.detail;
    // An async raw job keeps its KDRI answer.
    auto queued = post_render(
        *cli, "{\"mesh\":\"" + id_ + "\",\"width\":8,\"height\":4,\"format\":\"raw\"}", true);
    ASSERT_TRUE(queued);
    ASSERT_EQ(queued->status, 202) << queued->body;
    EXPECT_EQ(proto::decode_job_status(queued->body)->format, "raw");
    const std::string location = queued->get_header_value("Location");
    for (int i = 0; i < 3000; ++i) {
        auto result = cli->Get(location + "/result");
        ASSERT_TRUE(result);
        if (result->status == 200) {
            EXPECT_EQ(result->get_header_value("Content-Type"), "application/x-kdrt-image");
            // As the synchronous answer: the level a client encodes stitched raw tiles at.
            EXPECT_EQ(result->get_header_value("X-Kdrt-Png-Compression"),
                      std::to_string(kDefaultPngCompression));
            auto raw = proto::decode_raw_image(string_to_bytes(result->body));
            ASSERT_TRUE(raw) << raw.error();
            EXPECT_EQ(raw->region, (PixelRegion{0, 0, 8, 4}));
            return;
        }
        std::this_thread::sleep_for(std::chrono::milliseconds(10));
    }
    FAIL() << "the raw job did not finish";
}

TEST_F(HttpRender, BadRequestsNameTheProblem) {
    auto cli = server_->client();
    struct Case {
        std::string json;
        int status;
        const char* detail;
    };
    const std::string mesh = "\"mesh\":\"" + id_ + "\"";
    const std::vector<Case> cases = {
        {"{}", 400, "missing member \"mesh\""},
        {"{" + mesh + ",\"width\":0}", 400,
         "\"width\" is 0, must be in 1 .. 8192 (max_image_width)"},
        {"{" + mesh + ",\"spp\":5000}", 400, "\"spp\" is 5000, must be in 1 .. 1024 (max_spp)"},
        {"{" + mesh + ",\"shading\":\"toon\"}", 400, "unknown shading \"toon\""},
        {"{" + mesh + ",\"format\":\"gif\"}", 400,
         "unknown format \"gif\" (expected png, jpg, exr or raw)"},
        {"{" + mesh + ",\"colour\":1}", 400, "unknown member \"colour\""},
        {"{" + mesh + ",\"camera\":{\"eye\":[0,0,1]}}", 400, "missing member \"camera.look_at\""},
        {"{" + mesh + ",\"camera\":{\"eye\":[0,0,1],\"look_at\":[0,0,1]}}", 400,
         "camera eye and look_at are the same"},
        {"{" + mesh + ",\"width\":100,\"tile\":{\"x\":90,\"y\":0,\"w\":20,\"h\":5}}", 400,
         "\"tile.w\" is 20, must be in 1 .. 10 (the tile must lie inside the 100 x 512 frame)"},
        {"{\"mesh\":\"" + std::string(64, 'e') + "\"}", 404, "no mesh with id eeee"},
        {"{\"mesh\":", 400, "invalid JSON at byte"},
        // Numbers beyond a double are a 400 naming the member (they were a 500).
        {"{" + mesh + ",\"camera\":{\"eye\":[0,0,1e400],\"look_at\":[0,0,0]}}", 400,
         "\"camera.eye\": number overflow"},
        {"{" + mesh + ",\"width\":1e400}", 400, "\"width\": number overflow"},
        // One rule for every JSON body: a member given twice is refused (as the rays route does).
        {"{" + mesh + ",\"width\":64,\"width\":32}", 400, "duplicate member \"width\""},
        {"{" + mesh + ",\"camera\":{\"eye\":[0,0,1],\"eye\":[0,0,2],\"look_at\":[0,0,0]}}", 400,
         "duplicate member \"camera.eye\""},
        {"{" + mesh + ",\"compression\":10}", 400, "\"compression\" is 10, must be in 0 .. 9"},
        {"{" + mesh + ",\"compression\":-1}", 400,
         "\"compression\" must be a non-negative integer"},
        {"{" + mesh + ",\"format\":\"exr\",\"compression\":3}", 400,
         "\"compression\" applies to png only, not \"exr\""},
    };
    for (const Case& c : cases) {
        SCOPED_TRACE(c.json);
        auto p = expect_problem(post_render(*cli, c.json), c.status);
        EXPECT_NE(p.detail.find(c.detail), std::string::npos) << p.detail;
    }
    auto p = expect_problem(cli->Post("/v1/render", "{}", "text/plain"), 415);
    EXPECT_NE(p.detail.find("render expects Content-Type application/json"), std::string::npos)
        << p.detail;
}

TEST_F(HttpRender, AsyncJobReportsProgressAndGivesTheImage) {
    auto cli = server_->client();
    const std::string json =
        "{\"mesh\":\"" + id_ + "\",\"shading\":\"ao\",\"width\":128,\"height\":128,\"spp\":4}";
    auto res = post_render(*cli, json, /*async=*/true);
    ASSERT_TRUE(res);
    ASSERT_EQ(res->status, 202) << res->body;
    EXPECT_EQ(res->get_header_value("Preference-Applied"), "respond-async");
    auto job = proto::decode_job_status(res->body);
    ASSERT_TRUE(job) << job.error();
    EXPECT_EQ(res->get_header_value("Location"), "/v1/jobs/" + job->id);
    EXPECT_EQ(job->mesh, id_);
    EXPECT_EQ(job->format, "png");

    double last_progress = 0;
    proto::JobStatus status = *job;
    for (int i = 0; i < 6000 && status.state != proto::JobState::kDone; ++i) {
        auto poll = cli->Get("/v1/jobs/" + job->id);
        ASSERT_TRUE(poll);
        ASSERT_EQ(poll->status, 200);
        status = *proto::decode_job_status(poll->body);
        EXPECT_GE(status.progress, last_progress);
        EXPECT_LE(status.progress, 1.0);
        last_progress = status.progress;
        ASSERT_NE(status.state, proto::JobState::kFailed) << status.error;
        if (status.state != proto::JobState::kDone) {
            auto early = cli->Get("/v1/jobs/" + job->id + "/result");
            if (early->status == 409) {
                auto p = expect_problem(early, 409);
                EXPECT_EQ(p.kind, ProblemKind::kJobNotDone);
            }
            std::this_thread::sleep_for(std::chrono::milliseconds(5));
        }
    }
    ASSERT_EQ(status.state, proto::JobState::kDone);
    EXPECT_EQ(status.progress, 1.0);
    EXPECT_TRUE(status.render_ms.has_value());
    auto image = cli->Get("/v1/jobs/" + job->id + "/result");
    ASSERT_TRUE(image);
    ASSERT_EQ(image->status, 200);
    EXPECT_EQ(image->get_header_value("Content-Type"), "image/png");
    EXPECT_EQ(image->body, expected_image(request(json)));
    EXPECT_EQ(status.result_bytes, image->body.size());
    // Deleting a finished job forgets it.
    EXPECT_EQ(cli->Delete("/v1/jobs/" + job->id)->status, 204);
    expect_problem(cli->Get("/v1/jobs/" + job->id), 404);
}

TEST_F(HttpRender, JobsCanBeCancelledAndTheQueueIsBounded) {
    auto cli = server_->client();
    // Long renders: the first runs, the second waits, a third is over --max-jobs 2.
    const std::string slow =
        "{\"mesh\":\"" + id_ + "\",\"shading\":\"ao\",\"width\":1024,\"height\":1024,\"spp\":256}";
    auto running = proto::decode_job_status(post_render(*cli, slow, true)->body);
    auto queued = proto::decode_job_status(post_render(*cli, slow, true)->body);
    ASSERT_TRUE(running && queued);
    auto p = expect_problem(post_render(*cli, slow, true), 503);
    EXPECT_EQ(p.kind, ProblemKind::kOverCapacity);
    EXPECT_NE(p.detail.find("2 render jobs are queued or running (max_jobs)"), std::string::npos)
        << p.detail;

    // Cancel the queued one: cancelled at once.
    auto del = cli->Delete("/v1/jobs/" + queued->id);
    ASSERT_EQ(del->status, 202) << del->body;
    EXPECT_EQ(proto::decode_job_status(del->body)->state, proto::JobState::kCancelled);
    // Cancel the running one: it stops at its next tile.
    del = cli->Delete("/v1/jobs/" + running->id);
    ASSERT_EQ(del->status, 202) << del->body;
    EXPECT_TRUE(proto::decode_job_status(del->body)->cancel_requested);
    proto::JobStatus status;
    for (int i = 0; i < 3000; ++i) {
        status = *proto::decode_job_status(cli->Get("/v1/jobs/" + running->id)->body);
        if (status.state == proto::JobState::kCancelled) break;
        std::this_thread::sleep_for(std::chrono::milliseconds(10));
    }
    EXPECT_EQ(status.state, proto::JobState::kCancelled);
    EXPECT_LT(status.progress, 1.0);
    p = expect_problem(cli->Get("/v1/jobs/" + running->id + "/result"), 409);
    EXPECT_NE(p.detail.find("is cancelled and has no result"), std::string::npos) << p.detail;
    p = expect_problem(cli->Get("/v1/jobs/0123"), 404);
    EXPECT_EQ(p.kind, ProblemKind::kUnknownJob);
    EXPECT_EQ(server_->metric("kdrt_jobs_finished_total{outcome=\"cancelled\"}"), 2.0);
}

}  // namespace
}  // namespace kdrt::test

namespace kdrt::test {
namespace {

TEST(HttpRenderDefaults, LeftOutSizesRespectTheServerLimits) {
    TempDir dir;
    ServerProcess server({.cache_dir = dir.path() / "cache",
                          .args = {"--max-image-width", "128", "--max-image-height", "64"}});
    auto cli = server.client();
    const std::string id = upload_id(*cli, small_mesh(78, 500));
    auto res = cli->Post("/v1/render", "{\"mesh\":\"" + id + "\"}", "application/json");
    ASSERT_TRUE(res);
    ASSERT_EQ(res->status, 200) << res->body;
    auto image = proto::decode_image(string_to_bytes(res->body));
    ASSERT_TRUE(image);
    EXPECT_EQ(image->width, 128u);  // the default 512 used to be rendered anyway
    EXPECT_EQ(image->height, 64u);
}

}  // namespace
}  // namespace kdrt::test
