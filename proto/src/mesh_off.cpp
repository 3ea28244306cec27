// OFF (Object File Format): "[ST][C][N]OFF", counts "V F [E]", V vertex lines (first three numbers;
// colours, normals or texture coordinates after them are ignored), F face lines
// "n i0 .. in-1 [colour]". '#' starts a comment. One record per line.

#include <algorithm>
#include <string>

#include "mesh_common.h"

namespace kdrt::proto::detail {
namespace {

/// Accepts the header keyword of an OFF variant whose vertex lines start with x y z.
bool is_supported_off_keyword(std::string_view keyword) noexcept {
    if (keyword.starts_with("ST")) keyword.remove_prefix(2);
    if (keyword.starts_with("C")) keyword.remove_prefix(1);
    if (keyword.starts_with("N")) keyword.remove_prefix(1);
    return keyword == "OFF";
}

class OffParser {
public:
    OffParser(std::string_view text, const MeshLimits& limits)
        : text_(text), lines_(text), limits_(limits) {}

    Result<Mesh, ParseError> run() {
        std::string_view line;
        if (!next_content_line(line)) return Err{at_eof("expected the OFF header")};
        std::string_view rest = line;
        const std::string_view keyword = next_token(rest);
        if (!is_supported_off_keyword(keyword)) {
            std::string what =
                std::string(errors::kBadHeader) + ": expected 'OFF', found " + quote_token(keyword);
            if (keyword.ends_with("OFF"))
                what += " (only the [ST][C][N]OFF variants with 3D vertices are supported)";
            return Err{line_error(lines_.line_number(), what)};
        }
        if (rest.empty() && !next_content_line(rest))
            return Err{at_eof("expected the vertex and face counts")};
        if (auto error = counts(rest); !error.empty())
            return Err{line_error(lines_.line_number(), error)};

        const size_t remaining = text_.size() - lines_.offset();
        // Reserve no more than the remaining bytes can hold: a vertex line takes >= 6 bytes
        // ("0 0 0\n"), a triangle line >= 8 ("3 0 1 2\n").
        mesh_.positions.reserve(3 * std::min<uint64_t>(vertex_count_, remaining / 6));
        mesh_.indices.reserve(3 * std::min<uint64_t>(face_count_, remaining / 8));

        for (uint64_t v = 0; v < vertex_count_; ++v) {
            if (!next_content_line(line)) {
                return Err{at_eof("expected " + std::to_string(vertex_count_) +
                                  " vertices, found " + std::to_string(v))};
            }
            if (auto error = vertex(line, v); !error.empty())
                return Err{line_error(lines_.line_number(), error)};
        }
        for (uint64_t f = 0; f < face_count_; ++f) {
            if (!next_content_line(line)) {
                return Err{at_eof("expected " + std::to_string(face_count_) + " faces, found " +
                                  std::to_string(f))};
            }
            if (auto error = face(line); !error.empty())
                return Err{line_error(lines_.line_number(), error)};
        }
        if (next_content_line(line)) {
            return Err{line_error(lines_.line_number(),
                                  std::string(errors::kTrailingData) +
                                      " the last face (header declares " +
                                      std::to_string(vertex_count_) + " vertices and " +
                                      std::to_string(face_count_) + " faces)")};
        }
        return std::move(mesh_);
    }

private:
    /// Next line with content (comments and blanks removed); false at end of file.
    bool next_content_line(std::string_view& line) {
        std::string_view raw;
        while (lines_.next(raw)) {
            line = strip_comment(raw);
            if (!line.empty()) return true;
        }
        return false;
    }

    ParseError at_eof(std::string_view expected) const {
        return line_error(lines_.eof_line(),
                          std::string(errors::kUnexpectedEnd) + ": " + std::string(expected));
    }

