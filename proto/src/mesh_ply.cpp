// PLY (Stanford polygon file format): ascii, binary_little_endian and binary_big_endian.
// Reads x, y, z of element "vertex" (any scalar type) and the list property "vertex_indices"
// (or "vertex_index") of element "face" (any integer count and index types). Every other
// property and element, list-typed or not, is skipped. ASCII bodies are read as a stream of
// whitespace-separated tokens, so an item may span lines.

#include <algorithm>
#include <array>
#include <bit>
#include <cstring>
#include <optional>
#include <string>
#include <vector>

#include "byte_io.h"
#include "mesh_common.h"

namespace kdrt::proto::detail {
namespace {

enum class PlyType : uint8_t {
    kInt8,
    kUint8,
    kInt16,
    kUint16,
    kInt32,
    kUint32,
    kFloat32,
    kFloat64
};

struct PlyTypeInfo {
    std::string_view name;
    std::string_view alias;
    PlyType type;
    size_t size;
};

constexpr std::array<PlyTypeInfo, 8> kPlyTypes = {{
    {"char", "int8", PlyType::kInt8, 1},
    {"uchar", "uint8", PlyType::kUint8, 1},
    {"short", "int16", PlyType::kInt16, 2},
    {"ushort", "uint16", PlyType::kUint16, 2},
    {"int", "int32", PlyType::kInt32, 4},
    {"uint", "uint32", PlyType::kUint32, 4},
    {"float", "float32", PlyType::kFloat32, 4},
    {"double", "float64", PlyType::kFloat64, 8},
}};

std::optional<PlyType> ply_type_from_name(std::string_view name) noexcept {
    for (const PlyTypeInfo& info : kPlyTypes) {
        if (name == info.name || name == info.alias) return info.type;
    }
    return std::nullopt;
}

constexpr size_t ply_type_size(PlyType type) noexcept {
    return kPlyTypes[static_cast<size_t>(type)].size;
}
constexpr bool ply_type_is_integer(PlyType type) noexcept {
    return type != PlyType::kFloat32 && type != PlyType::kFloat64;
}

/// What the parser does with a property.
enum class Role : uint8_t { kSkip, kX, kY, kZ, kFaceIndices };

struct PlyProperty {
    std::string_view name;
    PlyType type = PlyType::kFloat32;  // scalar type, or item type of a list
    bool is_list = false;
    PlyType count_type = PlyType::kUint8;
    Role role = Role::kSkip;
};

struct PlyElement {
    std::string_view name;
    bool is_vertex = false;  // name == "vertex": its items are appended to the mesh
    uint64_t count = 0;
    uint64_t header_line = 0;
    std::vector<PlyProperty> properties;

    /// Smallest number of bytes one item can take in a binary body (lists may be empty).
    [[nodiscard]] size_t min_binary_bytes() const noexcept {
        size_t n = 0;
        for (const PlyProperty& p : properties)
            n += ply_type_size(p.is_list ? p.count_type : p.type);
        return n;
    }
};

enum class PlyEncoding { kAscii, kBinaryLittleEndian, kBinaryBigEndian };

/// Integer value of a binary scalar of integer type `type`.
int64_t load_integer(const std::byte* p, PlyType type, bool big_endian) noexcept {
    switch (type) {
        case PlyType::kInt8:
            return static_cast<int8_t>(p[0]);
        case PlyType::kUint8:
            return static_cast<uint8_t>(p[0]);
        case PlyType::kInt16:
            return static_cast<int16_t>(load_uint<uint16_t>(p, big_endian));
        case PlyType::kUint16:
            return load_uint<uint16_t>(p, big_endian);
        case PlyType::kInt32:
            return static_cast<int32_t>(load_uint<uint32_t>(p, big_endian));
        case PlyType::kUint32:
            return load_uint<uint32_t>(p, big_endian);
        case PlyType::kFloat32:
        case PlyType::kFloat64:
            break;
    }
    return 0;  // unreachable: integer-ness is checked when the header is read
}

/// A binary scalar converted to float; `exact` receives the value before the conversion so
/// that a double too large for a float can be told from an infinity in the file.
float load_coordinate(const std::byte* p, PlyType type, bool big_endian, double& exact) noexcept {
    if (type == PlyType::kFloat32) {
        const float f = std::bit_cast<float>(load_uint<uint32_t>(p, big_endian));
        exact = f;
        return f;
    }
    if (type == PlyType::kFloat64) {
        exact = std::bit_cast<double>(load_uint<uint64_t>(p, big_endian));
        return static_cast<float>(exact);
    }
    exact = static_cast<double>(load_integer(p, type, big_endian));
    return static_cast<float>(exact);
}

class PlyParser {
public:
    PlyParser(std::span<const std::byte> data, const MeshLimits& limits)
        : data_(data), text_(as_text(data)), limits_(limits) {}

