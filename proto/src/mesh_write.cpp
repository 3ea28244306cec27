// write_mesh: the writers behind round-trip tests and conversion tools.

#include <charconv>
#include <cmath>
#include <cstring>
#include <limits>
#include <stdexcept>
#include <string>

#include "byte_io.h"
#include "mesh_common.h"

namespace kdrt::proto {
namespace {

void check_writable(const Mesh& mesh) {
    if (mesh.positions.size() % 3 != 0)
        throw std::invalid_argument("write_mesh: positions.size() is not a multiple of 3");
    if (mesh.indices.size() % 3 != 0)
        throw std::invalid_argument("write_mesh: indices.size() is not a multiple of 3");
    const size_t vertex_count = mesh.vertex_count();
    for (size_t i = 0; i < mesh.indices.size(); ++i) {
        if (mesh.indices[i] >= vertex_count) {
            throw std::invalid_argument("write_mesh: triangle " + std::to_string(i / 3) +
                                        " index " + std::to_string(mesh.indices[i]) +
                                        " out of range (mesh has " + std::to_string(vertex_count) +
                                        " vertices)");
        }
    }
}

void check_u32_counts(uint64_t vertices, uint64_t triangles, std::string_view format) {
    constexpr uint64_t kMax = std::numeric_limits<uint32_t>::max();
    if (vertices > kMax || triangles > kMax) {
        throw std::invalid_argument("write_mesh: " + std::string(format) + " stores counts as u32");
    }
}

/// Text accumulator; floats in shortest round-trip form.
class TextOut {
public:
    explicit TextOut(size_t reserve) { text_.reserve(reserve); }
    TextOut& operator<<(std::string_view s) {
        text_ += s;
        return *this;
    }
    TextOut& operator<<(char c) {
        text_ += c;
        return *this;
    }
    TextOut& operator<<(float v) { return number(v); }
    TextOut& operator<<(uint64_t v) { return number(v); }
    TextOut& operator<<(uint32_t v) { return number(v); }

