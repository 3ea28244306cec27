// STL, binary and ascii. Binary: 80-byte header, u32 triangle count, 50 bytes per triangle
// (f32 normal[3], f32 v0[3], v1[3], v2[3], u16 attribute), little-endian. A file is binary when
// 84 + 50 * count equals its size, even if its header starts with "solid" (many exporters do
// that); otherwise it is ascii if it starts with "solid". Each triangle gets its own 3 vertices.

#include <algorithm>
#include <bit>
#include <cstring>
#include <string>

#include "byte_io.h"
#include "mesh_common.h"

namespace kdrt::proto::detail {
namespace {

constexpr size_t kStlHeaderBytes = 84;
constexpr size_t kStlTriangleBytes = 50;

/// Triangle and vertex caps for `triangles` triangles; returns the problem or "".
std::string check_stl_limits(uint64_t triangles, const MeshLimits& limits) {
    if (triangles > limits.max_triangles)
        return limit_message("triangle", triangles, limits.max_triangles);
    if (3 * triangles > vertex_limit(limits)) {
        return limit_message("vertex", 3 * triangles, vertex_limit(limits)) +
               " (STL has 3 vertices per triangle)";
    }
    return {};
}

std::string binary_size_story(uint64_t count, uint64_t expected, size_t size) {
    return "header says " + std::to_string(count) + " triangles (" + std::to_string(expected) +
           " bytes) " + std::string(errors::kSizeMismatch) + " " + std::to_string(size) + " bytes";
}

Result<Mesh, ParseError> parse_binary_stl(std::span<const std::byte> data,
                                          const MeshLimits& limits) {
    const uint64_t count = load_le32(data.data() + 80);
    if (auto error = check_stl_limits(count, limits); !error.empty())
        return Err{byte_error(80, error)};
    Mesh mesh;
    mesh.positions.resize(9 * count);
    mesh.indices.resize(3 * count);
    const std::byte* p = data.data() + kStlHeaderBytes;
    for (uint64_t t = 0; t < count; ++t, p += kStlTriangleBytes) {
        for (int k = 0; k < 9; ++k) {
            // Bytes 0..11 are the normal, which kdrt recomputes when it needs one.
            const float value = load_le_f32(p + 12 + 4 * k);
            if (!std::isfinite(value)) {
                const uint64_t offset =
                    static_cast<uint64_t>(p - data.data()) + 12 + 4 * static_cast<uint64_t>(k);
                return Err{byte_error(offset, "triangle " + std::to_string(t) + " vertex " +
                                                  std::to_string(k / 3) + " coordinate " +
                                                  axis_name(k % 3) + " (" + non_finite_name(value) +
                                                  ") " + std::string(errors::kNonFinite))};
            }
            mesh.positions[9 * t + static_cast<uint64_t>(k)] = value;
        }
    }
    for (uint64_t i = 0; i < 3 * count; ++i) mesh.indices[i] = static_cast<uint32_t>(i);
    return mesh;
}

class AsciiStlParser {
public:
    AsciiStlParser(std::string_view text, const MeshLimits& limits)
        : tokens_(text), limits_(limits) {}

    Result<Mesh, ParseError> run() {
        std::string_view token = tokens_.next();
        if (!iequals(token, "solid")) return Err{unexpected(token, "'solid'")};
        tokens_.skip_rest_of_line();  // the solid's name
        bool in_solid = true;
        for (;;) {
            token = tokens_.next();
            if (token.empty()) {
                if (in_solid) return Err{unexpected(token, "'facet' or 'endsolid'")};
                break;
            }
            if (!in_solid) {
                // Some tools concatenate several solids in one file.
                if (!iequals(token, "solid"))
                    return Err{unexpected(token, "'solid' or the end of the file")};
                tokens_.skip_rest_of_line();
                in_solid = true;
                continue;
            }
            if (iequals(token, "endsolid")) {
                tokens_.skip_rest_of_line();
                in_solid = false;
                continue;
            }
            if (!iequals(token, "facet")) return Err{unexpected(token, "'facet' or 'endsolid'")};
            if (auto error = facet(); error) return Err{std::move(*error)};
        }
        return std::move(mesh_);
    }

private:
    /// "line N: expected X, found 'y'" or "line N: unexpected end of file: expected X".
    ParseError unexpected(std::string_view token, std::string_view expected) const {
        if (token.empty()) {
            return line_error(tokens_.line(), std::string(errors::kUnexpectedEnd) + ": " +
                                                  std::string(errors::kUnexpectedToken) + " " +
                                                  std::string(expected));
        }
        return line_error(tokens_.line(), std::string(errors::kUnexpectedToken) + " " +
                                              std::string(expected) + ", found " +
                                              quote_token(token));
    }

