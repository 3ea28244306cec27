#include "http/request_body.h"

#include <gtest/gtest.h>
#include <unistd.h>

#include <filesystem>
#include <string>

namespace kdrt::server {
namespace {

std::string as_string(std::span<const std::byte> bytes) {
    return {reinterpret_cast<const char*>(bytes.data()), bytes.size()};
}

std::string pattern(size_t n) {
    std::string s(n, '\0');
    for (size_t i = 0; i < n; ++i) s[i] = static_cast<char>('a' + i % 26);
    return s;
}

TEST(RequestBody, SmallBodiesStayInMemory) {
    RequestBody body(1000, 100, std::filesystem::temp_directory_path(), 10);
    EXPECT_TRUE(body.append("hello ", 6));
    EXPECT_TRUE(body.append("world", 5));
    ASSERT_TRUE(body.finish());
    EXPECT_FALSE(body.spooled());
    EXPECT_EQ(as_string(body.bytes()), "hello world");
    EXPECT_EQ(body.size(), 11u);
}

TEST(RequestBody, LargeBodiesAreSpooledAndMapped) {
    const std::string data = pattern(100000);
    RequestBody body(1 << 20, 1000, std::filesystem::temp_directory_path());
    for (size_t at = 0; at < data.size(); at += 777)
        ASSERT_TRUE(body.append(data.data() + at, std::min<size_t>(777, data.size() - at)));
    ASSERT_TRUE(body.finish());
    EXPECT_TRUE(body.spooled());
    EXPECT_EQ(as_string(body.bytes()), data);
}

TEST(RequestBody, RefusesMoreThanTheLimit) {
    RequestBody body(10, 100, std::filesystem::temp_directory_path());
    EXPECT_TRUE(body.append("0123456789", 10));
    EXPECT_FALSE(body.append("x", 1));
    EXPECT_TRUE(body.too_large());
    EXPECT_FALSE(body.append("", 0));  // stays refused
    EXPECT_EQ(body.size(), 10u);
}

TEST(RequestBody, ReportsAnUnusableSpoolDirectory) {
    RequestBody body(1000, 4, "/nonexistent-kdrt-dir");
    EXPECT_FALSE(body.append("0123456789", 10));
    EXPECT_FALSE(body.too_large());
    EXPECT_NE(body.error().find("cannot create a spool file in \"/nonexistent-kdrt-dir\""),
              std::string::npos)
        << body.error();
    EXPECT_FALSE(body.finish());
}

TEST(RequestBody, EmptyBody) {
    RequestBody body(10, 0, std::filesystem::temp_directory_path());
    ASSERT_TRUE(body.finish());
    EXPECT_TRUE(body.bytes().empty());
}

}  // namespace
}  // namespace kdrt::server
