// The scene and pose text files of `kdrt scene` (kdrt/proto/scene.h): one instance or pose a
// line, fields separated by spaces, tabs or commas.

#include <array>
#include <charconv>
#include <cmath>
#include <cstdint>
#include <limits>
#include <optional>
#include <set>
#include <span>
#include <string>
#include <string_view>
#include <vector>

#include "kdrt/proto/mesh_id.h"
#include "kdrt/proto/scene.h"
#include "kdrt/proto/text.h"

namespace kdrt::proto {
namespace {

/// The fields of one line.
std::vector<std::string_view> fields_of(std::string_view line) {
    std::vector<std::string_view> out;
    size_t at = 0;
    while (at < line.size()) {
        const size_t start = line.find_first_not_of(" \t,", at);
        if (start == std::string_view::npos) break;
        const size_t end = line.find_first_of(" \t,", start);
        out.push_back(line.substr(start, end == std::string_view::npos ? end : end - start));
        at = end == std::string_view::npos ? line.size() : end;
    }
    return out;
}

bool is_number(std::string_view field) {
    double value = 0;
    const auto [end, ec] = std::from_chars(field.data(), field.data() + field.size(), value);
    return end == field.data() + field.size() &&
           (ec == std::errc() || ec == std::errc::result_out_of_range);
}

/// Calls take(line number, fields) for every line with at least one field; stops at the first
/// error.
template <class Take>
std::optional<std::string> for_each_line(std::string_view text, Take take) {
    size_t line_number = 0;
    while (!text.empty()) {
        ++line_number;
        const size_t nl = text.find('\n');
        std::string_view line = text.substr(0, nl);
        text = nl == std::string_view::npos ? std::string_view{} : text.substr(nl + 1);
        if (!line.empty() && line.back() == '\r') line.remove_suffix(1);
        const size_t start = line.find_first_not_of(" \t");
        if (start == std::string_view::npos || line[start] == '#') continue;
        // A line of separators only (",", ", ,") has no field: blank, as take() needs one.
        const std::vector<std::string_view> fields = fields_of(line);
        if (fields.empty()) continue;
        if (auto error = take(line_number, fields)) return error;
    }
    return std::nullopt;
}

/// The transform of `numbers` (12 entries, 3 (a translation) or none), each a finite float.
std::optional<std::string> read_transform(std::span<const std::string_view> numbers,
                                          Transform& out) {
    if (numbers.size() != 0 && numbers.size() != 3 && numbers.size() != 12)
        return std::to_string(numbers.size()) +
               " transform numbers (expected 12, row-major 3 x 4; 3, a translation; or none)";
    std::array<float, 12> entries{};
    for (size_t k = 0; k < numbers.size(); ++k) {
        double value = 0;
        const auto [end, ec] =
            std::from_chars(numbers[k].data(), numbers[k].data() + numbers[k].size(), value);
        const bool in_range = ec == std::errc() && std::isfinite(value) &&
                              std::fabs(value) <= std::numeric_limits<float>::max();
        if (!in_range)
            return "transform entry " + std::to_string(k) + " " + quote_value(numbers[k]) +
                   " is not a finite float";
        entries[k] = static_cast<float>(value) + 0.0f;  // -0 reads as 0, as in the JSON
    }
    out = Transform{};
    if (numbers.size() == 12) {
        out.m = entries;
    } else if (numbers.size() == 3) {
        out.m[3] = entries[0];
        out.m[7] = entries[1];
        out.m[11] = entries[2];
    }
    return std::nullopt;
}

std::string at_line(size_t line, const std::string& what) {
    return "line " + std::to_string(line) + ": " + what;
}

}  // namespace

Result<std::vector<SceneInstanceSpec>, std::string> parse_scene_text(std::string_view text,
                                                                     const SceneLimits& limits) {
    std::vector<SceneInstanceSpec> out;
    std::set<std::string, std::less<>> names;
    auto error = for_each_line(
        text,
        [&](size_t line, const std::vector<std::string_view>& f) -> std::optional<std::string> {
            if (out.size() >= limits.max_instances)
                return at_line(line, "more than " + std::to_string(limits.max_instances) +
                                         " instances (max_instances)");
            SceneInstanceSpec inst;
            if (!is_mesh_id(f[0]))
                return at_line(line, "mesh " + quote_value(f[0]) +
                                         " is not a mesh id (64 lower-case hex digits)");
            inst.mesh = std::string(f[0]);
            std::span<const std::string_view> rest(f.begin() + 1, f.end());
            if (!rest.empty() && !is_number(rest.back())) {
                inst.name = std::string(rest.back());
                rest = rest.first(rest.size() - 1);
                if (!is_instance_name(inst.name))
                    return at_line(line, "name " + quote_value(inst.name) +
                                             " is not an instance name (1 to 128 characters from "
                                             "A-Z a-z 0-9 . _ : / -)");
                if (!names.insert(inst.name).second)
                    return at_line(line, "name " + quote_value(inst.name) + " is given twice");
            }
            if (auto bad = read_transform(rest, inst.transform)) return at_line(line, *bad);
            out.push_back(std::move(inst));
            return std::nullopt;
        });
    if (error) return Err{std::move(*error)};
    return out;
}

Result<std::vector<PoseEntry>, std::string> parse_pose_text(std::string_view text,
                                                            const SceneLimits& limits) {
    std::vector<PoseEntry> out;
    auto error = for_each_line(
        text,
        [&](size_t line, const std::vector<std::string_view>& f) -> std::optional<std::string> {
            if (out.size() >= limits.max_instances)
                return at_line(line, "more than " + std::to_string(limits.max_instances) +
                                         " poses (max_instances)");
            PoseEntry pose;
            uint32_t id = 0;
            const auto [end, ec] = std::from_chars(f[0].data(), f[0].data() + f[0].size(), id);
            if (ec == std::errc() && end == f[0].data() + f[0].size()) {
                pose.geometry_id = id;
            } else if (is_instance_name(f[0]) && !is_number(f[0])) {
                pose.name = std::string(f[0]);
            } else {
                return at_line(line, "instance " + quote_value(f[0]) +
                                         " is neither a geometry id nor an instance name");
            }
            const std::span<const std::string_view> numbers(f.begin() + 1, f.end());
            if (numbers.empty())
                return at_line(line, "no transform (expected 12 numbers, or 3: a translation)");
            if (auto bad = read_transform(numbers, pose.transform)) return at_line(line, *bad);
            out.push_back(std::move(pose));
            return std::nullopt;
        });
    if (error) return Err{std::move(*error)};
    if (out.empty()) return Err{std::string("no poses (one pose a line: INSTANCE T)")};
    return out;
}

}  // namespace kdrt::proto
