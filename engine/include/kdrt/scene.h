#pragma once
/// Scenes: many meshes, each placed by an affine transform, queried as one (a two-level
/// structure, as Embree's instances and Open3D's RaycastingScene give).
///
/// A Scene is a list of instances. Instance i (its geometry id is i) is a mesh's immutable
/// kD-tree, shared and never copied or rebuilt, and a transform `world = L * object + t`. Above
/// them a top-level SAH kD-tree is built over the instances' world-space boxes (an instance whose
/// box straddles a split plane is referenced on both sides, as the mesh build does for
/// triangles). A new pose makes a new Scene that shares every mesh tree: only the top level is
/// rebuilt, O(n log n) in the instance count.
///
/// Ray arithmetic (the contract the oracle and every query share). A world ray reaching instance
/// i is carried into object space by object_ray(): origin Linv * (o - t) and direction Linv * d,
/// each computed in double from the float inputs (Linv is the inverse of L computed in double)
/// and rounded once to float per component; tmin and tmax are kept. The direction is not
/// normalised, so a hit's t is the same number in both spaces. The bottom level is the mesh kernel
/// unchanged (kdrt/trace.h, kdrt/query.h, kdrt/distance.h), so within one instance every answer
/// has the mesh kernel's bits and guarantees (watertight, exact ties). Across instances there is
/// no watertightness: a ray through an edge two instances share in world space sees two rounded
/// object rays and may hit both or (rarely) neither, as in any instancing tracer.
///
/// Tie rule: the closest t wins; at exactly equal t the lowest geometry id, then the lowest prim
/// (the mesh kernel's rule within an instance). So an answer does not depend on traversal order,
/// ISA, mode or thread count. The top-level walk widens its cells by a margin over the rounding
/// of object_ray, so it never skips an instance that holds a hit: every answer is the minimum, by
/// the tie rule, of the mesh queries of every instance on its object ray, and so equals
/// SceneOracle's bit for bit wherever the mesh kernel equals its own brute force (tested on every
/// ISA and mode).
///
/// Thread safety: a Scene is immutable after build_scene (copies share its data); every query is
/// safe concurrently from any number of threads.

#include <array>
#include <cstdint>
#include <limits>
#include <memory>
#include <optional>
#include <span>
#include <stdexcept>
#include <string>
#include <vector>

#include "kdrt/distance.h"
#include "kdrt/distance_types.h"
#include "kdrt/hit_clearance.h"
#include "kdrt/image.h"
#include "kdrt/kdtree.h"
#include "kdrt/query.h"
#include "kdrt/render.h"
#include "kdrt/render_settings.h"
#include "kdrt/scan.h"
#include "kdrt/scan_types.h"
#include "kdrt/trace.h"
#include "kdrt/types.h"

