#include "kdrt/proto/config_json.h"

#include <nlohmann/json.hpp>

#include "json_strict.h"

namespace kdrt::proto {

Result<std::vector<ConfigEntry>, std::string> parse_config_object(std::string_view text) {
    using json = nlohmann::ordered_json;
    auto parsed = detail::parse_json_strict<json>(text, /*ignore_comments=*/true);
    if (!parsed) return Err{std::move(parsed).error()};
    const json& doc = *parsed;
    if (!doc.is_object()) return Err{std::string("the configuration must be a JSON object")};
    std::vector<ConfigEntry> out;
    for (const auto& [key, value] : doc.items()) {
        ConfigEntry entry{key, false};
        if (value.is_boolean()) {
            entry.value = value.get<bool>();
        } else if (value.is_number_integer()) {
            if (value.is_number_unsigned() &&
                value.get<uint64_t>() > static_cast<uint64_t>(INT64_MAX))
                return Err{"\"" + key + "\": integer too large"};
            entry.value = value.get<int64_t>();
        } else if (value.is_number_float()) {
            entry.value = value.get<double>();
        } else if (value.is_string()) {
            entry.value = value.get<std::string>();
        } else if (value.is_array()) {
            std::vector<std::string> list;
            for (const auto& element : value) {
                if (!element.is_string())
                    return Err{"\"" + key + "\": every element must be a string"};
                list.push_back(element.get<std::string>());
            }
            entry.value = std::move(list);
        } else {
            return Err{"\"" + key +
                       "\": expected a boolean, number, string or array of strings, got " +
                       std::string(value.type_name())};
        }
        out.push_back(std::move(entry));
    }
    return out;
}

}  // namespace kdrt::proto
