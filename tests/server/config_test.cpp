#include "core/config.h"

#include <gtest/gtest.h>
#include <unistd.h>

#include <algorithm>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <limits>

#include "kdrt/mesh.h"
#include "kdrt/proto/config_json.h"
#include "kdrt/proto/file_io.h"
#include "kdrt/proto/image_format.h"
#include "kdrt/proto/json_api.h"
#include "kdrt/proto/ray_batch.h"
#include "kdrt/render.h"

namespace kdrt::server {
namespace {

Invocation parse_ok(const std::vector<std::string>& args,
                    const std::vector<std::string>& env = {}) {
    auto r = parse_invocation(args, env);
    EXPECT_TRUE(r) << (r ? "" : r.error());
    return r ? *r : Invocation{};
}

std::string parse_error(const std::vector<std::string>& args,
                        const std::vector<std::string>& env = {}) {
    auto r = parse_invocation(args, env);
    EXPECT_FALSE(r);
    return r ? "" : r.error();
}

TEST(Config, DefaultsWithoutAnything) {
    const Invocation inv = parse_ok({});
    EXPECT_EQ(inv.mode, Invocation::Mode::kServe);
    EXPECT_EQ(inv.config.listen, "127.0.0.1:8080");
    EXPECT_EQ(inv.config.memory_budget, 2ull << 30);
    EXPECT_EQ(inv.config.max_json_rays, 100000u);
    EXPECT_TRUE(inv.config.preload.empty());
}

TEST(Config, FlagsInBothFormsAndPreloadLists) {
    const Invocation inv =
        parse_ok({"--listen", "0.0.0.0:9000", "--threads=3", "--memory-budget", "512M", "--preload",
                  "a.obj", "b.ply", "--token", "t", "--log-format", "json"});
    EXPECT_EQ(inv.config.listen, "0.0.0.0:9000");
    EXPECT_EQ(inv.config.threads, 3u);
    EXPECT_EQ(inv.config.memory_budget, 512ull << 20);
    EXPECT_EQ(inv.config.preload, (std::vector<std::string>{"a.obj", "b.ply"}));
    EXPECT_EQ(inv.config.token, "t");
    EXPECT_EQ(inv.config.log_format, "json");
    EXPECT_EQ(inv.config.web_viewer, "on");
    EXPECT_EQ(parse_ok({"--web-viewer", "off"}).config.web_viewer, "off");
    EXPECT_EQ(inv.config.scene_sync, "commit");
    EXPECT_EQ(parse_ok({"--scene-sync", "none"}).config.scene_sync, "none");
}

TEST(Config, FileThenEnvironmentThenFlags) {
    const auto path = std::filesystem::temp_directory_path() /
                      ("kdrt-config-test-" + std::to_string(::getpid()) + ".json");
    std::ofstream(path)
        << "{ // settings\n \"threads\": 4, \"http_threads\": 9, \"max_spp\": 7,\n"
           " \"preload\": [\"x.off\"], \"memory_budget\": \"1G\", \"cache_dir\": \"/c\" }";
    const Invocation inv = parse_ok({"--http-threads", "11", "--config", path.string()},
                                    {"KDRT_THREADS=5", "KDRT_HTTP_THREADS=10",
                                     "KDRT_PRELOAD=a.obj:b.obj", "KDRT_UNRELATED=1", "HOME=/root"});
    EXPECT_EQ(inv.config.config_file, path.string());
    EXPECT_EQ(inv.config.max_spp, 7u);  // file
    EXPECT_EQ(inv.config.memory_budget, 1ull << 30);
    EXPECT_EQ(inv.config.cache_dir, "/c");
    EXPECT_EQ(inv.config.threads, 5u);        // environment beats the file
    EXPECT_EQ(inv.config.http_threads, 11u);  // flag beats both
    EXPECT_EQ(inv.config.preload, (std::vector<std::string>{"a.obj", "b.obj"}));
    // KDRT_CONFIG names the file too.
    const Invocation from_env = parse_ok({}, {"KDRT_CONFIG=" + path.string()});
    EXPECT_EQ(from_env.config.threads, 4u);
    std::filesystem::remove(path);
}

TEST(Config, ErrorsNameTheSettingAndSource) {
    EXPECT_EQ(parse_error({"--threads", "x"}), "--threads: \"x\" is not a non-negative integer");
    EXPECT_EQ(parse_error({"--threads"}), "--threads needs a value");
    EXPECT_EQ(parse_error({"--http-threads", "0"}), "--http-threads: \"0\" is outside 1..4096");
    EXPECT_EQ(parse_error({"--memory-budget", "12Q"}),
              "--memory-budget: \"12Q\" is not a byte count (digits with an optional K, M, G or T "
              "suffix)");
    EXPECT_EQ(parse_error({"--listen", "8080"}),
              "--listen: \"8080\" is not HOST:PORT (e.g. 127.0.0.1:8080)");
    EXPECT_EQ(parse_error({"--listen", "h:99999"}),
              "--listen: \"h:99999\" has no port number 0..65535 after the last ':'");
    EXPECT_EQ(parse_error({"--log-level", "loud"}),
              "--log-level: \"loud\" is not one of trace, debug, info, warn, error, critical, off");
    EXPECT_EQ(parse_error({"--web-viewer", "yes"}), "--web-viewer: \"yes\" is not one of on, off");
    EXPECT_EQ(parse_error({"--frobnicate"}),
              "unknown argument \"--frobnicate\" (kdrt-server --help lists the flags)");
    EXPECT_EQ(parse_error({}, {"KDRT_MAX_RAYS=0"}), "KDRT_MAX_RAYS: \"0\" is outside 1..67108864");
    EXPECT_EQ(parse_error({"--preload"}), "--preload needs at least one value");
    EXPECT_EQ(parse_error({"--mesh-id"}), "--mesh-id needs at least one mesh file");

    const auto path = std::filesystem::temp_directory_path() /
                      ("kdrt-config-bad-" + std::to_string(::getpid()) + ".json");
    std::ofstream(path) << "{\"thread\": 4}";
    EXPECT_EQ(parse_error({"--config", path.string()}),
              path.string() + ": unknown setting \"thread\" (kdrt-server --help lists them)");
    std::ofstream(path, std::ios::trunc) << "{\"threads\": \"many\"}";
    EXPECT_EQ(parse_error({"--config", path.string()}),
              path.string() + ": \"threads\": \"many\" is not a non-negative integer");
    std::ofstream(path, std::ios::trunc) << "{\"listen\": 80}";
    EXPECT_EQ(parse_error({"--config", path.string()}),
              path.string() + ": \"listen\" must be a string");
    std::filesystem::remove(path);
}

TEST(Config, Commands) {
    EXPECT_EQ(parse_ok({"--help"}).mode, Invocation::Mode::kHelp);
    EXPECT_EQ(parse_ok({"--threads", "2", "-h"}).mode, Invocation::Mode::kHelp);
    EXPECT_EQ(parse_ok({"--version"}).mode, Invocation::Mode::kVersion);
    const Invocation ids = parse_ok({"--mesh-id", "a.obj", "b.off"});
    EXPECT_EQ(ids.mode, Invocation::Mode::kMeshId);
    EXPECT_EQ(ids.mesh_files, (std::vector<std::string>{"a.obj", "b.off"}));
}

TEST(Config, HelpListsEverySetting) {
    const std::string help = help_text();
    for (const std::string& key : setting_keys()) {
        std::string flag = "--" + key;
        std::replace(flag.begin(), flag.end(), '_', '-');
        EXPECT_NE(help.find(flag), std::string::npos) << flag;
    }
}

TEST(Config, ShippedConfigFileListsEverySettingWithItsDefault) {
    const std::string path = std::string(KDRT_SOURCE_DIR) + "/config/kdrt.json";
    auto bytes = proto::read_file_bytes(path);
    ASSERT_TRUE(bytes) << bytes.error();
    const std::string text(reinterpret_cast<const char*>(bytes->data()), bytes->size());
    auto entries = proto::parse_config_object(text);
    ASSERT_TRUE(entries) << entries.error();
    std::vector<std::string> keys;
    for (const auto& e : *entries) keys.push_back(e.key);
    EXPECT_EQ(keys, setting_keys());
    // Each value, re-read through the same parser, equals the built-in default.
    for (const auto& e : *entries) {
        auto one =
            proto::parse_config_object("{\"" + e.key + "\": " + setting_default_json(e.key) + "}");
        ASSERT_TRUE(one) << e.key;
        EXPECT_EQ((*one)[0].value, e.value) << e.key;
    }
    // Every setting has a comment line above it.
    for (const std::string& key : setting_keys()) {
        const size_t at = text.find("\"" + key + "\":");
        ASSERT_NE(at, std::string::npos) << key;
        const size_t line_start = text.rfind('\n', at);
        const size_t prev_line = text.rfind('\n', line_start - 1);
        EXPECT_NE(text.substr(prev_line + 1, line_start - prev_line).find("//"), std::string::npos)
            << key;
    }
    // And the server accepts it as is.
    EXPECT_TRUE(parse_invocation({"--config", path}, {}));
}

// A setting's range is the range of the layer that enforces it: a value the renderer, the mesh
// parsers or the batch decoders would refuse on every request is refused at start-up instead.
TEST(Config, RangesAreTheLimitsOfTheLayerThatEnforcesThem) {
    const std::string image = std::to_string(kMaxImageSize);
    EXPECT_EQ(parse_error({"--max-image-width", "20000"}),
              "--max-image-width: \"20000\" is outside 1.." + image);
    EXPECT_EQ(parse_error({"--max-image-height=20000"}),
              "--max-image-height: \"20000\" is outside 1.." + image);
    EXPECT_EQ(parse_error({}, {"KDRT_MAX_IMAGE_WIDTH=65536"}),
              "KDRT_MAX_IMAGE_WIDTH: \"65536\" is outside 1.." + image);
    const auto path = std::filesystem::temp_directory_path() /
                      ("kdrt-config-range-" + std::to_string(::getpid()) + ".json");
    std::ofstream(path) << "{\"max_image_height\": 20000}";
    EXPECT_EQ(parse_error({"--config", path.string()}),
              path.string() + ": \"max_image_height\": \"20000\" is outside 1.." + image);
    std::filesystem::remove(path);

    const Invocation largest = parse_ok({"--max-image-width", image, "--max-image-height", image});
    EXPECT_EQ(largest.config.max_image_width, kMaxImageSize);
    EXPECT_EQ(largest.config.max_image_height, kMaxImageSize);

    const auto one_past = [](uint64_t limit) { return std::to_string(limit + 1); };
    EXPECT_EQ(parse_error({"--max-spp", one_past(kMaxSamplesPerPixel)}),
              "--max-spp: \"" + one_past(kMaxSamplesPerPixel) + "\" is outside 1.." +
                  std::to_string(kMaxSamplesPerPixel));
    EXPECT_EQ(parse_error({"--max-triangles", one_past(kMaxTriangles)}),
              "--max-triangles: \"" + one_past(kMaxTriangles) + "\" is outside 1.." +
                  std::to_string(kMaxTriangles));
    const uint32_t max_rays = proto::DecodeLimits{}.max_rays;
    EXPECT_EQ(
        parse_error({"--max-rays", one_past(max_rays)}),
        "--max-rays: \"" + one_past(max_rays) + "\" is outside 1.." + std::to_string(max_rays));
    EXPECT_EQ(parse_error({"--max-json-rays", one_past(proto::kMaxJsonRays)}),
              "--max-json-rays: \"" + one_past(proto::kMaxJsonRays) + "\" is outside 1.." +
                  std::to_string(proto::kMaxJsonRays));
    EXPECT_EQ(
        parse_error({"--png-compression", "10"}),
        "--png-compression: \"10\" is outside 0.." + std::to_string(proto::kMaxPngCompression));
    // The smallest raw render answers one RGB pixel: its KDRI header and 3 floats, 44 bytes.
    EXPECT_EQ(parse_ok({"--max-raw-render-bytes", "44"}).config.max_raw_render_bytes, 44u);
    EXPECT_EQ(parse_ok({"--max-raw-render-bytes", "64M"}).config.max_raw_render_bytes, 64u << 20);
    EXPECT_EQ(parse_error({"--max-raw-render-bytes", "43"}),
              "--max-raw-render-bytes: \"43\" is outside 44.." +
                  std::to_string(std::numeric_limits<uint64_t>::max()));
}

TEST(Config, ByteCountsAndListenAddresses) {
    EXPECT_EQ(*parse_bytes("0"), 0u);
    EXPECT_EQ(*parse_bytes("4k"), 4096u);
    EXPECT_EQ(*parse_bytes("3T"), 3ull << 40);
    EXPECT_FALSE(parse_bytes("99999999999999999999"));
    EXPECT_FALSE(parse_bytes("20000000T"));
    EXPECT_FALSE(parse_bytes("M"));
    EXPECT_EQ(*split_listen("[::1]:80"), (std::pair<std::string, int>{"::1", 80}));
    EXPECT_EQ(*split_listen("localhost:0"), (std::pair<std::string, int>{"localhost", 0}));
}

}  // namespace
}  // namespace kdrt::server

