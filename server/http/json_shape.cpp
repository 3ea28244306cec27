#include "http/json_shape.h"

#include <vector>

#include "kdrt/proto/text.h"

namespace kdrt::server {
namespace {

/// An array or object the scan is inside, and the value in it the scan is at.
struct Level {
    bool object = false;
    bool expect_key = false;  ///< an object after '{' or ',': the next string is a member name
    size_t index = 0;         ///< an array: the element
    std::string_view key;     ///< an object: the member (its raw text between the quotes)
};

/// The path of the container `levels.back()` (the position in each enclosing level), or with
/// `value`, of the value the scan is at in it.
std::string path_of(const std::vector<Level>& levels, bool value) {
    std::string path;
    const size_t end = levels.size() - (value || levels.empty() ? 0 : 1);
    for (size_t i = 0; i < end; ++i) {
        const Level& level = levels[i];
        if (level.object) {
            if (!path.empty()) path += '.';
            const std::string_view key = level.key.substr(0, proto::kQuotedValueBytes);
            path += key;
            if (key.size() < level.key.size()) path += "...";
        } else {
            path.append("[").append(std::to_string(level.index)).append("]");
        }
    }
    return path;
}

/// `what` at byte `at`, in the container `levels.back()` (none: the top level), or at the value
/// the scan is at in it.
JsonShapeError shape_error(const std::string& what, size_t at, const std::vector<Level>& levels,
                           bool value) {
    JsonShapeError error;
    error.path = path_of(levels, value);
    error.detail = what;
    error.detail.append(" (at byte ").append(std::to_string(at));
    if (!error.path.empty()) error.detail.append(", in ").append(proto::in_quotes(error.path));
    error.detail.append(")");
    return error;
}

}  // namespace

std::optional<JsonShapeError> json_shape_error(std::string_view text,
                                               const JsonShapeLimits& limits) {
    std::vector<Level> levels;  // at most max_depth deep
    size_t values = 1;
    bool in_string = false, in_key = false;
    size_t string_start = 0;
    for (size_t i = 0; i < text.size(); ++i) {
        const char c = text[i];
        if (in_string) {
            if (c == '\\') {
                ++i;  // the escaped character cannot end the string
            } else if (c == '"') {
                in_string = false;
                if (in_key) levels.back().key = text.substr(string_start, i - string_start);
                in_key = false;
            }
            continue;
        }
        switch (c) {
            case '"':
                in_string = true;
                string_start = i + 1;
                in_key = !levels.empty() && levels.back().expect_key;
                if (in_key) levels.back().expect_key = false;
                break;
            case '[':
            case '{':
                if (levels.size() + 1 > limits.max_depth)
                    return shape_error(
                        "JSON nesting deeper than " + std::to_string(limits.max_depth) + " levels",
                        i, levels, true);
                [[fallthrough]];
            case ',':
                if (++values > limits.max_values)
                    return shape_error(
                        "JSON body with more than " + std::to_string(limits.max_values) + " values",
                        i, levels, false);
                if (c != ',') {
                    Level level;
                    level.object = level.expect_key = c == '{';
                    levels.push_back(level);
                } else if (!levels.empty()) {
                    Level& level = levels.back();
                    level.expect_key = level.object;
                    ++level.index;
                }
                break;
            case ']':
            case '}':
                if (!levels.empty()) levels.pop_back();
                break;
            default:
                break;
        }
    }
    return std::nullopt;
}

}  // namespace kdrt::server