    Result<Mesh, ParseError> run() {
        if (auto error = read_header(); error) return Err{std::move(*error)};
        if (auto error = assign_roles(); error) return Err{std::move(*error)};
        std::optional<ParseError> error =
            encoding_ == PlyEncoding::kAscii ? read_ascii_body() : read_binary_body();
        if (error) return Err{std::move(*error)};
        return std::move(mesh_);
    }

private:
    // ---- header -------------------------------------------------------------------------------

    std::optional<ParseError> read_header() {
        LineReader lines(text_);
        std::string_view line;
        if (!lines.next(line) || strip_comment(line) != "ply") {
            return line_error(1, std::string(errors::kBadHeader) +
                                     ": not a PLY file (the first line must be 'ply')");
        }
        bool have_format = false;
        while (lines.next(line)) {
            const uint64_t n = lines.line_number();
            std::string_view rest = line;
            const std::string_view keyword = next_token(rest);
            if (keyword.empty() || keyword == "comment" || keyword == "obj_info") continue;
            if (keyword == "end_header") {
                if (!have_format) {
                    return line_error(n, std::string(errors::kBadHeader) +
                                             ": no 'format' line before end_header");
                }
                body_offset_ = lines.offset();
                body_first_line_ = n + 1;
                return std::nullopt;
            }
            std::optional<ParseError> error;
            if (keyword == "format") {
                if (have_format)
                    return line_error(n,
                                      std::string(errors::kBadHeader) + ": second 'format' line");
                have_format = true;
                error = format_line(rest, n);
            } else if (keyword == "element") {
                error = element_line(rest, n);
            } else if (keyword == "property") {
                error = property_line(rest, n);
            } else {
                // Exporters write lines PLY does not define (Blender 2.4x: "Created by
                // Blender3D 247 - www.blender.org, source file: ..." without "comment"). They
                // carry no data; skip them, and say so.
                if (limits_.warnings)
                    limits_.warnings->push_back("line " + std::to_string(n) +
                                                ": PLY header line with unknown keyword " +
                                                quote_token(keyword) + " skipped");
                continue;
            }
            if (error) return error;
        }
        return line_error(lines.eof_line(), std::string(errors::kBadHeader) + ": " +
                                                std::string(errors::kMissingEndHeader));
    }

    std::optional<ParseError> format_line(std::string_view rest, uint64_t n) {
        const std::string_view name = next_token(rest), version = next_token(rest);
        if (name == "ascii") {
            encoding_ = PlyEncoding::kAscii;
        } else if (name == "binary_little_endian") {
            encoding_ = PlyEncoding::kBinaryLittleEndian;
        } else if (name == "binary_big_endian") {
            encoding_ = PlyEncoding::kBinaryBigEndian;
        } else {
            return line_error(n,
                              std::string(errors::kUnknownPlyFormat) + " " + quote_token(name) +
                                  " (expected ascii, binary_little_endian or binary_big_endian)");
        }
        if (version != "1.0" || !next_token(rest).empty()) {
            return line_error(n, std::string(errors::kBadHeader) + ": unsupported PLY version " +
                                     quote_token(version) + " (expected 1.0)");
        }
        return std::nullopt;
    }

