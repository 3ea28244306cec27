// Scene ray queries: the top-level walk (scene_internal.h) hands each instance it reaches to the
// mesh's public queries (kdrt/trace.h, kdrt/query.h) on the object-space ray. Batches trace blocks
// of rays in rounds: every ray resumes its own top-level walk to its next leaf with an instance it
// reaches (and stops once the next cell starts beyond its closest hit), and the rays that reach one
// instance in a round go to the mesh's batch entry together, so coherent rays become the mesh
// kernel's packets. The lidar's nearest hits go in the same rounds.

#include <immintrin.h>

#include <algorithm>
#include <array>
#include <bit>
#include <cmath>
#include <cstddef>
#include <cstring>
#include <limits>
#include <map>
#include <utility>

#include <tbb/blocked_range.h>
#include <tbb/enumerable_thread_specific.h>
#include <tbb/parallel_for.h>
#include <tbb/task_arena.h>

#include "batch_schedule.h"
#include "geometry.h"
#include "kdrt/query.h"
#include "kdrt/scene.h"
#include "kdrt/trace.h"
#include "packet.h"
#include "scene_clearance.h"
#include "scene_in_turn_ops.h"
#include "scene_internal.h"
#include "scene_packet.h"

namespace kdrt {

/// Whether every ray starts where the first does (==, component by component: a NaN differs
/// from everything, -0 equals +0). The comparisons of 64 rays at a time are gathered with no
/// branch (SSE2: a ray's ox, oy, oz and tmin in one register), so a camera's block costs two
/// instructions a ray.
bool detail::share_origin(std::span<const Ray> rays) noexcept {
    static_assert(offsetof(Ray, oy) == 4 && offsetof(Ray, oz) == 8);
    if (rays.empty()) return true;
    const __m128 o = _mm_loadu_ps(&rays[0].ox);
    for (size_t i = 0; i < rays.size(); i += 64) {
        const size_t end = std::min(rays.size(), i + 64);
        __m128 differ = _mm_setzero_ps();
        for (size_t k = i; k < end; ++k)
            differ = _mm_or_ps(differ, _mm_cmpneq_ps(_mm_loadu_ps(&rays[k].ox), o));
        if (_mm_movemask_ps(differ) & 7) return false;
    }
    return true;
}

namespace {

using detail::InstanceData;
using detail::SceneData;

/// The "not found yet" answer: t = tmax, so a hit exactly at tmax still counts, and geom = kNoHit,
/// so the tie rule lets any instance's hit at tmax win.
SceneHit no_hit_yet(const Ray& ray) noexcept {
    return SceneHit{ray.tmax, kNoHit, 0.0f, 0.0f, kNoHit};
}

SceneHit finish(const SceneHit& best) noexcept { return best.is_hit() ? best : SceneHit{}; }

void offer(SceneHit& best, const Hit& h, uint32_t geom) noexcept {
    if (!h.is_hit()) return;
    const SceneHit c{h.t, h.prim, h.u, h.v, geom};
    if (detail::scene_hit_less(c, best)) best = c;
}

/// A ray's candidate instance: its geometry id and the widened entry t of its world box.
struct Candidate {
    float entry;
    uint32_t geom;
};

/// Every instance the top-level walk reaches for `ray` (valid) within [tmin, tmax], once each, in
/// order of entry (then geometry id).
void candidates(const SceneData& s, const Ray& ray, std::vector<Candidate>& out) {
    const size_t first = out.size();
    const detail::TopRay p = detail::make_top_ray(s, ray);
    detail::walk_top(
        s, ray, p, [&] { return ray.tmax; },
        [&](uint32_t geom, float entry) {
            out.push_back({entry, geom});
            return true;
        });
    const auto begin = out.begin() + static_cast<std::ptrdiff_t>(first);
    std::sort(begin, out.end(), [](const Candidate& a, const Candidate& b) {
        return a.entry < b.entry || (a.entry == b.entry && a.geom < b.geom);
    });
    out.erase(std::unique(begin, out.end(),
                          [](const Candidate& a, const Candidate& b) { return a.geom == b.geom; }),
              out.end());
}

/// Fewer rays than this reaching one instance in a round are traced one by one (a batch call's
/// set-up would cost more than its packets save).
constexpr size_t kMinGroup = 8;
/// Rays per block of a parallel batch.
constexpr size_t kBlock = 1024;

/// One block of the batch, on the calling thread. AnyHit: occlusion into `occ_out`; else closest
/// hits into `hits_out`.
/// True when the rounds pay for a block: its rays share an origin (camera rays) or go nearly the
/// same way (every unit direction component within 0.5 of the others', as shadow rays towards a
/// light), so the rays reaching one instance in a round are many and coherent. Otherwise
/// (diffuse bounces, random rays) each ray walks alone and stops at its first cell past its
/// closest hit, which costs less than collecting every instance along it.
bool rounds_pay(std::span<const Ray> rays) noexcept {
    // One origin first: it needs no square roots (camera rays, lidar beams).
    if (detail::share_origin(rays)) return true;
    float lo[3] = {2, 2, 2}, hi[3] = {-2, -2, -2};
    const auto narrow = [&] {
        return hi[0] - lo[0] < 0.5f && hi[1] - lo[1] < 0.5f && hi[2] - lo[2] < 0.5f;
    };
    for (size_t i = 0; i < rays.size(); ++i) {
        const Ray& r = rays[i];
        const float len = std::sqrt(r.dx * r.dx + r.dy * r.dy + r.dz * r.dz);
        if (!(len > 0.0f) || !std::isfinite(len)) continue;
        const float d[3] = {r.dx / len, r.dy / len, r.dz / len};
        for (int a = 0; a < 3; ++a) {
            lo[a] = std::min(lo[a], d[a]);
            hi[a] = std::max(hi[a], d[a]);
        }
        // The spread only grows: once an axis' reaches 0.5 the answer is false (incoherent
        // blocks, whose every ray this used to normalise, mostly end here after a few rays).
        if (i % 16 == 15 && !narrow()) return false;
    }
    return narrow();
}

/// What a round does with an instance a ray reaches: nothing (already traced), take it, or stop
/// the ray's walk.
enum class Take { kSkip, kTaken, kStop };

/// Takes `walk` to the next leaf where take(geom) takes an instance the ray's widened segment
/// [ray.tmin, limit] reaches, offering every such instance of that leaf. kTaken then; kSkip when
/// the walk ended (no cell starts at or before `limit`); kStop at once when take says so.
template <class TakeFn>
Take take_next_leaf(const SceneData& s, const Ray& ray, const detail::TopRay& p,
                    detail::TopWalk& walk, float limit, TakeFn&& take) {
    for (;;) {
        const detail::TopNode* leaf = walk.next_leaf(s, p, limit);
        if (!leaf) return Take::kSkip;
        bool found = false;
        const uint32_t end = leaf->first_ref() + leaf->count();
        for (uint32_t r = leaf->first_ref(); r < end; ++r) {
            const uint32_t geom = s.refs[r];
            float t0 = ray.tmin, t1 = limit;
            if (!detail::clip_widened(p, s.inst[geom].world, t0, t1)) continue;
            const Take t = take(geom);
            if (t == Take::kStop) return t;
            found = found || t == Take::kTaken;
        }
        if (found) return Take::kTaken;
    }
}

/// Scratch of for_each_instance.
struct InstanceGroups {
    std::vector<uint32_t> slot;   ///< per instance: its group in this round, or kNoHit
    std::vector<uint32_t> geoms;  ///< the round's instances, in the order of their first pair
    std::vector<size_t> end;      ///< per group: where its pairs start, then where they end
    std::vector<std::pair<uint32_t, uint32_t>> grouped;
};

/// A round's (geom, ray) pairs grouped by instance (a counting sort: instances in the order of
/// their first pair, each one's rays in the order of their pairs), as fn(geom, first, end) per
/// instance. The order does not change an answer: each instance is traced with the ray's bound
/// at the time, and the best hit over instances is a minimum.
template <class Fn>
void for_each_instance(std::vector<std::pair<uint32_t, uint32_t>>& pairs, InstanceGroups& g,
                       size_t instances, Fn&& fn) {
    if (g.slot.size() != instances) g.slot.assign(instances, kNoHit);
    g.geoms.clear();
    g.end.clear();
    for (const auto& pair : pairs) {
        uint32_t& k = g.slot[pair.first];
        if (k == kNoHit) {
            k = static_cast<uint32_t>(g.geoms.size());
            g.geoms.push_back(pair.first);
            g.end.push_back(0);
        }
        ++g.end[k];
    }
    size_t sum = 0;
    for (size_t& e : g.end) sum += std::exchange(e, sum);
    g.grouped.resize(pairs.size());
    for (const auto& pair : pairs) g.grouped[g.end[g.slot[pair.first]]++] = pair;
    pairs.swap(g.grouped);
    size_t g0 = 0;
    for (size_t k = 0; k < g.geoms.size(); ++k) {
        g.slot[g.geoms[k]] = kNoHit;
        fn(g.geoms[k], g0, g.end[k]);
        g0 = g.end[k];
    }
}

/// The top-level walks of a block's rays, taken one leaf further each round. Rays whose direction
/// components have the same signs (none zero) walk in packets of up to kPacketLanes
/// (detail::TopPacket: one node visit for every lane), taken in ray order within each of the
/// eight sign classes; the others, a class's last ray when it is alone, and a packet's last live
/// lane walk alone (detail::TopWalk, a packet's lane handed over with its cells). Either way a ray
/// reaches the leaves its own TopWalk would reach, in the same order.
struct TopRounds {
    std::vector<detail::TopRay> top;     ///< per ray: its world ray for the top level
    std::vector<detail::TopWalk> walk;   ///< per ray: where its walk stands when alone
    std::vector<detail::TopCell> cells;  ///< per ray: kTopStack cells, that walk's stack
    std::vector<detail::TopPacket> packets;
    std::vector<detail::TopPacketCell> packet_cells;  ///< per packet: kTopStack cells
    std::vector<uint32_t> alone;                      ///< rays walking alone whose walk goes on
    std::vector<uint32_t> grouped;                    ///< live packets
    std::vector<uint32_t> order;                      ///< scratch: rays by sign class
    std::vector<uint8_t> sign_class;
    const detail::TopPacketOps* ops = nullptr;  ///< the packets' steps for the batch's ISA

