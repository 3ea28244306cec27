// The top level's packet walk (scene_packet.h) with the eight lanes in one AVX2 register instead
// of two SSE halves: the same float operations lane by lane (no FMA: -ffp-contract=off and no
// fma target), so the same cells, leaves and instances. Only the code after the pragma is
// compiled for AVX2, and it lives in an anonymous namespace (simd.h says why).
#include <immintrin.h>

#include <cstdint>
#include <cstring>

#include "kdrt/trace.h"
#include "scene_internal.h"
#include "scene_packet.h"

#pragma GCC push_options
#pragma GCC target("avx2,popcnt")

namespace kdrt::detail {
namespace {

using F8 = float __attribute__((vector_size(32)));
using I8 = int32_t __attribute__((vector_size(32)));

static_assert(sizeof(Lanes) == sizeof(F8) && alignof(Lanes) >= alignof(F8));

inline F8 load(const Lanes& l) noexcept {
    F8 v;
    std::memcpy(&v, &l, sizeof v);
    return v;
}

inline void store(Lanes& l, F8 v) noexcept { std::memcpy(&l, &v, sizeof v); }

inline F8 broadcast(float x) noexcept { return F8{} + x; }

inline uint32_t bits(I8 m) noexcept {
    return static_cast<uint32_t>(_mm256_movemask_ps(reinterpret_cast<__m256>(m)));
}

/// TopPacket::next_leaf, the two halves as one.
const TopNode* next_leaf_avx2(TopPacket& pk, const SceneData& s, const Lanes& limit_lanes,
                              uint32_t& at) noexcept {
    const F8 limit = load(limit_lanes);
    while (pk.size > 0) {
        const TopPacketCell& cell = pk.stack[--pk.size];
        uint32_t mask = cell.mask & pk.lanes & ~pk.ended;
        if (!mask) continue;
        F8 tmin = load(cell.tmin), tmax = load(cell.tmax);
        const uint32_t late = bits(tmin > limit);
        pk.ended |= late & mask;
        mask &= ~late;
        if (!mask) continue;
        uint32_t index = cell.node;
        const TopNode* node = &s.nodes[index];
        while (!node->is_leaf()) {
            const int axis = node->axis();
            const uint32_t low = node->first_child(), high = low + 1;
            const uint32_t near = pk.forward[axis] ? low : high;
            const uint32_t far = pk.forward[axis] ? high : low;
            const F8 t_split = (broadcast(node->split()) - load(pk.org[axis])) * load(pk.inv[axis]);
            const F8 eps = load(pk.eps[axis]);
            const F8 near_max = t_split + eps, far_min = t_split - eps;
            const uint32_t need_near = bits(~(near_max < tmin)) & mask;
            const uint32_t need_far = bits(~(far_min > tmax)) & mask;
            if (!(need_near | need_far)) break;  // never: a lane needs one side at least
            if (need_far) {
                const F8 far_tmin = far_min > tmin ? far_min : tmin;
                if (!need_near) {
                    tmin = far_tmin;
                    index = far;
                    mask = need_far;
                    node = &s.nodes[index];
                    continue;
                }
                TopPacketCell& pushed = pk.stack[pk.size++];
                store(pushed.tmin, far_tmin);
                store(pushed.tmax, tmax);
                pushed.node = far;
                pushed.mask = need_far;
            }
            tmax = near_max < tmax ? near_max : tmax;
            index = near;
            mask = need_near;
            node = &s.nodes[index];
        }
        if (!node->is_leaf()) continue;
        at = mask;
        return node;
    }
    return nullptr;
}

/// TopPacket::reach, the two halves as one.
uint32_t reach_avx2(const TopPacket& pk, const Aabb& box, const Lanes& limit,
                    uint32_t mask) noexcept {
    F8 t0 = load(pk.ray_tmin), t1 = load(limit);
    const F8 delta = load(pk.delta);
    for (int a = 0; a < 3; ++a) {
        const F8 lo = broadcast(box.lo[a]) - delta, hi = broadcast(box.hi[a]) + delta;
        const F8 org = load(pk.org[a]), inv = load(pk.inv[a]);
        const F8 a0 = (lo - org) * inv;
        const F8 a1 = (hi - org) * inv;
        const I8 swap = a0 > a1;
        const F8 n0 = swap ? a1 : a0, n1 = swap ? a0 : a1;
        t0 = n0 > t0 ? n0 : t0;
        t1 = n1 < t1 ? n1 : t1;
    }
    return bits(t0 <= t1) & mask;
}

}  // namespace
}  // namespace kdrt::detail

#pragma GCC pop_options

namespace kdrt::detail {

const TopPacketOps& top_packet_ops_avx2() noexcept {
    static constexpr TopPacketOps kOps{&next_leaf_avx2, &reach_avx2};
    return kOps;
}

}  // namespace kdrt::detail
