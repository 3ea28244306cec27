#pragma once
// Internal: the top level of a scene walked by packets of rays (scene_trace.cpp's rounds). A
// packet is up to kPacketLanes rays whose direction components have the same signs (none zero);
// each node visit tests the split plane for every lane at once (SSE, the x86-64 baseline, two
// 4-lane halves; with AVX2 one 8-lane register: top_packet_ops, scene_packet_steps.h) and keeps
// one stack of cells with a lane mask each. Per lane it is TopWalk's
// arithmetic and order exactly: the same plane and box tests on the same floats, the same cells in
// the same order, and a lane leaves each cell that starts beyond its limit (as TopWalk drops it),
// so a lane reaches the leaves (and the instances) its own TopWalk would reach.

#include <bit>
#include <cstdint>
#include <cstring>
#include <span>

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
    /// One store (an element insert into the vector costs several instructions).
    void set(int lane, float x) noexcept {
        std::memcpy(reinterpret_cast<char*>(this) + 4 * lane, &x, sizeof x);
    }
    static Lanes fill(float x) noexcept { return Lanes{{F4{} + x, F4{} + x}}; }
};

/// A cell of a packet's walk: its node, the lanes in it and their widened [tmin, tmax].
struct TopPacketCell {
    Lanes tmin, tmax;
    uint32_t node = 0;
    uint32_t mask = 0;
};

struct TopPacket;

/// TopPacketOps::start_patch's answer for rays that are not one packet's.
inline constexpr uint32_t kNotOnePacket = ~0u;

/// The hot steps of a packet's walk (scene_packet_steps.h), compiled for one instruction set.
struct TopPacketOps {
    /// The next leaf any lane reaches with its cell starting at or before its `limit`, and the
    /// lanes there (`at`), or nullptr when no lane's walk goes on. A lane leaves a cell that starts
    /// beyond its limit, and walks on in the cells below it (as TopWalk::next_leaf drops the cell).
    const TopNode* (*next_leaf)(TopPacket& packet, const SceneData& s, const Lanes& limit,
                                uint32_t& at) noexcept;
    /// The lanes of `mask` whose widened segment [ray.tmin, limit] reaches `box` (clip_widened's
    /// arithmetic lane by lane).
    uint32_t (*reach)(const TopPacket& packet, const Aabb& box, const Lanes& limit,
                      uint32_t mask) noexcept;
    /// reach() that also gives each lane's clipped segment: `tmin` (in: the lanes' tmin) and
    /// `tmax` (in: their tmax) become clip_widened's [tmin, tmax], bit for bit.
    uint32_t (*clip)(const TopPacket& packet, const Aabb& box, Lanes& tmin, Lanes& tmax,
                     uint32_t mask) noexcept;
    /// TopPacket::start of `count` (1 .. kPacketLanes) rays rays[first + order[l]] as the caller
    /// gives them, bit for bit (the same lanes, the same root cell), with each lane's TopRay
    /// fields (make_top_ray's reciprocal direction, margin and its t widths) computed in the
    /// packet's registers from the rays themselves, and `limit` = the rays' tmax. The rays must be
    /// valid and of one octant (the same direction sign bits). A lane whose direction has a zero
    /// component cannot walk in a packet: it is left out (not in `lanes`, nor the root cell), and
    /// the lanes left out are returned (the caller traces their rays alone).
    uint32_t (*start)(TopPacket& packet, const SceneData& s, const Ray* rays, uint32_t first,
                      const uint16_t* order, int count, TopPacketCell* storage,
                      Lanes& limit) noexcept;
    /// start() of rays that the caller has not checked: when they are all valid and of one
    /// octant, start()'s work and answer; else kNotOnePacket, and the packet is not touched.
    uint32_t (*start_patch)(TopPacket& packet, const SceneData& s, const Ray* rays, uint32_t first,
                            const uint16_t* order, int count, TopPacketCell* storage,
                            Lanes& limit) noexcept;
    /// Every lane's object ray in instance `in`: out[l] = to_object(in, lane l's ray) with tmax =
    /// tmax[l], bit for bit (the same double arithmetic, lanes side by side). All kPacketLanes
    /// lanes are written; those not holding a ray hold no ray.
    void (*object_rays)(const TopPacket& packet, const InstanceData& in, const Lanes& tmax,
                        Ray* out) noexcept;
};

/// A packet's top-level walk that, as TopWalk, can stop at any leaf and resume later. The stack
/// (kTopStack cells: one push per level at most, as TopWalk's) is the caller's.
struct TopPacket {
    Lanes org[3], dir[3], inv[3], eps[3], delta, ray_tmin;
    uint32_t ray[kPacketLanes] = {};  ///< the batch's ray index of each lane
    uint32_t lanes = 0;               ///< lanes holding a ray
    uint32_t ended = 0;               ///< lanes whose walk ended (or that left the packet)
    bool forward[3] = {};             ///< the lanes' direction signs (all alike)
    TopPacketCell* stack = nullptr;
    int size = 0;

    /// Starts the walk of `count` (1 .. kPacketLanes) valid rays `index[]` of `rays` with the same
    /// direction signs and no zero component, `top[index]` their TopRays; the root box is clipped
    /// lane by lane with `ops.clip`.
    void start(const SceneData& s, std::span<const Ray> rays, std::span<const TopRay> top,
               const uint32_t* index, int count, TopPacketCell* storage,
               const TopPacketOps& ops) noexcept {
        stack = storage;
        size = 0;
        lanes = ended = 0;
        for (int a = 0; a < 3; ++a) {
            org[a] = Lanes::fill(0.0f);
            dir[a] = inv[a] = eps[a] = Lanes::fill(1.0f);
            forward[a] = top[index[0]].dir[a] > 0.0f;
        }
        delta = ray_tmin = Lanes::fill(0.0f);
        TopPacketCell root;
        root.tmin = root.tmax = Lanes::fill(0.0f);
        root.mask = 0;
        for (int l = 0; l < count; ++l) {
            const uint32_t i = index[l];
            const TopRay& p = top[i];
            ray[l] = i;
            lanes |= 1u << l;
            for (int a = 0; a < 3; ++a) {
                org[a].set(l, p.org[a]);
                dir[a].set(l, p.dir[a]);
                inv[a].set(l, p.inv[a]);
                eps[a].set(l, p.eps[a]);
            }
            delta.set(l, p.delta);
            ray_tmin.set(l, rays[i].tmin);
            root.tmin.set(l, rays[i].tmin);
            root.tmax.set(l, rays[i].tmax);
        }
        if (!s.refs.empty()) root.mask = ops.clip(*this, s.bounds, root.tmin, root.tmax, lanes);
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
};

/// Whether every ray of `rays` starts where the first does (==, component by component: a NaN
/// differs from everything, -0 equals +0; true for none), as a coherent block's first test
/// (scene_trace.cpp's rounds_pay).
bool share_origin(std::span<const Ray> rays) noexcept;

/// The steps in two SSE halves (scene_packet_sse.cpp) and in one AVX2 register
/// (scene_packet_avx2.cpp; only for a CPU that has it).
const TopPacketOps& top_packet_ops_sse() noexcept;
const TopPacketOps& top_packet_ops_avx2() noexcept;

/// The walk's steps for `isa` (a supported one): AVX2 registers for kAvx2 and kAvx512, SSE
/// halves for kSse4 and kScalar.
inline const TopPacketOps& top_packet_ops(Isa isa) noexcept {
    return isa == Isa::kAvx2 || isa == Isa::kAvx512 ? top_packet_ops_avx2() : top_packet_ops_sse();
}

}  // namespace kdrt::detail