namespace kdrt {

/// Largest instance count the engine takes (callers such as the server set their own, lower
/// limit through SceneBuildOptions::max_instances).
inline constexpr uint32_t kMaxSceneInstances = 1u << 24;

/// An affine transform as a row-major 3x4 matrix: world = L * object + t, L = m[r][0..2] (r the
/// row), t = (m[0][3], m[1][3], m[2][3]). The implied last row is 0 0 0 1. Default: the identity.
/// A 4x4 row-major pose (kdrt/scan_types.h's Pose) is its first three rows.
struct Affine3x4 {
    float m[3][4] = {{1, 0, 0, 0}, {0, 1, 0, 0}, {0, 0, 1, 0}};
    friend bool operator==(const Affine3x4&, const Affine3x4&) = default;
};

/// One instance as the caller gives it.
struct SceneInstance {
    /// The mesh's tree (required: a null tree is refused). Shared, never modified.
    std::shared_ptr<const KdTree> tree;
    /// Object to world. Every entry finite and L invertible (see build_scene); refused otherwise.
    Affine3x4 transform;
    /// build_surface_index(*tree), needed only for signed distance (DistanceOptions::sign);
    /// instances of one mesh should share it. Null: signed distance queries refuse this scene.
    std::shared_ptr<const SurfaceIndex> surface;
    /// build_hit_clearance(*tree), optional; instances of one mesh should share it. With it a
    /// single merged return (single-return scans) skips the every-hit window where the closest
    /// hit is provably alone; without it every such hit gets its window. The same answers either
    /// way. One of another triangle count than the tree is refused ("clearance").
    std::shared_ptr<const HitClearance> clearance;
};

/// A new transform for one instance (Scene::with_transforms).
struct InstancePose {
    uint32_t geom = 0;  ///< the instance (its index, its geometry id)
    Affine3x4 transform;
};

/// Top-level build settings. The costs are relative (only the ratio and the bonus matter).
struct SceneBuildOptions {
    /// Refuse more instances than this (checked first, before any work): 0 .. kMaxSceneInstances.
    uint32_t max_instances = kMaxSceneInstances;
    float traversal_cost = 1.0f;  ///< C_trav: one top-level traversal step
    /// C_inst: entering one instance (a transform and a bottom-level traversal): several steps.
    float instance_cost = 4.0f;
    float empty_bonus = 0.2f;  ///< a split with an empty side costs (1 - bonus) times as much
    friend bool operator==(const SceneBuildOptions&, const SceneBuildOptions&) = default;
};

/// A scene that cannot be built: what() says why, e.g. "scene instance 3 transform[1][2] is NaN"
/// or "scene instance 7 transform is singular (det 0)". instance_index() names the instance
/// (for "too many instances": the first over the limit); field() names the field as the request
/// JSON spells it: "tree", "transform", "transform[r][c]", "geom", "instances", "surface",
/// "clearance".
class SceneError : public std::invalid_argument {
public:
    SceneError(std::optional<uint32_t> instance_index, std::string field, const std::string& what)
        : std::invalid_argument(what), instance_index_(instance_index), field_(std::move(field)) {}
    [[nodiscard]] std::optional<uint32_t> instance_index() const noexcept {
        return instance_index_;
    }
    [[nodiscard]] const std::string& field() const noexcept { return field_; }

private:
    std::optional<uint32_t> instance_index_;
    std::string field_;
};

/// Figures of a scene's top level (its meshes' trees have their own TreeStats).
struct SceneStats {
    uint64_t instances = 0;
    uint64_t nodes = 0;  ///< top-level nodes
    uint64_t leaves = 0;
    uint64_t refs = 0;  ///< instance references in the leaves (an instance may be in several)
    uint32_t max_depth = 0;
    /// Bytes the scene holds beside its meshes' trees: per-instance data plus the top level.
    uint64_t bytes = 0;
    double bytes_per_instance = 0;
    double build_ms = 0;  ///< validation, inverses, world boxes and the top-level build
};

namespace detail {
struct SceneData;
}

/// An immutable two-level scene. Cheap to copy (shared data). A default Scene is empty: every
/// query misses or finds nothing.
class Scene {
public:
    Scene() noexcept;

    /// Number of instances; geometry ids are 0 .. size() - 1.
    [[nodiscard]] uint32_t size() const noexcept;
    /// The instance with geometry id `geom` (< size()).
    [[nodiscard]] const SceneInstance& instance(uint32_t geom) const noexcept;
    /// Every instance, by geometry id (a copy: shares the trees; for building a changed scene).
    [[nodiscard]] std::vector<SceneInstance> instances() const;
    /// World-space box of instance `geom`: the exact image of its tree's root box (transformed in
    /// double, rounded outwards). Empty for an instance whose mesh has no hittable triangle.
    [[nodiscard]] Aabb world_bounds(uint32_t geom) const noexcept;
    /// Union of the instances' world boxes (empty for an empty scene).
    [[nodiscard]] const Aabb& bounds() const noexcept;
    [[nodiscard]] const SceneStats& stats() const noexcept;
    [[nodiscard]] const SceneBuildOptions& options() const noexcept;

    /// `world` carried into the object space of instance `geom` (file comment: the arithmetic
    /// every query and the oracle use). An invalid ray stays invalid.
    [[nodiscard]] Ray object_ray(uint32_t geom, const Ray& world) const noexcept;
    /// Linv of instance `geom`, row-major, in double (what object_ray uses).
    [[nodiscard]] std::array<double, 9> inverse_linear(uint32_t geom) const noexcept;
    /// The uniform scale s of instance `geom` when L is a similarity (s times a rotation or a
    /// mirror: L^T L = s^2 I within 1e-5 of s^2 in every entry), else nullopt. Distance queries
    /// need it (world distance = s * object distance).
    [[nodiscard]] std::optional<double> similarity_scale(uint32_t geom) const noexcept;

