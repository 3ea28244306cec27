#include "cli_args.h"

#include <algorithm>
#include <cctype>
#include <charconv>
#include <cmath>
#include <filesystem>

#include "kdrt/client/server_url.h"
#include "kdrt/proto/text.h"

namespace kdrt::cli {
namespace {

using proto::in_quotes;

const OptionSpec* find_long(std::span<const OptionSpec> specs, std::string_view name) {
    for (const OptionSpec& s : specs)
        if (s.name == name) return &s;
    return nullptr;
}

const OptionSpec* find_short(std::span<const OptionSpec> specs, char name) {
    for (const OptionSpec& s : specs)
        if (s.short_name != 0 && s.short_name == name) return &s;
    return nullptr;
}

/// Splits "a,b,c" into exactly `count` parts.
std::optional<std::vector<std::string_view>> split_commas(std::string_view text, size_t count) {
    std::vector<std::string_view> parts;
    size_t start = 0;
    for (;;) {
        const size_t comma = text.find(',', start);
        parts.push_back(text.substr(
            start, comma == std::string_view::npos ? std::string_view::npos : comma - start));
        if (comma == std::string_view::npos) break;
        start = comma + 1;
    }
    if (parts.size() != count) return std::nullopt;
    return parts;
}

}  // namespace

bool ParsedArgs::has(std::string_view name) const {
    return values.find(name) != values.end() ||
           std::find(flags.begin(), flags.end(), name) != flags.end();
}

std::optional<std::string> ParsedArgs::value(std::string_view name) const {
    const auto it = values.find(name);
    if (it == values.end()) return std::nullopt;
    return it->second;
}

ParseResult<ParsedArgs> parse_args(std::span<const std::string> args,
                                   std::span<const OptionSpec> specs, std::string_view command) {
    ParsedArgs out;
    const std::string see = " (see " + std::string(command) + " --help)";
    bool options_done = false;
    for (size_t i = 0; i < args.size(); ++i) {
        const std::string& arg = args[i];
        if (options_done || arg.size() < 2 || arg[0] != '-') {
            out.positional.push_back(arg);
            continue;
        }
        if (arg == "--") {
            options_done = true;
            continue;
        }
        const OptionSpec* spec = nullptr;
        std::string shown;
        std::optional<std::string> inline_value;
        if (arg[1] == '-') {
            const size_t eq = arg.find('=');
            const std::string_view name = std::string_view(arg).substr(
                2, eq == std::string::npos ? std::string::npos : eq - 2);
            if (eq != std::string::npos) inline_value = arg.substr(eq + 1);
            spec = find_long(specs, name);
            shown = "--" + std::string(name);
        } else if (arg.size() == 2) {
            spec = find_short(specs, arg[1]);
            shown = arg;
        } else if (std::isdigit(static_cast<unsigned char>(arg[1])) || arg[1] == '.') {
            out.positional.push_back(arg);  // a negative number
            continue;
        }
        if (!spec)
            return proto::Err{"unknown option " + in_quotes(shown.empty() ? arg : shown) + " for " +
                              std::string(command) + see};
        if (!spec->takes_value) {
            if (inline_value)
                return proto::Err{"option --" + std::string(spec->name) + " takes no value" + see};
            if (std::find(out.flags.begin(), out.flags.end(), spec->name) == out.flags.end())
                out.flags.emplace_back(spec->name);
            continue;
        }
        if (!inline_value) {
            if (i + 1 >= args.size()) {
                std::string message = "option " + shown;
                message += " needs a value";
                message += see;
                return proto::Err{std::move(message)};
            }
            inline_value = args[++i];
        }
        out.values[std::string(spec->name)] = *inline_value;
    }
    return out;
}

ParseResult<GlobalSettings> global_settings(const ParsedArgs& args,
                                            const std::map<std::string, std::string>& env) {
    GlobalSettings g;
    if (auto server = args.value("server")) {
        g.server = *server;
    } else if (const auto it = env.find("KDRT_SERVER"); it != env.end() && !it->second.empty()) {
        g.server = it->second;
    } else {
        g.server = std::string(kDefaultServerUrl);
    }
    if (auto url = parse_server_url(g.server); !url) return proto::Err{url.error()};
    if (auto token = args.value("token")) g.token = *token;
    if (auto timeout = args.value("timeout")) {
        auto seconds = parse_number(*timeout);
        if (!seconds || *seconds <= 0)
            return proto::Err{"--timeout: " + in_quotes(*timeout) +
                              " is not a positive number of seconds"};
        g.timeout_s = *seconds;
    }
    if (auto retries = args.value("retries")) {
        auto n = parse_uint(*retries, 0, 100);
        if (!n) return proto::Err{"--retries: " + n.error()};
        g.retries = static_cast<unsigned>(*n);
    }
    return g;
}

ParseResult<uint64_t> parse_uint(std::string_view text, uint64_t min, uint64_t max) {
    uint64_t value = 0;
    const auto [end, ec] = std::from_chars(text.data(), text.data() + text.size(), value);
    if (text.empty() || ec == std::errc::invalid_argument || end != text.data() + text.size())
        return proto::Err{in_quotes(text) + " is not a whole number"};
    if (ec == std::errc::result_out_of_range || value < min || value > max)
        return proto::Err{in_quotes(text) + " is not in " + std::to_string(min) + " .. " +
                          std::to_string(max)};
    return value;
}

ParseResult<double> parse_number(std::string_view text) {
    double value = 0;
    std::string_view digits = text;
    if (!digits.empty() && digits.front() == '+') digits.remove_prefix(1);
    const auto [end, ec] = std::from_chars(digits.data(), digits.data() + digits.size(), value);
    if (digits.empty() || ec != std::errc() || end != digits.data() + digits.size() ||
        !std::isfinite(value))
        return proto::Err{in_quotes(text) + " is not a finite number"};
    return value;
}

ParseResult<std::pair<uint32_t, uint32_t>> parse_size(std::string_view text) {
    const size_t x = text.find_first_of("xX");
    const std::string bad = in_quotes(text) + " is not WIDTHxHEIGHT (e.g. 1024x768)";
    if (x == std::string_view::npos) return proto::Err{bad};
    auto w = parse_uint(text.substr(0, x), 1, kMaxImageSize);
    auto h = parse_uint(text.substr(x + 1), 1, kMaxImageSize);
    if (!w || !h) return proto::Err{bad + ", each side 1 .. " + std::to_string(kMaxImageSize)};
    return std::pair{static_cast<uint32_t>(*w), static_cast<uint32_t>(*h)};
}

ParseResult<Vec3> parse_vec3(std::string_view text) {
    const std::string bad = in_quotes(text) + " is not three numbers x,y,z";
    auto parts = split_commas(text, 3);
    if (!parts) return proto::Err{bad};
    Vec3 v;
    for (int i = 0; i < 3; ++i) {
        auto n = parse_number((*parts)[static_cast<size_t>(i)]);
        if (!n || std::fabs(*n) > 3.4e38) return proto::Err{bad};
        v[i] = static_cast<float>(*n);
    }
    return v;
}

ParseResult<PixelRegion> parse_region(std::string_view text) {
    const std::string bad = in_quotes(text) + " is not x,y,w,h (whole numbers, w and h at least 1)";
    auto parts = split_commas(text, 4);
    if (!parts) return proto::Err{bad};
    uint64_t v[4];
    for (size_t i = 0; i < 4; ++i) {
        auto n = parse_uint((*parts)[i], i < 2 ? 0 : 1, kMaxImageSize);
        if (!n) return proto::Err{bad};
        v[i] = *n;
    }
    return PixelRegion{static_cast<uint32_t>(v[0]), static_cast<uint32_t>(v[1]),
                       static_cast<uint32_t>(v[2]), static_cast<uint32_t>(v[3])};
}

std::optional<std::string> image_format_for_path(std::string_view path) {
    std::string ext = std::filesystem::path(path).extension().string();
    std::transform(ext.begin(), ext.end(), ext.begin(),
                   [](unsigned char c) { return static_cast<char>(std::tolower(c)); });
    if (ext == ".png") return "png";
    if (ext == ".jpg" || ext == ".jpeg") return "jpg";
    if (ext == ".exr") return "exr";
    return std::nullopt;
}

}  // namespace kdrt::cli
