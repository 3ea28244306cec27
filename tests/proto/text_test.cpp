#include "kdrt/proto/text.h"

#include <gtest/gtest.h>

#include <cmath>
#include <limits>
#include <nlohmann/json.hpp>
#include <string>

namespace kdrt::proto {
namespace {

TEST(Text, InQuotesAddsDoubleQuotesWithoutEscaping) {
    EXPECT_EQ(in_quotes("abc"), "\"abc\"");
    EXPECT_EQ(in_quotes(""), "\"\"");
    EXPECT_EQ(in_quotes("a\"b\\c"), "\"a\"b\\c\"");
}

TEST(Text, HexWritesExactlyTheGivenDigitCount) {
    EXPECT_EQ(hex(0x1f, 4), "001f");
    EXPECT_EQ(hex(0xab, 2), "ab");
    EXPECT_EQ(hex(0x12345, 2), "45");  // only the low 4 * digits bits
    EXPECT_EQ(hex(0, 0), "");
    EXPECT_EQ(hex(0xfedcba9876543210ull, 16), "fedcba9876543210");
}

TEST(Text, AppendHexWritesTwoDigitsPerByte) {
    const unsigned char bytes[] = {0x00, 0x0f, 0xa0, 0xff};
    std::string out = "x";
    append_hex(out, bytes);
    EXPECT_EQ(out, "x000fa0ff");
}

TEST(Text, NonFiniteNames) {
    EXPECT_EQ(non_finite_name(std::numeric_limits<double>::quiet_NaN()), "NaN");
    EXPECT_EQ(non_finite_name(-std::numeric_limits<double>::quiet_NaN()), "NaN");
    EXPECT_EQ(non_finite_name(std::numeric_limits<double>::infinity()), "+inf");
    EXPECT_EQ(non_finite_name(-std::numeric_limits<double>::infinity()), "-inf");
    EXPECT_EQ(non_finite_name(std::numeric_limits<float>::infinity()), "+inf");
}

TEST(Text, JsonStringEscapesQuotesBackslashesAndControlCharacters) {
    EXPECT_EQ(json_string("plain"), "\"plain\"");
    EXPECT_EQ(json_string("a\"b\\c"), "\"a\\\"b\\\\c\"");
    EXPECT_EQ(json_string("\n\r\t"), "\"\\n\\r\\t\"");
    EXPECT_EQ(json_string(std::string("\x01\x1f\b\f", 4)), "\"\\u0001\\u001f\\u0008\\u000c\"");
    EXPECT_EQ(json_string(std::string(1, '\0')), "\"\\u0000\"");
    EXPECT_EQ(json_string("\x7f"), "\"\x7f\"");                // DEL is not a control in JSON
    EXPECT_EQ(json_string("caf\xc3\xa9"), "\"caf\xc3\xa9\"");  // UTF-8 copied as it is
}

TEST(Text, JsonStringReadsBackThroughAJsonParser) {
    std::string all;
    for (int c = 1; c < 0x80; ++c) all.push_back(static_cast<char>(c));
    const auto parsed = nlohmann::json::parse(json_string(all));
    ASSERT_TRUE(parsed.is_string());
    EXPECT_EQ(parsed.get<std::string>(), all);
}

TEST(Text, AppendJsonStringAppends) {
    std::string out = "[";
    append_json_string(out, "k");
    EXPECT_EQ(out, "[\"k\"");
}

}  // namespace
}  // namespace kdrt::proto
