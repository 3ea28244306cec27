// Scenes: validation of the instances, their inverses and world boxes, and the top-level SAH
// kD-tree over the world boxes (binned: O(n) per level, so O(n log n) in the instance count).

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstring>
#include <numeric>
#include <string>

#include "format.h"
#include "kdrt/scene.h"
#include "scene_internal.h"

namespace kdrt {
namespace {

using detail::InstanceData;
using detail::SceneData;
using detail::TopNode;

/// Largest condition number || |L| |L^-1| ||_inf of an instance's transform.
constexpr double kMaxCondition = 0x1p24;

[[noreturn]] void fail(uint32_t index, const std::string& field, const std::string& why) {
    throw SceneError(index, field, "scene instance " + std::to_string(index) + " " + why);
}

/// The float next to finite `f` towards -inf / +inf (std::nextafter's answer, inline: it is
/// called for most world-box coordinates; f is never the float range's end here).
float next_down(float f) noexcept {
    if (f == 0.0f) return -std::numeric_limits<float>::denorm_min();
    uint32_t bits;
    std::memcpy(&bits, &f, sizeof bits);
    bits = f > 0.0f ? bits - 1u : bits + 1u;
    std::memcpy(&f, &bits, sizeof bits);
    return f;
}
float next_up(float f) noexcept { return -next_down(-f); }

/// A float rounded towards -inf / +inf from a double (finite, within float range).
float round_down(double x) noexcept {
    auto f = static_cast<float>(x);
    if (static_cast<double>(f) > x) f = next_down(f);
    return f;
}
float round_up(double x) noexcept {
    auto f = static_cast<float>(x);
    if (static_cast<double>(f) < x) f = next_up(f);
    return f;
}

double box_magnitude(const Aabb& b) noexcept {
    double m = 0.0;
    for (int a = 0; a < 3; ++a)
        m = std::max(
            {m, std::fabs(static_cast<double>(b.lo[a])), std::fabs(static_cast<double>(b.hi[a]))});
    return m;
}

/// The least and greatest image of row r of `world = L * p + t` over the box's 8 corners (in
/// corner order: the first corner's value among equal ones).
void corner_scan(const std::array<double, 9>& L, const std::array<double, 3>& t, const Aabb& ob,
                 int r, double& lo, double& hi) noexcept {
    lo = std::numeric_limits<double>::infinity();
    hi = -std::numeric_limits<double>::infinity();
    for (int corner = 0; corner < 8; ++corner) {
        const double p[3] = {(corner & 1) ? ob.hi.x : ob.lo.x, (corner & 2) ? ob.hi.y : ob.lo.y,
                             (corner & 4) ? ob.hi.z : ob.lo.z};
        const double w = L[3 * r] * p[0] + L[3 * r + 1] * p[1] + L[3 * r + 2] * p[2] + t[r];
        lo = std::min(lo, w);
        hi = std::max(hi, w);
    }
}

/// The instance's clearance, if any, is one of its tree's triangle count (tree not null).
void check_clearance(uint32_t index, const SceneInstance& inst) {
    if (inst.clearance && inst.clearance->size() != inst.tree->tri_slots.size())
        fail(index, "clearance",
             "has a hit clearance of " + std::to_string(inst.clearance->size()) +
                 " triangles for a tree of " + std::to_string(inst.tree->tri_slots.size()));
}

/// Validates instance `index` placed by `m` (its transform, or a new one: no copy of the
/// instance's shared data) and computes everything the queries need of it.
/// `field` prefixes the entry names ("transform").
InstanceData prepare_instance(uint32_t index, const SceneInstance& inst, const Affine3x4& m) {
    if (!inst.tree) fail(index, "tree", "has no mesh tree");
    check_clearance(index, inst);
    for (int r = 0; r < 3; ++r) {
        for (int c = 0; c < 4; ++c) {
            if (!std::isfinite(m.m[r][c])) {
                const std::string field =
                    "transform[" + std::to_string(r) + "][" + std::to_string(c) + "]";
                fail(index, field, field + " is " + detail::format_float(m.m[r][c]));
            }
        }
    }
    InstanceData d;
    for (int r = 0; r < 3; ++r) {
        for (int c = 0; c < 3; ++c) d.lin[3 * r + c] = m.m[r][c];
        d.trans[r] = m.m[r][3];
    }
    const auto& L = d.lin;
    // Cofactors: inverse = adj / det.
    const std::array<double, 9> cof{
        L[4] * L[8] - L[5] * L[7], L[5] * L[6] - L[3] * L[8], L[3] * L[7] - L[4] * L[6],
        L[2] * L[7] - L[1] * L[8], L[0] * L[8] - L[2] * L[6], L[1] * L[6] - L[0] * L[7],
        L[1] * L[5] - L[2] * L[4], L[2] * L[3] - L[0] * L[5], L[0] * L[4] - L[1] * L[3]};
    d.det = L[0] * cof[0] + L[1] * cof[1] + L[2] * cof[2];
    d.identity_linear = L == std::array<double, 9>{1, 0, 0, 0, 1, 0, 0, 0, 1};
    double rows = 1.0;
    for (int r = 0; r < 3; ++r)
        rows *= std::sqrt(L[3 * r] * L[3 * r] + L[3 * r + 1] * L[3 * r + 1] +
                          L[3 * r + 2] * L[3 * r + 2]);
    // |det| / (product of row lengths) is 1 for orthogonal rows and 0 for dependent ones.
    if (!(std::fabs(d.det) > 1e-9 * rows) || !std::isfinite(d.det))
        fail(index, "transform",
             "transform is singular or nearly so (det " + std::to_string(d.det) + ")");
    for (int r = 0; r < 3; ++r)
        for (int c = 0; c < 3; ++c) d.inv[3 * r + c] = cof[3 * c + r] / d.det;  // adj = cof^T
    for (double v : d.inv) {
        if (!std::isfinite(v) || std::fabs(v) > std::numeric_limits<float>::max())
            fail(index, "transform", "transform's inverse overflows float");
    }
    // kappa = || |L| |L^-1| ||_inf, and |L|_inf.
    double lin_norm = 0.0;
    d.kappa = 1.0;
    for (int r = 0; r < 3; ++r) {
        double row = 0.0, lrow = 0.0;
        for (int c = 0; c < 3; ++c) {
            lrow += std::fabs(L[3 * r + c]);
            for (int k = 0; k < 3; ++k)
                row += std::fabs(L[3 * r + k]) * std::fabs(d.inv[3 * k + c]);
        }
        d.kappa = std::max(d.kappa, row);
        lin_norm = std::max(lin_norm, lrow);
    }
    // Beyond 2^24 one float ulp of an object ray is more than the transform's thinnest axis.
    if (!(d.kappa <= kMaxCondition))
        fail(index, "transform",
             "transform is nearly singular (condition number " + std::to_string(d.kappa) +
                 " above 2^24)");
    d.trans_mag = std::max({std::fabs(d.trans[0]), std::fabs(d.trans[1]), std::fabs(d.trans[2])});

    // Similarity: L^T L = s^2 I within 1e-5 s^2.
    std::array<double, 9> ltl{};
    for (int a = 0; a < 3; ++a)
        for (int b = 0; b < 3; ++b)
            for (int r = 0; r < 3; ++r) ltl[3 * a + b] += L[3 * r + a] * L[3 * r + b];
    const double s2 = (ltl[0] + ltl[4] + ltl[8]) / 3.0;
    bool similar = s2 > 0.0;
    for (int a = 0; a < 3 && similar; ++a)
        for (int b = 0; b < 3; ++b)
            if (!(std::fabs(ltl[3 * a + b] - (a == b ? s2 : 0.0)) <= 1e-5 * s2)) similar = false;
    if (similar) d.scale = std::sqrt(s2);

    const Aabb& ob = inst.tree->bounds;
    d.root_mag = box_magnitude(ob);
    d.lin_bounds = lin_norm * d.root_mag;
    if (!ob.empty()) {
        // Row r's least and greatest image over the 8 corners, each L[r][c] * p[c] + ... + t
        // summed left to right. A rounded sum is monotone in each term, so the corner taking
        // each term's least (greatest) product gives the least (greatest) sum: the same double
        // as the 8-corner scan, in 6 products a row instead of 24. Only the sign of a zero
        // could differ (the scan keeps the first corner's among equal ones; not seen in the
        // test's zero bounds, where ties pick the low corner in both): a zero bound is scanned.
        double lo[3], hi[3];
        for (int r = 0; r < 3; ++r) {
            double pl[3], ph[3];
            for (int c = 0; c < 3; ++c) {
                const double a = L[3 * r + c] * static_cast<double>(ob.lo[c]);
                const double b = L[3 * r + c] * static_cast<double>(ob.hi[c]);
                pl[c] = std::min(a, b);
                ph[c] = std::max(a, b);
            }
            lo[r] = pl[0] + pl[1] + pl[2] + d.trans[r];
            hi[r] = ph[0] + ph[1] + ph[2] + d.trans[r];
            if (lo[r] == 0.0 || hi[r] == 0.0) corner_scan(L, d.trans, ob, r, lo[r], hi[r]);
        }
        constexpr double kFloatMax = std::numeric_limits<float>::max();
        for (int a = 0; a < 3; ++a) {
            if (!(lo[a] >= -kFloatMax && hi[a] <= kFloatMax))
                fail(index, "transform", "transform puts the mesh beyond float range");
            d.world.lo[a] = round_down(lo[a]);
            d.world.hi[a] = round_up(hi[a]);
        }
    }
    return d;
}

// ---------------------------------------------------------------------------------------------
// The top-level build: binned SAH over the world boxes clipped to the cell, references
// duplicated across a split as the mesh build duplicates triangles.

constexpr int kBins = 32;

double half_area(const Aabb& b) noexcept {
    const double x = b.hi.x - b.lo.x, y = b.hi.y - b.lo.y, z = b.hi.z - b.lo.z;
    return x * y + y * z + z * x;
}

struct TopBuilder {
    /// The instances' world boxes, contiguous (InstanceData is large: reading the boxes from it
    /// costs a cache line each).
    const std::vector<Aabb>& boxes;
    const SceneBuildOptions& opt;
    std::vector<TopNode>& nodes;
    std::vector<uint32_t>& refs;
    uint32_t max_depth = 0;
    int depth_cap = 0;
    uint64_t leaves = 0;

