// What the `kdrt` binary loads at start (ldd: few shared libraries, no OpenImageIO), and its
// image module (kdrt-image-module.so, kdrt/proto/image_module.h): a kdrt without the module, or
// with one that cannot load, refuses the commands that write images with a message naming what
// to install, before any request; every other command runs without it. That the module's bytes
// are the server's is tested by the commands that use it (Cli.SplitRenderWritesTheBytesOf...,
// CliScan.PinholeFilesHoldTheEnginesScan).

#include <gtest/gtest.h>

#include <cstdio>
#include <filesystem>
#include <fstream>
#include <sstream>
#include <string>
#include <vector>

#include "cli_runner.h"
#include "server_process.h"

namespace kdrt::test {
namespace {

namespace fs = std::filesystem;

/// The bound: `kdrt` loads at most this many shared libraries (ldd's lines).
constexpr size_t kMaxSharedLibraries = 30;

/// ldd's output for `binary` (one line per library, the vDSO and the loader included).
std::vector<std::string> ldd(const std::string& binary) {
    std::vector<std::string> lines;
    FILE* pipe = ::popen(("ldd '" + binary + "' 2>&1").c_str(), "r");
    if (!pipe) return lines;
    char buf[4096];
    while (std::fgets(buf, sizeof buf, pipe)) lines.emplace_back(buf);
    ::pclose(pipe);
    return lines;
}

TEST(CliStartup, LoadsFewSharedLibrariesAndNoImageLibrary) {
    const std::vector<std::string> libs = ldd(KDRT_CLI_BINARY);
    ASSERT_FALSE(libs.empty()) << "ldd printed nothing for " << KDRT_CLI_BINARY;
    std::string all;
    for (const std::string& l : libs) all += l;
    EXPECT_LE(libs.size(), kMaxSharedLibraries) << all;
    EXPECT_FALSE(contains(all, "not found")) << all;
    for (const char* image_library : {"OpenImageIO", "libOpenEXR", "libpng", "libjpeg"})
        EXPECT_FALSE(contains(all, image_library)) << image_library << " in\n" << all;
}

TEST(CliStartup, TheImageModuleIsBesideTheBinaryAndLoadsOpenImageIO) {
    const fs::path module = fs::path(KDRT_CLI_BINARY).parent_path() / "kdrt-image-module.so";
    ASSERT_TRUE(fs::exists(module)) << module;
    std::string all;
    for (const std::string& l : ldd(module.string())) all += l;
    EXPECT_TRUE(contains(all, "OpenImageIO")) << all;
    EXPECT_FALSE(contains(all, "not found")) << all;
}

/// A copy of kdrt in an empty directory: no module beside it or under ../lib*/kdrt.
class CliWithoutModule : public ::testing::Test {
protected:
    void SetUp() override {
        bin_ = dir_.path() / "prefix" / "bin";
        fs::create_directories(bin_);
        fs::copy_file(KDRT_CLI_BINARY, bin_ / "kdrt");
        out_ = (dir_.path() / "out").string();
    }
    CliRun kdrt(std::vector<std::string> args) {
        args.insert(args.end(), {"--server", "http://127.0.0.1:9", "--retries", "0"});
        return run_cli(args, {.binary = (bin_ / "kdrt").string()});
    }
    TempDir dir_;
    fs::path bin_;
    std::string out_;
};

const std::string kId(64, 'a');

TEST_F(CliWithoutModule, ImageCommandsNameTheMissingModuleAndThePackageBeforeAnyRequest) {
    for (const std::vector<std::string>& args : std::vector<std::vector<std::string>>{
             {"render", kId, "-o", out_ + ".png", "--split", "2"},
             {"scan", kId, "--pinhole", "-o", out_ + ".exr", "--eye", "0,0,5", "--look-at",
              "0,0,0"},
         }) {
        const CliRun run = kdrt(args);
        // Exit 1, not 3: the server (a closed port) was never asked.
        EXPECT_EQ(run.exit_code, 1) << args[0] << ": " << run.err;
        EXPECT_TRUE(contains(run.err, "kdrt " + args[0] + ": ")) << run.err;
        EXPECT_TRUE(contains(run.err, "kdrt-image-module.so")) << run.err;
        EXPECT_TRUE(contains(run.err, (bin_ / "kdrt-image-module.so").string())) << run.err;
        EXPECT_TRUE(contains(run.err, "libopenimageio")) << run.err;
        EXPECT_FALSE(contains(run.err, "is kdrt-server running")) << run.err;
        EXPECT_FALSE(fs::exists(args[3])) << args[3];
    }
}

TEST_F(CliWithoutModule, OtherCommandsRunWithoutIt) {
    // These reach the (closed) server: exit 3, the connection error, nothing about the module.
    for (const std::vector<std::string>& args : std::vector<std::vector<std::string>>{
             {"health"},
             {"meshes"},
             {"render", kId, "-o", out_ + ".png"},  // unsplit: the server's bytes, no encoder
             {"scan", kId, "--pinhole", "-o", out_ + ".kdrz", "--eye", "0,0,5", "--look-at",
              "0,0,0"},
         }) {
        const CliRun run = kdrt(args);
        EXPECT_EQ(run.exit_code, 3) << args[0] << ": " << run.err;
        EXPECT_FALSE(contains(run.err, "image module")) << run.err;
    }
    const CliRun help = run_cli({"--help"}, {.binary = (bin_ / "kdrt").string()});
    EXPECT_EQ(help.exit_code, 0);
    EXPECT_TRUE(contains(help.out, "usage: kdrt")) << help.out;
}

TEST_F(CliWithoutModule, AModuleThatCannotLoadIsNamedWithDlopensReason) {
    // Installed layout (bin/../lib/kdrt) with a file that is not a shared object.
    const fs::path libdir = (bin_ / KDRT_IMAGE_MODULE_RELDIR_FROM_BIN).lexically_normal();
    fs::create_directories(libdir);
    std::ofstream(libdir / "kdrt-image-module.so") << "not an ELF file\n";
    const CliRun run = kdrt({"render", kId, "-o", out_ + ".png", "--split", "2"});
    EXPECT_EQ(run.exit_code, 1) << run.err;
    EXPECT_TRUE(contains(run.err, "cannot load the image module")) << run.err;
    EXPECT_TRUE(contains(run.err, (libdir / "kdrt-image-module.so").string())) << run.err;
    EXPECT_TRUE(contains(run.err, "libopenimageio")) << run.err;
}

TEST_F(CliWithoutModule, TheInstalledLayoutFindsTheBuiltModule) {
    // The real module under bin/../<libdir>/kdrt is found (the render then fails to connect).
    const fs::path libdir = (bin_ / KDRT_IMAGE_MODULE_RELDIR_FROM_BIN).lexically_normal();
    fs::create_directories(libdir);
    fs::copy_file(fs::path(KDRT_CLI_BINARY).parent_path() / "kdrt-image-module.so",
                  libdir / "kdrt-image-module.so");
    const CliRun run = kdrt({"render", kId, "-o", out_ + ".png", "--split", "2"});
    EXPECT_EQ(run.exit_code, 3) << run.err;
    EXPECT_FALSE(contains(run.err, "image module")) << run.err;
}

}  // namespace
}  // namespace kdrt::test
