#include "core/log.h"

#include <spdlog/sinks/stdout_sinks.h>
#include <spdlog/spdlog.h>

#include <atomic>
#include <charconv>
#include <variant>

namespace kdrt::server {
namespace {

std::atomic<bool> g_json{false};

spdlog::level::level_enum to_spdlog(LogLevel level) {
    switch (level) {
        case LogLevel::kTrace:
            return spdlog::level::trace;
        case LogLevel::kDebug:
            return spdlog::level::debug;
        case LogLevel::kInfo:
            return spdlog::level::info;
        case LogLevel::kWarn:
            return spdlog::level::warn;
        case LogLevel::kError:
            return spdlog::level::err;
        case LogLevel::kCritical:
            return spdlog::level::critical;
        case LogLevel::kOff:
            return spdlog::level::off;
    }
    return spdlog::level::info;
}

void append_text_value(std::string& out, const proto::JsonScalar& value) {
    std::visit(
        [&](const auto& v) {
            using V = std::decay_t<decltype(v)>;
            if constexpr (std::is_same_v<V, std::string> || std::is_same_v<V, std::string_view>) {
                const bool quote = v.empty() || v.find_first_of(" \"=") != std::string_view::npos;
                if (quote) out.push_back('"');
                for (const char c : v) {
                    if (quote && (c == '"' || c == '\\')) out.push_back('\\');
                    out.push_back(c == '\n' ? ' ' : c);
                }
                if (quote) out.push_back('"');
            } else if constexpr (std::is_same_v<V, bool>) {
                out += v ? "true" : "false";
            } else if constexpr (std::is_same_v<V, double>) {
                char buf[32];
                const auto r = std::to_chars(buf, buf + sizeof buf, v, std::chars_format::fixed, 3);
                out.append(buf, r.ptr);
            } else {
                out += std::to_string(v);
            }
        },
        value);
}

}  // namespace

void setup_logging(std::string_view level, std::string_view format) {
    auto logger = spdlog::stderr_logger_mt("kdrt");
    spdlog::set_default_logger(logger);
    g_json = format == "json";
    if (g_json) {
        // The message is the rest of a JSON object: "msg": "...", "key": value, ...
        spdlog::set_pattern(R"({"time":"%Y-%m-%dT%H:%M:%S.%fZ","level":"%l",%v})",
                            spdlog::pattern_time_type::utc);
    } else {
        spdlog::set_pattern("%Y-%m-%d %H:%M:%S.%e %-5l %v");
    }
    spdlog::set_level(spdlog::level::from_str(std::string(level)));
    spdlog::flush_on(spdlog::level::info);
}

bool log_enabled(LogLevel level) noexcept {
    return spdlog::default_logger_raw()->should_log(to_spdlog(level));
}

void log_event(LogLevel level, std::string_view message,
               std::initializer_list<proto::JsonField> fields) {
    const auto spd_level = to_spdlog(level);
    if (!spdlog::default_logger_raw()->should_log(spd_level)) return;
    std::string line;
    if (g_json) {
        std::vector<proto::JsonField> all;
        all.reserve(fields.size() + 1);
        all.push_back({"msg", message});
        all.insert(all.end(), fields.begin(), fields.end());
        line = proto::encode_flat_object(all);
        line = line.substr(1, line.size() - 2);  // the pattern supplies the braces
    } else {
        line.assign(message);
        for (const proto::JsonField& f : fields) {
            line.push_back(' ');
            line += f.key;
            line.push_back('=');
            append_text_value(line, f.value);
        }
    }
    spdlog::default_logger_raw()->log(spd_level, "{}", line);
}

}  // namespace kdrt::server