namespace kdrt::server {
namespace {

TEST(Config, TokenFromAFileOrTheEnvironmentNotOnlyTheCommandLine) {
    const std::filesystem::path file =
        std::filesystem::temp_directory_path() / ("kdrt-token-" + std::to_string(::getpid()));
    std::ofstream(file) << "s3cret-token\n";
    EXPECT_EQ(parse_ok({"--token-file", file.string()}).config.token, "s3cret-token");
    EXPECT_EQ(parse_ok({}, {"KDRT_TOKEN_FILE=" + file.string()}).config.token, "s3cret-token");
    EXPECT_EQ(parse_ok({}, {"KDRT_TOKEN=from-env"}).config.token, "from-env");
    EXPECT_EQ(parse_error({"--token-file", file.string(), "--token", "x"}),
              "token and token_file are both set; give the token one way");
    std::ofstream(file, std::ios::trunc) << "two\nlines\n";
    EXPECT_NE(parse_error({"--token-file", file.string()}).find("more than one line"),
              std::string::npos);
    std::ofstream(file, std::ios::trunc) << "\n";
    EXPECT_NE(parse_error({"--token-file", file.string()}).find("is empty"), std::string::npos);
    std::filesystem::remove(file);
    EXPECT_NE(parse_error({"--token-file", file.string()}).find("token_file: "), std::string::npos);
    EXPECT_NE(help_text().find("--token-file"), std::string::npos);
    EXPECT_NE(help_text().find("/proc/PID/cmdline"), std::string::npos);
}

TEST(Config, TokensFileGivesEachTokenItsRoles) {
    const std::filesystem::path file =
        std::filesystem::temp_directory_path() / ("kdrt-tokens-" + std::to_string(::getpid()));
    std::ofstream(file)
        << "# comment\nread r1-0123456789abcdef\n\n  write\tw1-0123456789abcdef \r\n"
           "read,write rw1-0123456789abcdef\nwrite,read wr1-0123456789abcdef\n";
    const ServerConfig c = parse_ok({"--tokens-file", file.string(), "--token", "full"}).config;
    ASSERT_EQ(c.role_tokens.size(), 4u);
    EXPECT_EQ(c.role_tokens[0].token, "r1-0123456789abcdef");
    EXPECT_EQ(c.role_tokens[0].roles, kRoleRead);
    EXPECT_EQ(c.role_tokens[1].token, "w1-0123456789abcdef");
    EXPECT_EQ(c.role_tokens[1].roles, kRoleWrite);
    EXPECT_EQ(c.role_tokens[2].roles, kRoleRead | kRoleWrite);
    EXPECT_EQ(c.role_tokens[3].roles, kRoleRead | kRoleWrite);
    // The single token keeps full access, beside the file's.
    const std::vector<ApiToken> all = accepted_tokens(c);
    ASSERT_EQ(all.size(), 5u);
    EXPECT_EQ(all[0].token, "full");
    EXPECT_EQ(all[0].roles, kRoleRead | kRoleWrite);
    EXPECT_TRUE(accepted_tokens(ServerConfig{}).empty());
    EXPECT_EQ(parse_ok({}, {"KDRT_TOKENS_FILE=" + file.string()}).config.role_tokens.size(), 4u);
    EXPECT_EQ(role_names(kRoleRead), "read");
    EXPECT_EQ(role_names(kRoleRead | kRoleWrite), "read,write");

    const auto refused = [&](const std::string& text) {
        std::ofstream(file, std::ios::trunc) << text;
        return parse_error({"--tokens-file", file.string()});
    };
    const std::string origin = "tokens_file \"" + file.string() + "\"";
    const std::string a = "a-0123456789abcdef", b = "b-0123456789abcdef";
    EXPECT_EQ(refused("read " + a + "\nadmin " + b + "\n"),
              origin + " line 2: unknown role \"admin\" (read, write)");
    EXPECT_EQ(refused("read\n"),
              origin + " line 1: expected 'ROLES TOKEN' (ROLES: read, write or read,write)");
    EXPECT_EQ(refused("read " + a + " " + b + "\n"),
              origin + " line 1: the token holds a space or a control character");
    EXPECT_EQ(refused("read " + a + "\nwrite " + a + "\n"),
              origin + " line 2: the token of an earlier line again");
    EXPECT_EQ(refused("# nothing\n\n"), origin + " holds no token");
    // Tokens shorter than 16 characters are refused, naming the file and line, not the token
    // (issue 25 item 12).
    EXPECT_EQ(refused("read " + a + "\n\nwrite x\n"),
              origin +
                  " line 3: the token has 1 characters; a token needs at least 16 (a random one: "
                  "head -c 24 /dev/urandom | base64)");
    EXPECT_EQ(refused("read 0123456789abcde\n"),
              origin +
                  " line 1: the token has 15 characters; a token needs at least 16 (a random one: "
                  "head -c 24 /dev/urandom | base64)");
    std::ofstream(file, std::ios::trunc) << "read same-0123456789abcdef\n";
    EXPECT_EQ(parse_error({"--tokens-file", file.string(), "--token", "same-0123456789abcdef"}),
              origin + " repeats the token of token/token_file");
    std::filesystem::remove(file);
    EXPECT_EQ(parse_error({"--tokens-file", file.string()}).rfind("tokens_file: ", 0), 0u);
    EXPECT_NE(help_text().find("--tokens-file"), std::string::npos);
}

TEST(Config, SecretFilesOthersCanReadAreWarnedAbout) {
    // A tokens file (or token file) with group or other permission bits is taken, with a
    // warning for the log naming the file and its mode (issue 25 item 12).
    namespace fs = std::filesystem;
    const fs::path tokens =
        fs::temp_directory_path() / ("kdrt-tokens-mode-" + std::to_string(::getpid()));
    const fs::path token =
        fs::temp_directory_path() / ("kdrt-token-mode-" + std::to_string(::getpid()));
    std::ofstream(tokens) << "read r1-0123456789abcdef\n";
    std::ofstream(token) << "t-0123456789abcdef\n";
    const std::vector<std::string> args = {"--tokens-file", tokens.string(), "--token-file",
                                           token.string()};
    fs::permissions(tokens, fs::perms::owner_read | fs::perms::owner_write);
    fs::permissions(token, fs::perms::owner_read);
    EXPECT_TRUE(parse_ok(args).warnings.empty());
    fs::permissions(tokens, fs::perms::owner_read | fs::perms::owner_write | fs::perms::group_read |
                                fs::perms::others_read);
    fs::permissions(token, fs::perms::owner_read | fs::perms::group_write);
    const std::vector<std::string> warnings = parse_ok(args).warnings;
    ASSERT_EQ(warnings.size(), 2u);
    EXPECT_EQ(warnings[0], "token_file \"" + token.string() +
                               "\" can be written by users other than its owner (mode 0420): it "
                               "holds bearer tokens; chmod 600 it");
    EXPECT_EQ(warnings[1], "tokens_file \"" + tokens.string() +
                               "\" can be read by users other than its owner (mode 0644): it "
                               "holds bearer tokens; chmod 600 it");
    fs::remove(tokens);
    fs::remove(token);
}

}  // namespace
}  // namespace kdrt::server
