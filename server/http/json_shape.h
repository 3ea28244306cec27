#pragma once
/// A bound on a JSON text's shape, checked by one linear scan before the text is parsed into a
/// DOM: nlohmann::json spends some 40 bytes of memory per byte of `[[[[...]]]]` (a 32 MiB body
/// of nested arrays peaked at 1.36 GB), so a body that may become a DOM is first checked for its
/// nesting depth and its number of values. The scan does not validate the JSON (the parser
/// does); it only counts, outside strings, brackets and the commas between values, and follows
/// the member names and array indices on the way, to say where a limit was passed.

#include <cstddef>
#include <optional>
#include <string>
#include <string_view>

namespace kdrt::server {

struct JsonShapeLimits {
    size_t max_depth = 16;     ///< nested arrays and objects
    size_t max_values = 4096;  ///< values and members (an upper bound: commas + containers + 1)
};

/// Where and how a JSON text exceeds its JsonShapeLimits.
struct JsonShapeError {
    /// What exceeds which limit, the byte offset, and the path when there is one:
    /// `JSON body with more than 5 values (at byte 8, in "lidar.elevation_deg")`.
    std::string detail;
    /// Where, as a request's fields are named (members joined by '.', array elements by their
    /// index: `instances[3].transform`): the array or object that holds more values than
    /// allowed, or the value nested too deep. Empty at the top level. Member names longer than
    /// 64 bytes are cut there, with "...".
    std::string path;
};

/// Empty when `text` is within `limits`; else what exceeds them and where.
[[nodiscard]] std::optional<JsonShapeError> json_shape_error(std::string_view text,
                                                             const JsonShapeLimits& limits);

}  // namespace kdrt::server
