#include "bench_args.h"

#include <algorithm>
#include <charconv>

namespace kdrt::bench {

Args::Args(std::span<char* const> args, std::span<const std::string_view> value_options,
           std::span<const std::string_view> flag_options) {
    bool options_done = false;  // after "--" everything is positional
    for (size_t i = 0; i < args.size(); ++i) {
        const std::string_view arg = args[i];
        if (options_done || arg.size() < 2 || arg[0] != '-') {
            positional_.emplace_back(arg);
            continue;
        }
        if (arg == "--") {
            options_done = true;
            continue;
        }
        if (arg == "--help" || arg == "-h") {
            help_ = true;
            continue;
        }
        if (!arg.starts_with("--")) throw UsageError("unknown option '" + std::string(arg) + "'");
        std::string_view name = arg.substr(2);
        std::optional<std::string_view> value;
        if (const size_t eq = name.find('='); eq != std::string_view::npos) {
            value = name.substr(eq + 1);
            name = name.substr(0, eq);
        }
        if (std::find(flag_options.begin(), flag_options.end(), name) != flag_options.end()) {
            if (value) throw UsageError("option '--" + std::string(name) + "' takes no value");
            if (!flags_.emplace(name).second)
                throw UsageError("option '--" + std::string(name) + "' is given more than once");
            continue;
        }
        if (std::find(value_options.begin(), value_options.end(), name) == value_options.end()) {
            throw UsageError("unknown option '--" + std::string(name) + "'");
        }
        if (!value) {
            if (i + 1 == args.size())
                throw UsageError("option '--" + std::string(name) + "' needs a value");
            value = std::string_view(args[++i]);
        }
        if (!options_.emplace(std::string(name), std::string(*value)).second) {
            throw UsageError("option '--" + std::string(name) + "' is given more than once");
        }
    }
}

void Args::expect_positional(std::span<const std::string_view> names) const {
    if (positional_.size() < names.size()) {
        throw UsageError("missing argument " + std::string(names[positional_.size()]));
    }
    if (positional_.size() > names.size()) {
        throw UsageError("unexpected argument '" + positional_[names.size()] + "'");
    }
}

std::optional<std::string> Args::get(std::string_view name) const {
    const auto it = options_.find(name);
    if (it == options_.end()) return std::nullopt;
    return it->second;
}

std::string Args::require(std::string_view name) const {
    auto value = get(name);
    if (!value) throw UsageError("option '--" + std::string(name) + "' is required");
    return *value;
}

uint64_t Args::get_uint(std::string_view name, uint64_t fallback, uint64_t min_value,
                        uint64_t max_value) const {
    const auto text = get(name);
    if (!text) return fallback;
    uint64_t value = 0;
    const char* end = text->data() + text->size();
    const auto [ptr, ec] = std::from_chars(text->data(), end, value);
    if (text->empty() || ec != std::errc() || ptr != end || value < min_value ||
        value > max_value) {
        throw UsageError("option '--" + std::string(name) + "': '" + *text +
                         "' is not an integer in [" + std::to_string(min_value) + ", " +
                         std::to_string(max_value) + "]");
    }
    return value;
}

float Args::get_float(std::string_view name, float fallback, float min_value,
                      float max_value) const {
    const auto text = get(name);
    if (!text) return fallback;
    float value = 0;
    const char* end = text->data() + text->size();
    const auto [ptr, ec] = std::from_chars(text->data(), end, value);
    // Negated range test: NaN fails it too.
    if (text->empty() || ec != std::errc() || ptr != end ||
        !(value >= min_value && value <= max_value)) {
        throw UsageError("option '--" + std::string(name) + "': '" + *text +
                         "' is not a number in [" + std::to_string(min_value) + ", " +
                         std::to_string(max_value) + "]");
    }
    return value;
}

}  // namespace kdrt::bench
