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
    VF<W> org_k[3];  // the origin permuted into the lane's (kx, ky, kz) frame
    VF<W> sx, sy, sz;
    VM<W> kx, ky, kz;
    VF<W> ray_tmin, ray_tmax;
    VF<W> tmin, tmax;  // the root interval: the ray clipped to the scene box (empty for dead lanes)
    uint32_t near_is_high[3];
    int uniform_k;  // -1, or the kz shared by every lane (then kx, ky are shared too)
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

/// Lane-wise v[k]: one coordinate of a vertex, per lane's axis k.
template <int W>
inline VF<W> pick_coord(const float* v, VM<W> k) {
    return pick<W>(k, simd::broadcast<W>(v[0]), simd::broadcast<W>(v[1]), simd::broadcast<W>(v[2]));
}

template <int W>
inline VF<W> abs(VF<W> x) {
    VU<W> bits;
    __builtin_memcpy(&bits, &x, sizeof bits);
    bits &= 0x7FFFFFFFu;
    __builtin_memcpy(&x, &bits, sizeof x);
    return x;
}

/// Loads `count` (1..W) valid rays into a packet, computing lane by lane what prepare_ray,
/// clip_to_box and traversal_eps compute for a single ray, with the same operations in the same
/// order. Lanes past `count` are dead (empty interval).
template <int W>
inline void setup_packet(const KdTree& tree, const Ray* rays, const uint16_t* index, int count,
                         Packet<W>& pk) {
    alignas(64) float field[8][W];
    for (int l = 0; l < W; ++l) {
        float r[8];
        __builtin_memcpy(r, &rays[index[l < count ? l : 0]], sizeof r);
        for (int f = 0; f < 8; ++f) field[f][l] = r[f];
    }
    const VF<W> o[3] = {simd::load<W>(field[0]), simd::load<W>(field[1]), simd::load<W>(field[2])};
    const VF<W> d[3] = {simd::load<W>(field[4]), simd::load<W>(field[5]), simd::load<W>(field[6])};
    const VF<W> ray_tmin = simd::load<W>(field[3]), ray_tmax = simd::load<W>(field[7]);
    VF<W> inv[3];
    for (int a = 0; a < 3; ++a) inv[a] = 1.0f / d[a];
    // prepare_ray: kz where |d| is largest (first on ties), kx and ky after it, swapped when
    // d[kz] < 0; the shear constants.
    const VF<W> ad0 = abs<W>(d[0]), ad1 = abs<W>(d[1]), ad2 = abs<W>(d[2]);
    VM<W> kz = simd::select<W>(ad1 > ad0, simd::broadcast_i<W>(1), simd::broadcast_i<W>(0));
    kz = simd::select<W>(ad2 > (kz == 0 ? ad0 : ad1), simd::broadcast_i<W>(2), kz);
    VM<W> kx = simd::select<W>(kz == 2, simd::broadcast_i<W>(0), kz + 1);
    VM<W> ky = simd::select<W>(kx == 2, simd::broadcast_i<W>(0), kx + 1);
    const VF<W> dkz = pick<W>(kz, d[0], d[1], d[2]);
    const VM<W> swap = dkz < 0.0f;
    const VM<W> kx_swapped = simd::select<W>(swap, ky, kx);
    ky = simd::select<W>(swap, kx, ky);
    kx = kx_swapped;
    pk.sx = pick<W>(kx, d[0], d[1], d[2]) / dkz;
    pk.sy = pick<W>(ky, d[0], d[1], d[2]) / dkz;
    pk.sz = 1.0f / dkz;
    pk.kx = kx;
    pk.ky = ky;
    pk.kz = kz;
    pk.org_k[0] = pick<W>(kx, o[0], o[1], o[2]);
    pk.org_k[1] = pick<W>(ky, o[0], o[1], o[2]);
    pk.org_k[2] = pick<W>(kz, o[0], o[1], o[2]);
    // clip_to_box
    const VF<W> inf = simd::broadcast<W>(__builtin_inff());
    VF<W> tmin = ray_tmin, tmax = ray_tmax;
    VM<W> miss = simd::broadcast_i<W>(0);
    VF<W> m = simd::broadcast<W>(bounds_magnitude(tree.bounds));
    for (int a = 0; a < 3; ++a) {
        const VM<W> parallel = abs<W>(inv[a]) == inf;
        miss |= parallel & ((o[a] < tree.bounds.lo[a]) | (o[a] > tree.bounds.hi[a]));
        const VF<W> t0 = (tree.bounds.lo[a] - o[a]) * inv[a],
                    t1 = (tree.bounds.hi[a] - o[a]) * inv[a];
        const VM<W> order = t0 > t1;
        const VF<W> near = simd::select<W>(order, t1, t0), far = simd::select<W>(order, t0, t1);
        tmin = simd::select<W>(parallel, tmin, simd::select<W>(near > tmin, near, tmin));
        tmax = simd::select<W>(parallel, tmax, simd::select<W>(far < tmax, far, tmax));
        const VF<W> oa = abs<W>(o[a]);
        m = simd::select<W>(oa > m, oa, m);  // interval_margin
    }
    alignas(64) int32_t lane[W];
    for (int l = 0; l < W; ++l) lane[l] = l;
    VM<W> lane_v;
    __builtin_memcpy(&lane_v, lane, sizeof lane_v);
    const VM<W> alive = (lane_v < count) & ~miss & (tmin <= tmax);
    pk.tmin = simd::select<W>(alive, tmin, inf);
    pk.tmax = simd::select<W>(alive, tmax, -inf);
    // traversal_eps
    const VF<W> delta = m * 0x1p-20f;
    for (int a = 0; a < 3; ++a) {
        const VF<W> ai = abs<W>(inv[a]);
        pk.eps[a] = simd::select<W>(ai == inf, simd::broadcast<W>(0.0f), delta * ai);
        pk.org[a] = o[a];
        pk.inv[a] = inv[a];
    }
    pk.ray_tmin = ray_tmin;
    pk.ray_tmax = ray_tmax;
    for (int a = 0; a < 3; ++a) pk.near_is_high[a] = __builtin_signbit(field[4 + a][0]) ? 1u : 0u;
    const int kz0 = pk.kz[0];
    pk.uniform_k = simd::none<W>(kz != kz0) && simd::none<W>(kx != pk.kx[0]) ? kz0 : -1;
}

