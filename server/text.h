#pragma once
/// Small string helpers for messages.

#include <string>
#include <string_view>

namespace kdrt::server {

/// `text` in double quotes. Built piecewise: GCC 12 reports a false -Wrestrict for
/// "\"" + str + "\"".
[[nodiscard]] inline std::string in_quotes(std::string_view text) {
    std::string out;
    out.reserve(text.size() + 2);
    out.push_back('"');
    out.append(text);
    out.push_back('"');
    return out;
}

}  // namespace kdrt::server
