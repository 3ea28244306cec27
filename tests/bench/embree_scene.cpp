// Embree instancing for `kdrt-bench scene instances --compare embree` (embree_scene.h). Embree 4
// or 3 through its public headers, selected by embree_api.h.

#include "embree_scene.h"

#include "embree_api.h"

#include <tbb/blocked_range.h>
#include <tbb/parallel_for.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <limits>
#include <mutex>

namespace kdrt::bench {
namespace {

using Clock = std::chrono::steady_clock;

double ms_since(Clock::time_point start) {
    return std::chrono::duration<double, std::milli>(Clock::now() - start).count();
}

constexpr size_t kBlock = 256;

std::mutex g_error_mutex;
std::string g_first_error;

void on_error(void*, RTCError code, const char* message) {
    const std::lock_guard lock(g_error_mutex);
    if (g_first_error.empty())
        g_first_error = "Embree error " + std::to_string(static_cast<int>(code)) + ": " +
                        (message ? message : "(no message)");
}

void check(RTCDevice device, const char* what) {
    const RTCError code = rtcGetDeviceError(device);
    const std::lock_guard lock(g_error_mutex);
    if (code != RTC_ERROR_NONE || !g_first_error.empty())
        throw EmbreeError(std::string(what) + " failed: " +
                          (g_first_error.empty() ? "code " + std::to_string(static_cast<int>(code))
                                                 : g_first_error));
}

/// Writes lane `lane` of an Embree ray; scalar fields for RTCRay, arrays for RTCRay8.
template <class R>
void set_ray(R& e, int lane, const Ray& r) noexcept {
    auto put = [&](auto& field, auto value) {
        if constexpr (std::is_array_v<std::remove_reference_t<decltype(field)>>)
            field[lane] = value;
        else
            field = value;
    };
    put(e.org_x, r.ox);
    put(e.org_y, r.oy);
    put(e.org_z, r.oz);
    put(e.dir_x, r.dx);
    put(e.dir_y, r.dy);
    put(e.dir_z, r.dz);
    put(e.tnear, r.tmin);
    put(e.tfar, r.tmax);
    put(e.time, 0.0f);
    put(e.mask, ~0u);
    put(e.id, 0u);
    put(e.flags, 0u);
}

}  // namespace

struct EmbreeInstanceScene::Impl {
    RTCDevice device = nullptr;
    RTCScene blas = nullptr;
    RTCScene top = nullptr;
    std::vector<RTCGeometry> instances;
    double blas_ms = 0, top_ms = 0;

    ~Impl() {
        for (RTCGeometry g : instances) rtcReleaseGeometry(g);
        if (top) rtcReleaseScene(top);
        if (blas) rtcReleaseScene(blas);
        if (device) rtcReleaseDevice(device);
    }

