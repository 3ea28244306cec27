#pragma once
// Internal: allocation-free scanning of text mesh files held in memory (lines, tokens, numbers).
// Numbers go through std::from_chars: locale-independent, exact (correctly rounded), no iostreams.

#include <charconv>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <limits>
#include <string>
#include <string_view>
#include <system_error>
#include <type_traits>

#include "kdrt/proto/text.h"

namespace kdrt::proto::detail {

/// Blanks inside a line. '\r' counts, so CRLF files and stray CRs need no special casing.
[[nodiscard]] constexpr bool is_blank(char c) noexcept {
    return c == ' ' || c == '\t' || c == '\r' || c == '\v' || c == '\f';
}

/// Next blank-separated token of `rest`, advancing `rest` past it; empty when none is left.
[[nodiscard]] inline std::string_view next_token(std::string_view& rest) noexcept {
    size_t i = 0;
    while (i < rest.size() && is_blank(rest[i])) ++i;
    size_t j = i;
    while (j < rest.size() && !is_blank(rest[j])) ++j;
    const std::string_view token = rest.substr(i, j - i);
    rest.remove_prefix(j);
    return token;
}

/// `line` without a '#' comment and the blanks around what is left.
[[nodiscard]] inline std::string_view strip_comment(std::string_view line) noexcept {
    if (const size_t hash = line.find('#'); hash != std::string_view::npos)
        line = line.substr(0, hash);
    while (!line.empty() && is_blank(line.back())) line.remove_suffix(1);
    while (!line.empty() && is_blank(line.front())) line.remove_prefix(1);
    return line;
}

/// Physical lines of a buffer, numbered from 1. A line excludes its '\n'.
class LineReader {
public:
    explicit LineReader(std::string_view text) noexcept : text_(text) {}

    /// Stores the next line in `line`; false when the buffer is exhausted.
    bool next(std::string_view& line) noexcept {
        if (pos_ >= text_.size()) return false;
        const char* begin = text_.data() + pos_;
        const void* nl = std::memchr(begin, '\n', text_.size() - pos_);
        const size_t len = nl != nullptr ? static_cast<size_t>(static_cast<const char*>(nl) - begin)
                                         : text_.size() - pos_;
        line = std::string_view(begin, len);
        pos_ += len + (nl != nullptr ? 1 : 0);
        ++line_number_;
        return true;
    }

    /// Byte offset just past the line last returned (past its '\n').
    [[nodiscard]] size_t offset() const noexcept { return pos_; }

    /// Number of the line last returned by next() (0 before the first call).
    [[nodiscard]] uint64_t line_number() const noexcept { return line_number_; }

    /// Line to blame for an unexpected end of file: the last line, or the empty line after a
    /// final '\n'.
    [[nodiscard]] uint64_t eof_line() const noexcept {
        uint64_t newlines = 0;
        for (char c : text_) newlines += c == '\n' ? 1 : 0;
        return newlines + 1;
    }

private:
    std::string_view text_;
    size_t pos_ = 0;
    uint64_t line_number_ = 0;
};

/// Whitespace-separated tokens across lines (PLY ascii bodies, ascii STL), tracking line numbers.
class TokenReader {
public:
    explicit TokenReader(std::string_view text, uint64_t first_line = 1) noexcept
        : text_(text), line_(first_line) {}

    /// Next token, or empty at the end. line() is then the line of that token (or the last line).
    [[nodiscard]] std::string_view next() noexcept {
        skip_space();
        const size_t begin = pos_;
        while (pos_ < text_.size() && !is_blank(text_[pos_]) && text_[pos_] != '\n') ++pos_;
        return text_.substr(begin, pos_ - begin);
    }

    /// Skips everything up to and including the next '\n'.
    void skip_rest_of_line() noexcept {
        const void* nl = std::memchr(text_.data() + pos_, '\n', text_.size() - pos_);
        if (nl == nullptr) {
            pos_ = text_.size();
            return;
        }
        pos_ = static_cast<size_t>(static_cast<const char*>(nl) - text_.data()) + 1;
        ++line_;
    }

    /// True when only whitespace is left.
    [[nodiscard]] bool at_end() noexcept {
        skip_space();
        return pos_ >= text_.size();
    }

