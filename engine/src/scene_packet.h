#pragma once
// Internal: the top level of a scene walked by packets of rays (scene_trace.cpp's rounds). A
// packet is up to kPacketLanes rays whose direction components have the same signs (none zero);
// each node visit tests the split plane for every lane at once (SSE, the x86-64 baseline, two
// 4-lane halves; with AVX2 one 8-lane register, scene_packet_avx2.cpp, top_packet_ops) and keeps
// one stack of cells with a lane mask each. Per lane it is TopWalk's
// arithmetic and order exactly: the same plane and box tests on the same floats, the same cells
// front to back, and a lane's walk ends at the first cell that starts beyond its limit, so a lane
// reaches the leaves (and the instances) its own TopWalk would reach.

#include <xmmintrin.h>

#include <bit>
#include <cstdint>

#include "kdrt/trace.h"

#include "scene_internal.h"

namespace kdrt::detail {

inline constexpr int kPacketLanes = 8;

using F4 = float __attribute__((vector_size(16)));
using I4 = int32_t __attribute__((vector_size(16)));

/// kPacketLanes floats, one per lane, as two SSE halves (one AVX2 register: aligned for it).
struct alignas(32) Lanes {
    F4 h[2];
    [[nodiscard]] float get(int lane) const noexcept { return h[lane >> 2][lane & 3]; }
    void set(int lane, float x) noexcept { h[lane >> 2][lane & 3] = x; }
    static Lanes fill(float x) noexcept { return Lanes{{F4{} + x, F4{} + x}}; }
};

/// Bit i set when lane i of the half is true (movemask), shifted to the half's lanes.
[[gnu::always_inline]] inline uint32_t lane_bits(I4 m, int half) noexcept {
    return static_cast<uint32_t>(_mm_movemask_ps(reinterpret_cast<__m128>(m))) << (4 * half);
}

/// A cell of a packet's walk: its node, the lanes in it and their widened [tmin, tmax].
struct TopPacketCell {
    Lanes tmin, tmax;
    uint32_t node = 0;
    uint32_t mask = 0;
};

/// A packet's top-level walk that, as TopWalk, can stop at any leaf and resume later. The stack
/// (kTopStack cells: one push per level at most, as TopWalk's) is the caller's.
struct TopPacket {
    Lanes org[3], inv[3], eps[3], delta, ray_tmin;
    uint32_t ray[kPacketLanes] = {};  ///< the batch's ray index of each lane
    uint32_t lanes = 0;               ///< lanes holding a ray
    uint32_t ended = 0;               ///< lanes whose walk ended (or that left the packet)
    bool forward[3] = {};             ///< the lanes' direction signs (all alike)
    TopPacketCell* stack = nullptr;
    int size = 0;

    /// Starts the walk of `count` (1 .. kPacketLanes) valid rays `index[]` of `rays` with the same
    /// direction signs and no zero component, `top[index]` their TopRays.
    void start(const SceneData& s, std::span<const Ray> rays, std::span<const TopRay> top,
               const uint32_t* index, int count, TopPacketCell* storage) noexcept {
        stack = storage;
        size = 0;
        lanes = ended = 0;
        for (int a = 0; a < 3; ++a) {
            org[a] = Lanes::fill(0.0f);
            inv[a] = eps[a] = Lanes::fill(1.0f);
            forward[a] = top[index[0]].dir[a] > 0.0f;
        }
        delta = ray_tmin = Lanes::fill(0.0f);
        TopPacketCell root;
        root.tmin = root.tmax = Lanes::fill(0.0f);
        for (int l = 0; l < count; ++l) {
            const uint32_t i = index[l];
            const TopRay& p = top[i];
            ray[l] = i;
            lanes |= 1u << l;
            for (int a = 0; a < 3; ++a) {
                org[a].set(l, p.org[a]);
                inv[a].set(l, p.inv[a]);
                eps[a].set(l, p.eps[a]);
            }
            delta.set(l, p.delta);
            ray_tmin.set(l, rays[i].tmin);
            float tmin = rays[i].tmin, tmax = rays[i].tmax;
            if (!s.refs.empty() && clip_widened(p, s.bounds, tmin, tmax)) {
                root.mask |= 1u << l;
                root.tmin.set(l, tmin);
                root.tmax.set(l, tmax);
            }
        }
        if (root.mask) stack[size++] = root;
    }

    /// The lanes whose walk goes on.
    [[nodiscard]] uint32_t live() const noexcept {
        uint32_t m = 0;
        for (int k = 0; k < size; ++k) m |= stack[k].mask;
        return m & lanes & ~ended;
    }

    /// Ends the walk of the lanes in `m` (their rays are done, or walk on alone).
    void end(uint32_t m) noexcept { ended |= m; }

    /// Lane `lane`'s cells, bottom of the stack first, into `walk` (its storage set): the walk
    /// TopWalk would have at this point, for the lane to go on alone.
    void hand_over(int lane, TopWalk& walk) const noexcept {
        walk.size = 0;
        for (int k = 0; k < size; ++k)
            if (stack[k].mask >> lane & 1u)
                walk.stack[walk.size++] = {stack[k].node, stack[k].tmin.get(lane),
                                           stack[k].tmax.get(lane)};
    }