/// The watertight test of one triangle against the lanes in `active`; returns the lanes hit with
/// tmin <= t (per lane t, u, v written). Same arithmetic as intersect_triangle, lane by lane.
template <int W>
inline VM<W> intersect_triangle_packet(const Packet<W>& pk, const TriVerts& tri, VM<W> active,
                                       VF<W>& t_out, VF<W>& u_out, VF<W>& v_out) {
    // The vertices relative to the origin in each lane's (kx, ky, kz) frame: tri.v[k] - org[k].
    VF<W> a_x, a_y, a_z, b_x, b_y, b_z, c_x, c_y, c_z;
    if (pk.uniform_k >= 0) {  // coherent packets: every lane has the same frame, no per-lane picks
        const int kz = pk.uniform_k, kx = pk.kx[0], ky = pk.ky[0];
        a_x = tri.v0[kx] - pk.org_k[0], a_y = tri.v0[ky] - pk.org_k[1],
        a_z = tri.v0[kz] - pk.org_k[2];
        b_x = tri.v1[kx] - pk.org_k[0], b_y = tri.v1[ky] - pk.org_k[1],
        b_z = tri.v1[kz] - pk.org_k[2];
        c_x = tri.v2[kx] - pk.org_k[0], c_y = tri.v2[ky] - pk.org_k[1],
        c_z = tri.v2[kz] - pk.org_k[2];
    } else {
        // (A helper function, not a lambda: a lambda would not inherit the ISA target.)
        a_x = pick_coord<W>(tri.v0, pk.kx) - pk.org_k[0],
        a_y = pick_coord<W>(tri.v0, pk.ky) - pk.org_k[1];
        a_z = pick_coord<W>(tri.v0, pk.kz) - pk.org_k[2];
        b_x = pick_coord<W>(tri.v1, pk.kx) - pk.org_k[0],
        b_y = pick_coord<W>(tri.v1, pk.ky) - pk.org_k[1];
        b_z = pick_coord<W>(tri.v1, pk.kz) - pk.org_k[2];
        c_x = pick_coord<W>(tri.v2, pk.kx) - pk.org_k[0],
        c_y = pick_coord<W>(tri.v2, pk.ky) - pk.org_k[1];
        c_z = pick_coord<W>(tri.v2, pk.kz) - pk.org_k[2];
    }
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
            fu[l] = static_cast<float>(static_cast<double>(fcx[l]) * fby[l] -
                                       static_cast<double>(fcy[l]) * fbx[l]);
            fv[l] = static_cast<float>(static_cast<double>(fax[l]) * fcy[l] -
                                       static_cast<double>(fay[l]) * fcx[l]);
            fw[l] = static_cast<float>(static_cast<double>(fbx[l]) * fay[l] -
                                       static_cast<double>(fby[l]) * fax[l]);
        }
        u = simd::load<W>(fu);
        v = simd::load<W>(fv);
        w = simd::load<W>(fw);
    }
    const VM<W> outside =
        ((u < 0.0f) | (v < 0.0f) | (w < 0.0f)) & ((u > 0.0f) | (v > 0.0f) | (w > 0.0f));
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
            const uint32_t near_child = node.first_child() + pk.near_is_high[axis];
            const uint32_t far_child = node.first_child() + (pk.near_is_high[axis] ^ 1u);
            // Per lane as in the scalar kernel: near needed unless near_max < tmin, far needed
            // unless far_min > tmax; a lane in the split plane (NaN t_split) fails every
            // comparison, so it needs both, and min/max below keep its interval unchanged.
            const VM<W> need_near = active & ~(near_max < tmin);
            const VM<W> need_far = active & ~(far_min > tmax);
            const bool go_near = simd::any<W>(need_near), go_far = simd::any<W>(need_far);
            if (go_near && go_far) {
                StackEntry<W>& e = stack[stack_size++];
                e.tmin = simd::max<W>(far_min, tmin);
                e.tmax = tmax;
                e.node = far_child;
                tmax = simd::min<W>(near_max, tmax);
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

// Sort keys of the rays of a block: the direction octant in the top bits, so a packet never
// mixes octants; below it, for blocks whose origins differ, the Morton code of the origin (4 bits
// per axis, relative to the block's origin bounds) and of the direction (2 bits per axis of
// |d_axis| / |d|). Rays that start near each other and go the same way end up side by side.
constexpr int kOriginShift = 6;
constexpr int kOctantShift = 18;
constexpr int kKeyBits = 21;
constexpr int kRadixBits = 7;  // 3 passes of 128 buckets: cheap for a 256-ray render tile too
// Blocks whose unit directions span less than this in every axis keep their input order.
constexpr float kSortSpread = 0.5f;
// Coherent blocks are traced in runs of this many rays, bucketed by octant: a run's rays and its
// buckets stay in L1.
constexpr int kCoherentRun = 256;
// Every kSampleStride-th valid ray of a block is looked at to decide whether to sort it; the
// origin quantization uses the sample's bounds too (rays outside them clamp to the edge levels).
constexpr int kSampleStride = 64;

/// Bits 0..3 of x spread to bits 0, 3, 6, 9.
constexpr uint32_t spread3(uint32_t x) {
    x &= 0xFu;
    x = (x | (x << 4)) & 0x0C3u;
    x = (x | (x << 2)) & 0x249u;
    return x;
}

constexpr uint32_t morton3(uint32_t x, uint32_t y, uint32_t z) {
    return spread3(x) | (spread3(y) << 1) | (spread3(z) << 2);
}

/// Level 0..levels-1 of v, clamped to [0, 1] (v = 1 lands in the top level).
inline uint32_t quantize(double v, uint32_t levels) {
    const double q = v * levels;
    if (!(q > 0.0)) return 0;
    return q < static_cast<double>(levels) ? static_cast<uint32_t>(q) : levels - 1;
}

/// One stable counting-sort pass over `bits` bits of the keys from `shift`.
inline void radix_pass(const uint32_t* key_in, const uint16_t* index_in, uint32_t* key_out,
                       uint16_t* index_out, int n, int shift, int bits) {
    uint16_t start[(1 << kRadixBits) + 1];
    const int buckets = 1 << bits;
    for (int b = 0; b <= buckets; ++b) start[b] = 0;
    const uint32_t mask = static_cast<uint32_t>(buckets - 1);
    for (int i = 0; i < n; ++i) ++start[((key_in[i] >> shift) & mask) + 1];
    for (int b = 0; b < buckets; ++b) start[b + 1] = static_cast<uint16_t>(start[b + 1] + start[b]);
    for (int i = 0; i < n; ++i) {
        const uint16_t at = start[(key_in[i] >> shift) & mask]++;
        key_out[at] = key_in[i];
        index_out[at] = index_in[i];
    }
}

/// Whether a block is worth sorting, from a sample of its valid rays (a heuristic: it only
/// picks the order, never an answer): the origins differ and the unit directions spread by
/// kSortSpread or more in some axis. Pinhole cameras (one origin), shadow rays towards a light
/// and orthographic views (one direction) come in an image's order, as coherent as it gets.
/// Writes the sample's origin bounds, for the sort's origin levels.
inline bool block_is_incoherent(const Ray* block, int n, float lo[3], float hi[3]) {
    float dir_lo[3] = {2.0f, 2.0f, 2.0f}, dir_hi[3] = {-2.0f, -2.0f, -2.0f};
    for (int a = 0; a < 3; ++a) {
        lo[a] = __builtin_inff();
        hi[a] = -__builtin_inff();
    }
    for (int i = 0; i < n; i += kSampleStride) {
        const Ray& r = block[i];
        if (!ray_is_valid(r)) continue;
        const float o[3] = {r.ox, r.oy, r.oz};
        // |d| in double: the squares of finite floats cannot overflow there.
        const float inv_len = static_cast<float>(
            1.0 / __builtin_sqrt(double{r.dx} * r.dx + double{r.dy} * r.dy + double{r.dz} * r.dz));
        const float d[3] = {r.dx * inv_len, r.dy * inv_len, r.dz * inv_len};
        for (int a = 0; a < 3; ++a) {
            lo[a] = o[a] < lo[a] ? o[a] : lo[a];
            hi[a] = o[a] > hi[a] ? o[a] : hi[a];
            dir_lo[a] = d[a] < dir_lo[a] ? d[a] : dir_lo[a];
            dir_hi[a] = d[a] > dir_hi[a] ? d[a] : dir_hi[a];
        }
    }
    bool origins_differ = false;
    float spread = 0;
    for (int a = 0; a < 3; ++a) {
        origins_differ |= hi[a] > lo[a];
        spread = dir_hi[a] - dir_lo[a] > spread ? dir_hi[a] - dir_lo[a] : spread;
    }
    return origins_differ && spread >= kSortSpread;
}

/// True for a ray the kernels trace; any other is answered as a miss here, at `at`.
template <bool AnyHit>
inline bool traceable_or_miss(const KdTree& tree, const Ray& r, size_t at, Hit* hits,
                              uint8_t* occluded, TraceCounters& counters) {
    if (ray_is_valid(r) && !tree.bounds.empty()) return true;
    if constexpr (AnyHit)
        occluded[at] = 0;
    else
        hits[at] = Hit{};
    ++counters.invalid_rays;
    return false;
}

/// Collects the valid rays of block[0, n) (indices into the block, keys with their octant) and
/// answers the invalid ones as misses. Returns how many are valid.
template <bool AnyHit>
inline int collect_valid(const KdTree& tree, const Ray* block, size_t base, int n, Hit* hits,
                         uint8_t* occluded, TraceCounters& counters, uint32_t* key,
                         uint16_t* index) {
    int valid = 0;
    for (int i = 0; i < n; ++i) {
        const Ray& r = block[i];
        if (!traceable_or_miss<AnyHit>(tree, r, base + static_cast<size_t>(i), hits, occluded,
                                       counters))
            continue;
        index[valid] = static_cast<uint16_t>(i);
        key[valid] = octant(r) << kOctantShift;
        ++valid;
    }
    return valid;
}

/// Adds the origin and direction Morton codes to the octant keys of the valid rays and sorts
/// them (3 radix passes). The result is in key/index or in key_tmp/index_tmp: returns whether
/// it is in the latter.
inline bool sort_by_origin_and_direction(const Ray* block, int valid, const float lo[3],
                                         const float hi[3], uint32_t* key, uint16_t* index,
                                         uint32_t* key_tmp, uint16_t* index_tmp) {
    double extent = 0;  // in double: hi - lo of finite floats cannot overflow there
    for (int a = 0; a < 3; ++a) {
        const double e = static_cast<double>(hi[a]) - lo[a];
        extent = e > extent ? e : extent;
    }
    for (int j = 0; j < valid; ++j) {
        const Ray& r = block[index[j]];
        const double o[3] = {r.ox, r.oy, r.oz}, d[3] = {r.dx, r.dy, r.dz};
        const double len = __builtin_sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2]);
        uint32_t qo[3], qd[3];
        for (int a = 0; a < 3; ++a) {
            qo[a] = quantize((o[a] - lo[a]) / extent, 16);  // origins outside the sample clamp
            qd[a] = quantize(__builtin_fabs(d[a]) / len, 4);
        }
        key[j] |= (morton3(qo[0], qo[1], qo[2]) << kOriginShift) | morton3(qd[0], qd[1], qd[2]);
    }
    bool in_tmp = false;
    for (int shift = 0; shift < kKeyBits; shift += kRadixBits) {
        if (in_tmp)
            radix_pass(key_tmp, index_tmp, key, index, valid, shift, kRadixBits);
        else
            radix_pass(key, index, key_tmp, index_tmp, valid, shift, kRadixBits);
        in_tmp = !in_tmp;
    }
    return in_tmp;
}