    /// A scene with the same instances and options, the listed ones moved (applied in order; a
    /// later entry for the same instance wins). Shares every mesh tree and the unchanged
    /// instances' precomputed data; validates the new transforms first (SceneError naming the
    /// entry's geometry id, field "geom" for an unknown one) and rebuilds only the top level.
    [[nodiscard]] Scene with_transforms(std::span<const InstancePose> poses) const;
    [[nodiscard]] Scene with_transform(uint32_t geom, const Affine3x4& transform) const;
    /// A scene with the same instances, transforms, options and top level (shared or copied,
    /// never rebuilt: O(instances)), instance g carrying `per_instance[g]` as its
    /// SceneInstance::clearance (null: none). `per_instance` has size() entries, else
    /// std::invalid_argument; a clearance of another triangle count than its instance's tree is
    /// refused as build_scene refuses it (SceneError, field "clearance").
    [[nodiscard]] Scene with_clearances(
        std::span<const std::shared_ptr<const HitClearance>> per_instance) const;
    /// Throws exactly the SceneError with_transforms(poses) would throw, without building
    /// anything (O(poses)): a caller can accept a pose update, then build the scene while it
    /// stores the update. After it returns, with_transforms(poses) throws only std::bad_alloc.
    void check_transforms(std::span<const InstancePose> poses) const;

    /// Internal (the queries' data).
    [[nodiscard]] const detail::SceneData& data() const noexcept { return *data_; }

private:
    explicit Scene(std::shared_ptr<const detail::SceneData> data) noexcept;
    friend Scene build_scene(std::vector<SceneInstance> instances,
                             const SceneBuildOptions& options);
    std::shared_ptr<const detail::SceneData> data_;
};

/// Validates every instance, then builds the scene: inverses, world boxes and the top-level tree.
/// Checks, in order, each naming the instance and field (SceneError): more than
/// options.max_instances (or kMaxSceneInstances) instances ("instances"); per instance, a null
/// tree ("tree"), a NaN or infinite entry ("transform[r][c]"), a singular or nearly singular L
/// ("transform": |det L| below 1e-9 of the product of its row lengths, a condition number
/// || |L| |L^-1| ||_inf above 2^24, or an inverse or world box beyond float range). Uses the
/// calling thread's oneTBB arena; O(n log n) in the instance count; never reads a mesh tree beyond
/// its bounds. Throws std::bad_alloc.
[[nodiscard]] Scene build_scene(std::vector<SceneInstance> instances,
                                const SceneBuildOptions& options = {});

// ------------------------------------------------------------------------------------------------
// Closest hit and occlusion

/// A scene's closest-hit answer: the Hit of instance `geom`'s mesh (prim in that mesh's input
/// order; u, v its barycentrics there) and the geometry id. A miss is t = +inf, prim = geom =
/// kNoHit, u = v = 0.
struct SceneHit {
    float t = std::numeric_limits<float>::infinity();
    uint32_t prim = kNoHit;
    float u = 0.0f;
    float v = 0.0f;
    uint32_t geom = kNoHit;

