#pragma once
// Internal: packet traversal of the kD-tree (Stoll 2005: "if any ray wants to go left, go left
// with mask"), one template over the SIMD width W. Included only by the per-ISA translation units
// after their `#pragma GCC target`; everything is in an anonymous namespace (see simd.h).
//
// Per lane the kernel makes exactly the scalar kernel's decisions (trace.cpp): the same widened
// cell intervals, the same culling of stack entries against the lane's closest hit, the same
// watertight triangle test and tie rule. A lane is active in a cell when its interval there is
// not empty; the packet descends into a child when any active lane needs it. So every lane tests
// exactly the triangles its single ray would, and the answers are bit-identical.

#include "packet.h"
#include "ray_prep.h"
#include "simd.h"

namespace kdrt::detail {
namespace {

template <int W>
using VF = simd::Float<W>;
template <int W>
using VM = simd::Mask<W>;
template <int W>
using VU = simd::UInt<W>;

/// A packet's rays in SoA form with their per-lane set-up.
template <int W>
struct alignas(64) Packet {
    VF<W> org[3];
    VF<W> inv[3];
    VF<W> eps[3];
    VF<W> sx, sy, sz;
    VM<W> kx, ky, kz;
    VF<W> ray_tmin, ray_tmax;
    VF<W> tmin, tmax;  // the root interval: the ray clipped to the scene box (empty for dead lanes)
    uint32_t near_is_high[3];
};

template <int W>
struct alignas(64) StackEntry {
    VF<W> tmin, tmax;
    uint32_t node;
};

/// Best hit per lane.
template <int W>
struct alignas(64) PacketHits {
    VF<W> t, u, v;
    VU<W> prim;
};

/// Lane-wise choice of one of three per-axis values: k == 0 ? x : k == 1 ? y : z.
template <int W>
inline VF<W> pick(VM<W> k, VF<W> x, VF<W> y, VF<W> z) {
    return k == 0 ? x : (k == 1 ? y : z);
}

/// Loads `count` (1..W) rays into a packet. Lanes past `count` are dead (empty interval).
template <int W>
inline void setup_packet(const KdTree& tree, const Ray* rays, const uint16_t* index, int count, Packet<W>& pk) {
    alignas(64) float org[3][W], inv[3][W], eps[3][W], sx[W], sy[W], sz[W], rtmin[W], rtmax[W], tmin[W], tmax[W];
    alignas(64) int32_t kx[W], ky[W], kz[W];
    for (int l = 0; l < W; ++l) {
        const Ray& r = rays[index[l < count ? l : 0]];
        const PreparedRay p = prepare_ray(r);
        float lo = r.tmin, hi = r.tmax;
        const bool alive = l < count && clip_to_box(p, tree.bounds, lo, hi);
        float e[3];
        traversal_eps(p, tree.bounds, e);
        for (int a = 0; a < 3; ++a) {
            org[a][l] = p.org[a];
            inv[a][l] = p.inv_dir[a];
            eps[a][l] = e[a];
        }
        sx[l] = p.sx;
        sy[l] = p.sy;
        sz[l] = p.sz;
        kx[l] = p.kx;
        ky[l] = p.ky;
        kz[l] = p.kz;
        rtmin[l] = r.tmin;
        rtmax[l] = r.tmax;
        tmin[l] = alive ? lo : __builtin_inff();
        tmax[l] = alive ? hi : -__builtin_inff();
        if (l == 0) {
            for (int a = 0; a < 3; ++a) pk.near_is_high[a] = __builtin_signbit(p.inv_dir[a]) ? 1u : 0u;
        }
    }
    for (int a = 0; a < 3; ++a) {
        pk.org[a] = simd::load<W>(org[a]);
        pk.inv[a] = simd::load<W>(inv[a]);
        pk.eps[a] = simd::load<W>(eps[a]);
    }
    pk.sx = simd::load<W>(sx);
    pk.sy = simd::load<W>(sy);
    pk.sz = simd::load<W>(sz);
    __builtin_memcpy(&pk.kx, kx, sizeof pk.kx);
    __builtin_memcpy(&pk.ky, ky, sizeof pk.ky);
    __builtin_memcpy(&pk.kz, kz, sizeof pk.kz);
    pk.ray_tmin = simd::load<W>(rtmin);
    pk.ray_tmax = simd::load<W>(rtmax);
    pk.tmin = simd::load<W>(tmin);
    pk.tmax = simd::load<W>(tmax);
}

/// The watertight test of one triangle against the lanes in `active`; returns the lanes hit with
/// tmin <= t (per lane t, u, v written). Same arithmetic as intersect_triangle, lane by lane.
template <int W>
inline VM<W> intersect_triangle_packet(const Packet<W>& pk, const TriVerts& tri, VM<W> active, VF<W>& t_out,
                                       VF<W>& u_out, VF<W>& v_out) {
    const VF<W> a0 = tri.v0[0] - pk.org[0], a1 = tri.v0[1] - pk.org[1], a2 = tri.v0[2] - pk.org[2];
    const VF<W> b0 = tri.v1[0] - pk.org[0], b1 = tri.v1[1] - pk.org[1], b2 = tri.v1[2] - pk.org[2];
    const VF<W> c0 = tri.v2[0] - pk.org[0], c1 = tri.v2[1] - pk.org[1], c2 = tri.v2[2] - pk.org[2];
    const VF<W> a_x = pick<W>(pk.kx, a0, a1, a2), a_y = pick<W>(pk.ky, a0, a1, a2), a_z = pick<W>(pk.kz, a0, a1, a2);
    const VF<W> b_x = pick<W>(pk.kx, b0, b1, b2), b_y = pick<W>(pk.ky, b0, b1, b2), b_z = pick<W>(pk.kz, b0, b1, b2);
    const VF<W> c_x = pick<W>(pk.kx, c0, c1, c2), c_y = pick<W>(pk.ky, c0, c1, c2), c_z = pick<W>(pk.kz, c0, c1, c2);
    const VF<W> ax = a_x - pk.sx * a_z, ay = a_y - pk.sy * a_z;
    const VF<W> bx = b_x - pk.sx * b_z, by = b_y - pk.sy * b_z;
    const VF<W> cx = c_x - pk.sx * c_z, cy = c_y - pk.sy * c_z;
    VF<W> u = cx * by - cy * bx;
    VF<W> v = ax * cy - ay * cx;
    VF<W> w = bx * ay - by * ax;
    const VM<W> zero_edge = active & ((u == 0.0f) | (v == 0.0f) | (w == 0.0f));
    if (simd::any<W>(zero_edge)) {
        // The scalar kernel's double-precision retry, for the lanes that need it.
        alignas(64) float fu[W], fv[W], fw[W], fax[W], fay[W], fbx[W], fby[W], fcx[W], fcy[W];
        simd::store<W>(fu, u);
        simd::store<W>(fv, v);
        simd::store<W>(fw, w);
        simd::store<W>(fax, ax);
        simd::store<W>(fay, ay);
        simd::store<W>(fbx, bx);
        simd::store<W>(fby, by);
        simd::store<W>(fcx, cx);
        simd::store<W>(fcy, cy);
        for (uint32_t m = simd::bits<W>(zero_edge); m; m &= m - 1) {
            const int l = __builtin_ctz(m);
            fu[l] = static_cast<float>(static_cast<double>(fcx[l]) * fby[l] - static_cast<double>(fcy[l]) * fbx[l]);
            fv[l] = static_cast<float>(static_cast<double>(fax[l]) * fcy[l] - static_cast<double>(fay[l]) * fcx[l]);
            fw[l] = static_cast<float>(static_cast<double>(fbx[l]) * fay[l] - static_cast<double>(fby[l]) * fax[l]);
        }
        u = simd::load<W>(fu);
        v = simd::load<W>(fv);
        w = simd::load<W>(fw);
    }
    const VM<W> outside = ((u < 0.0f) | (v < 0.0f) | (w < 0.0f)) & ((u > 0.0f) | (v > 0.0f) | (w > 0.0f));
    const VF<W> det = u + v + w;
    VM<W> hit = active & ~outside & (det != 0.0f);
    if (simd::none<W>(hit)) return hit;
    const VF<W> az = pk.sz * a_z, bz = pk.sz * b_z, cz = pk.sz * c_z;
    const VF<W> t_scaled = u * az + v * bz + w * cz;
    const VF<W> t = t_scaled / det;
    hit &= t >= pk.ray_tmin;
    t_out = t;
    u_out = v / det;
    v_out = w / det;
    return hit;
}

/// Traverses the tree with one packet. Closest hit: `best` holds per-lane answers (initialised by
/// the caller to t = ray tmax, prim = kNoHit). Any hit: returns the lanes occluded.
template <int W, bool AnyHit>
inline VM<W> traverse_packet(const KdTree& tree, const Packet<W>& pk, PacketHits<W>& best) {
    const KdNode* nodes = tree.nodes.data();
    const uint32_t* refs = tree.leaf_refs.data();
    const TriVerts* tris = tree.tris.data();
    StackEntry<W> stack[kMaxDepth + 1];
    int stack_size = 0;
    VM<W> done = simd::broadcast_i<W>(0);  // any-hit lanes already occluded
    VF<W> tmin = pk.tmin, tmax = pk.tmax;
    uint32_t node_index = 0;
    if (simd::none<W>(tmin <= tmax)) return done;
    for (;;) {
        KdNode node = nodes[node_index];
        while (!node.is_leaf()) {
            const int axis = node.axis();
            const VF<W> t_split = (node.split() - pk.org[axis]) * pk.inv[axis];
            const VF<W> near_max = t_split + pk.eps[axis], far_min = t_split - pk.eps[axis];
            const VM<W> active = tmin <= tmax;
            const VM<W> in_plane = t_split != t_split;
            const uint32_t near_child = node.first_child() + pk.near_is_high[axis];
            const uint32_t far_child = node.first_child() + (pk.near_is_high[axis] ^ 1u);
            // Per lane as in the scalar kernel: near needed unless near_max < tmin, far needed
            // unless far_min > tmax; a lane in the split plane (NaN) needs both, unchanged.
            const VM<W> need_near = active & ~(near_max < tmin);
            const VM<W> need_far = active & ~(far_min > tmax);
            const bool go_near = simd::any<W>(need_near), go_far = simd::any<W>(need_far);
            if (go_near && go_far) {
                StackEntry<W>& e = stack[stack_size++];
                e.tmin = simd::select<W>(in_plane, tmin, simd::max<W>(far_min, tmin));
                e.tmax = tmax;
                e.node = far_child;
                tmax = simd::select<W>(in_plane, tmax, simd::min<W>(near_max, tmax));
                node_index = near_child;
            } else if (go_near) {
                node_index = near_child;
            } else if (go_far) {
                node_index = far_child;
            } else {
                break;  // no live lane here: go to the stack
            }
            node = nodes[node_index];
        }
        if (node.is_leaf()) {
            VM<W> active = (tmin <= tmax) & ~done;
            const uint32_t end = node.first_ref() + node.prim_count();
            for (uint32_t r = node.first_ref(); r < end; ++r) {
                const uint32_t prim = refs[r];
                VF<W> t, u, v;
                VM<W> hit = intersect_triangle_packet<W>(pk, tris[prim], active, t, u, v);
                if (simd::none<W>(hit)) continue;
                if constexpr (AnyHit) {
                    hit &= t <= pk.ray_tmax;
                    done |= hit;
                    active &= ~hit;
                    if (simd::none<W>(active)) break;
                } else {
                    const VU<W> prim_v = simd::broadcast_u<W>(prim);
                    hit &= (t < best.t) | ((t == best.t) & (prim_v < best.prim));
                    best.t = simd::select<W>(hit, t, best.t);
                    best.u = simd::select<W>(hit, u, best.u);
                    best.v = simd::select<W>(hit, v, best.v);
                    best.prim = simd::select<W>(hit, prim_v, best.prim);
                }
            }
        }
        // Pop the next cell in which some lane is still live: its interval is not empty, it has
        // not been occluded, and it starts no later than the lane's closest hit.
        for (;;) {
            if (stack_size == 0) return done;
            const StackEntry<W>& e = stack[--stack_size];
            VM<W> live = (e.tmin <= e.tmax) & ~done;
            if constexpr (!AnyHit) live &= e.tmin <= best.t;
            if (simd::any<W>(live)) {
                tmin = simd::select<W>(live, e.tmin, simd::broadcast<W>(__builtin_inff()));
                tmax = e.tmax;
                node_index = e.node;
                break;
            }
        }
    }
}

/// Octant of a valid ray: the sign bits of its direction (those of its reciprocal, too).
inline uint32_t octant(const Ray& r) {
    return (__builtin_signbit(r.dx) ? 1u : 0u) | (__builtin_signbit(r.dy) ? 2u : 0u) |
           (__builtin_signbit(r.dz) ? 4u : 0u);
}

/// The auto policy: a packet pays when enough of its lanes are alive. Measured on the bunny (one
/// thread, every width): packets beat single rays on primary (2.3x), shadow (2.9x) and diffuse
/// bounce rays (1.6x), and tie on uniformly random rays; a packet with fewer than half its lanes
/// alive (an octant's tail) does less useful work per traversal step than the single-ray kernel.
inline bool packet_pays(int lanes, int width) { return lanes >= 2 && lanes * 2 >= width; }

/// Traces `count` rays: sorts them into direction octants (keeping input order inside each),
/// cuts each octant into packets of W, and traces each packet as a packet or as single rays.
template <int W, bool AnyHit>
void trace_rays(const KdTree& tree, const Ray* rays, size_t count, Hit* hits, uint8_t* occluded, Policy policy,
                TraceCounters& counters) {
    for (size_t base = 0; base < count; base += kBlockRays) {
        const size_t n = count - base < kBlockRays ? count - base : kBlockRays;
        const Ray* block = rays + base;
        uint16_t bucket[8][kBlockRays];
        int bucket_size[8] = {0, 0, 0, 0, 0, 0, 0, 0};
        for (size_t i = 0; i < n; ++i) {
            if (!ray_is_valid(block[i]) || tree.bounds.empty()) {
                if constexpr (AnyHit) occluded[base + i] = 0;
                else hits[base + i] = Hit{};
                ++counters.invalid_rays;
                continue;
            }
            const uint32_t o = octant(block[i]);
            bucket[o][bucket_size[o]++] = static_cast<uint16_t>(i);
        }
        for (int o = 0; o < 8; ++o) {
            for (int first = 0; first < bucket_size[o]; first += W) {
                const int lanes = bucket_size[o] - first < W ? bucket_size[o] - first : W;
                const uint16_t* index = &bucket[o][first];
                const bool as_packet = policy == Policy::kPacket ||
                                       (policy == Policy::kAuto && packet_pays(lanes, W));
                if (!as_packet) {
                    for (int l = 0; l < lanes; ++l) {
                        const size_t i = base + index[l];
                        if constexpr (AnyHit) occluded[i] = kdrt::occluded(tree, rays[i]) ? 1 : 0;
                        else hits[i] = kdrt::intersect(tree, rays[i]);
                    }
                    counters.single_rays += static_cast<uint64_t>(lanes);
                    continue;
                }
                Packet<W> pk;
                setup_packet<W>(tree, block, index, lanes, pk);
                PacketHits<W> best;
                best.t = pk.ray_tmax;
                best.u = simd::broadcast<W>(0.0f);
                best.v = simd::broadcast<W>(0.0f);
                best.prim = simd::broadcast_u<W>(kNoHit);
                const VM<W> occ = traverse_packet<W, AnyHit>(tree, pk, best);
                ++counters.packets;
                counters.packet_rays += static_cast<uint64_t>(lanes);
                if constexpr (AnyHit) {
                    const uint32_t mask = simd::bits<W>(occ);
                    for (int l = 0; l < lanes; ++l) occluded[base + index[l]] = (mask >> l) & 1u;
                } else {
                    alignas(64) float t[W], u[W], v[W];
                    alignas(64) uint32_t prim[W];
                    simd::store<W>(t, best.t);
                    simd::store<W>(u, best.u);
                    simd::store<W>(v, best.v);
                    __builtin_memcpy(prim, &best.prim, sizeof prim);
                    for (int l = 0; l < lanes; ++l) {
                        hits[base + index[l]] = prim[l] == kNoHit ? Hit{} : Hit{t[l], prim[l], u[l], v[l]};
                    }
                }
            }
        }
    }
}

template <int W>
void intersect_rays(const KdTree& tree, const Ray* rays, size_t count, Hit* hits, Policy policy,
                    TraceCounters& counters) {
    trace_rays<W, false>(tree, rays, count, hits, nullptr, policy, counters);
}

template <int W>
void occluded_rays(const KdTree& tree, const Ray* rays, size_t count, uint8_t* occluded, Policy policy,
                   TraceCounters& counters) {
    trace_rays<W, true>(tree, rays, count, nullptr, occluded, policy, counters);
}

}  // namespace
}  // namespace kdrt::detail
