#pragma once
/// Scenes on the wire: the JSON of a scene (POST /v1/scenes, GET /v1/scenes/{id}, the stored
/// revision files), of a batch pose update and of an instance edit; KDRX, the binary pose batch;
/// and the geometry-id plane that turns every mesh answer format (KDRH, KDRM, KDRD, KDRZ, KDRL,
/// KDRB) into its scene form. Layouts and worked hex examples: proto/FORMATS.md, "Scenes".
///
/// proto keeps its own value types here (Transform, SceneDocument) instead of including
/// kdrt/scene.h, which declares engine functions: a client that installs proto sees value types
/// only. Transform's 12 floats are the engine's Affine3x4 row by row (the server copies them).
///
/// Thread-safe, no shared state; decoders return an error naming the first problem (for JSON:
/// the instance or pose index and the field, "instances[3].transform[1][2]") and never throw on
/// bad input; encoders may throw std::bad_alloc.

#include <array>
#include <cstddef>
#include <cstdint>
#include <optional>
#include <span>
#include <string>
#include <string_view>
#include <variant>
#include <vector>

#include "kdrt/proto/ray_batch_header.h"
#include "kdrt/proto/result.h"

namespace kdrt::proto {

inline constexpr std::string_view kSceneMediaType = "application/json";
inline constexpr std::string_view kPoseBatchMagic = "KDRX";
inline constexpr std::string_view kPoseBatchMediaType = "application/x-kdrt-poses";
/// KDRX record: u32 geometry id, then the 12 transform entries (f32, row-major 3 x 4).
inline constexpr size_t kPoseRecordBytes = 52;
/// The flag bit (offset 6 of every answer header) saying a geometry-id plane ends the body.
inline constexpr uint16_t kGeometryIdFlag = 0x0100;
/// The geometry id of a miss (and of a KDRD record that found nothing): kdrt::kNoHit.
inline constexpr uint32_t kNoGeometry = 0xFFFFFFFFu;
/// A scene id: 32 lower-case hex digits (128 random bits). Mesh ids have 64.
inline constexpr size_t kSceneIdLength = 32;
/// An instance name: 1 .. 128 characters from [A-Za-z0-9._:/-].
inline constexpr size_t kMaxInstanceNameLength = 128;

[[nodiscard]] bool is_scene_id(std::string_view text) noexcept;
/// True for a valid instance name (the rule above).
[[nodiscard]] bool is_instance_name(std::string_view text) noexcept;

/// An affine object-to-world transform, row-major 3 x 4: world = L * object + t, L = m[4r + c]
/// for c < 3, t = (m[3], m[7], m[11]). Default: the identity.
struct Transform {
    std::array<float, 12> m{1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0};
    friend bool operator==(const Transform&, const Transform&) = default;
};

/// One instance of a scene: its mesh (a mesh id), its pose and an optional name (empty: none).
/// Its geometry id is its index in SceneDocument::instances.
struct SceneInstanceSpec {
    std::string mesh;
    Transform transform;
    std::string name;
    friend bool operator==(const SceneInstanceSpec&, const SceneInstanceSpec&) = default;
};

/// A scene revision. `id` and `revision` are empty / 0 in a create request.
struct SceneDocument {
    std::string id;
    uint64_t revision = 0;
    std::vector<SceneInstanceSpec> instances;
    friend bool operator==(const SceneDocument&, const SceneDocument&) = default;
};

/// The server's caps, checked while parsing and before the instances are decoded.
struct SceneLimits {
    uint32_t max_instances = 65536;  ///< max_instances: instances of one scene (and poses a batch)
};

/// A refused scene request: `field` names the member as the request spells it
/// ("instances[3].transform[1][2]", "poses[0].geometry_id", "remove[2]", "instances"; empty for a
/// syntax error); `index` the instance or pose entry when there is one; `detail` says what is
/// wrong; `over_limit` when a server limit was exceeded (HTTP 413); `unknown_reference` when a
/// geometry id or name names no instance of the scene (HTTP 422 naming it, like an unknown mesh).
struct SceneRequestError {
    std::string field;
    std::optional<uint32_t> index;
    std::string detail;
    bool over_limit = false;
    bool unknown_reference = false;
};

/// POST /v1/scenes:
///
///   {"instances": [{"mesh": "<64 hex digits>", "transform": [1,0,0,0, 0,1,0,0, 0,0,1,2],
///                   "name": "shelf-1"}, ...]}
///
/// "instances" (required, 0 .. limits.max_instances entries, counted before any is decoded);
/// each: "mesh" (required, a mesh id: 64 lower-case hex digits), "transform" (default the
/// identity; 12 numbers row-major, 3 rows of 4, or 4 rows of 4 whose last row is 0 0 0 1; every
/// entry finite and within float range), "name" (optional, is_instance_name, unique in the
/// scene). Whether the mesh exists and whether L is invertible are the caller's checks (the store
/// and kdrt::build_scene, which name the instance too). Strict JSON (unknown or duplicate members
/// refused). With `stored` the document may also carry "id", "revision", each instance's
/// "geometry_id" (its index) and "format": "kdrt-scene" (what encode_scene_json writes).
[[nodiscard]] Result<SceneDocument, SceneRequestError> decode_scene_json(
    std::string_view text, const SceneLimits& limits = {}, bool stored = false);
/// A create request for `instances` (POST /v1/scenes): {"instances": [{"mesh", "transform" (12
/// numbers), "name" (when set)}]}, which decode_scene_json reads back equal.
[[nodiscard]] std::string encode_scene_request(std::span<const SceneInstanceSpec> instances);
/// The document as JSON: {"format": "kdrt-scene", "id", "revision", "instances": [{"geometry_id",
/// "mesh", "transform" (12 numbers), "name" (when set)}]}; floats printed so they read back to
/// the same float. decode_scene_json(text, limits, true) reads it back equal.
[[nodiscard]] std::string encode_scene_json(const SceneDocument& scene);

/// KDRS, a stored scene revision (the server's revision files; FORMATS.md "Stored scene
/// revisions"): a 64-byte header (magic, version, flags 0, revision, scene id, instance, mesh and
/// name byte counts), each distinct mesh id once, then per instance planes of u32 mesh indices,
/// 12 f32 transforms and u8 name lengths, the names, and a u64 checksum of every byte before it.
inline constexpr std::string_view kSceneFileMagic = "KDRS";
inline constexpr uint16_t kSceneFileVersion = 1;
/// `scene` as KDRS (id and revision set; names valid, as every stored document's are).
[[nodiscard]] std::vector<std::byte> encode_scene_file(const SceneDocument& scene);
/// Reads KDRS back: the exact size, the checksum, every mesh id, mesh index, transform entry
/// (finite) and name (valid, unique); no instance limit (a stored revision stays readable under
/// a lower max_instances). The error names the byte offset and what is wrong there.
[[nodiscard]] Result<SceneDocument, std::string> decode_scene_file(
    std::span<const std::byte> bytes);
/// The checksum at the end of a KDRS file (the tree blob's, FORMATS.md "Tree blob").
[[nodiscard]] uint64_t scene_file_checksum(std::span<const std::byte> bytes) noexcept;
/// What the first kSceneFileHeaderBytes of a KDRS say, read without the rest: its revision and
/// its whole size in bytes (64 + 64 M + 53 N + B + 8). Lets a reader walk a file of KDRS
/// records back to back (the server's scene revision log, FORMATS.md "Scene revision log").
struct SceneFileHeader {
    uint64_t revision = 0;
    uint64_t size = 0;
};
inline constexpr size_t kSceneFileHeaderBytes = 64;
/// The header of the KDRS starting at `header` (at least kSceneFileHeaderBytes): the magic,
/// version 1, flags and reserved 0, revision >= 1, distinct meshes <= instances. Checks no
/// mesh id, name or checksum (decode_scene_file does). The error names the offset.
[[nodiscard]] Result<SceneFileHeader, std::string> read_scene_file_header(
    std::span<const std::byte> header);
/// True when `bytes` (a whole KDRS, as sized by its header) ends with the checksum of the rest.
[[nodiscard]] bool scene_file_checksum_matches(std::span<const std::byte> bytes) noexcept;
/// A stored revision file in either form: KDRS, or the JSON of encode_scene_json that stores
/// written before KDRS hold (told apart by the first byte). The error says which form and what.
[[nodiscard]] Result<SceneDocument, std::string> decode_stored_scene(
    std::span<const std::byte> bytes);

/// One scene of GET /v1/scenes.
struct SceneListItem {
    std::string id;
    uint64_t revision = 0;
    uint64_t instances = 0;
};
/// {"scenes": [{"id", "revision", "instances"}, ...]}.
[[nodiscard]] std::string encode_scene_list(std::span<const SceneListItem> scenes);
/// {"id", "revision", "instances"}: the answer to a pose update (small, whatever the scene's size).
[[nodiscard]] std::string encode_scene_revision(const SceneListItem& scene);
/// Reads encode_scene_list's document back (a client's GET /v1/scenes); the error says what is
/// wrong and where ("scenes[2]: \"revision\" is not an integer >= 1"). Unknown members are
/// ignored, so a newer server may add some.
[[nodiscard]] Result<std::vector<SceneListItem>, std::string> decode_scene_list(
    std::string_view text);
/// Reads encode_scene_revision's document back (the answer to a pose update).
[[nodiscard]] Result<SceneListItem, std::string> decode_scene_revision(std::string_view text);

/// One entry of a pose update: the instance by geometry id or by name (exactly one), and its pose.
struct PoseEntry {
    std::optional<uint32_t> geometry_id;
    std::string name;
    Transform transform;
};

/// PATCH /v1/scenes/{id}/poses:
///
///   {"poses": [{"geometry_id": 3, "transform": [...]}, {"name": "car", "transform": [...]}]}
///
/// "poses" required, 1 .. limits.max_instances entries; each with exactly one of "geometry_id"
/// (an integer) and "name", and "transform" (required, as above). Later entries for the same
/// instance win.
[[nodiscard]] Result<std::vector<PoseEntry>, SceneRequestError> decode_pose_json(
    std::string_view text, const SceneLimits& limits = {});
[[nodiscard]] std::string encode_pose_json(std::span<const PoseEntry> poses);

/// The scene text file (`kdrt scene create FILE`): one instance a line,
///
///   MESH [T] [NAME]
///
/// MESH a mesh id (64 lower-case hex digits); T the transform as 12 numbers (row-major 3 x 4, as
/// in the JSON) or 3 (a translation), none for the identity; NAME an instance name
/// (is_instance_name, unique). Fields are separated by spaces, tabs or commas; blank lines and
/// lines starting with '#' are skipped. The instances' order is their geometry ids'. Errors name
/// the line and field ("line 3: transform entry 5 \"1e40\" is not a finite float"); more than
/// limits.max_instances instances is refused as such.
[[nodiscard]] Result<std::vector<SceneInstanceSpec>, std::string> parse_scene_text(
    std::string_view text, const SceneLimits& limits = {});
/// The pose text file (`kdrt scene poses ID FILE`): one pose a line, `INSTANCE T`, INSTANCE a
/// geometry id (decimal digits) or an instance name, T 12 or 3 numbers as above. Same rules.
[[nodiscard]] Result<std::vector<PoseEntry>, std::string> parse_pose_text(
    std::string_view text, const SceneLimits& limits = {});

/// KDRX, the binary pose batch (same route, Content-Type application/x-kdrt-poses): the 16-byte
/// batch header (magic KDRX, version 1, flags 0, count, reserved 0), then `count` 52-byte
/// records: u32 geometry id, f32 x 12 (row-major 3 x 4). Checks the header as every batch
/// (count <= limits.max_instances as kTooManyRays, the exact size), then each entry finite
/// (kNonFiniteRay, "pose 4: transform[1][3] is NaN").
[[nodiscard]] std::vector<std::byte> encode_pose_batch(std::span<const PoseEntry> poses);
[[nodiscard]] Result<std::vector<PoseEntry>, DecodeError> decode_pose_batch(
    std::span<const std::byte> body, const SceneLimits& limits = {});

/// A pose resolved against a scene: the geometry id and the pose.
struct ResolvedPose {
    uint32_t geometry_id = 0;
    Transform transform;
};
/// Resolves every entry's geometry id or name against `scene` (unknown_reference naming
/// "poses[i].geometry_id" or "poses[i].name" otherwise), keeping the order.
[[nodiscard]] Result<std::vector<ResolvedPose>, SceneRequestError> resolve_poses(
    const SceneDocument& scene, std::span<const PoseEntry> poses);
/// KDRS of `base` as revision `revision` with `poses` applied in order (a later entry for one
/// instance wins): exactly encode_scene_file of that updated document, without making it (a pose
/// update stores its revision before, and without, copying the scene's document). Precondition:
/// every geometry_id < base.instances.size() (resolve_poses' answer).
[[nodiscard]] std::vector<std::byte> encode_scene_file(const SceneDocument& base, uint64_t revision,
                                                       std::span<const ResolvedPose> poses);

/// POST /v1/scenes/{id}/instances:
///
///   {"remove": [3, "car"], "add": [{"mesh": "...", "transform": [...], "name": "bus"}]}
///
/// "remove": geometry ids (integers) or names of the current revision; "add": instances as in a
/// create request. At least one of them non-empty.
struct InstanceEdit {
    std::vector<std::variant<uint32_t, std::string>> remove;
    std::vector<SceneInstanceSpec> add;
};
[[nodiscard]] Result<InstanceEdit, SceneRequestError> decode_instance_edit_json(
    std::string_view text, const SceneLimits& limits = {});
[[nodiscard]] std::string encode_instance_edit_json(const InstanceEdit& edit);
/// The next revision's instances: the removed ones taken out (the others keep their order, so
/// geometry ids after a removed one move down), then the added ones appended. Refuses (naming
/// the entry) an unknown or repeated removal, a name that would appear twice, and a result over
/// limits.max_instances ("add", over_limit). `scene.id` and `revision` are kept.
[[nodiscard]] Result<SceneDocument, SceneRequestError> apply_instance_edit(
    const SceneDocument& scene, const InstanceEdit& edit, const SceneLimits& limits = {});

// ---- Geometry ids in answers ------------------------------------------------------------------

/// The scene form of a mesh answer body (KDRH, KDRM, KDRD, KDRZ, KDRL or KDRB): flag bit 8
/// (kGeometryIdFlag) set in the header's flags, and after the mesh body a plane of u32 geometry
/// ids, one per record (KDRH, KDRD: count; KDRM: hit records H; KDRZ: pixels W x H; KDRL,
/// KDRB: points N), kNoGeometry for a miss. Every other byte is the mesh form's.
/// Appends the plane to `body` (a mesh answer of one of those formats) and sets the flag.
/// Precondition: geometry_ids.size() is the body's record count.
void append_geometry_ids(std::vector<std::byte>& body, std::span<const uint32_t> geometry_ids);
/// The same in place: `out` holds a mesh answer of `mesh_bytes` bytes with room for the plane
/// after it (e.g. a pooled buffer the answer is sent from); sets the flag, writes the plane and
/// returns the scene answer's size. Precondition as append_geometry_ids'.
size_t write_geometry_ids(std::span<std::byte> out, size_t mesh_bytes,
                          std::span<const uint32_t> geometry_ids);
/// Bytes of the plane for `records` records.
[[nodiscard]] constexpr uint64_t geometry_id_plane_bytes(uint64_t records) noexcept {
    return 4 * records;
}

/// A scene answer split into its mesh body (flag bit 8 cleared; decode it with the format's own
/// decoder) and its geometry ids.
struct SplitAnswer {
    std::vector<std::byte> mesh_body;
    std::vector<uint32_t> geometry_ids;
};
/// Splits a scene answer: the magic (one of the six), the header's size, flag bit 8 set, the
/// record count (<= limits.max_rays; KDRZ: W x H) and a body at least as long as the plane. The
/// mesh body's own checks (its exact size among them) are its decoder's.
[[nodiscard]] Result<SplitAnswer, DecodeError> split_geometry_ids(std::span<const std::byte> body,
                                                                  const DecodeLimits& limits = {});

}  // namespace kdrt::proto