    std::optional<ParseError> element_line(std::string_view rest, uint64_t n) {
        PlyElement element;
        element.name = next_token(rest);
        const std::string_view count = next_token(rest);
        element.header_line = n;
        if (element.name.empty() || parse_int(count, element.count) != NumberStatus::kOk ||
            !next_token(rest).empty()) {
            return line_error(
                n, std::string(errors::kBadHeader) +
                       ": expected 'element <name> <count>' with a non-negative integer count");
        }
        // Only the elements the mesh comes from must be unique (and a linear scan over all
        // names would make a header of many elements quadratic).
        bool& seen = element.name == "vertex" ? seen_vertex_element_ : seen_face_element_;
        if (element.name == "vertex" || element.name == "face") {
            if (seen)
                return line_error(n, std::string(errors::kBadHeader) + ": second element " +
                                         quote_token(element.name));
            seen = true;
        }
        if (element.name == "vertex" && element.count > vertex_limit(limits_)) {
            return line_error(n, limit_message("vertex", element.count, vertex_limit(limits_)));
        }
        if (element.name == "face" && element.count > limits_.max_triangles) {
            return line_error(n, limit_message("face", element.count, limits_.max_triangles));
        }
        element.is_vertex = element.name == "vertex";
        elements_.push_back(element);
        return std::nullopt;
    }

    std::optional<ParseError> property_line(std::string_view rest, uint64_t n) {
        if (elements_.empty())
            return line_error(n, std::string(errors::kBadHeader) + ": property before any element");
        PlyProperty property;
        std::string_view type_name = next_token(rest);
        if (type_name == "list") {
            property.is_list = true;
            const std::string_view count_type = next_token(rest);
            const auto count = ply_type_from_name(count_type);
            if (!count)
                return line_error(
                    n, std::string(errors::kUnknownPlyType) + " " + quote_token(count_type));
            if (!ply_type_is_integer(*count)) {
                return line_error(n, std::string(errors::kBadHeader) + ": list count type " +
                                         quote_token(count_type) + " is not an integer type");
            }
            property.count_type = *count;
            type_name = next_token(rest);
        }
        const auto type = ply_type_from_name(type_name);
        if (!type)
            return line_error(n,
                              std::string(errors::kUnknownPlyType) + " " + quote_token(type_name));
        property.type = *type;
        property.name = next_token(rest);
        if (property.name.empty() || !next_token(rest).empty()) {
            return line_error(
                n, std::string(errors::kBadHeader) +
                       ": expected 'property <type> <name>' or 'property list <count type> "
                       "<item type> <name>'");
        }
        elements_.back().properties.push_back(property);
        property_lines_.push_back(n);
        return std::nullopt;
    }

    /// Finds the vertex coordinates and face indices and checks their types.
    std::optional<ParseError> assign_roles() {
        size_t property_index = 0;
        for (PlyElement& e : elements_) {
            const bool is_vertex = e.name == "vertex", is_face = e.name == "face";
            bool have[3] = {false, false, false};
            bool have_indices = false;
            for (PlyProperty& p : e.properties) {
                const uint64_t line = property_lines_[property_index++];
                if (is_vertex && (p.name == "x" || p.name == "y" || p.name == "z")) {
                    const int axis = p.name[0] - 'x';
                    if (have[axis])
                        return line_error(line, std::string(errors::kBadHeader) +
                                                    ": second property " + quote_token(p.name));
                    if (p.is_list)
                        return line_error(line, std::string(errors::kBadHeader) +
                                                    ": vertex property " + quote_token(p.name) +
                                                    " is a list");
                    have[axis] = true;
                    p.role = static_cast<Role>(static_cast<int>(Role::kX) + axis);
                } else if (is_face && !have_indices &&
                           (p.name == "vertex_indices" || p.name == "vertex_index")) {
                    if (!p.is_list)
                        return line_error(line, std::string(errors::kBadHeader) +
                                                    ": face property " + quote_token(p.name) +
                                                    " is not a list");
                    if (!ply_type_is_integer(p.type)) {
                        return line_error(line, std::string(errors::kBadHeader) +
                                                    ": face property " + quote_token(p.name) +
                                                    " has a non-integer item type");
                    }
                    have_indices = true;
                    p.role = Role::kFaceIndices;
                }
            }
            if (is_vertex) {
                vertex_count_ = e.count;
                for (int axis = 0; axis < 3; ++axis) {
                    if (!have[axis]) {
                        return line_error(e.header_line, "element vertex " +
                                                             std::string(errors::kMissingProperty) +
                                                             " '" + axis_name(axis) + "'");
                    }
                }
            }
            if (is_face && !have_indices && e.count > 0) {
                return line_error(e.header_line,
                                  "element face " + std::string(errors::kMissingProperty) +
                                      " 'vertex_indices' (or 'vertex_index') of list type");
            }
        }
        // Without a vertex element vertex_count_ stays 0, so any face index is out of range.
        return std::nullopt;
    }