    std::optional<ParseError> expect(std::string_view keyword) {
        const std::string_view token = tokens_.next();
        if (iequals(token, keyword)) return std::nullopt;
        return unexpected(token, quote_token(keyword));
    }

    std::optional<ParseError> facet() {
        const uint64_t triangle = mesh_.indices.size() / 3;
        if (auto error = check_stl_limits(triangle + 1, limits_); !error.empty())
            return line_error(tokens_.line(), error);
        if (auto error = expect("normal")) return error;
        for (int axis = 0; axis < 3; ++axis) {
            // The normal is ignored, but must be a number (NaN normals of degenerate facets are
            // common).
            const std::string_view token = tokens_.next();
            float ignored = 0;
            if (token.empty()) return unexpected(token, "a normal component");
            if (parse_float(token, ignored) == NumberStatus::kInvalid) {
                return line_error(tokens_.line(),
                                  "facet normal " + std::string(1, axis_name(axis)) + " " +
                                      quote_token(token) + " " + std::string(errors::kNotANumber));
            }
        }
        if (auto error = expect("outer")) return error;
        if (auto error = expect("loop")) return error;
        for (int corner = 0; corner < 3; ++corner) {
            if (auto error = expect("vertex")) return error;
            const uint64_t vertex = mesh_.positions.size() / 3;
            float xyz[3];
            for (int axis = 0; axis < 3; ++axis) {
                const std::string_view token = tokens_.next();
                if (token.empty()) return unexpected(token, "a vertex coordinate");
                if (auto error = parse_coordinate(token, vertex, axis, xyz[axis]); !error.empty()) {
                    return line_error(tokens_.line(), error);
                }
            }
            mesh_.positions.insert(mesh_.positions.end(), xyz, xyz + 3);
            mesh_.indices.push_back(static_cast<uint32_t>(vertex));
        }
        if (auto error = expect("endloop")) return error;
        if (auto error = expect("endfacet")) return error;
        return std::nullopt;
    }

    TokenReader tokens_;
    const MeshLimits& limits_;
    Mesh mesh_;
};

/// True if the data starts (after blanks) with the keyword "solid".
bool starts_with_solid(std::string_view text) noexcept {
    size_t i = 0;
    while (i < text.size() && (is_blank(text[i]) || text[i] == '\n')) ++i;
    if (text.size() - i < 5 || !iequals(text.substr(i, 5), "solid")) return false;
    return text.size() - i == 5 || is_blank(text[i + 5]) || text[i + 5] == '\n';
}

/// True if the text has a byte no text file contains (NUL and other C0 controls but blanks).
bool has_control_bytes(std::string_view text) noexcept {
    for (char c : text) {
        const auto u = static_cast<unsigned char>(c);
        if (u < 0x20 && !is_blank(c) && c != '\n') return true;
    }
    return false;
}

}  // namespace

Result<Mesh, ParseError> parse_stl(std::span<const std::byte> data, const MeshLimits& limits) {
    const size_t size = data.size();
    uint64_t count = 0, expected = 0;
    if (size >= kStlHeaderBytes) {
        count = load_le32(data.data() + 80);
        expected = kStlHeaderBytes + kStlTriangleBytes * count;
        if (expected == size) return parse_binary_stl(data, limits);
    }
    const std::string_view text = without_bom(as_text(data));
    if (starts_with_solid(text)) {
        auto ascii = AsciiStlParser(text, limits).run();
        // A binary file whose header starts with "solid" but whose size is off reads as broken
        // ascii; control bytes give it away, and the message then tells both stories.
        if (!ascii && size >= kStlHeaderBytes && has_control_bytes(text)) {
            ascii.error().message +=
                " (and not binary STL either: " + binary_size_story(count, expected, size) + ")";
        }
        return ascii;
    }
    if (size < kStlHeaderBytes) {
        return Err{byte_error(size, std::string(errors::kTruncated) +
                                        " the 84-byte binary STL header (" + std::to_string(size) +
                                        " bytes), and it is not ascii STL (no 'solid')")};
    }
    if (expected > size) {
        const uint64_t complete = (size - kStlHeaderBytes) / kStlTriangleBytes;
        return Err{byte_error(kStlHeaderBytes + complete * kStlTriangleBytes,
                              std::string(errors::kTruncated) + " triangle " +
                                  std::to_string(complete) + ": " +
                                  binary_size_story(count, expected, size))};
    }
    return Err{byte_error(expected, std::string(errors::kTrailingData) + " the last triangle: " +
                                        binary_size_story(count, expected, size))};
}

}  // namespace kdrt::proto::detail
