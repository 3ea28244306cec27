// Every hit along a ray: a scalar traversal that visits every leaf the ray passes within
// [tmin, tmax] (the cells of the closest-hit kernel, without its early exit), the same triangle
// test (ray_prep.h), then sort, de-duplication (a triangle referenced by several leaves) and the
// optional merging of coincident hits. Batches go through the packet kernels' every-hit
// traversal (packet_kernel.h, traverse_packet_all: each lane makes this traversal's decisions,
// so it finds the same raw hits), which hands each ray's raw hits back here for the same sort,
// de-duplication and merge; a ray with more raw hits than a packet lane keeps is traced again
// alone. Measured on the bunny (2 threads, tests/bench/README.md): packets trace primary rays
// 3x, diffuse 1.9x and random 1.15x as fast as single rays.

#include <algorithm>
#include <array>
#include <cmath>

#include <tbb/blocked_range.h>
#include <tbb/parallel_for.h>

#include "geometry.h"
#include "kdrt/query.h"
#include "packet.h"
#include "ray_prep.h"
#include "wide_kernel.h"

namespace kdrt {
namespace {

struct StackEntry {
    uint32_t node;
    float tmin;
    float tmax;
};

bool hit_less(const Hit& a, const Hit& b) noexcept {
    return a.t < b.t || (a.t == b.t && a.prim < b.prim);
}

/// Appends every hit with ray.tmin <= t <= ray.tmax of a triangle in a leaf the ray passes;
/// a triangle in several leaves is appended once per leaf (the caller removes the copies).
void collect(const KdTree& tree, const Ray& ray, std::vector<Hit>& out) {
    if (!detail::ray_is_valid(ray) || tree.bounds.empty()) return;
    const detail::PreparedRay p = detail::prepare_ray(ray);
    float eps[3];
    detail::traversal_eps(p, tree.bounds, eps);
    float tmin = ray.tmin, tmax = ray.tmax;
    if (!detail::clip_to_box(p, tree.bounds, eps, tmin, tmax)) return;
    const uint32_t near_is_high[3] = {std::signbit(p.inv_dir[0]) ? 1u : 0u,
                                      std::signbit(p.inv_dir[1]) ? 1u : 0u,
                                      std::signbit(p.inv_dir[2]) ? 1u : 0u};
    const KdNode* nodes = tree.nodes.data();
    const uint32_t* refs = tree.leaf_refs.data();
    const TriVerts* tris = tree.tris.data();
    const uint32_t* ids = tree.tri_ids.data();

    std::array<StackEntry, kMaxDepth + 2> stack;
    int stack_size = 0;
    uint32_t node_index = 0;
    for (;;) {
        KdNode node = nodes[node_index];
        // The closest-hit kernel's cell decisions (trace.cpp): each side's interval widened by
        // eps, a NaN split distance (a ray in the split plane) visiting both sides.
        while (!node.is_leaf()) {
            const int axis = node.axis();
            const float t_split = (node.split() - p.org[axis]) * p.inv_dir[axis];
            const uint32_t near_child = node.first_child() + near_is_high[axis];
            const uint32_t far_child = node.first_child() + (near_is_high[axis] ^ 1u);
            const float near_max = t_split + eps[axis], far_min = t_split - eps[axis];
            const bool need_near = !(near_max < tmin), need_far = !(far_min > tmax);
            if (need_near && need_far) {
                stack[stack_size++] = {far_child, far_min > tmin ? far_min : tmin, tmax};
                tmax = near_max < tmax ? near_max : tmax;
            }
            node_index = need_near ? near_child : far_child;
            node = nodes[node_index];
        }
        // Four references at a time in one pass (wide::intersect4, the closest-hit single-ray
        // kernel's leaf test); the spare lanes of a short block repeat its first triangle and
        // are not read.
        const uint32_t end = node.first_ref() + node.prim_count();
        for (uint32_t r = node.first_ref(); r < end; r += 4) {
            const uint32_t n = std::min(end - r, 4u);
            uint32_t slot[4];
            for (uint32_t i = 0; i < 4; ++i)
                slot[i] = refs[r + (i < n ? i : 0)] & ~KdTree::kLastRef;
            const TriVerts* const block[4] = {&tris[slot[0]], &tris[slot[1]], &tris[slot[2]],
                                              &tris[slot[3]]};
            detail::wide::Hits4 h;
            uint32_t hits = detail::wide::intersect4(p, block, ray.tmin, h) & ((1u << n) - 1u);
            hits &= detail::wide::bits4(h.t <= ray.tmax);
            for (; hits; hits &= hits - 1) {
                const int l = __builtin_ctz(hits);
                out.push_back(Hit{h.t[l], ids[slot[l]], h.v[l] / h.det[l], h.w[l] / h.det[l]});
            }
        }
        if (stack_size == 0) return;
        const StackEntry& e = stack[--stack_size];
        node_index = e.node;
        tmin = e.tmin;
        tmax = e.tmax;
    }
}

bool shares_vertex(const TriVerts& a, const TriVerts& b) noexcept {
    const float* pa[3] = {a.v0, a.v1, a.v2};
    const float* pb[3] = {b.v0, b.v1, b.v2};
    for (const float* x : pa)
        for (const float* y : pb)
            if (x[0] == y[0] && x[1] == y[1] && x[2] == y[2]) return true;
    return false;
}

/// True when `ray` runs along the right-hand normal of `tri` (d . n > 0, in double).
bool faces_along(const TriVerts& tri, const Ray& ray) noexcept {
    const double e1[3] = {double{tri.v1[0]} - tri.v0[0], double{tri.v1[1]} - tri.v0[1],
                          double{tri.v1[2]} - tri.v0[2]};
    const double e2[3] = {double{tri.v2[0]} - tri.v0[0], double{tri.v2[1]} - tri.v0[1],
                          double{tri.v2[2]} - tri.v0[2]};
    const double n[3] = {e1[1] * e2[2] - e1[2] * e2[1], e1[2] * e2[0] - e1[0] * e2[2],
                         e1[0] * e2[1] - e1[1] * e2[0]};
    return n[0] * ray.dx + n[1] * ray.dy + n[2] * ray.dz > 0.0;
}

float max_abs(const TriVerts& tri, float m) noexcept {
    for (const float* v : {tri.v0, tri.v1, tri.v2})
        for (int a = 0; a < 3; ++a) m = std::max(m, std::fabs(v[a]));
    return m;
}

/// AllHitsOptions::merge_coincident on hits sorted by (t, prim); `tri_of(prim)` gives a
/// triangle. Returns the new count.
template <class TriOf>
size_t merge_groups(TriOf tri_of, const Ray& ray, Hit* hits, size_t n) {
    const float dmax = std::max({std::fabs(ray.dx), std::fabs(ray.dy), std::fabs(ray.dz)});
    const float org_max = std::max({std::fabs(ray.ox), std::fabs(ray.oy), std::fabs(ray.oz)});
    size_t out = 0;
    size_t i = 0;
    while (i < n) {
        const float tol =
            max_abs(tri_of(hits[i].prim), org_max) * detail::kMergeToleranceScale / dmax;
        size_t j = i + 1;
        while (j < n && hits[j].t - hits[i].t <= tol) {
            const TriVerts& tj = tri_of(hits[j].prim);
            bool joined = false;
            for (size_t k = i; k < j && !joined; ++k)
                joined = shares_vertex(tj, tri_of(hits[k].prim));
            if (!joined) break;
            ++j;
        }
        // The lowest prim facing each way.
        size_t along = n, against = n;
        for (size_t k = i; k < j; ++k) {
            size_t& pick = faces_along(tri_of(hits[k].prim), ray) ? along : against;
            if (pick == n || hits[k].prim < hits[pick].prim) pick = k;
        }
        Hit picked[2];
        size_t count = 0;
        if (along != n) picked[count++] = hits[along];
        if (against != n) picked[count++] = hits[against];
        if (count == 2 && hit_less(picked[1], picked[0])) std::swap(picked[0], picked[1]);
        for (size_t k = 0; k < count; ++k) hits[out++] = picked[k];
        i = j;
    }
    return out;
}

void sort_unique(std::vector<Hit>& hits) {
    std::sort(hits.begin(), hits.end(), hit_less);
    // Copies of one triangle (from several leaves) have the same t and prim: adjacent.
    hits.erase(
        std::unique(hits.begin(), hits.end(),
                    [](const Hit& a, const Hit& b) { return a.prim == b.prim && a.t == b.t; }),
        hits.end());
}

/// Rays per parallel task of a batch: a few of the kernels' scheduling blocks' worth of sorting
/// freedom (an incoherent block is sorted whole), and enough tasks to keep every core busy.
constexpr size_t kTaskRays = 1024;

/// One task's answers, kept in the order the rays were traced: ray i's kept hits are
/// arena[start[i], + kept[i]).
struct TaskAnswers {
    std::vector<Hit> arena;
    std::vector<uint64_t> start;
    std::vector<uint32_t> kept;
};

/// The AllHitsSink of one task (rays [0, count) of `rays`): each ray's raw hits sorted, made
/// unique and merged here, its count written to counts[i], its nearest max_hits kept.
struct TaskSink : detail::AllHitsSink {
    const KdTree* tree;
    const Ray* rays;
    bool merge_coincident;
    uint32_t max_hits;
    uint32_t* counts;
    TaskAnswers* out;
    std::vector<Hit> scratch;