    void make_leaf(uint32_t index, std::vector<uint32_t>& geoms) {
        // The references arrive sorted (the root's list is, and a split keeps their order).
        if (!std::is_sorted(geoms.begin(), geoms.end())) std::sort(geoms.begin(), geoms.end());
        nodes[index] = TopNode{(static_cast<uint32_t>(geoms.size()) << 2) | 3u,
                               static_cast<uint32_t>(refs.size())};
        refs.insert(refs.end(), geoms.begin(), geoms.end());
        ++leaves;
    }

    void build(uint32_t index, std::vector<uint32_t> geoms, const Aabb& cell, int depth) {
        max_depth = std::max(max_depth, static_cast<uint32_t>(depth));
        const auto n = static_cast<double>(geoms.size());
        const double leaf_cost = opt.instance_cost * n;
        if (geoms.size() <= 1 || depth >= depth_cap) return make_leaf(index, geoms);
        const double area = half_area(cell);
        double best_cost = std::numeric_limits<double>::infinity();
        int best_axis = -1;
        float best_split = 0.0f;
        const Vec3 ext = cell.extent();
        const double side_sum[3] = {static_cast<double>(ext.y) + ext.z,
                                    static_cast<double>(ext.x) + ext.z,
                                    static_cast<double>(ext.x) + ext.y};
        const double side_product[3] = {static_cast<double>(ext.y) * ext.z,
                                        static_cast<double>(ext.x) * ext.z,
                                        static_cast<double>(ext.x) * ext.y};
        // Few references need few candidate planes: the per-node cost stays O(n), not O(bins).
        // (n + 2 planes for n references give the 16- and 1,000-instance grids the trees of 4 n,
        // at a fifth less build work; the sweep over the bins is most of a small node's cost.)
        const int bins = std::min(kBins, static_cast<int>(geoms.size()) + 2);
        // The bins of all three axes in one pass over the references.
        std::array<std::array<uint32_t, kBins>, 3> starts{}, ends{};
        double to_bin[3];
        for (int axis = 0; axis < 3; ++axis) {
            const double extent = static_cast<double>(cell.hi[axis]) - cell.lo[axis];
            to_bin[axis] = extent > 0.0 ? bins / extent : 0.0;
        }
        for (uint32_t g : geoms) {
            const Aabb& b = boxes[g];  // clamped into the cell's bins
            for (int axis = 0; axis < 3; ++axis) {
                const double lo = cell.lo[axis];
                const auto bin = [&](float x) {
                    return static_cast<size_t>(
                        std::clamp(static_cast<int>((x - lo) * to_bin[axis]), 0, bins - 1));
                };
                ++starts[axis][bin(std::max(b.lo[axis], cell.lo[axis]))];
                ++ends[axis][bin(std::min(b.hi[axis], cell.hi[axis]))];
            }
        }
        for (int axis = 0; axis < 3; ++axis) {
            const double lo = cell.lo[axis], hi = cell.hi[axis], extent = hi - lo;
            if (!(extent > 0.0)) continue;
            uint32_t left = 0, right = static_cast<uint32_t>(geoms.size());
            for (int k = 1; k < bins; ++k) {
                left += starts[axis][static_cast<size_t>(k - 1)];
                right -= ends[axis][static_cast<size_t>(k - 1)];
                const auto split = static_cast<float>(lo + extent * k / bins);
                if (!(split > cell.lo[axis] && split < cell.hi[axis])) continue;
                // Half the surface of each side: its length here times the sum of the cell's
                // other two extents, plus their product.
                const double la = (split - lo) * side_sum[axis] + side_product[axis];
                const double ra = (hi - split) * side_sum[axis] + side_product[axis];
                double cost =
                    opt.traversal_cost + opt.instance_cost * (la * left + ra * right) / area;
                if (left == 0 || right == 0) cost *= 1.0 - opt.empty_bonus;
                if (cost < best_cost) {
                    best_cost = cost;
                    best_axis = axis;
                    best_split = split;
                }
            }
        }
        if (best_axis < 0 || !(best_cost < leaf_cost)) return make_leaf(index, geoms);
        // A box touching the plane goes to both sides: the traversal's margin reaches both.
        // Counted first, so each side is allocated once at its size (no growth).
        size_t n_left = 0, n_right = 0;
        for (uint32_t g : geoms) {
            const Aabb& b = boxes[g];
            n_left += b.lo[best_axis] <= best_split;
            n_right += b.hi[best_axis] >= best_split;
        }
        if (n_left == geoms.size() && n_right == geoms.size()) return make_leaf(index, geoms);
        std::vector<uint32_t> left(n_left), right(n_right);
        size_t l = 0, r = 0;
        for (uint32_t g : geoms) {
            const Aabb& b = boxes[g];
            if (b.lo[best_axis] <= best_split) left[l++] = g;
            if (b.hi[best_axis] >= best_split) right[r++] = g;
        }
        geoms.clear();
        geoms.shrink_to_fit();
        const auto first = static_cast<uint32_t>(nodes.size());
        nodes.resize(nodes.size() + 2);
        uint32_t split_bits;
        std::memcpy(&split_bits, &best_split, sizeof split_bits);
        nodes[index] = TopNode{(first << 2) | static_cast<uint32_t>(best_axis), split_bits};
        Aabb lcell = cell, rcell = cell;
        lcell.hi[best_axis] = best_split;
        rcell.lo[best_axis] = best_split;
        build(first, std::move(left), lcell, depth + 1);
        build(first + 1, std::move(right), rcell, depth + 1);
    }
};

/// Builds the top level and the statistics of `d` (its instances and inst filled).
void build_top(SceneData& d, std::chrono::steady_clock::time_point start) {
    d.bounds = Aabb{};
    d.first_not_similar.reset();
    d.first_without_surface.reset();
    d.kappa_max = 1.0;
    d.size_max = 0.0;
    std::vector<uint32_t> geoms;
    for (uint32_t g = 0; g < d.inst.size(); ++g) {
        const InstanceData& in = d.inst[g];
        d.kappa_max = std::max(d.kappa_max, in.kappa);
        d.size_max = std::max({d.size_max, in.trans_mag, in.lin_bounds});
        if (in.world.empty()) continue;
        if (!in.scale && !d.first_not_similar) d.first_not_similar = g;
        if (!d.instances[g].surface && !d.first_without_surface) d.first_without_surface = g;
        d.bounds.extend(in.world.lo);
        d.bounds.extend(in.world.hi);
        geoms.push_back(g);
    }
    d.size_max = std::max(d.size_max, box_magnitude(d.bounds));
    d.nodes.assign(1, TopNode{});
    d.refs.clear();
    std::vector<Aabb> boxes(d.inst.size());
    for (size_t g = 0; g < boxes.size(); ++g) boxes[g] = d.inst[g].world;
    TopBuilder builder{boxes, d.options, d.nodes, d.refs};
    const double n = static_cast<double>(std::max<size_t>(geoms.size(), 1));
    builder.depth_cap = std::min(detail::kTopMaxDepth, static_cast<int>(8.0 + 1.3 * std::log2(n)));
    if (!geoms.empty()) builder.build(0, std::move(geoms), d.bounds, 0);
    d.nodes.shrink_to_fit();
    d.refs.shrink_to_fit();
    {
        std::vector<uint8_t> listed(d.inst.size(), 0);
        d.refs_unique = true;
        for (const uint32_t g : d.refs) {
            if (listed[g]) d.refs_unique = false;
            listed[g] = 1;
        }
    }

    SceneStats& st = d.stats;
    st.instances = d.instances.size();
    st.nodes = d.nodes.size();
    st.leaves = builder.leaves;
    st.refs = d.refs.size();
    st.max_depth = builder.max_depth;
    st.bytes = sizeof(SceneData) + d.instances.capacity() * sizeof(SceneInstance) +
               d.inst.capacity() * sizeof(InstanceData) + d.nodes.capacity() * sizeof(TopNode) +
               d.refs.capacity() * sizeof(uint32_t);
    st.bytes_per_instance =
        d.instances.empty() ? 0.0 : static_cast<double>(st.bytes) / d.instances.size();
    st.build_ms =
        std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - start).count();
}

const SceneData& empty_scene() {
    static const SceneData data;  // no instances, no nodes: every walk stops at once
    return data;
}

}  // namespace

