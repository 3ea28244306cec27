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

TEST(Text, QuoteValueQuotesAShortPrefixOfALongValue) {
    EXPECT_EQ(quote_value("abc"), "\"abc\"");
    const std::string limit(kQuotedValueBytes, 'x');
    EXPECT_EQ(quote_value(limit), in_quotes(limit));
    const std::string huge((32u << 20) + 1, 'y');
    const std::string q = quote_value(huge);
    EXPECT_EQ(q, in_quotes(std::string(kQuotedValueBytes, 'y')) + "... (33554433 bytes)");
    // A UTF-8 sequence the cut would split is left out whole: "é" is 2 bytes, "€" 3.
    for (const char* wide : {"\xc3\xa9", "\xe2\x82\xac"}) {
        for (size_t pad = kQuotedValueBytes - 3; pad <= kQuotedValueBytes; ++pad) {
            std::string text(pad, 'a');
            for (int i = 0; i < 10; ++i) text += wide;
            const std::string out = quote_value(text);
            const std::string inside = out.substr(1, out.find("\"... (") - 1);
            ASSERT_LE(inside.size(), kQuotedValueBytes) << pad;
            EXPECT_EQ(text.compare(0, inside.size(), inside), 0);
            // It ends on a whole character: the next byte of the text starts one.
            EXPECT_NE(static_cast<unsigned char>(text[inside.size()]) & 0xC0, 0x80) << pad;
            EXPECT_GE(inside.size(), kQuotedValueBytes - 2) << pad;
        }
    }
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

TEST(Text, JsonStringEscapesEachByteOfLongMixedRunsAsItsRuleSays) {
    // Runs of plain bytes between escaped ones (the encoder copies runs whole): every byte
    // value at every position against the rule of text.h, byte by byte.
    std::string text;
    for (int rep = 0; rep < 3; ++rep)
        for (int c = 0; c < 256; ++c) {
            text.append(static_cast<size_t>(c % 7), 'a');
            text.push_back(static_cast<char>(c));
        }
    std::string want = "\"";
    for (const char c : text) {
        const auto u = static_cast<unsigned char>(c);
        if (c == '"' || c == '\\') {
            want += '\\';
            want += c;
        } else if (c == '\n') {
            want += "\\n";
        } else if (c == '\r') {
            want += "\\r";
        } else if (c == '\t') {
            want += "\\t";
        } else if (u < 0x20) {
            const char hex[] = "0123456789abcdef";
            want += "\\u00";
            want += hex[u >> 4];
            want += hex[u & 15];
        } else {
            want += c;
        }
    }
    want += '"';
    EXPECT_EQ(json_string(text), want);
    EXPECT_EQ(json_string("\"" + text + "\\"),
              "\"\\\"" + want.substr(1, want.size() - 2) + "\\\\\"");
}

TEST(Text, AppendJsonStringAppends) {
    std::string out = "[";
    append_json_string(out, "k");
    EXPECT_EQ(out, "[\"k\"");
}

}  // namespace
}  // namespace kdrt::proto
