#pragma once
// Internal: shared helpers of the mesh parsers and the per-format entry points.

#include <cmath>
#include <cstdint>
#include <span>
#include <string>
#include <string_view>

#include "kdrt/proto/errors.h"
#include "kdrt/proto/mesh_io.h"
#include "kdrt/proto/text.h"

namespace kdrt::proto::detail {

/// "line N: what", with ParseError::line = N.
[[nodiscard]] inline ParseError line_error(uint64_t line, std::string_view what) {
    ParseError e;
    e.message = "line " + std::to_string(line) + ": " + std::string(what);
    e.line = line;
    return e;
}

/// "byte N: what", with ParseError::byte_offset = N.
[[nodiscard]] inline ParseError byte_error(uint64_t offset, std::string_view what) {
    ParseError e;
    e.message = "byte " + std::to_string(offset) + ": " + std::string(what);
    e.byte_offset = offset;
    return e;
}

/// Effective vertex cap: indices are uint32, so never more than 2^32.
[[nodiscard]] constexpr uint64_t vertex_limit(const MeshLimits& limits) noexcept {
    return limits.max_vertices < (uint64_t{1} << 32) ? limits.max_vertices : (uint64_t{1} << 32);
}

[[nodiscard]] constexpr char axis_name(int axis) noexcept {
    return axis == 0 ? 'x' : (axis == 1 ? 'y' : 'z');
}

/// "<what> count N exceeds the limit L".
[[nodiscard]] inline std::string limit_message(std::string_view what, uint64_t count,
                                               uint64_t limit) {
    return std::string(what) + " count " + std::to_string(count) + " " +
           std::string(errors::kLimitExceeded) + " " + std::to_string(limit);
}

/// Text view of a byte buffer (char may alias any object).
[[nodiscard]] inline std::string_view as_text(std::span<const std::byte> data) noexcept {
    return {reinterpret_cast<const char*>(data.data()), data.size()};
}

/// Drops a UTF-8 byte order mark, which some editors put in front of text files.
[[nodiscard]] inline std::string_view without_bom(std::string_view text) noexcept {
    if (text.size() >= 3 && text.substr(0, 3) == "\xEF\xBB\xBF") text.remove_prefix(3);
    return text;
}

[[nodiscard]] Result<Mesh, ParseError> parse_obj(std::string_view text, const MeshLimits& limits);
[[nodiscard]] Result<Mesh, ParseError> parse_off(std::string_view text, const MeshLimits& limits);
[[nodiscard]] Result<Mesh, ParseError> parse_ply(std::span<const std::byte> data,
                                                 const MeshLimits& limits);
[[nodiscard]] Result<Mesh, ParseError> parse_stl(std::span<const std::byte> data,
                                                 const MeshLimits& limits);
[[nodiscard]] Result<Mesh, ParseError> parse_raw(std::span<const std::byte> data,
                                                 const MeshLimits& limits);

}  // namespace kdrt::proto::detail

#include "text_scan.h"

namespace kdrt::proto::detail {

/// Parses coordinate `axis` of vertex `vertex_index` (0-based) from a text token. Returns an empty
/// string on success, else the problem (without location) for a ParseError.
[[nodiscard]] inline std::string parse_coordinate(std::string_view token, uint64_t vertex_index,
                                                  int axis, float& out) {
    const NumberStatus status = parse_float(token, out);
    if (status == NumberStatus::kOk && std::isfinite(out)) return {};
    std::string what = "vertex " + std::to_string(vertex_index) + " coordinate " + axis_name(axis) +
                       " " + quote_token(token) + " ";
    if (status == NumberStatus::kInvalid) return what + std::string(errors::kNotANumber);
    if (status == NumberStatus::kOutOfRange)
        return what + std::string(errors::kNumberOutOfRange) + " in a float";
    return what + std::string(errors::kNonFinite);
}

}  // namespace kdrt::proto::detail