    /// Starts the walks of the rays of `rays` for which valid(i) holds; packets walk with the
    /// registers of `isa` (supported).
    template <class Valid>
    void start(const SceneData& s, std::span<const Ray> rays, Isa isa, Valid&& valid) {
        ops = &detail::top_packet_ops(isa);
        const size_t n = rays.size();
        top.resize(n);
        walk.resize(n);
        cells.resize(n * detail::kTopStack);
        alone.clear();
        grouped.clear();
        const size_t max_packets = n / detail::kPacketLanes + 8;
        packets.resize(max_packets);
        packet_cells.resize(max_packets * detail::kTopStack);
        // Sign class per ray: 0-7 the signs of a direction without a zero component, 8 alone,
        // 9 not walked (an invalid ray).
        size_t count[10] = {};
        order.resize(n);
        sign_class.resize(n);
        const Ray* last = nullptr;  // the last valid ray (its TopRay is top[last - rays.data()])
        for (size_t i = 0; i < n; ++i) {
            walk[i].stack = &cells[i * detail::kTopStack];
            walk[i].size = 0;
            uint8_t c = 9;
            if (valid(i)) {
                const Ray& r = rays[i];
                // Rays from one origin (a camera's, a lidar's) share the margin.
                const detail::TopRay& p = top[i] =
                    last && r.ox == last->ox && r.oy == last->oy && r.oz == last->oz
                        ? detail::make_top_ray_from(top[static_cast<size_t>(last - rays.data())], r)
                        : detail::make_top_ray(s, r);
                last = &r;
                // The direction's sign bits (a component is > 0 when its sign bit is clear and it
                // is not zero; valid rays have no NaN).
                const uint32_t bx = std::bit_cast<uint32_t>(p.dir[0]);
                const uint32_t by = std::bit_cast<uint32_t>(p.dir[1]);
                const uint32_t bz = std::bit_cast<uint32_t>(p.dir[2]);
                const bool zero = (bx << 1) == 0 || (by << 1) == 0 || (bz << 1) == 0;
                c = zero ? 8
                         : static_cast<uint8_t>((~bx >> 31) | (~by >> 31) << 1 | (~bz >> 31) << 2);
            }
            sign_class[i] = c;
            ++count[c];
        }
        size_t first[10] = {};
        for (int c = 0; c < 9; ++c) first[c + 1] = first[c] + count[c];
        size_t fill[9];
        std::copy(first, first + 9, fill);
        for (size_t i = 0; i < n; ++i)
            if (sign_class[i] < 9) order[fill[sign_class[i]]++] = static_cast<uint32_t>(i);
        for (int c = 0; c < 9; ++c) {
            for (size_t k = first[c]; k < first[c + 1];) {
                const size_t len =
                    c == 8 ? 1 : std::min<size_t>(detail::kPacketLanes, first[c + 1] - k);
                if (len == 1) {
                    const uint32_t i = order[k];
                    walk[i].start(s, rays[i], top[i], walk[i].stack);
                    if (!walk[i].done()) alone.push_back(i);
                } else {
                    const auto p = static_cast<uint32_t>(grouped.size());
                    packets[p].start(s, rays, top, &order[k], static_cast<int>(len),
                                     &packet_cells[p * detail::kTopStack], *ops);
                    if (keep_or_hand_over(p)) grouped.push_back(p);
                }
                k += len;
            }
        }
    }

    [[nodiscard]] bool done() const noexcept { return alone.empty() && grouped.empty(); }

