#include "kdrt/proto/result.h"

#include <gtest/gtest.h>

#include <memory>
#include <string>

namespace kdrt::proto {
namespace {

Result<int, std::string> half(int v) {
    if (v % 2 != 0) return Err{std::to_string(v) + " is odd"};
    return v / 2;
}

TEST(Result, HoldsValueOrError) {
    const auto ok = half(8);
    ASSERT_TRUE(ok.ok());
    EXPECT_TRUE(static_cast<bool>(ok));
    EXPECT_EQ(ok.value(), 4);
    EXPECT_EQ(*ok, 4);

    const auto bad = half(7);
    ASSERT_FALSE(bad.ok());
    EXPECT_FALSE(static_cast<bool>(bad));
    EXPECT_EQ(bad.error(), "7 is odd");
    EXPECT_EQ(bad.value_or(-1), -1);
    EXPECT_EQ(ok.value_or(-1), 4);
}

TEST(Result, SameValueAndErrorTypeStayDistinct) {
    const auto value = Result<std::string, std::string>::success("v");
    const auto error = Result<std::string, std::string>::failure("e");
    ASSERT_TRUE(value.ok());
    ASSERT_FALSE(error.ok());
    EXPECT_EQ(*value, "v");
    EXPECT_EQ(error.error(), "e");
    const Result<std::string, std::string> from_err = make_error(std::string("x"));
    EXPECT_FALSE(from_err.ok());
    EXPECT_EQ(from_err.error(), "x");
}

TEST(Result, MoveOnlyValueAndArrow) {
    struct Box {
        std::unique_ptr<int> p;
        int get() const { return *p; }
    };
    Result<Box, int> r = Box{std::make_unique<int>(42)};
    ASSERT_TRUE(r.ok());
    EXPECT_EQ(r->get(), 42);
    Box taken = std::move(r).value();
    EXPECT_EQ(*taken.p, 42);
}

TEST(Result, VoidSpecialisation) {
    const Result<void, std::string> ok;
    EXPECT_TRUE(ok.ok());
    const Result<void, std::string> bad = Err{std::string("nope")};
    ASSERT_FALSE(bad.ok());
    EXPECT_EQ(bad.error(), "nope");
    using VoidOrInt = Result<void, int>;
    EXPECT_TRUE(VoidOrInt::success().ok());
    EXPECT_EQ(VoidOrInt::failure(3).error(), 3);
}

TEST(ResultDeathTest, WrongAccessAborts) {
    GTEST_FLAG_SET(death_test_style, "threadsafe");
    const auto bad = half(3);
    EXPECT_DEATH((void)bad.value(), "value\\(\\) called on an error");
    const auto ok = half(2);
    EXPECT_DEATH((void)ok.error(), "error\\(\\) called on a value");
}

}  // namespace
}  // namespace kdrt::proto