    void reserve(const PlyElement& e, size_t min_item_bytes) {
        const size_t remaining = data_.size() - body_offset_;
        const uint64_t items =
            std::min<uint64_t>(e.count, remaining / std::max<size_t>(min_item_bytes, 1));
        if (e.name == "vertex") mesh_.positions.reserve(3 * items);
        if (e.name == "face") mesh_.indices.reserve(3 * items);
    }

    // ---- shared body helpers -----------------------------------------------------------------

    /// Checks a face's corner count; returns the problem or "".
    std::string check_corner_count(int64_t corners, uint64_t face) const {
        if (corners < 3) {
            return "face " + std::to_string(face) + " has " + std::to_string(corners) +
                   " vertices, a face " + std::string(errors::kTooFewCorners);
        }
        if (static_cast<uint64_t>(corners) > limits_.max_polygon_vertices) {
            return "face " + std::to_string(face) + " has " + std::to_string(corners) +
                   " vertices, more than the " + std::string(errors::kTooManyCorners) + " " +
                   std::to_string(limits_.max_polygon_vertices);
        }
        const uint64_t triangles = mesh_.indices.size() / 3 + static_cast<uint64_t>(corners) - 2;
        if (triangles > limits_.max_triangles)
            return limit_message("triangle", triangles, limits_.max_triangles);
        return {};
    }

    /// Appends corner `corner` (index `value`) of face `face` to the fan; returns the problem or
    /// "".
    std::string add_corner(int64_t value, uint64_t corner, uint64_t face) {
        if (value < 0 || static_cast<uint64_t>(value) >= vertex_count_) {
            return "face " + std::to_string(face) + " index " + std::to_string(value) + " " +
                   std::string(errors::kIndexOutOfRange) + " (mesh has " +
                   std::to_string(vertex_count_) + " vertices)";
        }
        const auto index = static_cast<uint32_t>(value);
        if (corner == 0) fan_first_ = index;
        if (corner >= 2)
            mesh_.indices.insert(mesh_.indices.end(), {fan_first_, fan_previous_, index});
        fan_previous_ = index;
        return {};
    }

    static std::string item_name(const PlyElement& e, uint64_t item) {
        return "element " + quote_token(e.name) + " item " + std::to_string(item) + " of " +
               std::to_string(e.count);
    }

    // ---- ascii body --------------------------------------------------------------------------