    /// The next leaf any lane reaches with its cell starting at or before its `limit`, and the
    /// lanes there (`at`), or nullptr when no lane's walk goes on. A lane whose cell starts beyond
    /// its limit ends (as TopWalk::next_leaf ends a walk).
    [[gnu::always_inline]] const TopNode* next_leaf(const SceneData& s, const Lanes& limit,
                                                    uint32_t& at) noexcept {
        while (size > 0) {
            const TopPacketCell cell = stack[--size];
            uint32_t mask = cell.mask & lanes & ~ended;
            if (!mask) continue;
            uint32_t late = 0;
            for (int h = 0; h < 2; ++h) late |= lane_bits(cell.tmin.h[h] > limit.h[h], h);
            ended |= late & mask;
            mask &= ~late;
            if (!mask) continue;
            Lanes tmin = cell.tmin, tmax = cell.tmax;
            uint32_t index = cell.node;
            const TopNode* node = &s.nodes[index];
            while (!node->is_leaf()) {
                const int axis = node->axis();
                const uint32_t low = node->first_child(), high = low + 1;
                const uint32_t near = forward[axis] ? low : high;
                const uint32_t far = forward[axis] ? high : low;
                const F4 split = F4{} + node->split();
                Lanes near_max, far_min;
                uint32_t need_near = 0, need_far = 0;
                for (int h = 0; h < 2; ++h) {
                    const F4 t_split = (split - org[axis].h[h]) * inv[axis].h[h];
                    near_max.h[h] = t_split + eps[axis].h[h];
                    far_min.h[h] = t_split - eps[axis].h[h];
                    need_near |= lane_bits(~(near_max.h[h] < tmin.h[h]), h);
                    need_far |= lane_bits(~(far_min.h[h] > tmax.h[h]), h);
                }
                need_near &= mask;
                need_far &= mask;
                if (!(need_near | need_far)) break;  // never: a lane needs one side at least
                if (need_far) {
                    // The far cell: [max(far_min, tmin), tmax], as TopWalk pushes it or goes on.
                    Lanes far_tmin;
                    for (int h = 0; h < 2; ++h)
                        far_tmin.h[h] = far_min.h[h] > tmin.h[h] ? far_min.h[h] : tmin.h[h];
                    if (!need_near) {
                        tmin = far_tmin;
                        index = far;
                        mask = need_far;
                        node = &s.nodes[index];
                        continue;
                    }
                    TopPacketCell& pushed = stack[size++];
                    pushed.tmin = far_tmin;
                    pushed.tmax = tmax;
                    pushed.node = far;
                    pushed.mask = need_far;
                }
                // The near cell: [tmin, min(near_max, tmax)]. (A lane needs one side at least:
                // need_near fails only past the split, where need_far holds.)
                for (int h = 0; h < 2; ++h)
                    tmax.h[h] = near_max.h[h] < tmax.h[h] ? near_max.h[h] : tmax.h[h];
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

    /// The lanes of `mask` whose widened segment [ray.tmin, limit] reaches `box` (clip_widened's
    /// arithmetic lane by lane).
    [[gnu::always_inline]] uint32_t reach(const Aabb& box, const Lanes& limit,
                                          uint32_t mask) const noexcept {
        uint32_t out = 0;
        for (int h = 0; h < 2; ++h) {
            F4 t0 = ray_tmin.h[h], t1 = limit.h[h];
            for (int a = 0; a < 3; ++a) {
                const F4 lo = box.lo[a] - delta.h[h], hi = box.hi[a] + delta.h[h];
                const F4 a0 = (lo - org[a].h[h]) * inv[a].h[h];
                const F4 a1 = (hi - org[a].h[h]) * inv[a].h[h];
                const I4 swap = a0 > a1;
                const F4 n0 = swap ? a1 : a0, n1 = swap ? a0 : a1;
                t0 = n0 > t0 ? n0 : t0;
                t1 = n1 < t1 ? n1 : t1;
            }
            out |= lane_bits(t0 <= t1, h);
        }
        return out & mask;
    }
};

/// The hot steps of a packet's walk for one instruction set: TopPacket::next_leaf and reach, or
/// the same arithmetic lane by lane in wider registers (the same cells, leaves and lanes).
struct TopPacketOps {
    const TopNode* (*next_leaf)(TopPacket& packet, const SceneData& s, const Lanes& limit,
                                uint32_t& at) noexcept;
    uint32_t (*reach)(const TopPacket& packet, const Aabb& box, const Lanes& limit,
                      uint32_t mask) noexcept;
};

/// AVX2 (scene_packet_avx2.cpp); only for a CPU that has it.
const TopPacketOps& top_packet_ops_avx2() noexcept;

/// The SSE steps (TopPacket's own).
inline const TopPacketOps& top_packet_ops_sse() noexcept {
    static constexpr TopPacketOps kOps{
        [](TopPacket& packet, const SceneData& s, const Lanes& limit, uint32_t& at) noexcept {
            return packet.next_leaf(s, limit, at);
        },
        [](const TopPacket& packet, const Aabb& box, const Lanes& limit, uint32_t mask) noexcept {
            return packet.reach(box, limit, mask);
        }};
    return kOps;
}

/// The walk's steps for `isa` (a supported one): AVX2 registers for kAvx2 and kAvx512, SSE
/// halves for kSse4 and kScalar.
inline const TopPacketOps& top_packet_ops(Isa isa) noexcept {
    return isa == Isa::kAvx2 || isa == Isa::kAvx512 ? top_packet_ops_avx2() : top_packet_ops_sse();
}

}  // namespace kdrt::detail
