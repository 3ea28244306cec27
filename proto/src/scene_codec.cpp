// Scenes: the KDRX pose batch, the geometry-id plane of scene answers, and the JSON-free scene
// logic (resolving poses, applying an instance edit).

#include <algorithm>
#include <cmath>
#include <cstring>
#include <stdexcept>
#include <string>
#include <unordered_map>
#include <unordered_set>

#include "byte_io.h"
#include "kdrt/proto/scene.h"
#include "kdrt/proto/text.h"
#include "ray_batch_checks.h"

namespace kdrt::proto {
namespace {

inline constexpr detail::BatchKind kPoses{kPoseBatchMagic, kPoseRecordBytes, 0, "pose", "poses"};

[[nodiscard]] DecodeError error(DecodeErrorCode code, std::string detail) {
    return DecodeError{code, std::move(detail)};
}

[[nodiscard]] std::string entry_name(size_t k) {
    return "transform[" + std::to_string(k / 4) + "][" + std::to_string(k % 4) + "]";
}

[[nodiscard]] SceneRequestError reference_error(std::string field, uint32_t index,
                                                std::string detail) {
    SceneRequestError e;
    e.field = std::move(field);
    e.index = index;
    e.detail = std::move(detail);
    e.unknown_reference = true;
    return e;
}

}  // namespace

bool is_scene_id(std::string_view text) noexcept {
    if (text.size() != kSceneIdLength) return false;
    for (const char c : text)
        if (!((c >= '0' && c <= '9') || (c >= 'a' && c <= 'f'))) return false;
    return true;
}

bool is_instance_name(std::string_view text) noexcept {
    if (text.empty() || text.size() > kMaxInstanceNameLength) return false;
    for (const char c : text) {
        const bool ok = (c >= '0' && c <= '9') || (c >= 'a' && c <= 'z') ||
                        (c >= 'A' && c <= 'Z') || c == '.' || c == '_' || c == ':' || c == '/' ||
                        c == '-';
        if (!ok) return false;
    }
    return true;
}

// ---- KDRX ---------------------------------------------------------------------------------------

std::vector<std::byte> encode_pose_batch(std::span<const PoseEntry> poses) {
    std::vector<std::byte> out(kBatchHeaderBytes + kPoseRecordBytes * poses.size());
    std::memcpy(out.data(), kPoseBatchMagic.data(), 4);
    detail::store_le16(out.data() + 4, kBatchVersion);
    detail::store_le16(out.data() + 6, 0);
    detail::store_le32(out.data() + 8, static_cast<uint32_t>(poses.size()));
    detail::store_le32(out.data() + 12, 0);
    std::byte* p = out.data() + kBatchHeaderBytes;
    for (const PoseEntry& pose : poses) {
        detail::store_le32(p, pose.geometry_id.value_or(kNoGeometry));
        for (size_t k = 0; k < 12; ++k) detail::store_le_f32(p + 4 + 4 * k, pose.transform.m[k]);
        p += kPoseRecordBytes;
    }
    return out;
}

Result<std::vector<PoseEntry>, DecodeError> decode_pose_batch(std::span<const std::byte> body,
                                                              const SceneLimits& limits) {
    DecodeLimits batch;
    batch.max_rays = limits.max_instances;
    auto header = detail::check_header(body, kPoses, batch);
    if (!header) return Err{std::move(header).error()};
    std::vector<PoseEntry> poses(header->count);
    const std::byte* p = body.data() + kBatchHeaderBytes;
    for (size_t i = 0; i < poses.size(); ++i, p += kPoseRecordBytes) {
        poses[i].geometry_id = detail::load_le32(p);
        for (size_t k = 0; k < 12; ++k) {
            const float v = detail::load_le_f32(p + 4 + 4 * k);
            if (!std::isfinite(v))
                return Err{error(DecodeErrorCode::kNonFiniteRay, "pose " + std::to_string(i) +
                                                                     ": " + entry_name(k) + " is " +
                                                                     non_finite_name(v))};
            poses[i].transform.m[k] = v == 0.0f ? 0.0f : v;  // -0 reads as 0, as in the JSON
        }
    }
    return poses;
}

// ---- Resolving and editing ----------------------------------------------------------------------

Result<std::vector<ResolvedPose>, SceneRequestError> resolve_poses(
    const SceneDocument& scene, std::span<const PoseEntry> poses) {
    std::unordered_map<std::string_view, uint32_t> by_name;
    for (size_t g = 0; g < scene.instances.size(); ++g)
        if (!scene.instances[g].name.empty())
            by_name.emplace(scene.instances[g].name, static_cast<uint32_t>(g));
    std::vector<ResolvedPose> out;
    out.reserve(poses.size());
    for (size_t i = 0; i < poses.size(); ++i) {
        const PoseEntry& pose = poses[i];
        // Spelled out only for an error (a batch may hold every instance's pose).
        const auto at = [i] { return "poses[" + std::to_string(i) + "]"; };
        const auto index = static_cast<uint32_t>(i);
        if (pose.geometry_id) {
            if (*pose.geometry_id >= scene.instances.size())
                return Err{reference_error(
                    at() + ".geometry_id", index,
                    in_quotes(at() + ".geometry_id") + " is " + std::to_string(*pose.geometry_id) +
                        ", but the scene has " + std::to_string(scene.instances.size()) +
                        " instances (geometry ids 0 .. n-1)")};
            out.push_back({*pose.geometry_id, pose.transform});
        } else {
            const auto it = by_name.find(pose.name);
            if (it == by_name.end())
                return Err{reference_error(at() + ".name", index,
                                           in_quotes(at() + ".name") + " is " +
                                               in_quotes(pose.name) +
                                               ", which names no instance of the scene")};
            out.push_back({it->second, pose.transform});
        }
    }
    return out;
}

Result<SceneDocument, SceneRequestError> apply_instance_edit(const SceneDocument& scene,
                                                             const InstanceEdit& edit,
                                                             const SceneLimits& limits) {
    const size_t n = scene.instances.size();
    std::unordered_map<std::string_view, uint32_t> by_name;
    for (size_t g = 0; g < n; ++g)
        if (!scene.instances[g].name.empty())
            by_name.emplace(scene.instances[g].name, static_cast<uint32_t>(g));
    std::vector<bool> removed(n, false);
    for (size_t i = 0; i < edit.remove.size(); ++i) {
        const std::string at = "remove[" + std::to_string(i) + "]";
        const auto index = static_cast<uint32_t>(i);
        uint32_t g = 0;
        if (const auto* id = std::get_if<uint32_t>(&edit.remove[i])) {
            if (*id >= n)
                return Err{reference_error(at, index,
                                           in_quotes(at) + " is geometry id " +
                                               std::to_string(*id) + ", but the scene has " +
                                               std::to_string(n) + " instances")};
            g = *id;
        } else {
            const std::string& name = std::get<std::string>(edit.remove[i]);
            const auto it = by_name.find(name);
            if (it == by_name.end())
                return Err{reference_error(at, index,
                                           in_quotes(at) + " is " + in_quotes(name) +
                                               ", which names no instance of the scene")};
            g = it->second;
        }
        if (removed[g]) {
            SceneRequestError e;
            e.field = at;
            e.index = index;
            e.detail = in_quotes(at) + " removes geometry id " + std::to_string(g) +
                       ", which an earlier entry already removes";
            return Err{std::move(e)};
        }
        removed[g] = true;
    }
    const size_t kept = n - static_cast<size_t>(std::count(removed.begin(), removed.end(), true));
    if (kept + edit.add.size() > limits.max_instances) {
        SceneRequestError e;
        e.field = "add";
        e.detail = "the scene would have " + std::to_string(kept + edit.add.size()) +
                   " instances, more than max_instances (" + std::to_string(limits.max_instances) +
                   ")";
        e.over_limit = true;
        return Err{std::move(e)};
    }
    SceneDocument out;
    out.id = scene.id;
    out.revision = scene.revision;
    out.instances.reserve(kept + edit.add.size());
    std::unordered_set<std::string_view> names;
    for (size_t g = 0; g < n; ++g)
        if (!removed[g]) {
            out.instances.push_back(scene.instances[g]);
            if (!scene.instances[g].name.empty()) names.insert(scene.instances[g].name);
        }
    for (size_t i = 0; i < edit.add.size(); ++i) {
        const std::string& name = edit.add[i].name;
        if (!name.empty() && !names.insert(name).second) {
            SceneRequestError e;
            e.field = "add[" + std::to_string(i) + "].name";
            e.index = static_cast<uint32_t>(i);
            e.detail = in_quotes(e.field) + " is " + in_quotes(name) +
                       ", which another instance of the scene already has";
            return Err{std::move(e)};
        }
    }
    out.instances.insert(out.instances.end(), edit.add.begin(), edit.add.end());
    return out;
}

// ---- The geometry-id plane ----------------------------------------------------------------------

namespace {

/// The header size and record count of a mesh answer body, or an error.
struct PlaneShape {
    size_t header_bytes = 0;
    uint64_t records = 0;
};

Result<PlaneShape, DecodeError> plane_shape(std::span<const std::byte> body,
                                            const DecodeLimits& limits) {
    if (body.size() < kBatchHeaderBytes)
        return Err{error(DecodeErrorCode::kTooShort, "body has " + std::to_string(body.size()) +
                                                         " bytes, less than the 16-byte header")};
    const std::string_view magic(reinterpret_cast<const char*>(body.data()), 4);
    PlaneShape shape;
    shape.header_bytes = kBatchHeaderBytes;
    if (magic == "KDRH" || magic == "KDRD" || magic == "KDRL" || magic == "KDRB") {
        shape.records = detail::load_le32(body.data() + 8);
        if (magic == "KDRL" || magic == "KDRB") shape.header_bytes = 32;
    } else if (magic == "KDRZ") {
        shape.records =
            uint64_t{detail::load_le32(body.data() + 8)} * detail::load_le32(body.data() + 12);
    } else if (magic == "KDRM") {
        shape.header_bytes = 32;
        if (body.size() < shape.header_bytes)
            return Err{
                error(DecodeErrorCode::kTooShort, "body has " + std::to_string(body.size()) +
                                                      " bytes, less than the 32-byte KDRM header")};
        shape.records = detail::load_uint<uint64_t>(body.data() + 16, false);
    } else {
        std::string shown;
        for (const char c : magic) shown += (c >= 0x20 && c < 0x7F) ? c : '?';
        return Err{
            error(DecodeErrorCode::kBadMagic,
                  "bad magic \"" + shown + "\", expected KDRH, KDRM, KDRD, KDRZ, KDRL or KDRB")};
    }
    if (body.size() < shape.header_bytes)
        return Err{error(DecodeErrorCode::kTooShort,
                         "body has " + std::to_string(body.size()) + " bytes, less than the " +
                             std::to_string(shape.header_bytes) + "-byte header")};
    if ((detail::load_le16(body.data() + 6) & kGeometryIdFlag) == 0)
        return Err{error(DecodeErrorCode::kBadFlags,
                         "flag bit 8 (geometry ids) is not set: not a scene answer")};
    if (shape.records > limits.max_rays)
        return Err{error(DecodeErrorCode::kTooManyRays,
                         "header says " + std::to_string(shape.records) + " records, limit is " +
                             std::to_string(limits.max_rays))};
    return shape;
}

}  // namespace

void append_geometry_ids(std::vector<std::byte>& body, std::span<const uint32_t> geometry_ids) {
    const size_t at = body.size();
    body.resize(at + geometry_id_plane_bytes(geometry_ids.size()));
    write_geometry_ids(body, at, geometry_ids);
}

size_t write_geometry_ids(std::span<std::byte> out, size_t mesh_bytes,
                          std::span<const uint32_t> geometry_ids) {
    const size_t size = mesh_bytes + geometry_id_plane_bytes(geometry_ids.size());
    if (mesh_bytes < 8 || out.size() < size)
        throw std::length_error(
            "write_geometry_ids: no mesh answer header or no room for the plane");
    const uint16_t flags = detail::load_le16(out.data() + 6);
    detail::store_le16(out.data() + 6, static_cast<uint16_t>(flags | kGeometryIdFlag));
    if (!geometry_ids.empty())  // an empty vector's data() may be null, which memcpy may not take
        std::memcpy(out.data() + mesh_bytes, geometry_ids.data(), 4 * geometry_ids.size());
    return size;
}

Result<SplitAnswer, DecodeError> split_geometry_ids(std::span<const std::byte> body,
                                                    const DecodeLimits& limits) {
    auto shape = plane_shape(body, limits);
    if (!shape) return Err{std::move(shape).error()};
    const uint64_t plane = geometry_id_plane_bytes(shape->records);
    if (body.size() < shape->header_bytes + plane)
        return Err{error(DecodeErrorCode::kLengthMismatch,
                         "header says " + std::to_string(shape->records) +
                             " records, so a geometry-id plane of " + std::to_string(plane) +
                             " bytes, but the body has " + std::to_string(body.size()) + " bytes")};
    SplitAnswer out;
    const size_t mesh_bytes = body.size() - plane;
    out.mesh_body.assign(body.begin(), body.begin() + static_cast<std::ptrdiff_t>(mesh_bytes));
    const uint16_t flags = detail::load_le16(out.mesh_body.data() + 6);
    detail::store_le16(out.mesh_body.data() + 6, static_cast<uint16_t>(flags & ~kGeometryIdFlag));
    out.geometry_ids.resize(shape->records);
    if (plane != 0)  // no records: geometry_ids.data() may be null, which memcpy may not take
        std::memcpy(out.geometry_ids.data(), body.data() + mesh_bytes, plane);
    return out;
}

}  // namespace kdrt::proto
