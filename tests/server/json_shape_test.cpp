// The JSON shape bound checked before a body is parsed into a DOM.

#include "http/json_shape.h"

#include <gtest/gtest.h>

#include <string>

namespace kdrt::server {
namespace {

TEST(JsonShape, AcceptsARenderRequest) {
    const std::string text =
        R"({"mesh":"ab","width":64,"height":64,"camera":{"eye":[0,0,1],"look_at":[0,0,0]}})";
    EXPECT_FALSE(json_shape_error(text, {.max_depth = 3, .max_values = 13}));
}

TEST(JsonShape, RefusesDeepNestingNamingWhere) {
    const std::string deep = std::string(9, '[') + std::string(9, ']');
    const auto error = json_shape_error(deep, {.max_depth = 8, .max_values = 100});
    ASSERT_TRUE(error);
    EXPECT_EQ(*error, "JSON nesting deeper than 8 levels at byte 8");
    EXPECT_FALSE(json_shape_error(std::string(8, '[') + std::string(8, ']'),
                                  {.max_depth = 8, .max_values = 100}));
}

TEST(JsonShape, RefusesTooManyValues) {
    const auto error = json_shape_error("[1,2,3,4,5]", {.max_depth = 8, .max_values = 5});
    ASSERT_TRUE(error);
    EXPECT_EQ(*error, "JSON body with more than 5 values (at byte 8)");
    EXPECT_FALSE(json_shape_error("[1,2,3,4]", {.max_depth = 8, .max_values = 5}));
}

TEST(JsonShape, IgnoresBracketsAndCommasInStrings) {
    const std::string text = R"({"mesh":"[[[[,,,,\"[[[["})";
    EXPECT_FALSE(json_shape_error(text, {.max_depth = 1, .max_values = 2}));
}

}  // namespace
}  // namespace kdrt::server
