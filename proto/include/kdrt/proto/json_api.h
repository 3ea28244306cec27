#pragma once
/// The JSON bodies and media types of the kdrt HTTP API v1 (documented in proto/openapi.yaml).
/// Encoders write compact JSON with shortest round-trip numbers; decoders take untrusted text,
/// never throw (except std::bad_alloc) and name the offending member in their errors.
/// All functions are thread-safe.

#include <cstdint>
#include <optional>
#include <span>
#include <string>
#include <string_view>
#include <variant>
#include <vector>

#include "kdrt/proto/mesh_io.h"
#include "kdrt/proto/result.h"
#include "kdrt/render_settings.h"
#include "kdrt/tree_stats.h"
#include "kdrt/types.h"

namespace kdrt::proto {

// ---- Media types -------------------------------------------------------------------------------

inline constexpr std::string_view kJsonMediaType = "application/json";
/// KDRR request bodies.
inline constexpr std::string_view kRaysMediaType = "application/x-kdrt-rays";
/// KDRH answers (closest hits).
inline constexpr std::string_view kHitsMediaType = "application/x-kdrt-hits";
/// KDRO answers (occlusion).
inline constexpr std::string_view kOcclusionMediaType = "application/x-kdrt-occlusion";
/// The raw mesh format of proto/FORMATS.md.
inline constexpr std::string_view kRawMeshMediaType = "application/x-kdrt-mesh";

/// The media type without parameters, lower case: "Application/JSON; charset=utf-8" ->
/// "application/json".
[[nodiscard]] std::string media_type_essence(std::string_view content_type);

/// Mesh format of an upload's Content-Type: model/obj, model/stl, application/ply (also
/// model/ply, application/x-ply), application/x-off (also model/off), application/x-kdrt-mesh.
/// Parameters and case are ignored. Anything else -> nullopt.
[[nodiscard]] std::optional<MeshFormat> mesh_format_from_media_type(std::string_view content_type);

/// The canonical media type of each mesh format (the first of each list above).
[[nodiscard]] std::string_view mesh_media_type(MeshFormat format) noexcept;

// ---- Meshes ------------------------------------------------------------------------------------

/// What the API reports about a stored mesh (POST/GET /v1/meshes...). Also the sidecar the
/// server keeps next to each stored mesh.
///
///   {"id": "<64 hex>", "triangles": 69451, "vertices": 35947,
///    "bounds": {"min": [x, y, z], "max": [x, y, z]}, "build_ms": 41.5,
///    "tree": {"nodes": ..., "leaves": ..., "empty_leaves": ..., "refs": ..., "max_depth": ...,
///             "mean_leaf_depth": ..., "mean_tris_per_leaf": ..., "sah_cost": ...,
///             "bytes": ..., "bytes_per_triangle": ...},
///    "in_memory": true}
struct MeshSummary {
    std::string id;
    uint64_t triangles = 0;
    uint64_t vertices = 0;
    Aabb bounds;     ///< of the mesh's referenced vertices (not the padded tree cell)
    TreeStats tree;  ///< build statistics; tree.build_ms is reported as "build_ms"
    std::optional<bool> in_memory;  ///< runtime state, omitted when unset (not stored on disk)
    /// Upload answers only: what the parser skipped (e.g. unknown PLY header lines); omitted
    /// when empty, never stored.
    std::vector<std::string> warnings;

