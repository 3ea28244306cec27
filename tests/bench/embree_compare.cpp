#include "embree_compare.h"

#include <sys/types.h>
#include <tbb/blocked_range.h>
#include <tbb/parallel_for.h>
#include <tbb/task_arena.h>

#include <algorithm>
#include <atomic>
#include <chrono>
#include <cmath>
#include <cstring>
#include <iterator>
#include <limits>
#include <memory>
#include <mutex>
#include <string>
#include <type_traits>

#include "embree_api.h"
#include "kdrt/trace.h"

namespace kdrt::bench {
namespace {

using Clock = std::chrono::steady_clock;

constexpr float kInf = std::numeric_limits<float>::infinity();

// Rays are handed out in blocks of this many (a multiple of every packet width); each block is
// one parallel task for every mode, so the modes differ only in how Embree is called.
constexpr size_t kBlockRays = 256;

// Relative t tolerance of the answer comparison (kdrt and Embree use different triangle tests).
constexpr double kRelativeTolerance = 1e-4;

/// Error and memory bookkeeping shared with Embree's callbacks (called from any thread).
struct DeviceState {
    std::atomic<int64_t> bytes{0};
    std::mutex mutex;
    std::string first_error;
};

void on_error(void* user, RTCError code, const char* message) {
    auto* state = static_cast<DeviceState*>(user);
    const std::lock_guard lock(state->mutex);
    if (state->first_error.empty()) {
        state->first_error = "Embree error " + std::to_string(static_cast<int>(code)) + ": " +
                             (message ? message : "(no message)");
    }
}

bool on_memory(void* user, ssize_t bytes, bool /*post*/) {
    // Positive before an allocation, negative after a release: the sum is what Embree holds.
    static_cast<DeviceState*>(user)->bytes.fetch_add(static_cast<int64_t>(bytes),
                                                     std::memory_order_relaxed);
    return true;
}

struct DeviceDeleter {
    void operator()(RTCDevice device) const noexcept { rtcReleaseDevice(device); }
};
struct SceneDeleter {
    void operator()(RTCScene scene) const noexcept { rtcReleaseScene(scene); }
};
using DevicePtr = std::unique_ptr<std::remove_pointer_t<RTCDevice>, DeviceDeleter>;
using ScenePtr = std::unique_ptr<std::remove_pointer_t<RTCScene>, SceneDeleter>;

void check(DeviceState& state, RTCDevice device, const char* what) {
    const RTCError code = rtcGetDeviceError(device);
    const std::lock_guard lock(state.mutex);
    if (code != RTC_ERROR_NONE || !state.first_error.empty()) {
        throw EmbreeError(std::string(what) + " failed: " +
                          (state.first_error.empty()
                               ? "Embree error " + std::to_string(static_cast<int>(code))
                               : state.first_error));
    }
}

/// kdrt's rule for a ray it traces (types.h); Embree gets the others as inactive rays.
bool ray_is_valid(const Ray& r) noexcept {
    const bool finite = std::isfinite(r.ox) && std::isfinite(r.oy) && std::isfinite(r.oz) &&
                        std::isfinite(r.dx) && std::isfinite(r.dy) && std::isfinite(r.dz);
    return finite && (r.dx != 0.0f || r.dy != 0.0f || r.dz != 0.0f) && r.tmin <= r.tmax;
}

/// Writes lane `lane` of an Embree ray (single: RTCRay, packets: RTCRayN with arrays).
template <typename EmbreeRay>
void set_lane(EmbreeRay& e, int lane, const Ray& r) noexcept {
    const bool valid = ray_is_valid(r);
    auto assign = [&](auto& field, auto value) {
        if constexpr (std::is_array_v<std::remove_reference_t<decltype(field)>>) {
            field[lane] = value;
        } else {
            field = value;
        }
    };
    assign(e.org_x, valid ? r.ox : 0.0f);
    assign(e.org_y, valid ? r.oy : 0.0f);
    assign(e.org_z, valid ? r.oz : 0.0f);
    assign(e.dir_x, valid ? r.dx : 0.0f);
    assign(e.dir_y, valid ? r.dy : 0.0f);
    assign(e.dir_z, valid ? r.dz : 1.0f);
    // Inactive rays: tnear > tfar.
    assign(e.tnear, valid ? r.tmin : kInf);
    assign(e.tfar, valid ? r.tmax : -kInf);
    assign(e.time, 0.0f);
    assign(e.mask, ~0u);
    assign(e.id, 0u);
    assign(e.flags, 0u);
}

template <typename EmbreeHit>
void clear_hit(EmbreeHit& h, int lane) noexcept {
    if constexpr (std::is_array_v<decltype(h.geomID)>) {
        h.geomID[lane] = RTC_INVALID_GEOMETRY_ID;
        h.instID[0][lane] = RTC_INVALID_GEOMETRY_ID;
    } else {
        h.geomID = RTC_INVALID_GEOMETRY_ID;
        h.instID[0] = RTC_INVALID_GEOMETRY_ID;
    }
}

template <typename EmbreeRayHit>
Hit read_hit(const EmbreeRayHit& rh, int lane) noexcept {
    Hit hit;
    if constexpr (std::is_array_v<decltype(rh.hit.geomID)>) {
        if (rh.hit.geomID[lane] != RTC_INVALID_GEOMETRY_ID) {
            hit = Hit{rh.ray.tfar[lane], rh.hit.primID[lane], rh.hit.u[lane], rh.hit.v[lane]};
        }
    } else {
        if (rh.hit.geomID != RTC_INVALID_GEOMETRY_ID) {
            hit = Hit{rh.ray.tfar, rh.hit.primID, rh.hit.u, rh.hit.v};
        }
    }
    return hit;
}

template <typename EmbreeRay>
uint8_t read_occluded(const EmbreeRay& ray, int lane) noexcept {
    // rtcOccluded sets tfar to -inf for an occluded ray; an inactive ray already has -inf, so
    // look at validity separately (the caller passes the kdrt ray's validity).
    if constexpr (std::is_array_v<decltype(ray.tfar)>) {
        return ray.tfar[lane] == -kInf ? 1 : 0;
    } else {
        return ray.tfar == -kInf ? 1 : 0;
    }
}

/// Traces rays [begin, end) with the given API shape; `W` = 1 (rtc*1), 0 (rtc*1M stream, Embree 3
/// only) or a packet width. Answers go to hits[i] or occluded[i].
/// `order` (packet widths only; empty: input order): the pass's k-th ray is rays[order[k]], its
/// answer goes to hits / occluded [order[k]].
template <int W, bool Occlusion>
void trace_block(RTCScene scene, QueryArgs& args, std::span<const Ray> rays, size_t begin,
                 size_t end, std::span<Hit> hits, std::span<uint8_t> occluded,
                 std::span<const uint32_t> order) {
    if constexpr (W == 1) {
        for (size_t i = begin; i < end; ++i) {
            if constexpr (Occlusion) {
                RTCRay ray;
                set_lane(ray, 0, rays[i]);
                query(rtcOccluded1, scene, &ray, args.occluded_args());
                occluded[i] = ray_is_valid(rays[i]) ? read_occluded(ray, 0) : 0;
            } else {
                RTCRayHit rh;
                set_lane(rh.ray, 0, rays[i]);
                clear_hit(rh.hit, 0);
                query(rtcIntersect1, scene, &rh, args.intersect_args());
                hits[i] = read_hit(rh, 0);
            }
        }
    } else if constexpr (W == 0) {
#if RTC_VERSION_MAJOR < 4
        const auto count = static_cast<unsigned>(end - begin);
        if constexpr (Occlusion) {
            RTCRay stream[kBlockRays];
            for (unsigned k = 0; k < count; ++k) set_lane(stream[k], 0, rays[begin + k]);
            rtcOccluded1M(scene, args.occluded_args(), stream, count, sizeof(RTCRay));
            for (unsigned k = 0; k < count; ++k) {
                occluded[begin + k] =
                    ray_is_valid(rays[begin + k]) ? read_occluded(stream[k], 0) : 0;
            }
        } else {
            RTCRayHit stream[kBlockRays];
            for (unsigned k = 0; k < count; ++k) {
                set_lane(stream[k].ray, 0, rays[begin + k]);
                clear_hit(stream[k].hit, 0);
            }
            rtcIntersect1M(scene, args.intersect_args(), stream, count, sizeof(RTCRayHit));
            for (unsigned k = 0; k < count; ++k) hits[begin + k] = read_hit(stream[k], 0);
        }
#endif
    } else {
        using RayHitW = std::conditional_t<W == 4, RTCRayHit4,
                                           std::conditional_t<W == 8, RTCRayHit8, RTCRayHit16>>;
        for (size_t first = begin; first < end; first += W) {
            alignas(64) int valid[W];
            RayHitW rh;
            const size_t lanes = std::min<size_t>(W, end - first);
            size_t at[W];
            for (int lane = 0; lane < W; ++lane) {
                const bool used = static_cast<size_t>(lane) < lanes;
                at[lane] = !used ? 0 : order.empty() ? first + lane : order[first + lane];
                const Ray r = used ? rays[at[lane]] : Ray{0, 0, 0, kInf, 0, 0, 1, -kInf};
                valid[lane] = used && ray_is_valid(r) ? -1 : 0;
                set_lane(rh.ray, lane, r);
                clear_hit(rh.hit, lane);
            }
            if constexpr (Occlusion) {
                if constexpr (W == 4)
                    query_packet(rtcOccluded4, valid, scene, &rh.ray, args.occluded_args());
                if constexpr (W == 8)
                    query_packet(rtcOccluded8, valid, scene, &rh.ray, args.occluded_args());
                if constexpr (W == 16)
                    query_packet(rtcOccluded16, valid, scene, &rh.ray, args.occluded_args());
                for (size_t lane = 0; lane < lanes; ++lane) {
                    occluded[at[lane]] =
                        valid[lane] ? read_occluded(rh.ray, static_cast<int>(lane)) : 0;
                }
            } else {
                if constexpr (W == 4)
                    query_packet(rtcIntersect4, valid, scene, &rh, args.intersect_args());
                if constexpr (W == 8)
                    query_packet(rtcIntersect8, valid, scene, &rh, args.intersect_args());
                if constexpr (W == 16)
                    query_packet(rtcIntersect16, valid, scene, &rh, args.intersect_args());
                for (size_t lane = 0; lane < lanes; ++lane) {
                    hits[at[lane]] = valid[lane] ? read_hit(rh, static_cast<int>(lane)) : Hit{};
                }
            }
        }
    }
}

/// One full pass over the batch in parallel over the current arena; returns seconds.
template <int W, bool Occlusion>
double trace_pass(RTCScene scene, bool coherent, std::span<const Ray> rays, std::span<Hit> hits,
                  std::span<uint8_t> occluded, std::span<const uint32_t> order) {
    const size_t blocks = (rays.size() + kBlockRays - 1) / kBlockRays;
    const auto start = Clock::now();
    tbb::parallel_for(tbb::blocked_range<size_t>(0, blocks),
                      [&](const tbb::blocked_range<size_t>& range) {
                          QueryArgs args(coherent);
                          for (size_t block = range.begin(); block != range.end(); ++block) {
                              const size_t begin = block * kBlockRays;
                              trace_block<W, Occlusion>(scene, args, rays, begin,
                                                        std::min(begin + kBlockRays, rays.size()),
                                                        hits, occluded, order);
                          }
                      });
    return std::chrono::duration<double>(Clock::now() - start).count();
}

/// The smallest t difference that counts, for a ray: 1e-4 relative to the larger t, but never
/// below 1e-7 of the scene's diagonal in distance (converted to t by the direction's length).
/// Hits a few ulps of the scene away from the origin (a ray starting on a surface) have t errors
/// of the coordinates' rounding in both tracers, which a purely relative test would count.
struct TScale {
    double floor = 0;  ///< scene diagonal * 1e-7 (distance)
    [[nodiscard]] bool same(const Ray& ray, float a, float b) const noexcept {
        const double len =
            std::sqrt(double{ray.dx} * ray.dx + double{ray.dy} * ray.dy + double{ray.dz} * ray.dz);
        const double scale =
            std::max(std::fabs(static_cast<double>(a)), std::fabs(static_cast<double>(b)));
        const double tol = std::max(kRelativeTolerance * scale, len > 0 ? floor / len : 0.0);
        return std::fabs(static_cast<double>(a) - b) <= tol;
    }
};

bool hits_differ(const TScale& ts, const Ray& ray, const Hit& kd, const Hit& em) noexcept {
    if (kd.prim != em.prim) return true;
    return kd.is_hit() && !ts.same(ray, kd.t, em.t);
}

bool share_a_corner(const TriVerts& a, const TriVerts& b) noexcept {
    const float* const ca[3] = {a.v0, a.v1, a.v2};
    const float* const cb[3] = {b.v0, b.v1, b.v2};
    for (const float* p : ca) {
        for (const float* q : cb) {
            if (p[0] == q[0] && p[1] == q[1] && p[2] == q[2]) return true;
        }
    }
    return false;
}

/// A difference that is a tie: both tracers hit at the same distance, and either kdrt's own
/// triangle test hits Embree's triangle there too (two triangles at one distance), or the two
/// triangles share a corner: the ray passes through their shared edge or vertex, where which
/// side is reported is up to each test's rounding (kdrt's watertight test picks exactly one;
/// Embree's test is not watertight and may pick the neighbour).
bool is_tie(const TScale& ts, std::span<const TriVerts> tris, const Ray& ray, const Hit& kd,
            const Hit& em) noexcept {
    if (!kd.is_hit() || !em.is_hit() || em.prim >= tris.size() || kd.prim >= tris.size())
        return false;
    if (!ts.same(ray, kd.t, em.t)) return false;
    if (share_a_corner(tris[kd.prim], tris[em.prim])) return true;
    const Hit other = brute_force_intersect(tris.subspan(em.prim, 1), ray);
    return other.is_hit() && ts.same(ray, other.t, kd.t);
}

double median(std::vector<double> values) {
    std::sort(values.begin(), values.end());
    const size_t mid = values.size() / 2;
    return values.size() % 2 == 1 ? values[mid] : 0.5 * (values[mid - 1] + values[mid]);
}

struct ModeSpec {
    const char* suffix;  ///< "1", "1M", "4", "8", "16", "8_patch", "16_patch"
    int width;           ///< template W
    RTCDeviceProperty support;
    bool patch = false;  ///< packets of square image patches (image_patch_order), not of rows
};

constexpr ModeSpec kModes[] = {
    {"1", 1, RTC_DEVICE_PROPERTY_TRIANGLE_GEOMETRY_SUPPORTED},
#if RTC_VERSION_MAJOR < 4
    {"1M", 0, RTC_DEVICE_PROPERTY_RAY_STREAM_SUPPORTED},
#endif
    {"4", 4, RTC_DEVICE_PROPERTY_NATIVE_RAY4_SUPPORTED},
    {"8", 8, RTC_DEVICE_PROPERTY_NATIVE_RAY8_SUPPORTED},
    {"16", 16, RTC_DEVICE_PROPERTY_NATIVE_RAY16_SUPPORTED},
    {"8_patch", 8, RTC_DEVICE_PROPERTY_NATIVE_RAY8_SUPPORTED, true},
    {"16_patch", 16, RTC_DEVICE_PROPERTY_NATIVE_RAY16_SUPPORTED, true},
};
static_assert(kHasRayStreams == (std::size(kModes) == 7));

/// The order in which packets of `width` rays are square patches of an image of res x res rays
/// in row order (kdrt-bench rays writes its sets so): bands of `rows` rows (4 for 16 lanes, 2 for
/// 8), each cut into patches of width / rows columns, a patch's rays row by row. This is how an
/// application tracing a camera's pixels forms its packets, and kdrt's packets of a camera's rays
/// are such patches too (batch_schedule.h, trace_patch_block), so Embree gets the same chance.
/// Empty when the ray count is not a square (the rays are then not known to be an image).
std::vector<uint32_t> image_patch_order(size_t count, int width) {
    const auto res = static_cast<size_t>(std::llround(std::sqrt(static_cast<double>(count))));
    if (res < 2 || res * res != count) return {};
    const size_t rows = width >= 16 ? 4 : 2;
    const size_t cols = static_cast<size_t>(width) / rows;
    std::vector<uint32_t> order;
    order.reserve(count);
    for (size_t y0 = 0; y0 < res; y0 += rows) {
        const size_t y1 = std::min(y0 + rows, res);
        for (size_t x0 = 0; x0 < res; x0 += cols) {
            const size_t x1 = std::min(x0 + cols, res);
            for (size_t y = y0; y < y1; ++y) {
                for (size_t x = x0; x < x1; ++x)
                    order.push_back(static_cast<uint32_t>(y * res + x));
            }
        }
    }
    return order;
}

/// What every scene's comparison shares: the device, the rays, kdrt's answers, the oracle's
/// triangles.
struct Comparison {
    DeviceState& state;
    RTCDevice device;
    const Mesh& mesh;
    const proto::RayBatch& batch;
    std::span<const Hit> kd_hits;
    std::span<const uint8_t> kd_occluded;
    std::span<const TriVerts> tris;  // by id, to recognise ties
    TScale t_scale;
    int reps;
};

/// A committed scene of the mesh, with its build time and the memory it keeps.
struct BuiltScene {
    ScenePtr scene;
    double build_ms = 0;
    double bytes_per_triangle = 0;
};

BuiltScene build_scene(const Comparison& c, RTCSceneFlags flags) {
    BuiltScene built;
    const int64_t bytes_before = c.state.bytes.load();
    built.scene.reset(rtcNewScene(c.device));
    check(c.state, c.device, "rtcNewScene");
    rtcSetSceneFlags(built.scene.get(), flags);
    rtcSetSceneBuildQuality(built.scene.get(), RTC_BUILD_QUALITY_HIGH);
    const Mesh& mesh = c.mesh;
    const size_t tri_count = mesh.triangle_count();
    if (tri_count > 0) {
        RTCGeometry geometry = rtcNewGeometry(c.device, RTC_GEOMETRY_TYPE_TRIANGLE);
        check(c.state, c.device, "rtcNewGeometry");
        auto* vertices = static_cast<float*>(
            rtcSetNewGeometryBuffer(geometry, RTC_BUFFER_TYPE_VERTEX, 0, RTC_FORMAT_FLOAT3,
                                    3 * sizeof(float), mesh.vertex_count()));
        auto* indices = static_cast<uint32_t*>(rtcSetNewGeometryBuffer(
            geometry, RTC_BUFFER_TYPE_INDEX, 0, RTC_FORMAT_UINT3, 3 * sizeof(uint32_t), tri_count));
        check(c.state, c.device, "rtcSetNewGeometryBuffer");
        std::memcpy(vertices, mesh.positions.data(), mesh.positions.size() * sizeof(float));
        std::memcpy(indices, mesh.indices.data(), mesh.indices.size() * sizeof(uint32_t));
        rtcSetGeometryBuildQuality(geometry, RTC_BUILD_QUALITY_HIGH);
        rtcCommitGeometry(geometry);
        rtcAttachGeometry(built.scene.get(), geometry);
        rtcReleaseGeometry(geometry);
        check(c.state, c.device, "creating the Embree triangle geometry");
    }
    const auto build_start = Clock::now();
    rtcCommitScene(built.scene.get());
    built.build_ms = std::chrono::duration<double, std::milli>(Clock::now() - build_start).count();
    check(c.state, c.device, "rtcCommitScene");
    // What the scene keeps after the build (vertex and index buffers included), per triangle.
    built.bytes_per_triangle = tri_count > 0
                                   ? static_cast<double>(c.state.bytes.load() - bytes_before) /
                                         static_cast<double>(tri_count)
                                   : 0.0;
    return built;
}

/// Builds the scene with `flags` and times every mode on it; mode names get `name_prefix`.
EmbreeSceneReport measure_scene(const Comparison& c, RTCSceneFlags flags,
                                const std::string& name_prefix) {
    EmbreeSceneReport report;
    BuiltScene built = build_scene(c, flags);
    report.build_ms = built.build_ms;
    report.bytes_per_triangle = built.bytes_per_triangle;
    const ScenePtr& scene = built.scene;

    const proto::RayBatch& batch = c.batch;
    const std::span<const Ray> rays = batch.rays;
    std::vector<Hit> hits(batch.occlusion ? 0 : rays.size());
    std::vector<uint8_t> occluded(batch.occlusion ? rays.size() : 0);
    const std::string prefix = batch.occlusion ? "occluded" : "intersect";
    for (const ModeSpec& spec : kModes) {
        if (rtcGetDeviceProperty(c.device, spec.support) == 0) continue;
        const std::vector<uint32_t> order =
            spec.patch ? image_patch_order(rays.size(), spec.width) : std::vector<uint32_t>{};
        if (spec.patch && order.empty()) continue;
        for (bool coherent : {false, true}) {
            auto pass = [&] {
                const auto run = [&]<int W>() {
                    return batch.occlusion ? trace_pass<W, true>(scene.get(), coherent, rays, hits,
                                                                 occluded, order)
                                           : trace_pass<W, false>(scene.get(), coherent, rays, hits,
                                                                  occluded, order);
                };
                switch (spec.width) {
                    case 0:
                        return run.template operator()<0>();
                    case 4:
                        return run.template operator()<4>();
                    case 8:
                        return run.template operator()<8>();
                    case 16:
                        return run.template operator()<16>();
                    default:
                        return run.template operator()<1>();
                }
            };
            std::vector<double> seconds;
            for (int rep = 0; rep <= c.reps; ++rep) {  // pass 0 is the warm-up
                const double s = pass();
                if (rep > 0) seconds.push_back(s);
            }
            check(c.state, c.device, ("rtc" + prefix + spec.suffix).c_str());

            EmbreeModeTiming timing;
            timing.name = name_prefix + prefix + spec.suffix + (coherent ? "_coherent" : "");
            const double median_seconds = median(seconds);
            timing.mrays_per_s =
                median_seconds > 0 ? static_cast<double>(rays.size()) / median_seconds / 1e6 : 0.0;
            for (size_t i = 0; i < rays.size(); ++i) {
                const bool differ = batch.occlusion
                                        ? (occluded[i] != 0) != (c.kd_occluded[i] != 0)
                                        : hits_differ(c.t_scale, rays[i], c.kd_hits[i], hits[i]);
                if (!differ) continue;
                ++timing.differences;
                if (batch.occlusion) continue;
                if (is_tie(c.t_scale, c.tris, rays[i], c.kd_hits[i], hits[i])) {
                    ++timing.ties;
                } else {
                    // Who is right? The brute-force oracle (every triangle, kdrt's watertight
                    // test).
                    const Hit truth = brute_force_intersect(c.tris, rays[i]);
                    if (std::memcmp(&truth, &c.kd_hits[i], sizeof(Hit)) == 0)
                        ++timing.kdrt_matches_oracle;
                }
            }
            if (report.best_mode.empty() || timing.mrays_per_s > report.best_mrays_per_s) {
                report.best_mode = timing.name;
                report.best_mrays_per_s = timing.mrays_per_s;
                report.differences = timing.differences;
                report.ties = timing.ties;
                report.kdrt_matches_oracle = timing.kdrt_matches_oracle;
            }
            report.modes.push_back(std::move(timing));
        }
    }
    return report;
}

}  // namespace

EmbreeReport compare_with_embree(const Mesh& mesh, const proto::RayBatch& batch,
                                 std::span<const Hit> kd_hits, std::span<const uint8_t> kd_occluded,
                                 const EmbreeOptions& options) {
    DeviceState state;
    const int threads = tbb::this_task_arena::max_concurrency();
    const std::string config = "threads=" + std::to_string(threads) + ",set_affinity=0,verbose=0";
    DevicePtr device(rtcNewDevice(config.c_str()));
    if (!device) {
        throw EmbreeError("rtcNewDevice(\"" + config + "\") failed: Embree error " +
                          std::to_string(static_cast<int>(rtcGetDeviceError(nullptr))));
    }
    rtcSetDeviceErrorFunction(device.get(), on_error, &state);
    rtcSetDeviceMemoryMonitorFunction(device.get(), on_memory, &state);

    const std::vector<TriVerts> tris = make_tri_verts(mesh);
    TScale t_scale;
    {
        Aabb box;
        for (const TriVerts& t : tris) {
            for (const float* c : {t.v0, t.v1, t.v2}) box.extend({c[0], c[1], c[2]});
        }
        if (!box.empty()) {
            const Vec3 e = box.extent();
            t_scale.floor =
                1e-7 * std::sqrt(double{e.x} * e.x + double{e.y} * e.y + double{e.z} * e.z);
        }
    }
    const Comparison comparison{state,       device.get(), mesh,    batch,       kd_hits,
                                kd_occluded, tris,         t_scale, options.reps};
    EmbreeReport report;
    report.version_major =
        static_cast<int>(rtcGetDeviceProperty(device.get(), RTC_DEVICE_PROPERTY_VERSION_MAJOR));
    // The first commit of a device also starts Embree's worker threads and first touches its
    // allocator's memory; an untimed build first makes both timed builds warm, as kdrt's build
    // time (the median of several builds in one process) is.
    build_scene(comparison, RTC_SCENE_FLAG_NONE);
    report.standard = measure_scene(comparison, RTC_SCENE_FLAG_NONE, "");
    report.robust = measure_scene(comparison, RTC_SCENE_FLAG_ROBUST, "robust_");
    return report;
}

}  // namespace kdrt::bench
