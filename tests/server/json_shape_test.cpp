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
    EXPECT_EQ(error->detail,
              "JSON nesting deeper than 8 levels (at byte 8, in \"[0][0][0][0][0][0][0][0]\")");
    EXPECT_FALSE(json_shape_error(std::string(8, '[') + std::string(8, ']'),
                                  {.max_depth = 8, .max_values = 100}));
}

TEST(JsonShape, RefusesTooManyValues) {
    const auto error = json_shape_error("[1,2,3,4,5]", {.max_depth = 8, .max_values = 5});
    ASSERT_TRUE(error);
    EXPECT_EQ(error->detail, "JSON body with more than 5 values (at byte 8)");
    EXPECT_EQ(error->path, "");
    EXPECT_FALSE(json_shape_error("[1,2,3,4]", {.max_depth = 8, .max_values = 5}));
}

TEST(JsonShape, NamesTheMemberWhereALimitWasPassed) {
    // The array or object being filled, as a request's fields are named (issue 25 item 13).
    const std::string lidar = R"({"format": "binary", "lidar": {"azimuth_steps": 4,
        "elevation_deg": [1, 2, 3, 4, 5, 6, 7, 8]}})";
    auto error = json_shape_error(lidar, {.max_depth = 6, .max_values = 10});
    ASSERT_TRUE(error);
    EXPECT_EQ(error->path, "lidar.elevation_deg");
    EXPECT_NE(error->detail.find(", in \"lidar.elevation_deg\")"), std::string::npos)
        << error->detail;
    // Array elements by index; names and values with brackets, commas and escaped quotes.
    const std::string nested =
        R"({"a,[": "x,\"]", "instances": [{"t": [1]}, {"t": [[1, 2], [3, 4, 5]]}]})";
    error = json_shape_error(nested, {.max_depth = 6, .max_values = 13});
    ASSERT_TRUE(error);
    EXPECT_EQ(error->path, "instances[1].t[1]");
    error = json_shape_error(nested, {.max_depth = 6, .max_values = 12});
    ASSERT_TRUE(error);
    EXPECT_EQ(error->path, "instances[1].t");
    error = json_shape_error(nested, {.max_depth = 3, .max_values = 100});
    ASSERT_TRUE(error);
    EXPECT_EQ(error->path, "instances[0].t");
    // A long member name is cut at 64 bytes.
    const std::string long_name = "{\"" + std::string(1000, 'k') + "\": [1, 2, 3]}";
    error = json_shape_error(long_name, {.max_depth = 6, .max_values = 3});
    ASSERT_TRUE(error);
    EXPECT_EQ(error->path, std::string(64, 'k') + "...");
}

TEST(JsonShape, IgnoresBracketsAndCommasInStrings) {
    const std::string text = R"({"mesh":"[[[[,,,,\"[[[["})";
    EXPECT_FALSE(json_shape_error(text, {.max_depth = 1, .max_values = 2}));
}

}  // namespace
}  // namespace kdrt::server
