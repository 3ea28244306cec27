#pragma once
/// Text helpers shared by every layer that writes messages or JSON: quoting a value in an error
/// message, hexadecimal digits, the names of non-finite numbers and JSON string escaping. One
/// definition each, so every message spells them the same way.

#include <cstddef>
#include <cstdint>
#include <span>
#include <string>
#include <string_view>

namespace kdrt::proto {

/// `text` between double quotes, as it is (no escaping): how error messages name a value, e.g.
/// `"x" is not a whole number`.
[[nodiscard]] std::string in_quotes(std::string_view text);

/// Bytes of a client's value an error message quotes (quote_value).
inline constexpr size_t kQuotedValueBytes = 64;

/// A value that came from a client (a JSON member or its string, a query parameter, a header, a
/// path) as an error message names it: in_quotes when it has at most kQuotedValueBytes bytes;
/// otherwise its first bytes up to that many (cut before a UTF-8 sequence that would not fit
/// whole), quoted, then "... (N bytes)". So a refusal never echoes a huge request value: every
/// client value in an error goes through this one helper.
[[nodiscard]] std::string quote_value(std::string_view text);

/// The low `4 * digits` bits of `value` as exactly `digits` lower-case hexadecimal digits, most
/// significant first, without a "0x" prefix: hex(0x1f, 4) == "001f". `digits` is 0 .. 16.
[[nodiscard]] std::string hex(uint64_t value, int digits);

/// Appends each byte of `bytes` as two lower-case hexadecimal digits, in order (digests).
void append_hex(std::string& out, std::span<const unsigned char> bytes);

/// "NaN", "+inf" or "-inf": the name of a non-finite `value` in an error message. A finite
/// value is named by its sign like an infinity ("+inf" or "-inf"); callers pass non-finite ones.
[[nodiscard]] std::string non_finite_name(double value);

/// Appends `text` to `out` as a quoted JSON string (RFC 8259): `"` and `\` are escaped, \n, \r
/// and \t by their short forms, every other control character below 0x20 as \u00XX; bytes
/// >= 0x20 (including UTF-8 sequences) are copied as they are.
void append_json_string(std::string& out, std::string_view text);

/// `text` as a quoted JSON string, escaped as append_json_string does.
[[nodiscard]] std::string json_string(std::string_view text);

}  // namespace kdrt::proto
