#pragma once
/// Configuration files: one JSON object of settings, with // and /* */ comments allowed (the
/// shipped config/kdrt.json documents every setting in comments). proto knows the syntax; the
/// caller (kdrt-server) knows the keys.

#include <cstdint>
#include <string>
#include <string_view>
#include <variant>
#include <vector>

#include "kdrt/proto/result.h"

namespace kdrt::proto {

/// A setting's value: a boolean, an integer, a real number, a string or a list of strings.
using ConfigValue = std::variant<bool, int64_t, double, std::string, std::vector<std::string>>;

struct ConfigEntry {
    std::string key;
    ConfigValue value;
};

/// Parses `text` as a JSON object whose members are scalars or arrays of strings, in file order.
/// Errors name the problem: invalid JSON (with nlohmann's line/column), a top level that is not
/// an object, or a member whose value is null, an object, or an array with a non-string element.
[[nodiscard]] Result<std::vector<ConfigEntry>, std::string> parse_config_object(
    std::string_view text);

}  // namespace kdrt::proto