Scene::Scene() noexcept
    : data_(std::shared_ptr<const SceneData>(std::shared_ptr<const SceneData>{}, &empty_scene())) {}

Scene::Scene(std::shared_ptr<const SceneData> data) noexcept : data_(std::move(data)) {}

uint32_t Scene::size() const noexcept { return static_cast<uint32_t>(data_->instances.size()); }
const SceneInstance& Scene::instance(uint32_t geom) const noexcept {
    return data_->instances[geom];
}
std::vector<SceneInstance> Scene::instances() const { return data_->instances; }
Aabb Scene::world_bounds(uint32_t geom) const noexcept { return data_->inst[geom].world; }
const Aabb& Scene::bounds() const noexcept { return data_->bounds; }
const SceneStats& Scene::stats() const noexcept { return data_->stats; }
const SceneBuildOptions& Scene::options() const noexcept { return data_->options; }

Ray Scene::object_ray(uint32_t geom, const Ray& world) const noexcept {
    return detail::to_object(data_->inst[geom], world);
}
std::array<double, 9> Scene::inverse_linear(uint32_t geom) const noexcept {
    return data_->inst[geom].inv;
}
std::optional<double> Scene::similarity_scale(uint32_t geom) const noexcept {
    return data_->inst[geom].scale;
}