    void finish(size_t i) {
        sort_unique(scratch);
        size_t n = scratch.size();
        if (merge_coincident && n > 1)
            n = merge_groups([&](uint32_t prim) -> const TriVerts& { return tree->triangle(prim); },
                             rays[i], scratch.data(), n);
        counts[i] = static_cast<uint32_t>(n);
        const size_t keep = std::min<size_t>(n, max_hits);
        out->start[i] = out->arena.size();
        out->kept[i] = static_cast<uint32_t>(keep);
        out->arena.insert(out->arena.end(), scratch.begin(),
                          scratch.begin() + static_cast<ptrdiff_t>(keep));
    }

    static void trace_single(AllHitsSink& base, size_t i) {
        auto& self = static_cast<TaskSink&>(base);
        self.scratch.clear();
        collect(*self.tree, self.rays[i], self.scratch);
        self.finish(i);
    }

    static void take_packet(AllHitsSink& base, const size_t* ids, int lanes, const Hit* raw,
                            const uint32_t* count) {
        auto& self = static_cast<TaskSink&>(base);
        for (int l = 0; l < lanes; ++l) {
            if (count[l] > detail::kPacketHitCapacity) {  // overflowed: this ray on its own
                trace_single(base, ids[l]);
                continue;
            }
            const Hit* first = raw + static_cast<size_t>(l) * detail::kPacketHitCapacity;
            self.scratch.assign(first, first + count[l]);
            self.finish(ids[l]);
        }
    }
};

/// Every hit of rays[0, count) on the calling thread: counts[i] written for each ray, the kept
/// hits (up to max_hits a ray) into `out`, which is sized here.
void trace_task(const KdTree& tree, const Ray* rays, size_t count, const AllHitsOptions& options,
                uint32_t max_hits, uint32_t* counts, TaskAnswers& out) {
    out.arena.clear();
    out.start.assign(count, 0);
    out.kept.assign(count, 0);
    std::fill(counts, counts + count, 0u);  // invalid rays reach neither sink call
    TaskSink sink;
    sink.single = &TaskSink::trace_single;
    sink.packet = &TaskSink::take_packet;
    sink.tree = &tree;
    sink.rays = rays;
    sink.merge_coincident = options.merge_coincident;
    sink.max_hits = max_hits;
    sink.counts = counts;
    sink.out = &out;
    const detail::PacketKernels* kernels =
        options.mode == TraceMode::kSingle
            ? nullptr
            : detail::packet_kernels_for(detail::resolve_isa(options.isa));
    if (kernels == nullptr) {
        for (size_t i = 0; i < count; ++i) TaskSink::trace_single(sink, i);
        return;
    }
    kernels->all_hits(tree, rays, count, sink, detail::policy_for(options.mode));
}

}  // namespace

uint32_t intersect_all(const KdTree& tree, const Ray& ray, bool merge_coincident,
                       std::vector<Hit>& out) {
    out.clear();
    collect(tree, ray, out);
    sort_unique(out);
    if (merge_coincident && out.size() > 1) {
        const size_t n =
            merge_groups([&](uint32_t prim) -> const TriVerts& { return tree.triangle(prim); }, ray,
                         out.data(), out.size());
        out.resize(n);
    }
    return static_cast<uint32_t>(out.size());
}

AllHits intersect_all(const KdTree& tree, std::span<const Ray> rays,
                      const AllHitsOptions& options) {
    AllHits result;
    result.counts.resize(rays.size());
    result.offsets.assign(rays.size() + 1, 0);
    const size_t tasks = (rays.size() + kTaskRays - 1) / kTaskRays;
    std::vector<TaskAnswers> answers(tasks);
    tbb::parallel_for(size_t{0}, tasks, [&](size_t b) {
        const size_t first = b * kTaskRays, n = std::min(kTaskRays, rays.size() - first);
        trace_task(tree, rays.data() + first, n, options, options.max_hits,
                   result.counts.data() + first, answers[b]);
        for (size_t i = 0; i < n; ++i) result.offsets[first + i + 1] = answers[b].kept[i];
    });
    for (size_t i = 0; i < rays.size(); ++i) result.offsets[i + 1] += result.offsets[i];
    result.hits.resize(result.offsets.back());
    tbb::parallel_for(size_t{0}, tasks, [&](size_t b) {
        const TaskAnswers& a = answers[b];
        const size_t first = b * kTaskRays;
        for (size_t i = 0; i < a.kept.size(); ++i) {
            const auto from = a.arena.begin() + static_cast<ptrdiff_t>(a.start[i]);
            std::copy(from, from + a.kept[i],
                      result.hits.begin() + static_cast<ptrdiff_t>(result.offsets[first + i]));
        }
    });
    return result;
}

void count_intersections(const KdTree& tree, std::span<const Ray> rays,
                         const AllHitsOptions& options, std::span<uint32_t> counts) {
    const size_t tasks = (rays.size() + kTaskRays - 1) / kTaskRays;
    tbb::parallel_for(
        tbb::blocked_range<size_t>(0, tasks, 1), [&](const tbb::blocked_range<size_t>& range) {
            TaskAnswers unused;
            for (size_t b = range.begin(); b != range.end(); ++b) {
                const size_t first = b * kTaskRays;
                trace_task(tree, rays.data() + first, std::min(kTaskRays, rays.size() - first),
                           options, 0, counts.data() + first, unused);
            }
        });
}

void count_intersections(const KdTree& tree, std::span<const Ray> rays, bool merge_coincident,
                         std::span<uint32_t> counts) {
    AllHitsOptions options;
    options.merge_coincident = merge_coincident;
    count_intersections(tree, rays, options, counts);
}

std::vector<Hit> brute_force_intersect_all(std::span<const TriVerts> tris, const Ray& ray,
                                           bool merge_coincident) {
    std::vector<Hit> out;
    if (!detail::ray_is_valid(ray)) return out;
    const detail::PreparedRay p = detail::prepare_ray(ray);
    for (uint32_t prim = 0; prim < tris.size(); ++prim) {
        float t, u, v;
        if (!detail::intersect_triangle(p, tris[prim], ray.tmin, t, u, v)) continue;
        if (t <= ray.tmax) out.push_back(Hit{t, prim, u, v});
    }
    std::sort(out.begin(), out.end(), hit_less);
    if (merge_coincident && out.size() > 1) {
        const size_t n = merge_groups([&](uint32_t prim) -> const TriVerts& { return tris[prim]; },
                                      ray, out.data(), out.size());
        out.resize(n);
    }
    return out;
}

Vec3 triangle_normal(const TriVerts& tri) noexcept {
    double n[3];
    const double len = detail::edge_cross(tri, n);
    if (!(len > 0.0) || !std::isfinite(len)) return {};
    return {static_cast<float>(n[0] / len), static_cast<float>(n[1] / len),
            static_cast<float>(n[2] / len)};
}

Vec3 hit_point(const TriVerts& tri, const Hit& hit) noexcept {
    const Vec3 v0{tri.v0[0], tri.v0[1], tri.v0[2]};
    const Vec3 v1{tri.v1[0], tri.v1[1], tri.v1[2]};
    const Vec3 v2{tri.v2[0], tri.v2[1], tri.v2[2]};
    return v0 * (1.0f - hit.u - hit.v) + v1 * hit.u + v2 * hit.v;
}

void hit_attributes(const KdTree& tree, std::span<const Hit> hits, std::span<Vec3> normals,
                    std::span<Vec3> points) {
    tbb::parallel_for(tbb::blocked_range<size_t>(0, hits.size(), 4096),
                      [&](const tbb::blocked_range<size_t>& range) {
                          for (size_t i = range.begin(); i != range.end(); ++i) {
                              const TriVerts& tri = tree.triangle(hits[i].prim);
                              if (!normals.empty()) normals[i] = triangle_normal(tri);
                              if (!points.empty()) points[i] = hit_point(tri, hits[i]);
                          }
                      });
}

}  // namespace kdrt