    [[nodiscard]] uint64_t line() const noexcept { return line_; }

private:
    void skip_space() noexcept {
        while (pos_ < text_.size()) {
            const char c = text_[pos_];
            if (c == '\n') {
                ++line_;
            } else if (!is_blank(c)) {
                break;
            }
            ++pos_;
        }
    }

    std::string_view text_;
    size_t pos_ = 0;
    uint64_t line_;
};

enum class NumberStatus { kOk, kInvalid, kOutOfRange };

/// Drops one leading '+' (from_chars refuses it, files use it), but not "+-".
[[nodiscard]] inline std::string_view without_plus(std::string_view token) noexcept {
    if (token.size() >= 2 && token[0] == '+' && token[1] != '-' && token[1] != '+')
        token.remove_prefix(1);
    return token;
}

/// Parses the whole token as a float, correctly rounded. "nan"/"inf" parse (callers decide);
/// a value below the float range rounds to a denormal or zero, one above is kOutOfRange.
[[nodiscard]] inline NumberStatus parse_float(std::string_view token, float& out) noexcept {
    token = without_plus(token);
    if (token.empty()) return NumberStatus::kInvalid;
    const char* end = token.data() + token.size();
    auto [ptr, ec] = std::from_chars(token.data(), end, out);
    if (ptr != end) return NumberStatus::kInvalid;
    if (ec == std::errc::result_out_of_range) {
        double d = 0;
        auto [ptr2, ec2] = std::from_chars(token.data(), end, d);
        if (ec2 != std::errc() || ptr2 != end || std::fabs(d) > std::numeric_limits<float>::max()) {
            return NumberStatus::kOutOfRange;
        }
        out = static_cast<float>(d);  // underflow: denormal or signed zero
        return NumberStatus::kOk;
    }
    return ec == std::errc() ? NumberStatus::kOk : NumberStatus::kInvalid;
}

/// Parses the whole token as a double (PLY double properties).
[[nodiscard]] inline NumberStatus parse_double(std::string_view token, double& out) noexcept {
    token = without_plus(token);
    if (token.empty()) return NumberStatus::kInvalid;
    const char* end = token.data() + token.size();
    auto [ptr, ec] = std::from_chars(token.data(), end, out);
    if (ptr != end) return NumberStatus::kInvalid;
    if (ec == std::errc::result_out_of_range) return NumberStatus::kOutOfRange;
    return ec == std::errc() ? NumberStatus::kOk : NumberStatus::kInvalid;
}

/// Parses the whole token as a decimal integer of type I (optional sign).
template <class I>
[[nodiscard]] NumberStatus parse_int(std::string_view token, I& out) noexcept {
    static_assert(std::is_integral_v<I>);
    token = without_plus(token);
    if (token.empty()) return NumberStatus::kInvalid;
    const char* end = token.data() + token.size();
    auto [ptr, ec] = std::from_chars(token.data(), end, out);
    if (ec == std::errc::result_out_of_range && ptr == end) return NumberStatus::kOutOfRange;
    return ec == std::errc() && ptr == end ? NumberStatus::kOk : NumberStatus::kInvalid;
}

/// A token for an error message: quoted, at most 40 characters, non-printables as \xNN.
[[nodiscard]] inline std::string quote_token(std::string_view token) {
    std::string s = "'";
    const size_t shown = token.size() > 40 ? 40 : token.size();
    for (size_t i = 0; i < shown; ++i) {
        const auto c = static_cast<unsigned char>(token[i]);
        if (c >= 0x20 && c < 0x7F && c != '\'' && c != '\\') {
            s += static_cast<char>(c);
        } else {
            s += "\\x";
            s += hex(c, 2);
        }
    }
    if (shown < token.size()) s += "...";
    return s + "'";
}

/// ASCII case-insensitive equality.
[[nodiscard]] constexpr bool iequals(std::string_view a, std::string_view b) noexcept {
    if (a.size() != b.size()) return false;
    for (size_t i = 0; i < a.size(); ++i) {
        char x = a[i], y = b[i];
        if (x >= 'A' && x <= 'Z') x = static_cast<char>(x - 'A' + 'a');
        if (y >= 'A' && y <= 'Z') y = static_cast<char>(y - 'A' + 'a');
        if (x != y) return false;
    }
    return true;
}

}  // namespace kdrt::proto::detail
