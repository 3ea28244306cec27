#include "http/json_shape.h"

namespace kdrt::server {

std::optional<std::string> json_shape_error(std::string_view text, const JsonShapeLimits& limits) {
    size_t depth = 0;
    size_t values = 1;
    bool in_string = false;
    for (size_t i = 0; i < text.size(); ++i) {
        const char c = text[i];
        if (in_string) {
            if (c == '\\')
                ++i;  // the escaped character cannot end the string
            else if (c == '"')
                in_string = false;
            continue;
        }
        switch (c) {
            case '"':
                in_string = true;
                break;
            case '[':
            case '{':
                if (++depth > limits.max_depth)
                    return "JSON nesting deeper than " + std::to_string(limits.max_depth) +
                           " levels at byte " + std::to_string(i);
                [[fallthrough]];
            case ',':
                if (++values > limits.max_values)
                    return "JSON body with more than " + std::to_string(limits.max_values) +
                           " values (at byte " + std::to_string(i) + ")";
                break;
            case ']':
            case '}':
                if (depth > 0) --depth;
                break;
            default:
                break;
        }
    }
    return std::nullopt;
}

}  // namespace kdrt::server