    std::string counts(std::string_view rest) {
        const std::string_view v = next_token(rest), f = next_token(rest), e = next_token(rest);
        uint64_t edges = 0;
        if (parse_int(v, vertex_count_) != NumberStatus::kOk ||
            parse_int(f, face_count_) != NumberStatus::kOk ||
            (!e.empty() && parse_int(e, edges) != NumberStatus::kOk) || !next_token(rest).empty()) {
            return std::string(errors::kBadHeader) +
                   ": expected 'vertex_count face_count [edge_count]' as non-negative integers";
        }
        if (vertex_count_ > vertex_limit(limits_))
            return limit_message("vertex", vertex_count_, vertex_limit(limits_));
        // Every face gives at least one triangle.
        if (face_count_ > limits_.max_triangles)
            return limit_message("face", face_count_, limits_.max_triangles);
        return {};
    }

    std::string vertex(std::string_view rest, uint64_t index) {
        float xyz[3];
        for (int axis = 0; axis < 3; ++axis) {
            const std::string_view token = next_token(rest);
            if (token.empty()) {
                return "vertex " + std::to_string(index) + " " +
                       std::string(errors::kMissingCoordinate) + ", found " + std::to_string(axis);
            }
            std::string error = parse_coordinate(token, index, axis, xyz[axis]);
            if (!error.empty()) return error;
        }
        mesh_.positions.insert(mesh_.positions.end(), xyz, xyz + 3);
        return {};
    }

    std::string face(std::string_view rest) {
        const std::string_view count_token = next_token(rest);
        uint64_t corners = 0;
        if (parse_int(count_token, corners) != NumberStatus::kOk) {
            return "face vertex count " + quote_token(count_token) + " " +
                   std::string(errors::kNotAnInteger);
        }
        if (corners < 3)
            return "face has " + std::to_string(corners) + " vertices, a face " +
                   std::string(errors::kTooFewCorners);
        if (corners > limits_.max_polygon_vertices) {
            return "face has " + std::to_string(corners) + " vertices, more than the " +
                   std::string(errors::kTooManyCorners) + " " +
                   std::to_string(limits_.max_polygon_vertices);
        }
        const uint64_t triangles = mesh_.indices.size() / 3;
        if (triangles + (corners - 2) > limits_.max_triangles) {
            return limit_message("triangle", triangles + (corners - 2), limits_.max_triangles);
        }
        const size_t indices_before = mesh_.indices.size();
        uint32_t first = 0, previous = 0;
        for (uint64_t c = 0; c < corners; ++c) {
            const std::string_view token = next_token(rest);
            int64_t index = 0;
            std::string error;
            if (token.empty()) {
                error = "face declares " + std::to_string(corners) + " vertices but lists " +
                        std::to_string(c);
            } else if (parse_int(token, index) != NumberStatus::kOk) {
                error =
                    "face index " + quote_token(token) + " " + std::string(errors::kNotAnInteger);
            } else if (index < 0 || static_cast<uint64_t>(index) >= vertex_count_) {
                error = "face index " + std::to_string(index) + " " +
                        std::string(errors::kIndexOutOfRange) + " (mesh has " +
                        std::to_string(vertex_count_) + " vertices)";
            }
            if (!error.empty()) {
                mesh_.indices.resize(indices_before);
                return error;
            }
            const auto current = static_cast<uint32_t>(index);
            if (c == 0) first = current;
            if (c >= 2) mesh_.indices.insert(mesh_.indices.end(), {first, previous, current});
            previous = current;
        }
        // Anything after the indices is a colour (0 to 4 numbers) and is ignored.
        return {};
    }

    std::string_view text_;
    LineReader lines_;
    const MeshLimits& limits_;
    Mesh mesh_;
    uint64_t vertex_count_ = 0;
    uint64_t face_count_ = 0;
};

}  // namespace

Result<Mesh, ParseError> parse_off(std::string_view text, const MeshLimits& limits) {
    return OffParser(without_bom(text), limits).run();
}

}  // namespace kdrt::proto::detail
