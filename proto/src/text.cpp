#include "kdrt/proto/text.h"

#include <cmath>

namespace kdrt::proto {
namespace {

constexpr char kHexDigits[] = "0123456789abcdef";

}  // namespace

std::string in_quotes(std::string_view text) {
    // Built piecewise: GCC 12 reports a false -Wrestrict for "\"" + str + "\"".
    std::string out;
    out.reserve(text.size() + 2);
    out.push_back('"');
    out.append(text);
    out.push_back('"');
    return out;
}

std::string quote_value(std::string_view text) {
    if (text.size() <= kQuotedValueBytes) return in_quotes(text);
    // Cut at a character boundary: a continuation byte (10xxxxxx) at the cut belongs to a
    // sequence that started before it, which is left out whole (at most 3 bytes back).
    size_t cut = kQuotedValueBytes;
    while (cut > kQuotedValueBytes - 3 && (static_cast<unsigned char>(text[cut]) & 0xC0) == 0x80)
        --cut;
    return in_quotes(text.substr(0, cut)) + "... (" + std::to_string(text.size()) + " bytes)";
}

std::string hex(uint64_t value, int digits) {
    std::string out(static_cast<size_t>(digits), '0');
    for (int i = digits - 1; i >= 0; --i, value >>= 4)
        out[static_cast<size_t>(i)] = kHexDigits[value & 15];
    return out;
}

void append_hex(std::string& out, std::span<const unsigned char> bytes) {
    out.reserve(out.size() + 2 * bytes.size());
    for (const unsigned char b : bytes) {
        out.push_back(kHexDigits[b >> 4]);
        out.push_back(kHexDigits[b & 15]);
    }
}

std::string non_finite_name(double value) {
    if (std::isnan(value)) return "NaN";
    return value > 0 ? "+inf" : "-inf";
}

void append_json_string(std::string& out, std::string_view text) {
    out.push_back('"');
    size_t i = 0;
    while (i < text.size()) {
        // A run of bytes copied as they are (ids, names: the whole string), in one append.
        size_t j = i;
        while (j < text.size() && static_cast<unsigned char>(text[j]) >= 0x20 && text[j] != '"' &&
               text[j] != '\\')
            ++j;
        out.append(text.data() + i, j - i);
        if (j == text.size()) break;
        i = j + 1;
        const char c = text[j];
        const auto u = static_cast<unsigned char>(c);
        switch (c) {
            case '"':
                out += "\\\"";
                break;
            case '\\':
                out += "\\\\";
                break;
            case '\n':
                out += "\\n";
                break;
            case '\r':
                out += "\\r";
                break;
            case '\t':
                out += "\\t";
                break;
            default:
                if (u < 0x20) {
                    out += "\\u00";
                    out.push_back(kHexDigits[u >> 4]);
                    out.push_back(kHexDigits[u & 15]);
                } else {
                    out.push_back(c);
                }
        }
    }
    out.push_back('"');
}

std::string json_string(std::string_view text) {
    std::string out;
    out.reserve(text.size() + 2);
    append_json_string(out, text);
    return out;
}

}  // namespace kdrt::proto