Scene build_scene(std::vector<SceneInstance> instances, const SceneBuildOptions& options) {
    const auto start = std::chrono::steady_clock::now();
    const uint32_t limit = std::min(options.max_instances, kMaxSceneInstances);
    if (instances.size() > limit) {
        throw SceneError(limit, "instances",
                         "scene has " + std::to_string(instances.size()) +
                             " instances, more than the limit of " + std::to_string(limit));
    }
    auto d = std::make_shared<SceneData>();
    d->options = options;
    d->inst.reserve(instances.size());
    for (uint32_t i = 0; i < instances.size(); ++i)
        d->inst.push_back(prepare_instance(i, instances[i], instances[i].transform));
    d->instances = std::move(instances);
    build_top(*d, start);
    return Scene(std::move(d));
}

namespace {
void check_pose_geom(const InstancePose& pose, size_t instances) {
    if (pose.geom >= instances) {
        throw SceneError(pose.geom, "geom",
                         "pose geom " + std::to_string(pose.geom) +
                             " names no scene instance (the scene has " +
                             std::to_string(instances) + ")");
    }
}
}  // namespace

Scene Scene::with_transforms(std::span<const InstancePose> poses) const {
    const auto start = std::chrono::steady_clock::now();
    auto d = std::make_shared<SceneData>();
    d->options = data_->options;
    d->instances = data_->instances;
    d->inst = data_->inst;
    for (const InstancePose& pose : poses) {
        check_pose_geom(pose, d->instances.size());
        // In place (d is this call's own): no copy of the instance's shared pointers.
        SceneInstance& moved = d->instances[pose.geom];
        d->inst[pose.geom] = prepare_instance(pose.geom, moved, pose.transform);
        moved.transform = pose.transform;
    }
    build_top(*d, start);
    return Scene(std::move(d));
}

Scene Scene::with_clearances(
    std::span<const std::shared_ptr<const HitClearance>> per_instance) const {
    if (per_instance.size() != data_->instances.size()) {
        throw std::invalid_argument("with_clearances: " + std::to_string(per_instance.size()) +
                                    " clearances for " + std::to_string(data_->instances.size()) +
                                    " instances");
    }
    auto d = std::make_shared<SceneData>(*data_);
    for (uint32_t g = 0; g < per_instance.size(); ++g) {
        SceneInstance& in = d->instances[g];
        in.clearance = per_instance[g];
        check_clearance(g, in);
    }
    return Scene(std::move(d));
}

void Scene::check_transforms(std::span<const InstancePose> poses) const {
    for (const InstancePose& pose : poses) {
        check_pose_geom(pose, data_->instances.size());
        (void)prepare_instance(pose.geom, data_->instances[pose.geom], pose.transform);
    }
}

Scene Scene::with_transform(uint32_t geom, const Affine3x4& transform) const {
    const InstancePose pose{geom, transform};
    return with_transforms(std::span<const InstancePose>(&pose, 1));
}

}  // namespace kdrt
