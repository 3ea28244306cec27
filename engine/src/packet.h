#pragma once
// Internal: the interface between the generic batch tracer and the per-ISA packet kernels.

#include <cstddef>
#include <cstdint>
#include <optional>

#include "kdrt/kdtree.h"
#include "kdrt/trace.h"
#include "kdrt/types.h"

namespace kdrt::detail {

/// How a block decides between packets and single rays (TraceMode, as the kernels see it).
/// kIncoherentAsPacket, kIncoherentAsSingle and kIncoherentMeasured are auto with its way for
/// incoherent blocks fixed (RunTracer::incoherent_block): sorted packets, single rays in input
/// order, or every block measured (half each way; under kIncoherentMeasured also every coherent
/// any-hit block, RunTracer::coherent_block). kCoherentSorted is auto with every coherent any-hit
/// block in packets sorted by origin (trace_origin_sorted_block); kCoherentSortMeasured is auto
/// with every coherent any-hit block measured half sorted, half in input order
/// (RunTracer::sort_measured); kCoherentPairMeasured is auto with every coherent any-hit block
/// measured as sorted packets against single rays, whole blocks in pairs, one each way
/// (RunTracer::sorted_pair_measured). Tests reach every way with them; policy_for never gives them.
enum class Policy : uint32_t {
    kAuto = 0,
    kSingle = 1,
    kPacket = 2,
    kIncoherentAsPacket = 3,
    kIncoherentAsSingle = 4,
    kIncoherentMeasured = 5,
    kCoherentSorted = 6,
    kCoherentSortMeasured = 7,
    kCoherentPairMeasured = 8
};

/// What a kernel did, summed over a batch (per-thread, added up afterwards).
struct TraceCounters {
    uint64_t packets = 0;      ///< packets traversed
    uint64_t packet_rays = 0;  ///< rays traced inside packets
    uint64_t single_rays = 0;  ///< rays traced with the single-ray kernel
    uint64_t invalid_rays =
        0;  ///< rays answered as misses without tracing (NaN, zero direction, ...)
    uint64_t sorted_rays = 0;  ///< valid rays of blocks sorted by origin and direction
    // The work done, counted only by the counting kernels (TraceOptions::count_work). A packet's
    // node visit or triangle test counts once per live lane, so the per-ray figures compare
    // across modes.
    uint64_t steps = 0;          ///< inner nodes visited, summed over rays
    uint64_t leaves = 0;         ///< leaves visited, summed over rays
    uint64_t tri_tests = 0;      ///< ray-triangle tests
    uint64_t packet_visits = 0;  ///< nodes (inner and leaf) visited by packets
    uint64_t packet_lanes = 0;   ///< live lanes summed over those visits
    uint64_t wide_visits = 0;    ///< wide nodes visited by the single-ray kernel
    /// Of tri_tests, lanes of closest-hit packet tests skipped as repeats (the packet mailbox).
    uint64_t tri_skips = 0;
    // The packet mailbox's own measure, kept by every kernel (not reported): packet tests looked
    // up in it, and of those skipped, in the closest-hit packets that used it.
    uint64_t mail_looked = 0;
    uint64_t mail_skipped = 0;
};

/// The scalar kernel (trace.cpp) with its work counted: the same answers as intersect/occluded.
Hit intersect_counted(const KdTree& tree, const Ray& ray, TraceCounters& counters) noexcept;
bool occluded_counted(const KdTree& tree, const Ray& ray, TraceCounters& counters) noexcept;

using IntersectKernel = void (*)(const KdTree& tree, const Ray* rays, size_t count, Hit* hits,
                                 Policy policy, TraceCounters& counters);
using OccludedKernel = void (*)(const KdTree& tree, const Ray* rays, size_t count,
                                uint8_t* occluded, Policy policy, TraceCounters& counters);

/// Where an every-hit kernel delivers its rays' hits (multi_hit.cpp implements it, outside the
/// per-ISA translation units, so no standard-library code is instantiated for an ISA).
struct AllHitsSink {
    /// Ray `ray` (an index into the kernel's rays) is left to the caller's single-ray traversal.
    void (*single)(AllHitsSink& self, size_t ray);
    /// A packet's answers: lane l is ray rays[l]; its raw hits (every hit in [tmin, tmax] of each
    /// leaf the ray passes, unsorted; a triangle in several leaves once per leaf) are
    /// raw[l * capacity, + min(count[l], capacity)). count[l] > capacity: the lane overflowed and
    /// only the first `capacity` were kept (the caller traces that ray again on its own).
    void (*packet)(AllHitsSink& self, const size_t* rays, int lanes, const Hit* raw,
                   const uint32_t* count);
};

/// Raw hits a packet keeps per lane before the lane overflows (AllHitsSink::packet).
inline constexpr uint32_t kPacketHitCapacity = 48;

/// Every hit of `count` rays: each valid ray goes to sink.packet (within a packet of same-octant
/// rays) or sink.single, as the policy decides (invalid ones to neither: they have no hits).
using AllHitsKernel = void (*)(const KdTree& tree, const Ray* rays, size_t count, AllHitsSink& sink,
                               Policy policy);

/// The single-ray kernel (wide_kernel.h) compiled for one ISA: intersect / occluded of trace.h,
/// and the counting copies (intersect_counted / occluded_counted).
using SingleIntersect = Hit (*)(const KdTree& tree, const Ray& ray) noexcept;
using SingleOccluded = bool (*)(const KdTree& tree, const Ray& ray) noexcept;
using SingleIntersectCounted = Hit (*)(const KdTree& tree, const Ray& ray,
                                       TraceCounters& counters) noexcept;
using SingleOccludedCounted = bool (*)(const KdTree& tree, const Ray& ray,
                                       TraceCounters& counters) noexcept;

/// One ISA's kernels. Each traces `count` rays on the calling thread, answers in input order. The
/// counting ones also fill the work counters of TraceCounters (slower; same answers).
struct PacketKernels {
    int width;
    IntersectKernel intersect;
    OccludedKernel occluded;
    IntersectKernel intersect_counted;
    OccludedKernel occluded_counted;
    AllHitsKernel all_hits;
    SingleIntersect single_intersect;
    SingleOccluded single_occluded;
    SingleIntersectCounted single_intersect_counted;
    SingleOccludedCounted single_occluded_counted;
};

/// The kernels the single-ray queries of trace.h run on: those of default_isa(), nullptr when
/// that is Isa::kScalar (then trace.cpp's baseline copy runs). Chosen once.
const PacketKernels* single_ray_kernels() noexcept;

/// Defined in packet_sse4.cpp, packet_avx2.cpp, packet_avx512.cpp. Call only when the CPU has the
/// instruction set (isa_supported).
const PacketKernels* packet_kernels_sse4() noexcept;
const PacketKernels* packet_kernels_avx2() noexcept;
const PacketKernels* packet_kernels_avx512() noexcept;

/// The kernels of `isa`, nullptr for Isa::kScalar (isa_dispatch.cpp). `isa` must be supported.
const PacketKernels* packet_kernels_for(Isa isa) noexcept;

/// The ISA a batch asked for runs on: `isa` when given and supported, else default_isa()
/// (isa_dispatch.cpp).
Isa resolve_isa(const std::optional<Isa>& isa) noexcept;

/// The kernels' policy for a TraceMode (isa_dispatch.cpp).
Policy policy_for(TraceMode mode) noexcept;

/// Rays per block a kernel sorts for coherence (batch_schedule.h, schedule_rays): big enough that
/// rays from a few image rows find their neighbours across rows, small enough that the keys and
/// indices (24 KiB) stay in L1/L2 and fit 16-bit indices.
inline constexpr size_t kBlockRays = 4096;

// ---------------------------------------------------------------------------------------------
// A caller's packet (scene instancing, depth first)

/// Rays in a caller's packet (LaneKernels): a scene's top-level packet (scene_packet.h's
/// kPacketLanes) carries its lanes into an instance as one such packet.
inline constexpr int kLaneRays = 8;

/// The mesh kernels for a caller's packet of up to kLaneRays object-space rays and a lane mask:
/// the scene's depth-first walk hands them the lanes that reach one instance. Each lane's
/// current bound is its ray's tmax (the scene's closest hit so far); only the lanes of `mask`
/// are read and written, and each gets exactly the single-ray kernel's answer (intersect /
/// occluded of trace.h) for its ray, whatever the other lanes are. The caller merges a lane's
/// answer with its hits in other instances (the scene's tie rule puts the geometry id between
/// t and prim, so the mesh cannot merge them itself).
struct LaneKernels {
    /// hits[l] = intersect(tree, rays[l]) for each lane l of `mask`.
    void (*intersect)(const KdTree& tree, const Ray* rays, uint32_t mask, Hit* hits) noexcept;
    /// The lanes l of `mask` with occluded(tree, rays[l]).
    uint32_t (*occluded)(const KdTree& tree, const Ray* rays, uint32_t mask) noexcept;
};

/// Defined in packet_sse4.cpp (4-lane packets), packet_avx2.cpp and packet_avx512.cpp (8-lane
/// packets: a caller's packet has 8 rays at most). Call only when the CPU has the instruction
/// set; lane_kernels_for(Isa::kScalar) is nullptr (isa_dispatch.cpp).
const LaneKernels* lane_kernels_sse4() noexcept;
const LaneKernels* lane_kernels_avx2() noexcept;
const LaneKernels* lane_kernels_avx512() noexcept;
const LaneKernels* lane_kernels_for(Isa isa) noexcept;

}  // namespace kdrt::detail
