#pragma once
/// A bound on a JSON text's shape, checked by one linear scan before the text is parsed into a
/// DOM: nlohmann::json spends some 40 bytes of memory per byte of `[[[[...]]]]` (a 32 MiB body
/// of nested arrays peaked at 1.36 GB), so a body that may become a DOM is first checked for its
/// nesting depth and its number of values. The scan does not validate the JSON (the parser
/// does); it only counts, outside strings, brackets and the commas between values.

#include <cstddef>
#include <optional>
#include <string>
#include <string_view>

namespace kdrt::server {

struct JsonShapeLimits {
    size_t max_depth = 16;     ///< nested arrays and objects
    size_t max_values = 4096;  ///< values and members (an upper bound: commas + containers + 1)
};

/// Empty when `text` is within `limits`; else what exceeds them, naming the limit and the byte
/// offset where it was exceeded.
[[nodiscard]] std::optional<std::string> json_shape_error(std::string_view text,
                                                          const JsonShapeLimits& limits);

}  // namespace kdrt::server