    /// Field-wise equality (TreeStats has no operator== of its own).
    friend bool operator==(const MeshSummary& a, const MeshSummary& b) noexcept;
};

[[nodiscard]] std::string encode_mesh_summary(const MeshSummary& summary);
/// Inverse of encode_mesh_summary (floats and integers round-trip exactly).
[[nodiscard]] Result<MeshSummary, std::string> decode_mesh_summary(std::string_view text);

/// {"meshes": [summary, ...]}
[[nodiscard]] std::string encode_mesh_list(std::span<const MeshSummary> meshes);
[[nodiscard]] Result<std::vector<MeshSummary>, std::string> decode_mesh_list(std::string_view text);

// ---- JSON ray batches --------------------------------------------------------------------------

/// Default largest JSON batch (larger batches belong in KDRR).
inline constexpr size_t kDefaultMaxJsonRays = 100'000;
/// Largest JSON batch limit a server may configure (some 1.6 GB of JSON at ~100 bytes per ray).
inline constexpr size_t kMaxJsonRays = size_t{1} << 24;

/// Why a JSON ray batch was refused.
struct JsonError {
    enum class Code {
        kSyntax,   ///< not JSON
        kSchema,   ///< JSON, but not the expected document
        kTooMany,  ///< more rays than the limit
    };
    Code code = Code::kSyntax;
    /// Names the member and value: `rays[12]: expected 6 or 8 numbers, got 5`,
    /// `invalid JSON at byte 17: ...`, `rays[100000]: rays in a JSON batch exceed the limit of
    /// 100000`.
    std::string detail;
};

/// A decoded JSON ray request: {"rays": [[ox,oy,oz,dx,dy,dz] | [ox,oy,oz,dx,dy,dz,tmin,tmax], ...],
/// "occlusion": false}. "rays" is required, "occlusion" optional (default false), other members
/// are refused. Six numbers mean tmin = 0, tmax = +inf. Numbers are parsed from their text as
/// correctly rounded f32. An origin or direction component beyond the f32 range is refused;
/// tmin/tmax beyond it become -inf/+inf (JSON has no infinity literal).
struct JsonRayRequest {
    std::vector<Ray> rays;
    bool occlusion = false;
};

[[nodiscard]] Result<JsonRayRequest, JsonError> decode_json_rays(
    std::string_view text, size_t max_rays = kDefaultMaxJsonRays);
/// Writes a request decode_json_rays accepts: 8 numbers per ray, a tmax of +inf as 3.4028235e38
/// rounded up (1e39). NaN components are written as null and refused by the decoder.
[[nodiscard]] std::string encode_json_rays(std::span<const Ray> rays, bool occlusion);

/// {"hits": [{"t": 1.5, "prim": 12, "u": 0.2, "v": 0.3} | null, ...]} (null for a miss).
[[nodiscard]] std::string encode_json_hits(std::span<const Hit> hits);
[[nodiscard]] Result<std::vector<Hit>, std::string> decode_json_hits(std::string_view text);

/// {"occluded": [true, false, ...]}
[[nodiscard]] std::string encode_json_occlusion(std::span<const uint8_t> occluded);
[[nodiscard]] Result<std::vector<uint8_t>, std::string> decode_json_occlusion(
    std::string_view text);

// ---- Renders ----------------------------------------------------------------------------------

/// Caps a render request must respect (the server's max_image_width/height and max_spp).
struct RenderLimits {
    uint32_t max_width = 8192;
    uint32_t max_height = 8192;
    uint32_t max_spp = 1024;
};

/// POST /v1/render:
///   {"mesh": "<id>",                                  required
///    "camera": {"eye": [x,y,z], "look_at": [x,y,z],   optional; omitted = a default view
///               "up": [0,1,0], "fov": 40,              framing the mesh (up, fov, projection
///               "projection": "perspective",           and ortho_height have defaults)
///               "ortho_height": 1},
///    "width": 512, "height": 512, "spp": 1, "seed": 1,
///    "shading": "normals|eyelight|ao|diffuse|depth|primid|geomid",   default eyelight
///    "format": "png|exr|jpg|raw",       default png; raw: KDRI, the linear float pixels
///                                       (kdrt/proto/raw_image.h), for stitching regions
///    "compression": 0..9,                     optional, png only: zlib level (ImageEncodeOptions::
///                                             png_compression); omitted = the server's default
///    "tile": {"x": 0, "y": 0, "w": 256, "h": 256}}             optional; omitted = whole frame
/// Unknown members are refused. Ranges beyond the limits are refused naming the limit; the
/// engine's validate_render_settings checks the rest (camera geometry, tile inside the frame).
struct RenderRequest {
    std::string mesh;
    RenderSettings settings;     ///< camera/region/size/spp/shading/seed, ao_samples/ao_distance,
                                 ///< light.direction, bounces, sky and background from the request
    std::string format = "png";  ///< "png", "jpg"/"jpeg", "exr" or "raw" (lower case, as sent)
    std::optional<int> compression;  ///< PNG zlib level 0 .. 9, when sent
};

/// With `scene` (POST /v1/scenes/{id}/render, whose path names the scene) the same body without
/// "mesh": a "mesh" member is refused as unknown, and RenderRequest::mesh stays empty.
[[nodiscard]] Result<RenderRequest, JsonError> decode_render_request(
    std::string_view text, const RenderLimits& limits = {}, bool scene = false);
/// Writes every member decode_render_request reads (camera and tile only when set; ao_samples,
/// ao_distance, light, bounces, sky and background only when not at their defaults).
[[nodiscard]] std::string encode_render_request(const RenderRequest& request);

// ---- Jobs ---------------------------------------------------------------------------------------

enum class JobState { kQueued, kRunning, kDone, kFailed, kCancelled };

/// "queued", "running", "done", "failed", "cancelled".
[[nodiscard]] std::string_view job_state_name(JobState state) noexcept;
[[nodiscard]] std::optional<JobState> parse_job_state(std::string_view name) noexcept;

/// GET /v1/jobs/{id}:
///   {"id": "...", "state": "running", "progress": 0.42, "mesh": "<id>", "format": "png",
///    "created": 1767225600.123, "cancel_requested": false,
///    "render_ms": 12.5, "result": "/v1/jobs/<id>/result", "result_bytes": 1234,   (when done)
///    "error": "..."}                                                             (when failed)
struct JobStatus {
    std::string id;
    JobState state = JobState::kQueued;
    double progress = 0;  ///< 0 .. 1
    std::string mesh;     ///< a mesh render's mesh id (empty for a scene render)
    std::string scene;    ///< a scene render's scene id and revision (empty / 0 for a mesh's)
    uint64_t revision = 0;
    std::string format;
    double created = 0;  ///< Unix time in seconds
    bool cancel_requested = false;
    std::optional<double> render_ms;
    uint64_t result_bytes = 0;
    std::string error;
};

[[nodiscard]] std::string encode_job_status(const JobStatus& status);
[[nodiscard]] Result<JobStatus, std::string> decode_job_status(std::string_view text);

// ---- Small documents ---------------------------------------------------------------------------

/// A flat JSON object of scalars, in the given order (log records, /healthz, /readyz):
/// {"key": value, ...}. Doubles print in shortest form; non-finite doubles as null.
using JsonScalar = std::variant<std::string, std::string_view, int64_t, uint64_t, double, bool>;
struct JsonField {
    std::string_view key;
    JsonScalar value;
};
[[nodiscard]] std::string encode_flat_object(std::span<const JsonField> fields);

}  // namespace kdrt::proto