    std::vector<std::byte> bytes() const {
        std::vector<std::byte> out(text_.size());
        if (!text_.empty()) std::memcpy(out.data(), text_.data(), text_.size());
        return out;
    }

private:
    template <class T>
    TextOut& number(T v) {
        char buf[64];
        const auto result = std::to_chars(buf, buf + sizeof buf, v);
        text_.append(buf, result.ptr);
        return *this;
    }
    std::string text_;
};

void write_position(TextOut& out, const Mesh& mesh, size_t vertex) {
    out << mesh.positions[3 * vertex] << ' ' << mesh.positions[3 * vertex + 1] << ' '
        << mesh.positions[3 * vertex + 2];
}

std::vector<std::byte> write_obj(const Mesh& mesh) {
    TextOut out(mesh.positions.size() * 12 + mesh.indices.size() * 8 + 64);
    out << "# kdrt mesh: " << uint64_t{mesh.vertex_count()} << " vertices, "
        << uint64_t{mesh.triangle_count()} << " triangles\n";
    for (size_t v = 0; v < mesh.vertex_count(); ++v) {
        out << "v ";
        write_position(out, mesh, v);
        out << '\n';
    }
    for (size_t t = 0; t < mesh.triangle_count(); ++t) {
        out << "f " << mesh.indices[3 * t] + 1 << ' ' << mesh.indices[3 * t + 1] + 1 << ' '
            << mesh.indices[3 * t + 2] + 1 << '\n';
    }
    return out.bytes();
}

std::vector<std::byte> write_off(const Mesh& mesh) {
    TextOut out(mesh.positions.size() * 12 + mesh.indices.size() * 8 + 64);
    out << "OFF\n"
        << uint64_t{mesh.vertex_count()} << ' ' << uint64_t{mesh.triangle_count()} << " 0\n";
    for (size_t v = 0; v < mesh.vertex_count(); ++v) {
        write_position(out, mesh, v);
        out << '\n';
    }
    for (size_t t = 0; t < mesh.triangle_count(); ++t) {
        out << "3 " << mesh.indices[3 * t] << ' ' << mesh.indices[3 * t + 1] << ' '
            << mesh.indices[3 * t + 2] << '\n';
    }
    return out.bytes();
}

std::vector<std::byte> write_ply(const Mesh& mesh, const MeshWriteOptions& options) {
    check_u32_counts(mesh.vertex_count(), mesh.triangle_count(), "PLY (uint vertex_indices)");
    TextOut header(256);
    header << "ply\nformat "
           << (!options.binary
                   ? "ascii"
                   : (options.big_endian ? "binary_big_endian" : "binary_little_endian"))
           << " 1.0\ncomment written by kdrt\nelement vertex " << uint64_t{mesh.vertex_count()}
           << "\nproperty float x\nproperty float y\nproperty float z\nelement face "
           << uint64_t{mesh.triangle_count()}
           << "\nproperty list uchar uint vertex_indices\nend_header\n";
    if (!options.binary) {
        TextOut out(mesh.positions.size() * 12 + mesh.indices.size() * 8 + 256);
        std::vector<std::byte> head = header.bytes();
        out << std::string_view(reinterpret_cast<const char*>(head.data()), head.size());
        for (size_t v = 0; v < mesh.vertex_count(); ++v) {
            write_position(out, mesh, v);
            out << '\n';
        }
        for (size_t t = 0; t < mesh.triangle_count(); ++t) {
            out << "3 " << mesh.indices[3 * t] << ' ' << mesh.indices[3 * t + 1] << ' '
                << mesh.indices[3 * t + 2] << '\n';
        }
        return out.bytes();
    }
    std::vector<std::byte> out = header.bytes();
    const size_t body = out.size();
    out.resize(body + 12 * mesh.vertex_count() + 13 * mesh.triangle_count());
    std::byte* p = out.data() + body;
    for (float f : mesh.positions) {
        detail::store_uint(p, std::bit_cast<uint32_t>(f), options.big_endian);
        p += 4;
    }
    for (size_t t = 0; t < mesh.triangle_count(); ++t) {
        *p++ = std::byte{3};
        for (int k = 0; k < 3; ++k, p += 4)
            detail::store_uint(p, mesh.indices[3 * t + static_cast<size_t>(k)], options.big_endian);
    }
    return out;
}

/// Unit normal of a triangle by the right-hand rule; zero for a degenerate one.
Vec3 facet_normal(const Mesh& mesh, size_t t) {
    const Vec3 n =
        cross(mesh.corner(t, 1) - mesh.corner(t, 0), mesh.corner(t, 2) - mesh.corner(t, 0));
    const float length = std::sqrt(dot(n, n));
    if (!(length > 0.0f) || !std::isfinite(length)) return Vec3{};
    return n * (1.0f / length);
}

std::vector<std::byte> write_stl(const Mesh& mesh, const MeshWriteOptions& options) {
    if (!options.binary) {
        TextOut out(mesh.triangle_count() * 200 + 64);
        out << "solid kdrt\n";
        for (size_t t = 0; t < mesh.triangle_count(); ++t) {
            const Vec3 n = facet_normal(mesh, t);
            out << "facet normal " << n.x << ' ' << n.y << ' ' << n.z << "\n outer loop\n";
            for (int k = 0; k < 3; ++k) {
                out << "  vertex ";
                write_position(out, mesh, mesh.indices[3 * t + static_cast<size_t>(k)]);
                out << '\n';
            }
            out << " endloop\nendfacet\n";
        }
        out << "endsolid kdrt\n";
        return out.bytes();
    }
    check_u32_counts(0, mesh.triangle_count(), "binary STL");
    std::vector<std::byte> out(84 + 50 * mesh.triangle_count());
    // Deliberately not "solid...": readers that trust the header would take the file for ascii.
    constexpr std::string_view kHeader = "binary STL written by kdrt";
    std::memcpy(out.data(), kHeader.data(), kHeader.size());
    detail::store_le32(out.data() + 80, static_cast<uint32_t>(mesh.triangle_count()));
    std::byte* p = out.data() + 84;
    for (size_t t = 0; t < mesh.triangle_count(); ++t, p += 50) {
        const Vec3 n = facet_normal(mesh, t);
        const Vec3 v[4] = {n, mesh.corner(t, 0), mesh.corner(t, 1), mesh.corner(t, 2)};
        for (int i = 0; i < 4; ++i) {
            for (int a = 0; a < 3; ++a) detail::store_le_f32(p + 12 * i + 4 * a, v[i][a]);
        }
        // Bytes 48..49: attribute byte count, 0 (already zero).
    }
    return out;
}

std::vector<std::byte> write_raw(const Mesh& mesh) {
    check_u32_counts(mesh.vertex_count(), mesh.triangle_count(), "the raw format");
    std::vector<std::byte> out(8 + 4 * mesh.positions.size() + 4 * mesh.indices.size());
    detail::store_le32(out.data(), static_cast<uint32_t>(mesh.vertex_count()));
    detail::store_le32(out.data() + 4, static_cast<uint32_t>(mesh.triangle_count()));
    std::byte* p = out.data() + 8;
    for (float f : mesh.positions) {
        detail::store_le_f32(p, f);
        p += 4;
    }
    for (uint32_t i : mesh.indices) {
        detail::store_le32(p, i);
        p += 4;
    }
    return out;
}

}  // namespace

std::vector<std::byte> write_mesh(const Mesh& mesh, MeshFormat format,
                                  const MeshWriteOptions& options) {
    check_writable(mesh);
    switch (format) {
        case MeshFormat::kObj:
            return write_obj(mesh);
        case MeshFormat::kPly:
            return write_ply(mesh, options);
        case MeshFormat::kOff:
            return write_off(mesh);
        case MeshFormat::kStl:
            return write_stl(mesh, options);
        case MeshFormat::kRaw:
            return write_raw(mesh);
    }
    throw std::invalid_argument("write_mesh: unknown format");
}

}  // namespace kdrt::proto
