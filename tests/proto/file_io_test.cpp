#include "kdrt/proto/file_io.h"

#include <gmock/gmock.h>
#include <gtest/gtest.h>
#include <unistd.h>

#include <filesystem>

#include "proto_test_util.h"

namespace kdrt::proto {
namespace {

using ::testing::HasSubstr;

/// The path in double quotes (built piecewise: GCC 12 gives a false -Wrestrict on "\"" + s + "\"").
std::string quoted(const std::filesystem::path& path) {
    std::string s(1, '"');
    s += path.string();
    s += '"';
    return s;
}

/// A fresh directory per test, removed afterwards.
class FileIo : public ::testing::Test {
protected:
    void SetUp() override {
        const auto* info = ::testing::UnitTest::GetInstance()->current_test_info();
        dir_ = std::filesystem::temp_directory_path() /
               ("kdrt_proto_" + std::to_string(::getpid()) + "_" + info->name());
        std::filesystem::remove_all(dir_);
        std::filesystem::create_directories(dir_);
    }
    void TearDown() override { std::filesystem::remove_all(dir_); }

    std::filesystem::path dir_;
};

TEST_F(FileIo, WriteThenReadRoundTrips) {
    std::vector<std::byte> data(300000);
    for (size_t i = 0; i < data.size(); ++i) data[i] = static_cast<std::byte>(i * 7 + 3);
    const auto path = dir_ / "blob.bin";
    ASSERT_TRUE(write_file_bytes(path, data).ok());
    const auto back = read_file_bytes(path);
    ASSERT_TRUE(back.ok()) << back.error();
    EXPECT_EQ(*back, data);
    // Overwrite truncates.
    ASSERT_TRUE(write_file_bytes(path, std::span(data).first(5)).ok());
    EXPECT_EQ(read_file_bytes(path)->size(), 5u);
}

TEST_F(FileIo, EmptyFile) {
    const auto path = dir_ / "empty";
    ASSERT_TRUE(write_file_bytes(path, {}).ok());
    const auto back = read_file_bytes(path);
    ASSERT_TRUE(back.ok());
    EXPECT_TRUE(back->empty());
}

TEST_F(FileIo, MissingFileNamesPathAndReason) {
    const auto path = dir_ / "nope.kdrr";
    const auto r = read_file_bytes(path);
    ASSERT_FALSE(r.ok());
    EXPECT_THAT(r.error(), HasSubstr(quoted(path)));
    EXPECT_THAT(r.error(), HasSubstr("No such file or directory"));
}

TEST_F(FileIo, DirectoryIsNotAFile) {
    const auto r = read_file_bytes(dir_);
    ASSERT_FALSE(r.ok());
    EXPECT_THAT(r.error(), HasSubstr(dir_.string()));
    EXPECT_THAT(r.error(), HasSubstr("Is a directory"));
}

TEST_F(FileIo, SizeLimitRefusesLargerFiles) {
    const auto path = dir_ / "ten";
    ASSERT_TRUE(write_file_bytes(path, std::vector<std::byte>(10)).ok());
    EXPECT_TRUE(read_file_bytes(path, 10).ok());
    const auto r = read_file_bytes(path, 9);
    ASSERT_FALSE(r.ok());
    EXPECT_THAT(r.error(), HasSubstr("file has 10 bytes, limit is 9"));
}

TEST_F(FileIo, WriteIntoMissingDirectoryFails) {
    const auto path = dir_ / "no" / "such" / "dir" / "out.kdrh";
    const auto r = write_file_bytes(path, std::vector<std::byte>(4));
    ASSERT_FALSE(r.ok());
    EXPECT_THAT(r.error(), HasSubstr(path.string()));
    EXPECT_THAT(r.error(), HasSubstr("for writing: No such file or directory"));
}

TEST_F(FileIo, ReadsTestData) {
    const auto r = read_file_bytes(test::test_data("bunny00.off"));
    ASSERT_TRUE(r.ok()) << r.error();
    EXPECT_EQ(r->size(), std::filesystem::file_size(test::test_data("bunny00.off")));
}

}  // namespace
}  // namespace kdrt::proto