    std::optional<ParseError> read_ascii_body() {
        TokenReader tokens(text_.substr(body_offset_), body_first_line_);
        for (const PlyElement& e : elements_) {
            if (e.properties.empty()) continue;  // items without properties take no tokens
            reserve(e, 2 * e.properties.size());
            for (uint64_t item = 0; item < e.count; ++item) {
                float xyz[3] = {0, 0, 0};
                for (const PlyProperty& p : e.properties) {
                    std::string_view token = tokens.next();
                    if (token.empty()) return eof_in(tokens, e, item);
                    if (!p.is_list) {
                        if (auto error = ascii_scalar(token, p, e, item, xyz); !error.empty())
                            return line_error(tokens.line(), error);
                        continue;
                    }
                    int64_t count = 0;
                    if (parse_int(token, count) != NumberStatus::kOk || count < 0) {
                        return line_error(tokens.line(), item_name(e, item) + ": list length " +
                                                             quote_token(token) +
                                                             " is not a non-negative integer");
                    }
                    if (p.role == Role::kFaceIndices) {
                        if (auto error = check_corner_count(count, item); !error.empty())
                            return line_error(tokens.line(), error);
                    }
                    for (int64_t k = 0; k < count; ++k) {
                        token = tokens.next();
                        if (token.empty()) return eof_in(tokens, e, item);
                        if (p.role == Role::kFaceIndices) {
                            int64_t value = 0;
                            if (parse_int(token, value) != NumberStatus::kOk) {
                                return line_error(tokens.line(),
                                                  "face " + std::to_string(item) + " index " +
                                                      quote_token(token) + " " +
                                                      std::string(errors::kNotAnInteger));
                            }
                            if (auto error = add_corner(value, static_cast<uint64_t>(k), item);
                                !error.empty()) {
                                return line_error(tokens.line(), error);
                            }
                        } else if (auto error = skipped_number(token, p, e, item); !error.empty()) {
                            return line_error(tokens.line(), error);
                        }
                    }
                }
                if (e.is_vertex) mesh_.positions.insert(mesh_.positions.end(), xyz, xyz + 3);
            }
        }
        if (!tokens.at_end()) {
            const std::string_view token = tokens.next();
            return line_error(tokens.line(), std::string(errors::kTrailingData) +
                                                 " the last element: " + quote_token(token));
        }
        return std::nullopt;
    }

    ParseError eof_in(const TokenReader& tokens, const PlyElement& e, uint64_t item) const {
        return line_error(tokens.line(),
                          std::string(errors::kUnexpectedEnd) + " in " + item_name(e, item));
    }

    std::string skipped_number(std::string_view token, const PlyProperty& p, const PlyElement& e,
                               uint64_t item) const {
        double ignored = 0;
        if (parse_double(token, ignored) == NumberStatus::kInvalid) {
            return item_name(e, item) + " property " + quote_token(p.name) + ": " +
                   quote_token(token) + " " + std::string(errors::kNotANumber);
        }
        return {};
    }

    std::string ascii_scalar(std::string_view token, const PlyProperty& p, const PlyElement& e,
                             uint64_t item, float xyz[3]) const {
        if (p.role == Role::kSkip) return skipped_number(token, p, e, item);
        const int axis = static_cast<int>(p.role) - static_cast<int>(Role::kX);
        if (p.type == PlyType::kFloat32) return parse_coordinate(token, item, axis, xyz[axis]);
        // Integer and double coordinates; the message is only built on failure.
        const auto problem = [&](std::string_view what) {
            return "vertex " + std::to_string(item) + " coordinate " + axis_name(axis) + " " +
                   quote_token(token) + " " + std::string(what);
        };
        if (ply_type_is_integer(p.type)) {
            int64_t value = 0;
            if (parse_int(token, value) != NumberStatus::kOk) return problem(errors::kNotAnInteger);
            xyz[axis] = static_cast<float>(value);
            return {};
        }
        double value = 0;
        const NumberStatus status = parse_double(token, value);
        if (status == NumberStatus::kInvalid) return problem(errors::kNotANumber);
        if (status == NumberStatus::kOutOfRange) {
            return problem(std::string(errors::kNumberOutOfRange) + " in a double");
        }
        if (!std::isfinite(value)) return problem(errors::kNonFinite);
        xyz[axis] = static_cast<float>(value);
        if (!std::isfinite(xyz[axis])) {
            return problem(std::string(errors::kNumberOutOfRange) + " in a float");
        }
        return {};
    }

    // ---- binary body -------------------------------------------------------------------------