    /// One round: every live walk goes to its next leaf where take(i, geom) takes an instance ray
    /// i's widened segment [ray.tmin, limit(i)] reaches (a packet: to the next leaf where one of
    /// its lanes does), offering each such instance of that leaf. take returns Take: kTaken keeps
    /// the ray for the next round, kStop ends its walk at once and calls stopped(i). A walk that
    /// finds nothing more ends; rays for which gone(i) holds are dropped first.
    template <class Gone, class Limit, class TakeFn, class Stopped>
    void round(const SceneData& s, std::span<const Ray> rays, Gone&& gone, Limit&& limit,
               TakeFn&& take, Stopped&& stopped) {
        size_t kept = 0;
        for (const uint32_t i : alone) {
            if (gone(i)) continue;
            const Take t = take_next_leaf(s, rays[i], top[i], walk[i], limit(i),
                                          [&](uint32_t geom) { return take(i, geom); });
            if (t == Take::kStop)
                stopped(i);
            else if (t == Take::kTaken)
                alone[kept++] = i;
        }
        alone.resize(kept);
        size_t kept_packets = 0;
        for (size_t k = 0, live = grouped.size(); k < live; ++k) {
            const uint32_t p = grouped[k];
            detail::TopPacket& packet = packets[p];
            detail::Lanes lim = detail::Lanes::fill(0.0f);
            uint32_t drop = 0;
            for (uint32_t m = packet.lanes & ~packet.ended; m; m &= m - 1) {
                const int l = std::countr_zero(m);
                const uint32_t i = packet.ray[l];
                if (gone(i))
                    drop |= 1u << l;
                else
                    lim.set(l, limit(i));
            }
            packet.end(drop);
            uint32_t found = 0, at = 0;
            while (!found) {
                const detail::TopNode* leaf = ops->next_leaf(packet, s, lim, at);
                if (!leaf) break;
                const uint32_t end = leaf->first_ref() + leaf->count();
                for (uint32_t r = leaf->first_ref(); r < end && at; ++r) {
                    const uint32_t geom = s.refs[r];
                    for (uint32_t m = ops->reach(packet, s.inst[geom].world, lim, at); m;
                         m &= m - 1) {
                        const int l = std::countr_zero(m);
                        const Take t = take(packet.ray[l], geom);
                        if (t == Take::kStop) {
                            stopped(packet.ray[l]);
                            packet.end(1u << l);
                            at &= ~(1u << l);
                        } else if (t == Take::kTaken) {
                            found |= 1u << l;
                        }
                    }
                }
            }
            if (keep_or_hand_over(p)) grouped[kept_packets++] = p;
        }
        grouped.resize(kept_packets);
    }

private:
    /// Keeps packet `p` (true) when two lanes or more walk on; otherwise its one live lane, if
    /// any, goes on alone.
    bool keep_or_hand_over(uint32_t p) {
        detail::TopPacket& packet = packets[p];
        const uint32_t live = packet.live();
        // Two lanes or more (not std::popcount: without -mpopcnt it is a libgcc call).
        if ((live & (live - 1)) != 0) return true;
        if (live) {
            const int l = std::countr_zero(live);
            const uint32_t i = packet.ray[l];
            packet.hand_over(l, walk[i]);
            packet.end(live);
            alone.push_back(i);
        }
        return false;
    }
};

/// The object rays of pairs [g0, g1) (one instance's) into `out`, with tmax = tmax(ray index).
template <class Tmax>
void object_rays(const InstanceData& in, std::span<const Ray> rays,
                 const std::vector<std::pair<uint32_t, uint32_t>>& pairs, size_t g0, size_t g1,
                 Tmax&& tmax, std::vector<Ray>& out) {
    out.resize(g1 - g0);
    for (size_t k = g0; k < g1; ++k) {
        const uint32_t i = pairs[k].second;
        Ray o = detail::to_object(in, rays[i]);
        o.tmax = tmax(i);
        out[k - g0] = o;
    }
}

struct BlockScratch {
    TopRounds walks;
    std::vector<detail::Mailbox> mailbox;
    std::vector<SceneHit> best;
    std::vector<uint8_t> done;
    std::vector<uint8_t> valid;                        ///< per ray: detail::ray_is_valid
    std::vector<std::pair<uint32_t, uint32_t>> pairs;  ///< (geom, ray) of a round
    InstanceGroups groups;
    std::vector<Ray> rays;
    std::vector<Hit> hits;
    std::vector<uint8_t> occ;
    // The depth-first walk's (DepthFirst): the packet and its stack.
    detail::TopPacket packet;
    std::vector<detail::TopPacketCell> packet_cells;
    std::array<detail::Mailbox, detail::kPacketLanes> lane_mailbox;  ///< where refs_unique fails
};

struct Counts {
    uint64_t invalid = 0, visits = 0, batches = 0;
};

/// detail::ray_is_valid(r) without branches: every origin and direction component finite (its
/// exponent bits not all ones), the direction not zero (some component's bits other than the
/// sign set), and tmin <= tmax (false with a NaN).
inline bool ray_is_valid_bits(const Ray& r) noexcept {
    constexpr uint32_t kExp = 0x7f800000u;
    const uint32_t ox = std::bit_cast<uint32_t>(r.ox), oy = std::bit_cast<uint32_t>(r.oy),
                   oz = std::bit_cast<uint32_t>(r.oz), dx = std::bit_cast<uint32_t>(r.dx),
                   dy = std::bit_cast<uint32_t>(r.dy), dz = std::bit_cast<uint32_t>(r.dz);
    const bool finite = ((ox & kExp) != kExp) & ((oy & kExp) != kExp) & ((oz & kExp) != kExp) &
                        ((dx & kExp) != kExp) & ((dy & kExp) != kExp) & ((dz & kExp) != kExp);
    const bool nonzero = ((dx | dy | dz) << 1) != 0;
    return finite & nonzero & (r.tmin <= r.tmax);
}

/// valid[i] = detail::ray_is_valid(rays[i]) for each ray; returns the count of invalid rays.
size_t mark_valid(std::span<const Ray> rays, uint8_t* valid) noexcept {
    size_t invalid = 0;
    for (size_t i = 0; i < rays.size(); ++i) {
        valid[i] = ray_is_valid_bits(rays[i]) ? 1 : 0;
        invalid += 1 - valid[i];
    }
    return invalid;
}

/// The invalid rays of `rays` (detail::ray_is_valid).
size_t count_invalid(std::span<const Ray> rays) noexcept {
    size_t invalid = 0;
    for (const Ray& r : rays) invalid += ray_is_valid_bits(r) ? 0 : 1;
    return invalid;
}

/// The calling thread's block scratch, kept between batches: a batch's first block on a thread
/// no longer allocates and zero-fills the top-level walks' stacks (about 1 MB) anew. trace_block
/// starts no tasks, so a thread never uses it for two blocks at once.
BlockScratch& thread_scratch() {
    thread_local BlockScratch scratch;
    return scratch;
}

Isa resolved_isa(const TraceOptions& options) noexcept {
    return options.isa && isa_supported(*options.isa) ? *options.isa : default_isa();
}

SceneHit intersect_one(const SceneData& s, const Ray& ray, uint64_t* visits) noexcept;
bool occluded_one(const SceneData& s, const Ray& ray, uint64_t* visits) noexcept;

/// A coherent block's rays depth first, as Embree's instancing goes: packets of up to
/// kPacketLanes rays of one octant walk the top level (detail::TopPacket); at each instance a leaf
/// lists, the lanes that reach its box go into it at once (their object rays, to_object's, with
/// tmax their closest hit so far, through the mesh kernels' caller-packet entry, LaneKernels), and
/// the answers are merged at once, so each lane's bound falls before the walk goes on. Per lane
/// it is intersect_one's / occluded_one's walk: the same leaves in the same order, the same
/// instances with the same bounds and object rays (a mailbox per lane where an instance may be
/// listed twice), the same merge; an occluded lane ends. The packets are the order
/// trace_patch_block / trace_coherent_block give (batch_schedule.h: an image's square patches, or
/// runs in input order), whose calls this is (TraceRun): `order` indexes `block`, a part of the
/// scene block `rays`.
template <bool AnyHit>
struct DepthFirst {
    const SceneData& s;
    std::span<const Ray> rays;
    SceneHit* hits_out;  ///< closest hit: the answers, at the rays' indices in `rays`
    uint8_t* occ_out;    ///< AnyHit: the answers
    BlockScratch& b;
    const detail::TopPacketOps& ops;
    const detail::LaneKernels* lanes;  ///< nullptr: the scalar ISA (rays one by one)
    Counts& counts;
    bool mail;

    /// An image's rows of `row` rays from one point (image_row), rays [0, n) of `rays`, in
    /// trace_patch_block's patches (bands of up to kPatchRows rows, each patch the band's rows by
    /// kPacketLanes / rows columns) without its buckets: each patch whose rays are all valid and
    /// of one octant (nearly all) is a packet as it stands (TopPacketOps::start_patch checks it
    /// in the packet's registers); the others go by octant (operator()), their invalid rays
    /// answered as misses. The rows past the last whole band go as trace_coherent_block takes
    /// them.
    void patches(int n, int row, detail::TraceCounters& tc) const {
        constexpr int kLanes = detail::kPacketLanes;
        const int rows = std::min(n / row, detail::kPatchRows);
        const int cols = std::max(kLanes / rows, 1);
        const int band = rows * row;
        // A whole patch's rays from its first: rows by cols, row by row.
        using U8 = uint16_t __attribute__((vector_size(16)));
        static_assert(kLanes == 8);
        U8 step{};
        for (int k = 0; k < rows * cols && k < kLanes; ++k)
            step[k] = static_cast<uint16_t>(k / cols * row + k % cols);
        int first = 0;
        for (; first + band <= n; first += band) {
            for (int pc = 0; pc < row; pc += cols) {
                const int pe = std::min(pc + cols, row);
                std::array<uint16_t, kLanes> order;
                int count = 0;
                if (pe - pc == cols) {
                    const U8 o = step + static_cast<uint16_t>(first + pc);
                    std::memcpy(order.data(), &o, sizeof o);
                    count = rows * cols;
                } else {
                    for (int r = 0; r < rows; ++r)
                        for (int c = pc; c < pe; ++c)
                            order[count++] = static_cast<uint16_t>(first + r * row + c);
                }
                detail::TopPacket& pk = b.packet;
                detail::Lanes lim;
                const uint32_t flat = ops.start_patch(pk, s, rays.data(), 0, order.data(), count,
                                                      b.packet_cells.data(), lim);
                if (flat != detail::kNotOnePacket) {
                    walk(flat, lim);
                    continue;
                }
                // Another octant or an invalid ray in the patch: its rays by octant.
                std::array<std::array<uint16_t, kLanes>, 8> bucket;
                std::array<int, 8> size{};
                for (int k = 0; k < count; ++k) {
                    const int o = detail::octant_or_invalid(rays[order[k]]);
                    if (o < 0) {
                        miss(order[k], tc);
                        continue;
                    }
                    bucket[o][size[o]++] = order[k];
                }
                for (int o = 0; o < 8; ++o)
                    if (size[o]) (*this)(rays.data(), 0, bucket[o].data(), size[o]);
            }
        }
        if (first < n)
            detail::trace_coherent_block<AnyHit>(rays.data() + first, first, n - first,
                                                 b.hits.data(), occ_out, tc, *this);
    }

    void operator()(const Ray* block, size_t, const uint16_t* order, int count) const {
        const auto first = static_cast<uint32_t>(block - rays.data());
        for (int k = 0; k < count; k += detail::kPacketLanes) {
            const int n = std::min(count - k, detail::kPacketLanes);
            if (n == 1)
                single(first + order[k]);
            else
                packet(first, order + k, n);
        }
    }

private:
    void single(uint32_t i) const {
        if constexpr (AnyHit)
            occ_out[i] = occluded_one(s, rays[i], &counts.visits) ? 1 : 0;
        else
            hits_out[i] = intersect_one(s, rays[i], &counts.visits);
    }

