#include "kdrt/proto/mesh_id.h"

#include <openssl/evp.h>

#include <array>
#include <bit>
#include <cstring>
#include <memory>
#include <span>
#include <stdexcept>

#include "byte_io.h"
#include "kdrt/proto/text.h"

namespace kdrt::proto {
namespace {

using detail::store_le_f32;

struct MdCtxDeleter {
    void operator()(EVP_MD_CTX* ctx) const noexcept { EVP_MD_CTX_free(ctx); }
};

/// Incremental SHA-256 over OpenSSL's EVP interface.
class Sha256 {
public:
    Sha256() : ctx_(EVP_MD_CTX_new()) {
        if (!ctx_ || EVP_DigestInit_ex(ctx_.get(), EVP_sha256(), nullptr) != 1)
            throw std::runtime_error("OpenSSL: cannot initialise SHA-256");
    }
    void update(const void* data, size_t size) {
        if (EVP_DigestUpdate(ctx_.get(), data, size) != 1)
            throw std::runtime_error("OpenSSL: SHA-256 update failed");
    }
    std::string hex_digest() {
        std::array<unsigned char, EVP_MAX_MD_SIZE> digest{};
        unsigned int length = 0;
        if (EVP_DigestFinal_ex(ctx_.get(), digest.data(), &length) != 1)
            throw std::runtime_error("OpenSSL: SHA-256 final failed");
        std::string out;
        append_hex(out, std::span<const unsigned char>(digest.data(), length));
        return out;
    }

private:
    std::unique_ptr<EVP_MD_CTX, MdCtxDeleter> ctx_;
};

/// Writes the canonical bytes of triangles [first, first + count) to `out`.
void write_triangles(const Mesh& mesh, size_t first, size_t count, std::byte* out) {
    const size_t vertex_count = mesh.vertex_count();
    for (size_t t = first; t < first + count; ++t) {
        for (int c = 0; c < 3; ++c) {
            const uint32_t index = mesh.indices[3 * t + static_cast<size_t>(c)];
            if (index >= vertex_count)
                throw std::invalid_argument("mesh_id: triangle " + std::to_string(t) + " corner " +
                                            std::to_string(c) + " has index " +
                                            std::to_string(index) + " >= vertex count " +
                                            std::to_string(vertex_count));
            for (int a = 0; a < 3; ++a) {
                store_le_f32(
                    out, mesh.positions[3 * static_cast<size_t>(index) + static_cast<size_t>(a)]);
                out += 4;
            }
        }
    }
}

}  // namespace

std::vector<std::byte> canonical_triangles(const Mesh& mesh) {
    std::vector<std::byte> out(mesh.triangle_count() * kCanonicalTriangleBytes);
    write_triangles(mesh, 0, mesh.triangle_count(), out.data());
    return out;
}

std::string mesh_id(const Mesh& mesh) {
    // 1820 triangles = 65520 bytes per block: cache-resident, few EVP calls.
    constexpr size_t kBlockTriangles = 1820;
    std::vector<std::byte> block(kBlockTriangles * kCanonicalTriangleBytes);
    Sha256 sha;
    const size_t total = mesh.triangle_count();
    for (size_t first = 0; first < total; first += kBlockTriangles) {
        const size_t count = std::min(kBlockTriangles, total - first);
        write_triangles(mesh, first, count, block.data());
        sha.update(block.data(), count * kCanonicalTriangleBytes);
    }
    return sha.hex_digest();
}

std::string sha256_hex(std::span<const std::byte> data) {
    Sha256 sha;
    sha.update(data.data(), data.size());
    return sha.hex_digest();
}

}  // namespace kdrt::proto