/// Traces `count` rays of one octant, block[order[0..count)], W at a time: each group as a packet
/// or as single rays (the policy).
template <int W, bool AnyHit>
[[gnu::always_inline]] inline void trace_run(const KdTree& tree, const Ray* block, size_t base,
                                             const uint16_t* order, int count, Hit* hits,
                                             uint8_t* occluded, Policy policy,
                                             TraceCounters& counters) {
    for (int p = 0; p < count; p += W) {
        const int lanes = count - p < W ? count - p : W;
        const uint16_t* index = &order[p];
        const bool as_packet =
            policy == Policy::kPacket || (policy == Policy::kAuto && packet_pays(lanes, W));
        if (!as_packet) {
            for (int l = 0; l < lanes; ++l) {
                const size_t i = base + index[l];
                if constexpr (AnyHit)
                    occluded[i] = kdrt::occluded(tree, block[index[l]]) ? 1 : 0;
                else
                    hits[i] = kdrt::intersect(tree, block[index[l]]);
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

/// Traces `count` rays, block by block (kBlockRays). An incoherent block (block_is_incoherent)
/// is sorted whole by octant, origin and direction; a coherent one is traced in runs of
/// kCoherentRun rays, each only split by octant, keeping the input order and a small working set.
/// Every lane makes its single ray's decisions, so the grouping changes the speed, never an
/// answer.
template <int W, bool AnyHit>
void trace_rays(const KdTree& tree, const Ray* rays, size_t count, Hit* hits, uint8_t* occluded,
                Policy policy, TraceCounters& counters) {
    uint32_t key[kBlockRays], key_tmp[kBlockRays];
    uint16_t index[kBlockRays], index_tmp[kBlockRays];
    for (size_t base = 0; base < count; base += kBlockRays) {
        const int n = static_cast<int>(count - base < kBlockRays ? count - base : kBlockRays);
        const Ray* block = rays + base;
        float lo[3], hi[3];
        if (block_is_incoherent(block, n, lo, hi)) {
            const int valid =
                collect_valid<AnyHit>(tree, block, base, n, hits, occluded, counters, key, index);
            counters.sorted_rays += static_cast<uint64_t>(valid);
            const bool in_tmp =
                sort_by_origin_and_direction(block, valid, lo, hi, key, index, key_tmp, index_tmp);
            const uint32_t* sorted_key = in_tmp ? key_tmp : key;
            const uint16_t* sorted = in_tmp ? index_tmp : index;
            for (int first = 0; first < valid;) {  // one run per octant (the keys' top bits)
                const uint32_t oct = sorted_key[first] >> kOctantShift;
                int end = first + 1;
                while (end < valid && (sorted_key[end] >> kOctantShift) == oct) ++end;
                trace_run<W, AnyHit>(tree, block, base, sorted + first, end - first, hits, occluded,
                                     policy, counters);
                first = end;
            }
            continue;
        }
        for (int first = 0; first < n; first += kCoherentRun) {
            const int m = n - first < kCoherentRun ? n - first : kCoherentRun;
            const Ray* run = block + first;
            const size_t run_base = base + static_cast<size_t>(first);
            // Bucket the valid rays by octant (input order inside each), then trace the buckets.
            uint16_t bucket[8][kCoherentRun];
            int bucket_size[8] = {0, 0, 0, 0, 0, 0, 0, 0};
            for (int i = 0; i < m; ++i) {
                const Ray& r = run[i];
                if (!traceable_or_miss<AnyHit>(tree, r, run_base + static_cast<size_t>(i), hits,
                                               occluded, counters))
                    continue;
                const uint32_t o = octant(r);
                bucket[o][bucket_size[o]++] = static_cast<uint16_t>(i);
            }
            for (int o = 0; o < 8; ++o) {
                trace_run<W, AnyHit>(tree, run, run_base, bucket[o], bucket_size[o], hits, occluded,
                                     policy, counters);
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
void occluded_rays(const KdTree& tree, const Ray* rays, size_t count, uint8_t* occluded,
                   Policy policy, TraceCounters& counters) {
    trace_rays<W, true>(tree, rays, count, nullptr, occluded, policy, counters);
}

}  // namespace
}  // namespace kdrt::detail