    /// The lanes' answers so far: closest hit, each lane's best hit where `hit` has its bit (its
    /// t is the lane's limit; the other fields are set only there, so nothing is written up
    /// front); AnyHit, the occluded lanes in `hit`.
    struct Answers {
        uint32_t hit = 0;
        uint32_t prim[detail::kPacketLanes], geom[detail::kPacketLanes];
        float u[detail::kPacketLanes], v[detail::kPacketLanes];
        [[nodiscard]] SceneHit best(int l, const detail::Lanes& lim) const noexcept {
            return SceneHit{lim.get(l), prim[l], u[l], v[l], geom[l]};
        }
    };

    /// Ray i (invalid) answered as a miss, as the batch scheduler answers it (answer_miss).
    void miss(uint32_t i, detail::TraceCounters& tc) const {
        if constexpr (AnyHit)
            occ_out[i] = 0;
        else
            hits_out[i] = SceneHit{};
        ++tc.invalid_rays;
    }

    void packet(uint32_t first, const uint16_t* order, int n) const {
        // Each lane's TopRay and its limit (its closest hit so far: none yet, so its tmax) are
        // made in the packet's registers (TopPacketOps::start). Lanes whose direction has a zero
        // component are left out, and traced alone.
        detail::Lanes lim;
        walk(ops.start(b.packet, s, rays.data(), first, order, n, b.packet_cells.data(), lim), lim);
    }

    /// The depth-first walk of the packet b.packet (started, its lanes' limits `lim`); the lanes
    /// `flat` left out of it are traced alone.
    void walk(uint32_t flat, detail::Lanes& lim) const {
        detail::TopPacket& pk = b.packet;
        Answers ans;  // NOLINT(cppcoreguidelines-pro-type-member-init): set where `hit` says
        if (mail) b.lane_mailbox.fill(detail::Mailbox{});
        uint32_t at = 0;
        while (const detail::TopNode* leaf = ops.next_leaf(pk, s, lim, at)) {
            const uint32_t end = leaf->first_ref() + leaf->count();
            for (uint32_t r = leaf->first_ref(); r < end && at; ++r) {
                const uint32_t geom = s.refs[r];
                uint32_t m = ops.reach(pk, s.inst[geom].world, lim, at);
                if (mail)
                    for (uint32_t q = m; q; q &= q - 1)
                        if (b.lane_mailbox[std::countr_zero(q)].seen(geom)) m &= ~(q & -q);
                if (!m) continue;
                visit(pk, geom, m, lim, at, ans);
            }
        }
        // Every lane's answer, in place: its walk has ended (or it was occluded).
        for (uint32_t q = pk.lanes; q; q &= q - 1) {
            const int l = std::countr_zero(q);
            if constexpr (AnyHit)
                occ_out[pk.ray[l]] = static_cast<uint8_t>(ans.hit >> l & 1u);
            else
                hits_out[pk.ray[l]] = ans.hit >> l & 1u ? ans.best(l, lim) : SceneHit{};
        }
        for (uint32_t q = flat; q; q &= q - 1) single(pk.ray[std::countr_zero(q)]);
    }

