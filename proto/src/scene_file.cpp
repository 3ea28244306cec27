// KDRS, the binary form of a stored scene revision (the server's scenes/<id>/<revision>.json
// files; proto/FORMATS.md "Stored scene revisions").

#include <algorithm>
#include <bit>
#include <cmath>
#include <cstring>
#include <optional>
#include <string>
#include <unordered_map>
#include <unordered_set>

#include "byte_io.h"
#include "kdrt/proto/mesh_id.h"
#include "kdrt/proto/scene.h"

namespace kdrt::proto {
namespace {

constexpr size_t kHeaderBytes = 64;
constexpr size_t kMeshIdBytes = 64;
constexpr size_t kChecksumBytes = 8;
/// Bytes per instance besides its name: u32 mesh index, 12 f32, u8 name length.
constexpr uint64_t kInstanceBytes = 4 + 48 + 1;

uint64_t load_le64(const std::byte* p) noexcept { return detail::load_uint<uint64_t>(p, false); }
void store_le64(std::byte* p, uint64_t v) noexcept { detail::store_uint(p, v, false); }

}  // namespace

uint64_t scene_file_checksum(std::span<const std::byte> bytes) noexcept {
    // The tree blob's checksum (FORMATS.md "Tree blob"): 8-byte words, then the zero-padded tail.
    constexpr uint64_t kMul1 = 0xC2B2AE3D27D4EB4Full, kMul2 = 0x9E3779B97F4A7C15ull;
    uint64_t h = kMul2 ^ bytes.size();
    size_t i = 0;
    for (; i + 8 <= bytes.size(); i += 8)
        h = std::rotl(h ^ (load_le64(&bytes[i]) * kMul1), 31) * kMul2;
    std::byte tail[8] = {};
    std::memcpy(tail, bytes.data() + i, bytes.size() - i);
    h = std::rotl(h ^ (load_le64(tail) * kMul1), 31) * kMul2;
    h ^= h >> 33;
    h *= 0xFF51AFD7ED558CCDull;
    h ^= h >> 33;
    return h;
}

namespace {

/// KDRS of `scene` under revision `revision`, every byte but the checksum written; returns the
/// offset of the transform plane (instance i's 12 floats at that + 48 i).
size_t encode_without_checksum(const SceneDocument& scene, uint64_t revision,
                               std::vector<std::byte>& out) {
    const size_t n = scene.instances.size();
    std::vector<std::string_view> meshes;
    std::vector<uint32_t> mesh_index(n);
    std::unordered_map<std::string_view, uint32_t> index_of;
    uint64_t name_bytes = 0;
    for (size_t i = 0; i < n; ++i) {
        const SceneInstanceSpec& inst = scene.instances[i];
        name_bytes += inst.name.size();
        // Runs of one mesh (the common case: many placements of one model) skip the hash.
        if (i > 0 && inst.mesh == scene.instances[i - 1].mesh) {
            mesh_index[i] = mesh_index[i - 1];
            continue;
        }
        const auto [it, added] =
            index_of.try_emplace(inst.mesh, static_cast<uint32_t>(meshes.size()));
        if (added) meshes.push_back(inst.mesh);
        mesh_index[i] = it->second;
    }
    const size_t size = kHeaderBytes + kMeshIdBytes * meshes.size() + kInstanceBytes * n +
                        name_bytes + kChecksumBytes;
    out.resize(size);
    std::byte* p = out.data();
    std::memcpy(p, kSceneFileMagic.data(), 4);
    detail::store_le16(p + 4, kSceneFileVersion);
    detail::store_le16(p + 6, 0);
    store_le64(p + 8, revision);
    std::memcpy(p + 16, scene.id.data(), std::min(scene.id.size(), kSceneIdLength));
    detail::store_le32(p + 48, static_cast<uint32_t>(n));
    detail::store_le32(p + 52, static_cast<uint32_t>(meshes.size()));
    detail::store_le32(p + 56, static_cast<uint32_t>(name_bytes));
    detail::store_le32(p + 60, 0);
    p += kHeaderBytes;
    for (const std::string_view mesh : meshes) {
        std::memcpy(p, mesh.data(), std::min(mesh.size(), kMeshIdBytes));
        p += kMeshIdBytes;
    }
    for (size_t i = 0; i < n; ++i, p += 4) detail::store_le32(p, mesh_index[i]);
    const size_t transforms_at = static_cast<size_t>(p - out.data());
    for (const SceneInstanceSpec& inst : scene.instances)
        for (const float v : inst.transform.m) {
            detail::store_le_f32(p, v);
            p += 4;
        }
    for (const SceneInstanceSpec& inst : scene.instances)
        *p++ = static_cast<std::byte>(inst.name.size());
    for (const SceneInstanceSpec& inst : scene.instances) {
        std::memcpy(p, inst.name.data(), inst.name.size());
        p += inst.name.size();
    }
    return transforms_at;
}

void seal(std::vector<std::byte>& out) {
    const size_t body = out.size() - kChecksumBytes;
    store_le64(out.data() + body, scene_file_checksum(std::span<const std::byte>(out).first(body)));
}

}  // namespace

std::vector<std::byte> encode_scene_file(const SceneDocument& scene) {
    std::vector<std::byte> out;
    encode_without_checksum(scene, scene.revision, out);
    seal(out);
    return out;
}

std::vector<std::byte> encode_scene_file(const SceneDocument& base, uint64_t revision,
                                         std::span<const ResolvedPose> poses) {
    std::vector<std::byte> out;
    const size_t transforms_at = encode_without_checksum(base, revision, out);
    // In order, so a later entry for one instance overwrites an earlier one (as applied to a
    // document).
    for (const ResolvedPose& pose : poses) {
        std::byte* p = out.data() + transforms_at + 48 * size_t{pose.geometry_id};
        for (const float v : pose.transform.m) {
            detail::store_le_f32(p, v);
            p += 4;
        }
    }
    seal(out);
    return out;
}

namespace {

/// The checks of a KDRS header's fixed fields (magic, version, flags, reserved), shared by the
/// header read and the whole file's decode: the error naming the field's offset, or nothing.
std::optional<std::string> fixed_field_error(const std::byte* b) {
    if (std::memcmp(b, kSceneFileMagic.data(), 4) != 0)
        return "offset 0: the magic is not \"KDRS\"";
    if (const uint16_t v = detail::load_le16(b + 4); v != kSceneFileVersion)
        return "offset 4: version " + std::to_string(v) + ", this build reads version " +
               std::to_string(kSceneFileVersion);
    if (detail::load_le16(b + 6) != 0) return "offset 6: flags must be 0";
    if (detail::load_le32(b + 60) != 0) return "offset 60: reserved must be 0";
    return std::nullopt;
}

}  // namespace

Result<SceneFileHeader, std::string> read_scene_file_header(std::span<const std::byte> header) {
    static_assert(kSceneFileHeaderBytes == kHeaderBytes);
    const auto at = [](uint64_t offset, const std::string& what) {
        return Err{"offset " + std::to_string(offset) + ": " + what};
    };
    if (header.size() < kHeaderBytes)
        return Err{std::to_string(header.size()) + " bytes is shorter than a KDRS header (" +
                   std::to_string(kHeaderBytes) + ")"};
    const std::byte* b = header.data();
    if (auto error = fixed_field_error(b)) return Err{*std::move(error)};
    SceneFileHeader out;
    out.revision = load_le64(b + 8);
    if (out.revision == 0) return at(8, "revision must be >= 1");
    const uint64_t n = detail::load_le32(b + 48);
    const uint64_t meshes = detail::load_le32(b + 52);
    if (meshes > n || (n > 0 && meshes == 0))
        return at(52, std::to_string(meshes) + " meshes for " + std::to_string(n) + " instances");
    out.size = kHeaderBytes + kMeshIdBytes * meshes + kInstanceBytes * n +
               detail::load_le32(b + 56) + kChecksumBytes;
    return out;
}

bool scene_file_checksum_matches(std::span<const std::byte> bytes) noexcept {
    if (bytes.size() < kHeaderBytes + kChecksumBytes) return false;
    const size_t body = bytes.size() - kChecksumBytes;
    return load_le64(bytes.data() + body) == scene_file_checksum(bytes.first(body));
}

Result<SceneDocument, std::string> decode_scene_file(std::span<const std::byte> bytes) {
    const auto at = [](uint64_t offset, const std::string& what) {
        return Err{"offset " + std::to_string(offset) + ": " + what};
    };
    if (bytes.size() < kHeaderBytes + kChecksumBytes)
        return Err{std::to_string(bytes.size()) +
                   " bytes is shorter than a KDRS header and checksum (" +
                   std::to_string(kHeaderBytes + kChecksumBytes) + ")"};
    const std::byte* b = bytes.data();
    if (auto error = fixed_field_error(b)) return Err{*std::move(error)};
    const uint64_t n = detail::load_le32(b + 48);
    const uint64_t meshes = detail::load_le32(b + 52);
    const uint64_t name_bytes = detail::load_le32(b + 56);
    const uint64_t expected =
        kHeaderBytes + kMeshIdBytes * meshes + kInstanceBytes * n + name_bytes + kChecksumBytes;
    if (expected != bytes.size())
        return at(48, std::to_string(n) + " instances, " + std::to_string(meshes) + " meshes and " +
                          std::to_string(name_bytes) + " name bytes make " +
                          std::to_string(expected) + " bytes, but the file has " +
                          std::to_string(bytes.size()));
    const size_t body = bytes.size() - kChecksumBytes;
    if (load_le64(b + body) != scene_file_checksum(bytes.first(body)))
        return at(body, "checksum mismatch (the file is damaged)");

    SceneDocument doc;
    doc.revision = load_le64(b + 8);
    if (doc.revision == 0) return at(8, "revision must be >= 1");
    doc.id.assign(reinterpret_cast<const char*>(b + 16), kSceneIdLength);
    if (!is_scene_id(doc.id)) return at(16, "the scene id is not 32 lower-case hex digits");
    if (meshes > n || (n > 0 && meshes == 0))
        return at(52, std::to_string(meshes) + " meshes for " + std::to_string(n) + " instances");
    std::vector<std::string> mesh_ids(meshes);
    uint64_t offset = kHeaderBytes;
    {
        std::unordered_set<std::string_view> seen;
        for (uint64_t m = 0; m < meshes; ++m, offset += kMeshIdBytes) {
            mesh_ids[m].assign(reinterpret_cast<const char*>(b + offset), kMeshIdBytes);
            if (!is_mesh_id(mesh_ids[m]))
                return at(offset, "mesh " + std::to_string(m) + " is not a mesh id");
            if (!seen.insert(mesh_ids[m]).second)
                return at(offset, "mesh " + std::to_string(m) + " is listed twice");
        }
    }
    const uint64_t index_at = offset, transform_at = index_at + 4 * n,
                   length_at = transform_at + 48 * n;
    uint64_t name_at = length_at + n;
    doc.instances.resize(n);
    std::unordered_set<std::string_view> names;
    for (uint64_t i = 0; i < n; ++i) {
        SceneInstanceSpec& inst = doc.instances[i];
        const uint32_t m = detail::load_le32(b + index_at + 4 * i);
        if (m >= meshes)
            return at(index_at + 4 * i, "instance " + std::to_string(i) + ": mesh index " +
                                            std::to_string(m) + " of " + std::to_string(meshes));
        inst.mesh = mesh_ids[m];
        for (size_t k = 0; k < 12; ++k) {
            const uint64_t o = transform_at + 48 * i + 4 * k;
            inst.transform.m[k] = detail::load_le_f32(b + o);
            if (!std::isfinite(inst.transform.m[k]))
                return at(o, "instance " + std::to_string(i) + ": transform[" +
                                 std::to_string(k / 4) + "][" + std::to_string(k % 4) +
                                 "] is not finite");
        }
        const auto length = static_cast<uint8_t>(b[length_at + i]);
        if (length > 0) {
            if (name_at + length > body)
                return at(length_at + i,
                          "instance " + std::to_string(i) + ": its name runs past the name bytes");
            inst.name.assign(reinterpret_cast<const char*>(b + name_at), length);
            if (!is_instance_name(inst.name) || !names.insert(inst.name).second)
                return at(name_at, "instance " + std::to_string(i) +
                                       ": the name is not a valid instance name or is repeated");
            name_at += length;
        }
    }
    if (name_at != body)
        return at(name_at, "the name lengths add up to " + std::to_string(name_at - length_at - n) +
                               " bytes, the header says " + std::to_string(name_bytes));
    return doc;
}

}  // namespace kdrt::proto