    std::optional<ParseError> read_binary_body() {
        const bool big_endian = encoding_ == PlyEncoding::kBinaryBigEndian;
        const std::byte* const base = data_.data();
        size_t pos = body_offset_;
        const size_t end = data_.size();
        for (const PlyElement& e : elements_) {
            if (e.properties.empty()) continue;
            reserve(e, e.min_binary_bytes());
            for (uint64_t item = 0; item < e.count; ++item) {
                float xyz[3] = {0, 0, 0};
                for (const PlyProperty& p : e.properties) {
                    const size_t scalar_size = ply_type_size(p.is_list ? p.count_type : p.type);
                    if (end - pos < scalar_size) return truncated(pos, e, item, p, scalar_size);
                    if (!p.is_list) {
                        if (p.role != Role::kSkip) {
                            const int axis = static_cast<int>(p.role) - static_cast<int>(Role::kX);
                            double exact = 0;
                            xyz[axis] = load_coordinate(base + pos, p.type, big_endian, exact);
                            if (!std::isfinite(xyz[axis])) {
                                return byte_error(
                                    pos, "vertex " + std::to_string(item) + " coordinate " +
                                             axis_name(axis) + " " +
                                             (std::isfinite(exact)
                                                  ? std::string(errors::kNumberOutOfRange) +
                                                        " in a float"
                                                  : "(" + non_finite_name(exact) + ") " +
                                                        std::string(errors::kNonFinite)));
                            }
                        }
                        pos += scalar_size;
                        continue;
                    }
                    const int64_t count = load_integer(base + pos, p.count_type, big_endian);
                    if (count < 0) {
                        return byte_error(pos, item_name(e, item) + ": list length " +
                                                   std::to_string(count) + " is negative");
                    }
                    if (p.role == Role::kFaceIndices) {
                        if (auto error = check_corner_count(count, item); !error.empty())
                            return byte_error(pos, error);
                    }
                    pos += scalar_size;
                    const size_t item_size = ply_type_size(p.type);
                    if (static_cast<uint64_t>(count) > (end - pos) / item_size) {
                        return truncated(pos, e, item, p, static_cast<uint64_t>(count) * item_size);
                    }
                    if (p.role == Role::kFaceIndices) {
                        for (int64_t k = 0; k < count; ++k) {
                            const int64_t value = load_integer(base + pos, p.type, big_endian);
                            if (auto error = add_corner(value, static_cast<uint64_t>(k), item);
                                !error.empty()) {
                                return byte_error(pos, error);
                            }
                            pos += item_size;
                        }
                    } else {
                        pos += static_cast<size_t>(count) * item_size;
                    }
                }
                if (e.is_vertex) mesh_.positions.insert(mesh_.positions.end(), xyz, xyz + 3);
            }
        }
        // Tolerate a stray newline or padding after the data, nothing else.
        for (size_t i = pos; i < end; ++i) {
            const char c = static_cast<char>(base[i]);
            if (!is_blank(c) && c != '\n' && c != '\0') {
                return byte_error(i, std::string(errors::kTrailingData) + " the last element (" +
                                         std::to_string(end - pos) + " bytes left)");
            }
        }
        return std::nullopt;
    }

    ParseError truncated(size_t pos, const PlyElement& e, uint64_t item, const PlyProperty& p,
                         uint64_t needed) const {
        return byte_error(pos, std::string(errors::kTruncated) + " " + item_name(e, item) +
                                   " (property " + quote_token(p.name) + " needs " +
                                   std::to_string(needed) + " bytes, " +
                                   std::to_string(data_.size() - pos) + " left)");
    }

    std::span<const std::byte> data_;
    std::string_view text_;
    const MeshLimits& limits_;
    PlyEncoding encoding_ = PlyEncoding::kAscii;
    std::vector<PlyElement> elements_;
    std::vector<uint64_t> property_lines_;  // header line of each property, in declaration order
    bool seen_vertex_element_ = false;
    bool seen_face_element_ = false;
    size_t body_offset_ = 0;
    uint64_t body_first_line_ = 0;
    uint64_t vertex_count_ = 0;
    Mesh mesh_;
    uint32_t fan_first_ = 0;
    uint32_t fan_previous_ = 0;
};

}  // namespace

Result<Mesh, ParseError> parse_ply(std::span<const std::byte> data, const MeshLimits& limits) {
    return PlyParser(data, limits).run();
}

}  // namespace kdrt::proto::detail