    /// The lanes `m` of `pk` into instance `geom`.
    void visit(detail::TopPacket& pk, uint32_t geom, uint32_t m, detail::Lanes& lim, uint32_t& at,
               Answers& ans) const {
        const InstanceData& in = s.inst[geom];
        const KdTree& tree = *s.instances[geom].tree;
        // Every lane's object ray at once, tmax its limit (its ray's tmax, or its closest hit so
        // far).
        std::array<Ray, detail::kPacketLanes> obj;
        ops.object_rays(pk, in, lim, obj.data());
        for (uint32_t q = m; q; q &= q - 1) ++counts.visits;
        if constexpr (AnyHit) {
            uint32_t occ = 0;
            if (lanes) {
                occ = lanes->occluded(tree, obj.data(), m);
            } else {
                for (uint32_t q = m; q; q &= q - 1)
                    if (occluded(tree, obj[std::countr_zero(q)])) occ |= q & -q;
            }
            ans.hit |= occ;
            pk.end(occ);
            at &= ~occ;
        } else {
            std::array<Hit, detail::kPacketLanes> h;
            if (lanes) {
                lanes->intersect(tree, obj.data(), m, h.data());
            } else {
                for (uint32_t q = m; q; q &= q - 1) {
                    const int l = std::countr_zero(q);
                    h[l] = intersect(tree, obj[l]);
                }
            }
            for (uint32_t q = m; q; q &= q - 1) {
                const int l = std::countr_zero(q);
                if (!h[l].is_hit()) continue;
                // offer() against the lane's best so far: none yet is (tmax, kNoHit), which any
                // hit (t <= tmax, geom < kNoHit) beats.
                const SceneHit c{h[l].t, h[l].prim, h[l].u, h[l].v, geom};
                if (ans.hit >> l & 1u && !detail::scene_hit_less(c, ans.best(l, lim))) continue;
                ans.hit |= 1u << l;
                ans.prim[l] = c.prim, ans.geom[l] = c.geom, ans.u[l] = c.u, ans.v[l] = c.v;
                lim.set(l, c.t);
            }
        }
    }
};

/// A coherent block depth first (DepthFirst): an image's rows from one point in square patches
/// (image_row, trace_patch_block), other blocks in runs of input order (trace_coherent_block).
/// AnyHit: occlusion into `occ_out`; else closest hits into `hits_out`. Each answer is written
/// once, in place.
template <bool AnyHit>
void depth_first_block(const SceneData& s, std::span<const Ray> rays, std::span<SceneHit> hits_out,
                       std::span<uint8_t> occ_out, Isa isa, BlockScratch& b, Counts& counts) {
    static_assert(detail::kPacketLanes == detail::kLaneRays);
    const int n = static_cast<int>(rays.size());
    b.packet_cells.resize(detail::kTopStack);
    // The batch scheduler answers the invalid rays: occlusion in place, closest hits (its Hit
    // type) to scratch, and as SceneHit below.
    b.hits.resize(rays.size());
    detail::TraceCounters tc;
    const DepthFirst<AnyHit> run{s,
                                 rays,
                                 hits_out.data(),
                                 occ_out.data(),
                                 b,
                                 detail::top_packet_ops(isa),
                                 detail::lane_kernels_for(isa),
                                 counts,
                                 !s.refs_unique};
    static thread_local int row_guess = 0;
    const int row = detail::image_row(rays.data(), n, row_guess);
    if (row > 0) {
        row_guess = row;
        run.patches(n, row, tc);
    } else {
        detail::trace_coherent_block<AnyHit>(rays.data(), 0, n, b.hits.data(), occ_out.data(), tc,
                                             run);
    }
    counts.invalid += tc.invalid_rays;
    if constexpr (!AnyHit) {
        if (tc.invalid_rays > 0)
            for (size_t i = 0; i < rays.size(); ++i)
                if (!detail::ray_is_valid(rays[i])) hits_out[i] = SceneHit{};
    }
}

template <bool AnyHit>
void trace_block(const SceneData& s, std::span<const Ray> rays, std::span<SceneHit> hits_out,
                 std::span<uint8_t> occ_out, const TraceOptions& options, BlockScratch& b,
                 Counts& counts) {
    const size_t n = rays.size();
    if (options.mode == TraceMode::kSingle ||
        (options.mode == TraceMode::kAuto && !rounds_pay(rays))) {
        // Several rays' walks in turn, across the top level and the instances (scene_in_turn.h):
        // each ray's answer is intersect_one's / occluded_one's.
        counts.invalid += count_invalid(rays);
        const detail::SceneInTurnOps& ops = detail::scene_in_turn_ops(resolved_isa(options));
        if constexpr (AnyHit)
            ops.occluded(s, rays.data(), n, occ_out.data(), counts.visits);
        else
            ops.intersect(s, rays.data(), n, hits_out.data(), counts.visits);
        return;
    }
    // A coherent block under kAuto goes depth first (it never lost to the rounds: session 24);
    // kPacket keeps the rounds.
    if (options.mode == TraceMode::kAuto) {
        depth_first_block<AnyHit>(s, rays, hits_out, occ_out, resolved_isa(options), b, counts);
        return;
    }
    const bool mail = !s.refs_unique;  // else no instance can be reached twice
    if (mail) b.mailbox.assign(n, detail::Mailbox{});
    b.best.resize(n);
    b.done.assign(n, 0);
    b.valid.resize(n);
    counts.invalid += mark_valid(rays, b.valid.data());
    for (size_t i = 0; i < n; ++i) b.best[i] = no_hit_yet(rays[i]);
    b.walks.start(s, rays, resolved_isa(options), [&](size_t i) { return b.valid[i] != 0; });
    // Each round takes every live walk one leaf further: the next leaf whose cell starts at or
    // before its ray's closest hit so far with an instance the ray's widened segment reaches
    // (and its mailbox has not seen). A ray whose next cell starts beyond its closest hit stops
    // there, without walking the rest of the top level; an occluded ray is dropped.
    while (!b.walks.done()) {
        b.pairs.clear();
        b.walks.round(
            s, rays, [&](uint32_t i) { return AnyHit && b.done[i] != 0; },
            [&](uint32_t i) { return AnyHit ? rays[i].tmax : b.best[i].t; },
            [&](uint32_t i, uint32_t geom) {
                if (mail && b.mailbox[i].seen(geom)) return Take::kSkip;
                b.pairs.emplace_back(geom, i);
                return Take::kTaken;
            },
            [](uint32_t) {});
        if (b.pairs.empty()) break;
        for_each_instance(
            b.pairs, b.groups, s.inst.size(), [&](uint32_t geom, size_t g0, size_t g1) {
                if constexpr (AnyHit) {
                    // A ray occluded by an instance earlier in this round (one of the same top
                    // leaf: overlapping instances) is done: it is not traced again here.
                    size_t kept = g0;
                    for (size_t k = g0; k < g1; ++k)
                        if (!b.done[b.pairs[k].second]) b.pairs[kept++] = b.pairs[k];
                    g1 = kept;
                    if (g1 == g0) return;
                }
                const size_t count = g1 - g0;
                const KdTree& tree = *s.instances[geom].tree;
                object_rays(
                    s.inst[geom], rays, b.pairs, g0, g1,
                    [&](uint32_t i) { return AnyHit ? rays[i].tmax : b.best[i].t; }, b.rays);
                counts.visits += count;
                const bool batch = count >= kMinGroup;
                counts.batches += batch ? 1 : 0;
                if constexpr (AnyHit) {
                    b.occ.resize(count);
                    if (batch) {
                        occluded_block(tree, b.rays, b.occ, options);
                    } else {
                        for (size_t k = 0; k < count; ++k)
                            b.occ[k] = occluded(tree, b.rays[k]) ? 1 : 0;
                    }
                    for (size_t k = 0; k < count; ++k)
                        if (b.occ[k]) b.done[b.pairs[g0 + k].second] = 1;
                } else {
                    b.hits.resize(count);
                    if (batch) {
                        intersect_block(tree, b.rays, b.hits, options);
                    } else {
                        for (size_t k = 0; k < count; ++k) b.hits[k] = intersect(tree, b.rays[k]);
                    }
                    for (size_t k = 0; k < count; ++k)
                        offer(b.best[b.pairs[g0 + k].second], b.hits[k], geom);
                }
            });
    }
    for (size_t i = 0; i < n; ++i) {
        if constexpr (AnyHit)
            occ_out[i] = b.done[i];
        else
            hits_out[i] = finish(b.best[i]);
    }
}

template <bool AnyHit>
void trace_batch(const Scene& scene, std::span<const Ray> rays, std::span<SceneHit> hits,
                 std::span<uint8_t> occ, const TraceOptions& options, SceneTraceStats* stats) {
    const SceneData& s = scene.data();
    tbb::enumerable_thread_specific<Counts> counts;
    const size_t blocks = (rays.size() + kBlock - 1) / kBlock;
    tbb::parallel_for(
        tbb::blocked_range<size_t>(0, blocks, 1), [&](const tbb::blocked_range<size_t>& range) {
            for (size_t k = range.begin(); k != range.end(); ++k) {
                const size_t lo = k * kBlock, len = std::min(kBlock, rays.size() - lo);
                trace_block<AnyHit>(s, rays.subspan(lo, len),
                                    AnyHit ? std::span<SceneHit>() : hits.subspan(lo, len),
                                    AnyHit ? occ.subspan(lo, len) : std::span<uint8_t>(), options,
                                    thread_scratch(), counts.local());
            }
        });
    if (stats) {
        *stats = SceneTraceStats{};
        stats->isa = resolved_isa(options);
        stats->rays = rays.size();
        for (const Counts& c : counts) {
            stats->invalid_rays += c.invalid;
            stats->instance_visits += c.visits;
            stats->instance_batches += c.batches;
        }
    }
}

}  // namespace

namespace {

/// The single-ray closest hit: instances in the order the walk meets them, each traced with
/// tmax = the closest hit so far; the walk stops at the first cell beyond it.
SceneHit intersect_one(const SceneData& s, const Ray& ray, uint64_t* visits) noexcept {
    if (!detail::ray_is_valid(ray)) return SceneHit{};
    SceneHit best = no_hit_yet(ray);
    detail::Mailbox mailbox;
    const detail::TopRay p = detail::make_top_ray(s, ray);
    detail::walk_top(
        s, ray, p, [&] { return best.t; },
        [&](uint32_t geom, float) {
            if (mailbox.seen(geom)) return true;
            Ray o = detail::to_object(s.inst[geom], ray);
            o.tmax = best.t;
            if (visits) ++*visits;
            offer(best, intersect(*s.instances[geom].tree, o), geom);
            return true;
        });
    return finish(best);
}

bool occluded_one(const SceneData& s, const Ray& ray, uint64_t* visits) noexcept {
    if (!detail::ray_is_valid(ray)) return false;
    bool hit = false;
    detail::Mailbox mailbox;
    const detail::TopRay p = detail::make_top_ray(s, ray);
    detail::walk_top(
        s, ray, p, [&] { return ray.tmax; },
        [&](uint32_t geom, float) {
            if (mailbox.seen(geom)) return true;
            if (visits) ++*visits;
            hit = occluded(*s.instances[geom].tree, detail::to_object(s.inst[geom], ray));
            return !hit;
        });
    return hit;
}

}  // namespace

SceneHit intersect(const Scene& scene, const Ray& ray) noexcept {
    return intersect_one(scene.data(), ray, nullptr);
}

bool occluded(const Scene& scene, const Ray& ray) noexcept {
    return occluded_one(scene.data(), ray, nullptr);
}

void intersect(const Scene& scene, std::span<const Ray> rays, std::span<SceneHit> hits,
               const TraceOptions& options, SceneTraceStats* stats) noexcept {
    trace_batch<false>(scene, rays, hits, {}, options, stats);
}

void occluded(const Scene& scene, std::span<const Ray> rays, std::span<uint8_t> occluded_out,
              const TraceOptions& options, SceneTraceStats* stats) noexcept {
    trace_batch<true>(scene, rays, {}, occluded_out, options, stats);
}

namespace {

/// The calling thread's blocks of a batch. Its scratch is kept per thread between calls: the
/// renderer calls this once per tile and sample.
template <bool AnyHit>
void trace_on_this_thread(const Scene& scene, std::span<const Ray> rays, std::span<SceneHit> hits,
                          std::span<uint8_t> occ, const TraceOptions& options) noexcept {
    BlockScratch& scratch = thread_scratch();
    Counts counts;
    for (size_t lo = 0; lo < rays.size(); lo += kBlock) {
        const size_t len = std::min(kBlock, rays.size() - lo);
        trace_block<AnyHit>(scene.data(), rays.subspan(lo, len),
                            AnyHit ? hits : hits.subspan(lo, len),
                            AnyHit ? occ.subspan(lo, len) : occ, options, scratch, counts);
    }
}

}  // namespace

void intersect_block(const Scene& scene, std::span<const Ray> rays, std::span<SceneHit> hits,
                     const TraceOptions& options) noexcept {
    trace_on_this_thread<false>(scene, rays, hits, {}, options);
}

void occluded_block(const Scene& scene, std::span<const Ray> rays, std::span<uint8_t> occluded_out,
                    const TraceOptions& options) noexcept {
    trace_on_this_thread<true>(scene, rays, {}, occluded_out, options);
}

namespace detail {

void depth_first_intersect(const SceneData& s, std::span<const Ray> rays, std::span<SceneHit> hits,
                           Isa isa, uint64_t& visits) {
    Counts counts;
    for (size_t lo = 0; lo < rays.size(); lo += kBlock) {
        const size_t len = std::min(kBlock, rays.size() - lo);
        depth_first_block<false>(s, rays.subspan(lo, len), hits.subspan(lo, len), {}, isa,
                                 thread_scratch(), counts);
    }
    visits += counts.visits;
}

void depth_first_occluded(const SceneData& s, std::span<const Ray> rays,
                          std::span<uint8_t> occluded_out, Isa isa, uint64_t& visits) {
    Counts counts;
    for (size_t lo = 0; lo < rays.size(); lo += kBlock) {
        const size_t len = std::min(kBlock, rays.size() - lo);
        depth_first_block<true>(s, rays.subspan(lo, len), {}, occluded_out.subspan(lo, len), isa,
                                thread_scratch(), counts);
    }
    visits += counts.visits;
}

}  // namespace detail

// ---------------------------------------------------------------------------------------------
// Every hit

namespace {

void sort_hits(std::vector<SceneHit>& hits) {
    std::sort(hits.begin(), hits.end(), detail::scene_hit_less);
}

/// Every hit of `ray` into `out` (replaced), sorted; `tmp` and `cands` are scratch.
void all_hits(const SceneData& s, const Ray& ray, bool merge, std::vector<SceneHit>& out,
              std::vector<Hit>& tmp, std::vector<Candidate>& cands) {
    out.clear();
    if (!detail::ray_is_valid(ray)) return;
    cands.clear();
    candidates(s, ray, cands);
    for (const Candidate& c : cands) {
        intersect_all(*s.instances[c.geom].tree, detail::to_object(s.inst[c.geom], ray), merge,
                      tmp);
        for (const Hit& h : tmp) out.push_back({h.t, h.prim, h.u, h.v, c.geom});
    }
    sort_hits(out);
}

struct AllScratch {
    std::vector<SceneHit> hits;
    std::vector<Hit> tmp;
    std::vector<Candidate> cands;
};

}  // namespace

uint32_t intersect_all(const Scene& scene, const Ray& ray, bool merge_coincident,
                       std::vector<SceneHit>& out) {
    std::vector<Hit> tmp;
    std::vector<Candidate> cands;
    all_hits(scene.data(), ray, merge_coincident, out, tmp, cands);
    return static_cast<uint32_t>(out.size());
}

SceneAllHits intersect_all(const Scene& scene, std::span<const Ray> rays,
                           const AllHitsOptions& options) {
    const SceneData& s = scene.data();
    SceneAllHits result;
    result.counts.assign(rays.size(), 0);
    std::vector<std::vector<SceneHit>> kept(rays.size());
    tbb::enumerable_thread_specific<AllScratch> scratch;
    tbb::parallel_for(
        tbb::blocked_range<size_t>(0, rays.size(), 256),
        [&](const tbb::blocked_range<size_t>& range) {
            AllScratch& a = scratch.local();
            for (size_t i = range.begin(); i != range.end(); ++i) {
                all_hits(s, rays[i], options.merge_coincident, a.hits, a.tmp, a.cands);
                result.counts[i] = static_cast<uint32_t>(a.hits.size());
                const size_t keep = std::min<size_t>(a.hits.size(), options.max_hits);
                kept[i].assign(a.hits.begin(), a.hits.begin() + static_cast<std::ptrdiff_t>(keep));
            }
        });
    result.offsets.assign(rays.size() + 1, 0);
    for (size_t i = 0; i < rays.size(); ++i)
        result.offsets[i + 1] = result.offsets[i] + kept[i].size();
    result.hits.reserve(result.offsets.back());
    for (auto& k : kept) result.hits.insert(result.hits.end(), k.begin(), k.end());
    return result;
}

void count_intersections(const Scene& scene, std::span<const Ray> rays,
                         const AllHitsOptions& options, std::span<uint32_t> counts) {
    const SceneData& s = scene.data();
    tbb::enumerable_thread_specific<AllScratch> scratch;
    tbb::parallel_for(tbb::blocked_range<size_t>(0, rays.size(), 256),
                      [&](const tbb::blocked_range<size_t>& range) {
                          AllScratch& a = scratch.local();
                          for (size_t i = range.begin(); i != range.end(); ++i) {
                              all_hits(s, rays[i], options.merge_coincident, a.hits, a.tmp,
                                       a.cands);
                              counts[i] = static_cast<uint32_t>(a.hits.size());
                          }
                      });
}

// ---------------------------------------------------------------------------------------------
// The nearest hits (scan_lidar)

namespace {

/// How far past `t_kth` instance `geom`'s every-hit query must look so that the merged groups
/// starting at or before t_kth are those of the untruncated query: a group spans at most the
/// merge tolerance (AllHitsOptions::merge_coincident: 2^-18 of the largest coordinate of the
/// object origin and the group's first triangle, over the largest direction component), which
/// is bounded with the tree's root box; taken twice, plus a few ulps of t_kth for the float
/// subtraction of the group test. Without merging nothing beyond t_kth matters.
/// `root_mag` is the tree's InstanceData::root_mag (its root box's largest |coordinate|).
float truncated_tmax(double root_mag, const Ray& o, float t_kth, bool merge) noexcept {
    if (!merge) return t_kth;
    const double dmax = std::max({std::fabs(o.dx), std::fabs(o.dy), std::fabs(o.dz)});
    // The largest of the origin's and the root box's magnitudes (a maximum: in any order).
    const double mag =
        std::max({static_cast<double>(std::fabs(o.ox)), static_cast<double>(std::fabs(o.oy)),
                  static_cast<double>(std::fabs(o.oz)), root_mag});
    const double reach = static_cast<double>(t_kth) +
                         std::fabs(static_cast<double>(t_kth)) * 0x1p-20 +
                         2.0 * mag * double{detail::kMergeToleranceScale} / dmax;
    if (!(reach < std::numeric_limits<float>::max())) return std::numeric_limits<float>::max();
    auto f = static_cast<float>(reach);
    if (static_cast<double>(f) < reach) {
        // The next float up: for a positive finite f (below FLT_MAX here) its bits plus one,
        // which is what std::nextafter(f, FLT_MAX) gives, without the library call.
        if (f > 0.0f)
            f = std::bit_cast<float>(std::bit_cast<uint32_t>(f) + 1u);
        else
            f = std::nextafter(f, std::numeric_limits<float>::max());
    }
    return f;
}

struct NearestScratch {
    std::vector<Hit> tmp;
    /// The instances this ray traced (each exactly once): stamp[geom] == ray while traced, so
    /// the test costs O(1) however many instances a beam with many returns passes.
    std::vector<uint32_t> stamp;
    uint32_t ray = 0;
};

/// The window of the object ray `o` whose every-hit answer holds an instance's hits that may be
/// among the nearest k, given its closest hit `first` (a hit) on `o` traced with tmax = `limit`:
/// the ray's tmax when the ray's list held fewer than k hits, else the k-th hit's t (`full`).
Ray hits_window(double root_mag, Ray o, const Hit& first, float ray_tmax, float limit, bool full,
                uint32_t k, bool merge) noexcept {
    // Its first k merged hits lie in groups starting no later than the k-th hit so far; for
    // k = 1 no later than this closest hit, whose t is the first raw hit's of intersect_all, bit
    // for bit (kdrt/query.h).
    if (k == 1) {
        // Nothing of this instance lies before its closest hit: the every-hit query needs only
        // the cells around it.
        o.tmin = first.t;
        o.tmax = std::min(ray_tmax, truncated_tmax(root_mag, o, first.t, merge));
    } else {
        o.tmax = full ? std::min(ray_tmax, truncated_tmax(root_mag, o, limit, merge)) : ray_tmax;
    }
    return o;
}

/// Keeps the instance's merged hits `hits` (sorted by (t, prim)) that are among the nearest k
/// in `out`.
void keep_hits(std::span<const Hit> hits, uint32_t k, uint32_t geom, std::vector<SceneHit>& out) {
    if (k == 1) {
        // The loop below for one kept hit (a lidar's single return): only the instance's first
        // hit can be kept, since every later one comes after it in (t, prim) order.
        if (hits.empty()) return;
        const SceneHit c{hits[0].t, hits[0].prim, hits[0].u, hits[0].v, geom};
        if (out.empty())
            out.push_back(c);
        else if (detail::scene_hit_less(c, out[0]))
            out[0] = c;
        return;
    }
    // Once one hit is not kept, no later one is.
    for (const Hit& h : hits) {
        const SceneHit c{h.t, h.prim, h.u, h.v, geom};
        if (out.size() == k && !detail::scene_hit_less(c, out.back())) break;
        out.insert(std::upper_bound(out.begin(), out.end(), c, detail::scene_hit_less), c);
        if (out.size() > k) out.pop_back();
    }
}

/// True when `first` (a hit), the closest hit of the object ray `o`, is what its every-hit window
/// would answer for a single merged return (`clear`: the instance's tree's HitClearance, given only
/// for k = 1 with merging; scene_clearance.h), so the window can be skipped.
bool lone_return(const HitClearance* clear, const Ray& o, const Hit& first) noexcept {
    return clear && detail::hit_is_alone(*clear, o, first);
}

/// Takes instance `geom`'s hits into `out` (the nearest `k` so far, sorted by the tie rule), given
/// its closest hit `first` on the object ray `o` traced with tmax = `limit` (hits_window).
void take_instance(const KdTree& tree, double root_mag, const Ray& o, const Hit& first,
                   float ray_tmax, float limit, bool full, uint32_t k, bool merge, uint32_t geom,
                   const HitClearance* clear, std::vector<SceneHit>& out, std::vector<Hit>& tmp) {
    // None up to the k-th hit so far means no hit to keep (a merged hit is never before its
    // group's first, the instance's closest).
    if (!first.is_hit()) return;
    if (lone_return(clear, o, first)) {
        keep_hits(std::span<const Hit>(&first, 1), k, geom, out);
        return;
    }
    intersect_all(tree, hits_window(root_mag, o, first, ray_tmax, limit, full, k, merge), merge,
                  tmp);
    keep_hits(tmp, k, geom, out);
}

/// The nearest `k` (>= 1) hits of `ray` into `out` (replaced), sorted by the tie rule. The
/// top-level walk goes front to back with the limit at the k-th hit so far: an instance whose
/// widened box starts beyond it holds no hit that could be kept. Each instance is traced once,
/// first by the closest-hit kernel up to that limit, then (take_instance) fully within the
/// truncation above, so its hits are those of the oracle's every-hit query.
void nearest(const SceneData& s, const Ray& ray, uint32_t k, bool merge,
             std::span<const HitClearance* const> clear, std::vector<SceneHit>& out,
             NearestScratch& sc) {
    out.clear();
    if (!detail::ray_is_valid(ray)) return;
    if (sc.stamp.size() != s.inst.size() || ++sc.ray == 0) {
        sc.stamp.assign(s.inst.size(), 0);
        sc.ray = 1;
    }
    const detail::TopRay p = detail::make_top_ray(s, ray);
    detail::walk_top(
        s, ray, p, [&] { return out.size() < k ? ray.tmax : out.back().t; },
        [&](uint32_t geom, float) {
            if (sc.stamp[geom] == sc.ray) return true;
            sc.stamp[geom] = sc.ray;
            const KdTree& tree = *s.instances[geom].tree;
            Ray o = detail::to_object(s.inst[geom], ray);
            const bool full = out.size() == k;
            const float limit = full ? out.back().t : ray.tmax;
            o.tmax = limit;
            take_instance(tree, s.inst[geom].root_mag, o, intersect(tree, o), ray.tmax, limit, full,
                          k, merge, geom, clear.empty() ? nullptr : clear[geom], out, sc.tmp);
            return true;
        });
}

/// Rounds for the nearest hits pay up to this many hits per ray (each ray keeps its list).
constexpr uint32_t kRoundsMaxHits = 16;
/// Instances a ray may trace in rounds; one that reaches more is traced again alone (nearest),
/// since each instance must be traced once per ray and the rounds keep that list per ray.
constexpr uint32_t kRoundsMaxTraced = 16;

struct NearestRounds {
    TopRounds walks;
    std::vector<std::vector<SceneHit>> out;
    std::vector<float> limit;      ///< per ray: its k-th hit's t so far, or its tmax
    std::vector<uint32_t> traced;  ///< per ray kRoundsMaxTraced geometry ids
    std::vector<uint32_t> traced_count;
    std::vector<uint32_t> alone;  ///< rays that reached more instances than the rounds keep
    std::vector<std::pair<uint32_t, uint32_t>> pairs;  ///< (geom, ray) of a round
    InstanceGroups groups;
    std::vector<Ray> rays;
    std::vector<Hit> hits;
    std::vector<Ray> windows;  ///< every-hit windows of an instance's rays that hit it
    std::vector<uint32_t> window_of;
};

/// nearest() of each ray of a block whose rays are coherent, in rounds as trace_block's: each
/// round takes every live ray one leaf further along its top-level walk (up to its k-th hit so
/// far), and the rays reaching one instance go to the mesh's closest-hit batch entry together;
/// each closest hit then goes to take_instance, as nearest() takes it. `outs[i]` gets ray i's hits.
/// `clear`: per instance its tree's HitClearance, or empty (lone_return).
void nearest_rounds(const SceneData& s, std::span<const Ray> rays, uint32_t k, bool merge, Isa isa,
                    std::span<const HitClearance* const> clear, NearestRounds& b,
                    NearestScratch& sc) {
    const size_t n = rays.size();
    b.out.resize(n);
    b.traced.resize(n * kRoundsMaxTraced);
    b.traced_count.assign(n, 0);
    b.alone.clear();
    b.limit.resize(n);
    for (size_t i = 0; i < n; ++i) {
        b.out[i].clear();
        b.limit[i] = rays[i].tmax;
    }
    b.walks.start(s, rays, isa, [&](size_t i) { return detail::ray_is_valid(rays[i]); });
    // Ray i's current bound of t: its k-th hit so far, or its tmax (b.limit, kept up to date
    // whenever b.out[i] changes).
    const auto limit_of = [&](uint32_t i) { return b.limit[i]; };
    const auto update_limit = [&](uint32_t i) {
        const std::vector<SceneHit>& out = b.out[i];
        b.limit[i] = out.size() < k ? rays[i].tmax : out.back().t;
    };
    while (!b.walks.done()) {
        b.pairs.clear();
        b.walks.round(
            s, rays, [](uint32_t) { return false; }, limit_of,
            [&](uint32_t i, uint32_t geom) {
                uint32_t* traced = &b.traced[size_t{i} * kRoundsMaxTraced];
                uint32_t& count = b.traced_count[i];
                if (std::find(traced, traced + count, geom) != traced + count) return Take::kSkip;
                if (count == kRoundsMaxTraced) return Take::kStop;
                traced[count++] = geom;
                b.pairs.emplace_back(geom, i);
                return Take::kTaken;
            },
            [&](uint32_t i) { b.alone.push_back(i); });
        if (b.pairs.empty()) break;
        for_each_instance(
            b.pairs, b.groups, s.inst.size(), [&](uint32_t geom, size_t g0, size_t g1) {
                const size_t count = g1 - g0;
                const KdTree& tree = *s.instances[geom].tree;
                const double root_mag = s.inst[geom].root_mag;
                const HitClearance* cl = clear.empty() ? nullptr : clear[geom];
                object_rays(s.inst[geom], rays, b.pairs, g0, g1, limit_of, b.rays);
                b.hits.resize(count);
                if (count >= kMinGroup) {
                    intersect_block(tree, b.rays, b.hits, TraceOptions{TraceMode::kAuto, isa});
                } else {
                    for (size_t j = 0; j < count; ++j) b.hits[j] = intersect(tree, b.rays[j]);
                }
                if (count < kMinGroup) {
                    for (size_t j = 0; j < count; ++j) {
                        const uint32_t i = b.pairs[g0 + j].second;
                        std::vector<SceneHit>& out = b.out[i];
                        take_instance(tree, root_mag, b.rays[j], b.hits[j], rays[i].tmax,
                                      b.rays[j].tmax, out.size() == k, k, merge, geom, cl, out,
                                      sc.tmp);
                        update_limit(i);
                    }
                    return;
                }
                // The rays that hit it, their windows (take_instance's) in one every-hit batch,
                // which keeps the first k merged hits of each (more are never kept).
                b.windows.clear();
                b.window_of.clear();
                for (size_t j = 0; j < count; ++j) {
                    if (!b.hits[j].is_hit()) continue;
                    const uint32_t i = b.pairs[g0 + j].second;
                    if (lone_return(cl, b.rays[j], b.hits[j])) {
                        keep_hits(std::span<const Hit>(&b.hits[j], 1), k, geom, b.out[i]);
                        update_limit(i);
                        continue;
                    }
                    b.windows.push_back(hits_window(root_mag, b.rays[j], b.hits[j], rays[i].tmax,
                                                    b.rays[j].tmax, b.out[i].size() == k, k,
                                                    merge));
                    b.window_of.push_back(i);
                }
                if (b.windows.empty()) return;  // every hit was alone in its group
                AllHitsOptions options;
                options.merge_coincident = merge;
                options.max_hits = k;
                options.isa = isa;
                // Isolated: while the batch waits, this thread must not take another block of
                // this scan (it would reuse this thread's scratch, `b`, mid-round).
                AllHits all;
                tbb::this_task_arena::isolate(
                    [&] { all = intersect_all(tree, b.windows, options); });
                for (size_t w = 0; w < b.windows.size(); ++w) {
                    keep_hits(std::span<const Hit>(all.hits).subspan(
                                  all.offsets[w], all.offsets[w + 1] - all.offsets[w]),
                              k, geom, b.out[b.window_of[w]]);
                    update_limit(b.window_of[w]);
                }
            });
    }
    // Rays that reached more instances than the rounds keep: from the start, alone.
    for (const uint32_t i : b.alone) nearest(s, rays[i], k, merge, clear, b.out[i], sc);
}

}  // namespace

SceneAllHits detail::nearest_hits(const Scene& scene, std::span<const Ray> rays, uint32_t max_hits,
                                  bool merge_coincident, std::optional<Isa> isa_choice) {
    const SceneData& s = scene.data();
    const Isa isa = isa_choice && isa_supported(*isa_choice) ? *isa_choice : default_isa();
    SceneAllHits result;
    result.offsets.assign(rays.size() + 1, 0);
    if (max_hits == 0) return result;
    // A single merged return skips the every-hit window where the closest hit is provably alone
    // in its group, for the instances that carry their tree's clearance (kdrt/hit_clearance.h).
    std::vector<const HitClearance*> clear;
    if (max_hits == 1 && merge_coincident && !rays.empty()) {
        clear.resize(s.instances.size(), nullptr);
        for (size_t g = 0; g < s.instances.size(); ++g) clear[g] = s.instances[g].clearance.get();
    }
    constexpr size_t kRaysPerTask = kBlock;
    const size_t tasks = (rays.size() + kRaysPerTask - 1) / kRaysPerTask;
    std::vector<std::vector<SceneHit>> per_task(tasks);  // each task's rays' hits, in ray order
    struct Scratch {
        NearestScratch nearest;
        NearestRounds rounds;
        std::vector<SceneHit> hits;
    };
    tbb::parallel_for(
        tbb::blocked_range<size_t>(0, tasks, 1), [&](const tbb::blocked_range<size_t>& range) {
            // Kept per thread between scans (a scan every frame would otherwise allocate and
            // fault in its walks' stacks anew). A thread holds it for one block at a time: the
            // only wait inside a block is the isolated every-hit batch, which runs no other block.
            thread_local Scratch sc;
            for (size_t task = range.begin(); task != range.end(); ++task) {
                const size_t lo = task * kRaysPerTask;
                const size_t hi = std::min(rays.size(), lo + kRaysPerTask);
                std::vector<SceneHit>& kept = per_task[task];
                const std::span<const Ray> block = rays.subspan(lo, hi - lo);
                if (max_hits <= kRoundsMaxHits && rounds_pay(block)) {
                    nearest_rounds(s, block, max_hits, merge_coincident, isa, clear, sc.rounds,
                                   sc.nearest);
                    for (size_t i = lo; i < hi; ++i) {
                        const std::vector<SceneHit>& out = sc.rounds.out[i - lo];
                        result.offsets[i + 1] = out.size();
                        kept.insert(kept.end(), out.begin(), out.end());
                    }
                    continue;
                }
                for (size_t i = lo; i < hi; ++i) {
                    nearest(s, rays[i], max_hits, merge_coincident, clear, sc.hits, sc.nearest);
                    result.offsets[i + 1] = sc.hits.size();
                    kept.insert(kept.end(), sc.hits.begin(), sc.hits.end());
                }
            }
        });
    for (size_t i = 0; i < rays.size(); ++i) result.offsets[i + 1] += result.offsets[i];
    result.hits.reserve(result.offsets.back());
    for (const auto& kept : per_task)
        result.hits.insert(result.hits.end(), kept.begin(), kept.end());
    return result;
}

// ---------------------------------------------------------------------------------------------
// Hit attributes

Vec3 hit_normal(const Scene& scene, const SceneHit& hit) noexcept {
    if (!hit.is_hit()) return Vec3{};
    const SceneData& s = scene.data();
    const InstanceData& in = s.inst[hit.geom];
    const Vec3 n = triangle_normal(s.instances[hit.geom].tree->triangle(hit.prim));
    if (in.identity_linear) return n;
    double w[3];
    for (int j = 0; j < 3; ++j)  // (L^-T n)_j = sum_i Linv[i][j] n_i
        w[j] = in.inv[j] * n.x + in.inv[3 + j] * n.y + in.inv[6 + j] * n.z;
    const double len = std::sqrt(w[0] * w[0] + w[1] * w[1] + w[2] * w[2]);
    if (!(len > 0.0)) return Vec3{};
    const double scale = (in.det < 0.0 ? -1.0 : 1.0) / len;
    return Vec3{static_cast<float>(w[0] * scale), static_cast<float>(w[1] * scale),
                static_cast<float>(w[2] * scale)};
}

Vec3 hit_point(const Scene& scene, const SceneHit& hit) noexcept {
    if (!hit.is_hit()) {
        const float nan = std::numeric_limits<float>::quiet_NaN();
        return Vec3{nan, nan, nan};
    }
    const SceneData& s = scene.data();
    const Vec3 p = hit_point(s.instances[hit.geom].tree->triangle(hit.prim), hit.hit());
    const double q[3] = {p.x, p.y, p.z};
    return detail::to_world(s.inst[hit.geom], q);
}

void hit_attributes(const Scene& scene, std::span<const SceneHit> hits, std::span<Vec3> normals,
                    std::span<Vec3> points) {
    tbb::parallel_for(tbb::blocked_range<size_t>(0, hits.size(), 4096),
                      [&](const tbb::blocked_range<size_t>& range) {
                          for (size_t i = range.begin(); i != range.end(); ++i) {
                              if (!normals.empty()) normals[i] = hit_normal(scene, hits[i]);
                              if (!points.empty()) points[i] = hit_point(scene, hits[i]);
                          }
                      });
}

TriVerts world_triangle(const Scene& scene, uint32_t geom, uint32_t prim) noexcept {
    const SceneData& s = scene.data();
    const TriVerts& t = s.instances[geom].tree->triangle(prim);
    TriVerts w;
    const float* in[3] = {t.v0, t.v1, t.v2};
    float* out[3] = {w.v0, w.v1, w.v2};
    for (int c = 0; c < 3; ++c) {
        const double p[3] = {in[c][0], in[c][1], in[c][2]};
        const Vec3 v = detail::to_world(s.inst[geom], p);
        out[c][0] = v.x, out[c][1] = v.y, out[c][2] = v.z;
    }
    return w;
}

// ---------------------------------------------------------------------------------------------
// The oracle

SceneOracle::SceneOracle(const Scene& scene) : scene_(scene) {
    std::map<const KdTree*, std::shared_ptr<const std::vector<TriVerts>>> by_tree;
    for (uint32_t g = 0; g < scene.size(); ++g) {
        const KdTree* tree = scene.instance(g).tree.get();
        auto& tris = by_tree[tree];
        if (!tris) tris = std::make_shared<const std::vector<TriVerts>>(triangles_by_id(*tree));
        tris_.push_back(tris);
    }
}

SceneHit SceneOracle::intersect(const Ray& ray) const noexcept {
    if (!detail::ray_is_valid(ray)) return SceneHit{};
    SceneHit best = no_hit_yet(ray);
    for (uint32_t g = 0; g < scene_.size(); ++g)
        offer(best, brute_force_intersect(*tris_[g], scene_.object_ray(g, ray)), g);
    return finish(best);
}

bool SceneOracle::occluded(const Ray& ray) const noexcept {
    if (!detail::ray_is_valid(ray)) return false;
    for (uint32_t g = 0; g < scene_.size(); ++g)
        if (brute_force_occluded(*tris_[g], scene_.object_ray(g, ray))) return true;
    return false;
}

std::vector<SceneHit> SceneOracle::intersect_all(const Ray& ray, bool merge_coincident) const {
    std::vector<SceneHit> out;
    if (!detail::ray_is_valid(ray)) return out;
    for (uint32_t g = 0; g < scene_.size(); ++g) {
        for (const Hit& h :
             brute_force_intersect_all(*tris_[g], scene_.object_ray(g, ray), merge_coincident))
            out.push_back({h.t, h.prim, h.u, h.v, g});
    }
    sort_hits(out);
    return out;
}

}  // namespace kdrt