    template <bool Occlusion, int W>
    void run(std::span<const Ray> rays, bool coherent, std::span<SceneHit> hits,
             std::span<uint8_t> occ) {
        const size_t blocks = (rays.size() + kBlock - 1) / kBlock;
        tbb::parallel_for(
            tbb::blocked_range<size_t>(0, blocks), [&](const tbb::blocked_range<size_t>& br) {
                QueryArgs q(coherent);
                for (size_t b = br.begin(); b != br.end(); ++b) {
                    const size_t lo = b * kBlock, hi = std::min(rays.size(), lo + kBlock);
                    if constexpr (W == 1) {
                        for (size_t i = lo; i < hi; ++i) {
                            if constexpr (Occlusion) {
                                RTCRay r;
                                set_ray(r, 0, rays[i]);
                                query(rtcOccluded1, top, &r, q.occluded_args());
                                occ[i] = r.tfar == -std::numeric_limits<float>::infinity() ? 1 : 0;
                            } else {
                                RTCRayHit rh;
                                set_ray(rh.ray, 0, rays[i]);
                                rh.hit.geomID = RTC_INVALID_GEOMETRY_ID;
                                rh.hit.instID[0] = RTC_INVALID_GEOMETRY_ID;
                                query(rtcIntersect1, top, &rh, q.intersect_args());
                                hits[i] = rh.hit.geomID == RTC_INVALID_GEOMETRY_ID
                                              ? SceneHit{}
                                              : SceneHit{rh.ray.tfar, rh.hit.primID, rh.hit.u,
                                                         rh.hit.v, rh.hit.instID[0]};
                            }
                        }
                    } else {
                        for (size_t first = lo; first < hi; first += 8) {
                            alignas(32) int valid[8];
                            const size_t n = std::min<size_t>(8, hi - first);
                            if constexpr (Occlusion) {
                                alignas(32) RTCRay8 r;
                                for (int l = 0; l < 8; ++l) {
                                    valid[l] = static_cast<size_t>(l) < n ? -1 : 0;
                                    set_ray(r, l, rays[first + std::min<size_t>(l, n - 1)]);
                                }
                                query_packet(rtcOccluded8, valid, top, &r, q.occluded_args());
                                for (size_t l = 0; l < n; ++l)
                                    occ[first + l] =
                                        r.tfar[l] == -std::numeric_limits<float>::infinity() ? 1
                                                                                             : 0;
                            } else {
                                alignas(32) RTCRayHit8 rh;
                                for (int l = 0; l < 8; ++l) {
                                    valid[l] = static_cast<size_t>(l) < n ? -1 : 0;
                                    set_ray(rh.ray, l, rays[first + std::min<size_t>(l, n - 1)]);
                                    rh.hit.geomID[l] = RTC_INVALID_GEOMETRY_ID;
                                    rh.hit.instID[0][l] = RTC_INVALID_GEOMETRY_ID;
                                }
                                query_packet(rtcIntersect8, valid, top, &rh, q.intersect_args());
                                for (size_t l = 0; l < n; ++l)
                                    hits[first + l] =
                                        rh.hit.geomID[l] == RTC_INVALID_GEOMETRY_ID
                                            ? SceneHit{}
                                            : SceneHit{rh.ray.tfar[l], rh.hit.primID[l],
                                                       rh.hit.u[l], rh.hit.v[l],
                                                       rh.hit.instID[0][l]};
                            }
                        }
                    }
                }
            });
    }
};

EmbreeInstanceScene::EmbreeInstanceScene(const Mesh& mesh, std::span<const Affine3x4> transforms)
    : impl_(std::make_unique<Impl>()) {
    Impl& m = *impl_;
    m.device = rtcNewDevice(nullptr);
    if (!m.device) throw EmbreeError("rtcNewDevice failed");
    rtcSetDeviceErrorFunction(m.device, on_error, nullptr);
    auto start = Clock::now();
    m.blas = rtcNewScene(m.device);
    rtcSetSceneBuildQuality(m.blas, RTC_BUILD_QUALITY_HIGH);
    RTCGeometry tris = rtcNewGeometry(m.device, RTC_GEOMETRY_TYPE_TRIANGLE);
    auto* v = static_cast<float*>(rtcSetNewGeometryBuffer(tris, RTC_BUFFER_TYPE_VERTEX, 0,
                                                          RTC_FORMAT_FLOAT3, 3 * sizeof(float),
                                                          mesh.vertex_count()));
    auto* idx = static_cast<uint32_t*>(
        rtcSetNewGeometryBuffer(tris, RTC_BUFFER_TYPE_INDEX, 0, RTC_FORMAT_UINT3,
                                3 * sizeof(uint32_t), mesh.triangle_count()));
    check(m.device, "rtcSetNewGeometryBuffer");
    std::copy(mesh.positions.begin(), mesh.positions.end(), v);
    std::copy(mesh.indices.begin(), mesh.indices.end(), idx);
    rtcCommitGeometry(tris);
    rtcAttachGeometry(m.blas, tris);
    rtcReleaseGeometry(tris);
    rtcCommitScene(m.blas);
    check(m.device, "BLAS build");
    m.blas_ms = ms_since(start);

    start = Clock::now();
    m.top = rtcNewScene(m.device);
    for (uint32_t i = 0; i < transforms.size(); ++i) {
        RTCGeometry inst = rtcNewGeometry(m.device, RTC_GEOMETRY_TYPE_INSTANCE);
        rtcSetGeometryInstancedScene(inst, m.blas);
        rtcSetGeometryTransform(inst, 0, RTC_FORMAT_FLOAT3X4_ROW_MAJOR, &transforms[i].m[0][0]);
        rtcCommitGeometry(inst);
        rtcAttachGeometryByID(m.top, inst, i);  // instID = kdrt's geometry id
        m.instances.push_back(inst);
    }
    rtcCommitScene(m.top);
    check(m.device, "top-level build");
    m.top_ms = ms_since(start);
}

EmbreeInstanceScene::~EmbreeInstanceScene() = default;

double EmbreeInstanceScene::blas_build_ms() const noexcept { return impl_->blas_ms; }
double EmbreeInstanceScene::top_build_ms() const noexcept { return impl_->top_ms; }

double EmbreeInstanceScene::set_transforms(std::span<const Affine3x4> transforms) {
    const auto start = Clock::now();
    for (size_t i = 0; i < transforms.size(); ++i) {
        rtcSetGeometryTransform(impl_->instances[i], 0, RTC_FORMAT_FLOAT3X4_ROW_MAJOR,
                                &transforms[i].m[0][0]);
        rtcCommitGeometry(impl_->instances[i]);
    }
    rtcCommitScene(impl_->top);
    const double ms = ms_since(start);
    check(impl_->device, "pose update");
    return ms;
}

EmbreeSceneTiming EmbreeInstanceScene::trace(std::span<const Ray> rays, bool occlusion, int reps,
                                             std::span<SceneHit> hits, std::span<uint8_t> occ) {
    struct Mode {
        const char* name;
        int width;
        bool coherent;
    };
    const Mode modes[] = {{"1", 1, false}, {"8", 8, false}, {"8_coherent", 8, true}};
    const auto run_mode = [&](const Mode& mode) {
        if (occlusion) {
            if (mode.width == 1)
                impl_->run<true, 1>(rays, mode.coherent, hits, occ);
            else
                impl_->run<true, 8>(rays, mode.coherent, hits, occ);
        } else {
            if (mode.width == 1)
                impl_->run<false, 1>(rays, mode.coherent, hits, occ);
            else
                impl_->run<false, 8>(rays, mode.coherent, hits, occ);
        }
    };
    EmbreeSceneTiming out;
    const std::string prefix = occlusion ? "occluded" : "intersect";
    int best = 0;
    for (int k = 0; k < 3; ++k) {
        run_mode(modes[k]);  // warm-up
        std::vector<double> seconds;
        for (int r = 0; r < reps; ++r) {
            const auto start = Clock::now();
            run_mode(modes[k]);
            seconds.push_back(std::chrono::duration<double>(Clock::now() - start).count());
        }
        std::sort(seconds.begin(), seconds.end());
        const double mrays = static_cast<double>(rays.size()) / seconds[seconds.size() / 2] / 1e6;
        out.modes.emplace_back(prefix + modes[k].name, mrays);
        if (mrays > out.best_mrays_per_s) {
            out.best_mrays_per_s = mrays;
            out.best_mode = prefix + modes[k].name;
            best = k;
        }
    }
    check(impl_->device, "tracing");
    if (best != 2) run_mode(modes[best]);  // leave the best mode's answers in the outputs
    return out;
}

}  // namespace kdrt::bench
