// Wavefront OBJ: `v` and `f` statements. Faces are fan-triangulated in file order; indices are
// 1-based, negative ones count back from the last vertex defined so far.

#include <array>
#include <string>

#include "mesh_common.h"

namespace kdrt::proto::detail {
namespace {

/// Standard OBJ statements that carry nothing kdrt needs. Anything else is an error, so that a
/// file in another format is not silently read as an empty mesh.
constexpr std::array<std::string_view, 38> kIgnoredStatements = {
    "vt",    "vn",     "vp",       "o",        "g",    "s",          "usemtl",    "mtllib",
    "l",     "p",      "cstype",   "deg",      "bmat", "step",       "curv",      "curv2",
    "surf",  "parm",   "trim",     "hole",     "scrv", "sp",         "end",       "con",
    "mg",    "bevel",  "c_interp", "d_interp", "lod",  "shadow_obj", "trace_obj", "ctech",
    "stech", "maplib", "usemap",   "call",     "csh",  "res"};

bool is_ignored_statement(std::string_view keyword) noexcept {
    for (std::string_view k : kIgnoredStatements) {
        if (k == keyword) return true;
    }
    return false;
}

/// True when the part of a corner after the vertex index is valid: "", "/vt", "/vt/vn", "//vn".
bool valid_corner_suffix(std::string_view rest) noexcept {
    if (rest.empty()) return true;
    if (rest[0] != '/') return false;
    rest.remove_prefix(1);
    const size_t slash = rest.find('/');
    const std::string_view texcoord = rest.substr(0, slash);
    int64_t ignored = 0;
    if (slash == std::string_view::npos) return parse_int(texcoord, ignored) == NumberStatus::kOk;
    const std::string_view normal = rest.substr(slash + 1);
    if (!texcoord.empty() && parse_int(texcoord, ignored) != NumberStatus::kOk) return false;
    return parse_int(normal, ignored) == NumberStatus::kOk;
}

/// Trailing '\' of a comment-free line, which joins it with the next line.
bool ends_with_continuation(std::string_view stripped) noexcept {
    return !stripped.empty() && stripped.back() == '\\';
}

class ObjParser {
public:
    ObjParser(std::string_view text, const MeshLimits& limits) : lines_(text), limits_(limits) {}

    Result<Mesh, ParseError> run() {
        std::string_view raw;
        while (lines_.next(raw)) {
            const uint64_t line_number = lines_.line_number();
            std::string_view line = strip_comment(raw);
            if (ends_with_continuation(line)) line = join_continued(line);
            if (line.empty()) continue;
            std::string error = statement(line);
            if (!error.empty()) return Err{line_error(line_number, error)};
        }
        return std::move(mesh_);
    }

private:
    /// Joins `first` (ending in '\') with the following lines into joined_, which stays valid
    /// until the next call. Rare, so the copy does not matter.
    std::string_view join_continued(std::string_view first) {
        joined_.assign(first.substr(0, first.size() - 1));
        std::string_view raw;
        while (lines_.next(raw)) {
            const std::string_view part = strip_comment(raw);
            joined_ += ' ';
            if (!ends_with_continuation(part)) {
                joined_ += part;
                break;
            }
            joined_ += part.substr(0, part.size() - 1);
        }
        return joined_;
    }

    /// Handles one statement; returns the problem (without location) or "".
    std::string statement(std::string_view line) {
        std::string_view rest = line;
        const std::string_view keyword = next_token(rest);
        if (keyword == "v") return vertex(rest);
        if (keyword == "f") return face(rest);
        if (is_ignored_statement(keyword)) return {};
        return std::string(errors::kUnknownStatement) + " " + quote_token(keyword) +
               " (kdrt reads v and f, and skips the other standard OBJ statements)";
    }

    std::string vertex(std::string_view rest) {
        const uint64_t index = mesh_.positions.size() / 3;
        if (index >= vertex_limit(limits_))
            return limit_message("vertex", index + 1, vertex_limit(limits_));
        float xyz[3];
        for (int axis = 0; axis < 3; ++axis) {
            const std::string_view token = next_token(rest);
            if (token.empty()) {
                return "vertex " + std::string(errors::kMissingCoordinate) + ", found " +
                       std::to_string(axis);
            }
            std::string error = parse_coordinate(token, index, axis, xyz[axis]);
            if (!error.empty()) return error;
        }
        // Further values (w, or r g b colours) are allowed and ignored.
        mesh_.positions.insert(mesh_.positions.end(), xyz, xyz + 3);
        return {};
    }

    /// Resolves one corner token to a 0-based vertex index.
    std::string corner(std::string_view token, uint32_t& out) const {
        const size_t slash = token.find('/');
        const std::string_view index_text = token.substr(0, slash);
        int64_t index = 0;
        const NumberStatus status = parse_int(index_text, index);
        if (status == NumberStatus::kOutOfRange) {
            return "face index " + quote_token(index_text) + " is " +
                   std::string(errors::kIndexOutOfRange);
        }
        if (status != NumberStatus::kOk || !valid_corner_suffix(token.substr(index_text.size()))) {
            return "face vertex " + quote_token(token) +
                   " is not of the form v, v/vt, v//vn or v/vt/vn "
                   "with integer indices";
        }
        const auto defined = static_cast<int64_t>(mesh_.positions.size() / 3);
        if (index == 0)
            return "face index 0 is " + std::string(errors::kIndexOutOfRange) +
                   " (OBJ indices start at 1)";
        if (index > defined) {
            return "face index " + std::to_string(index) + " refers to a vertex " +
                   std::string(errors::kUndefinedVertex) + " (" + std::to_string(defined) +
                   " vertices so far)";
        }
        if (index < -defined) {
            return "face index " + std::to_string(index) + " is " +
                   std::string(errors::kIndexOutOfRange) + " (only " + std::to_string(defined) +
                   " vertices defined so far)";
        }
        out = static_cast<uint32_t>(index > 0 ? index - 1 : defined + index);
        return {};
    }

    std::string face(std::string_view rest) {
        uint32_t first = 0, previous = 0;
        uint64_t corner_count = 0;
        const size_t triangles_before = mesh_.indices.size();
        for (std::string_view token = next_token(rest); !token.empty(); token = next_token(rest)) {
            if (corner_count == limits_.max_polygon_vertices) {
                return "face has more than " + std::to_string(limits_.max_polygon_vertices) +
                       " vertices, the " + std::string(errors::kTooManyCorners);
            }
            uint32_t current = 0;
            std::string error = corner(token, current);
            if (!error.empty()) return error;
            if (corner_count == 0) {
                first = current;
            } else if (corner_count >= 2) {
                if (mesh_.indices.size() / 3 >= limits_.max_triangles) {
                    return limit_message("triangle", mesh_.indices.size() / 3 + 1,
                                         limits_.max_triangles);
                }
                mesh_.indices.insert(mesh_.indices.end(), {first, previous, current});
            }
            previous = current;
            ++corner_count;
        }
        if (corner_count < 3) {
            mesh_.indices.resize(triangles_before);
            return "face has " + std::to_string(corner_count) + " vertices, a face " +
                   std::string(errors::kTooFewCorners);
        }
        return {};
    }

    LineReader lines_;
    const MeshLimits& limits_;
    Mesh mesh_;
    std::string joined_;
};

}  // namespace

Result<Mesh, ParseError> parse_obj(std::string_view text, const MeshLimits& limits) {
    return ObjParser(without_bom(text), limits).run();
}

}  // namespace kdrt::proto::detail