    [[nodiscard]] bool is_hit() const noexcept { return prim != kNoHit; }
    /// The mesh-level part (what the instance's tree answered).
    [[nodiscard]] Hit hit() const noexcept { return Hit{t, prim, u, v}; }
    friend bool operator==(const SceneHit&, const SceneHit&) = default;
};
static_assert(sizeof(SceneHit) == 20);

/// Closest hit of `ray` with tmin <= t <= tmax over every instance (tie rule in the file comment).
/// An invalid ray (kdrt/types.h) misses. Thread-safe.
[[nodiscard]] SceneHit intersect(const Scene& scene, const Ray& ray) noexcept;
/// True when any instance is hit with tmin <= t <= tmax.
[[nodiscard]] bool occluded(const Scene& scene, const Ray& ray) noexcept;

/// What a scene batch did.
struct SceneTraceStats {
    Isa isa = Isa::kScalar;
    uint64_t rays = 0;
    uint64_t invalid_rays = 0;
    uint64_t instance_visits = 0;   ///< (ray, instance) pairs traced in the bottom level
    uint64_t instance_batches = 0;  ///< bottom-level batch calls (groups of rays, one instance)
};

/// Batch queries over all threads of the current oneTBB arena, answers in input order (`hits` /
/// `occluded_out` have rays.size() elements; 1 = occluded). The answers are those of the
/// single-ray functions, bit for bit, in every mode and ISA. Rays go in blocks of 1024.
/// kSingle traces ray by ray (the single-ray functions). kPacket traces a block in rounds: each
/// ray takes its next top-level candidate in order of entry (none once they start beyond its
/// closest hit), and the rays that reach one instance in a round go together to the mesh's batch
/// entry (intersect_block / occluded_block with options.mode and options.isa) when they are 8 or
/// more. kAuto uses rounds for a coherent block (one origin, or unit directions within 0.5 of
/// each other in every component: camera and shadow rays) and ray by ray otherwise.
void intersect(const Scene& scene, std::span<const Ray> rays, std::span<SceneHit> hits,
               const TraceOptions& options = {}, SceneTraceStats* stats = nullptr) noexcept;
void occluded(const Scene& scene, std::span<const Ray> rays, std::span<uint8_t> occluded_out,
              const TraceOptions& options = {}, SceneTraceStats* stats = nullptr) noexcept;
/// The same on the calling thread only (the renderer's tiles).
void intersect_block(const Scene& scene, std::span<const Ray> rays, std::span<SceneHit> hits,
                     const TraceOptions& options = {}) noexcept;
void occluded_block(const Scene& scene, std::span<const Ray> rays, std::span<uint8_t> occluded_out,
                    const TraceOptions& options = {}) noexcept;

// ------------------------------------------------------------------------------------------------
// Every hit along a ray

/// Every hit of a scene batch in CSR form, as AllHits: ray i's kept hits are
/// hits[offsets[i] .. offsets[i+1]), sorted by (t, geom, prim); counts[i] counts all of them.
struct SceneAllHits {
    std::vector<uint64_t> offsets;
    std::vector<SceneHit> hits;
    std::vector<uint32_t> counts;
};

/// Every hit of `ray` over every instance, sorted by (t, geom, prim). Each instance answers with
/// the mesh's intersect_all on the object ray, `merge_coincident` applied within the instance
/// (the mesh's rule); hits of different instances are never merged. `out` is replaced; returns
/// out.size(). Thread-safe; throws std::bad_alloc.
uint32_t intersect_all(const Scene& scene, const Ray& ray, bool merge_coincident,
                       std::vector<SceneHit>& out);
/// The same for a batch, parallel over the current arena, keeping the nearest options.max_hits
/// per ray (options.mode and isa are accepted; the answers are the same in each).
[[nodiscard]] SceneAllHits intersect_all(const Scene& scene, std::span<const Ray> rays,
                                         const AllHitsOptions& options);
/// The number of hits of each ray (SceneAllHits::counts) without keeping them.
void count_intersections(const Scene& scene, std::span<const Ray> rays,
                         const AllHitsOptions& options, std::span<uint32_t> counts);

// ------------------------------------------------------------------------------------------------
// Hit attributes

/// Unit right-hand normal of the world-space triangle of `hit` (the instance's triangle with each
/// corner mapped by the transform, winding kept): the object normal (triangle_normal) taken through
/// the inverse transpose of L, negated when det L < 0 (a mirror flips the winding's normal), in
/// double, normalised, rounded to float. Zero for a miss. `hit` must come from `scene`.
[[nodiscard]] Vec3 hit_normal(const Scene& scene, const SceneHit& hit) noexcept;
/// The world-space point of `hit`: L * p + t in double, rounded to float, p the object-space
/// hit_point (kdrt/query.h). NaN components for a miss.
[[nodiscard]] Vec3 hit_point(const Scene& scene, const SceneHit& hit) noexcept;
/// hit_normal and hit_point of each hit, in parallel over the current arena. Either output may
/// be empty (not computed); otherwise it has hits.size() entries.
void hit_attributes(const Scene& scene, std::span<const SceneHit> hits, std::span<Vec3> normals,
                    std::span<Vec3> points);
/// The world-space triangle of (geom, prim): each corner L * v + t in double, rounded to float.
[[nodiscard]] TriVerts world_triangle(const Scene& scene, uint32_t geom, uint32_t prim) noexcept;

// ------------------------------------------------------------------------------------------------
// Distance

/// The closest point of a scene: the instance's answer (prim, u, v, feature and side of its
/// mesh), with `distance` and `point` in world space, and the geometry id (kNoHit: nothing found).
struct SceneClosestPoint {
    ClosestPoint closest;
    uint32_t geom = kNoHit;
    [[nodiscard]] bool found() const noexcept { return closest.found(); }
};

/// Throws SceneError unless distance queries can run on `scene`: every instance with geometry
/// needs a similarity transform (similarity_scale; field "transform"), and with `sign` a surface
/// index ("surface"). The distance functions call it first.
void check_distance_query(const Scene& scene, bool sign);

/// The closest point of the scene to `p`. Each instance answers in object space (closest_point on
/// Linv (p - t), computed in double, rounded to float; no max distance), and its world distance is
/// s * d rounded to float (s its similarity scale, d the object distance in float); the world
/// point is L q + t in double rounded to float. Kept when world distance <= options.max_distance;
/// the smallest world distance wins, ties by the lowest geometry id. The side (options.sign) is the
/// nearest instance's: inside its solid or not (a mirrored instance's solid too). The top-level
/// search visits cells and instances near first and skips every one whose box is farther than the
/// best so far, so it equals SceneOracle::closest_point bit for bit. A NaN/Inf p finds nothing.
/// Throws SceneError (check_distance_query).
[[nodiscard]] SceneClosestPoint closest_point(const Scene& scene, Vec3 p,
                                              const DistanceOptions& options);
/// The same for a batch (out.size() == points.size()), in parallel over the current arena, in
/// tasks of a few points; the same answers at any thread count. `control` limits and cancels it as
/// the mesh batch (kdrt/distance.h), with the work counted per instance: top-level cells visited,
/// plus for each instance searched 1 and its mesh search's work (cells visited and triangles
/// tested). The cancel flag is checked and the work charged before each point and after each
/// instance, so one far point that searches every instance is stopped within it. A stopped batch
/// leaves some answers unwritten or incomplete (the status tells). Throws SceneError
/// (check_distance_query), std::bad_alloc.
DistanceStats closest_points(const Scene& scene, std::span<const Vec3> points,
                             std::span<SceneClosestPoint> out, const DistanceOptions& options,
                             const DistanceControl& control = {});

// ------------------------------------------------------------------------------------------------
// Scans and renders

/// A depth image of a scene: the mesh form (prim per pixel is the instance's triangle) and the
/// geometry id per pixel (kNoHit where nothing was hit).
struct SceneDepthImage {
    DepthImage image;
    std::vector<uint32_t> geom;  ///< width * height
};
/// A lidar scan of a scene: the mesh form (each point's prim is the instance's triangle) and the
/// geometry id of each point (geom[k] belongs to cloud.points[k]).
struct ScenePointCloud {
    PointCloud cloud;
    std::vector<uint32_t> geom;
};

/// scan_pinhole / scan_lidar (kdrt/scan.h, the same rays, ranges, depth and ordering) on a
/// scene: hits by the scene's closest hit and intersect_all (merge_coincident), normals by
/// hit_normal, points by hit_point. Throws ScanError for a bad spec, std::bad_alloc.
[[nodiscard]] SceneDepthImage scan_pinhole(const Scene& scene, const PinholeSpec& spec);
[[nodiscard]] ScenePointCloud scan_lidar(const Scene& scene, const LidarSpec& spec);

/// render() (kdrt/render.h: the same settings, validation, determinism and errors) of a scene.
/// The default camera frames scene.bounds(). Shading::kPrimId colours by (geom, prim), so
/// instances of one mesh differ; Shading::kGeomId by the geometry id alone (one colour an
/// instance).
[[nodiscard]] Image render(const Scene& scene, const RenderSettings& settings,
                           const RenderControl& control = {}, RenderStats* stats = nullptr);

// ------------------------------------------------------------------------------------------------
// The oracle

/// Brute force over a scene, for tests: every instance, object_ray, then every triangle of its
/// mesh (brute_force_intersect and friends on triangles_by_id), then the minimum over instances by
/// the tie rule. Holds each distinct mesh's triangles (built once). Thread-safe.
class SceneOracle {
public:
    explicit SceneOracle(const Scene& scene);
    [[nodiscard]] SceneHit intersect(const Ray& ray) const noexcept;
    [[nodiscard]] bool occluded(const Ray& ray) const noexcept;
    [[nodiscard]] std::vector<SceneHit> intersect_all(const Ray& ray, bool merge_coincident) const;
    /// Throws SceneError as closest_point does.
    [[nodiscard]] SceneClosestPoint closest_point(Vec3 p, const DistanceOptions& options) const;

private:
    Scene scene_;
    std::vector<std::shared_ptr<const std::vector<TriVerts>>> tris_;  ///< per geometry id
};

}  // namespace kdrt
