// The batch tracer: intersect / occluded over a batch (in parallel, one kernel block per task at
// the finest) and over one block on the calling thread, with the kernels of the chosen ISA.

#include <tbb/blocked_range.h>
#include <tbb/combinable.h>
#include <tbb/parallel_for.h>

#include <optional>
#include <string_view>

#include "kdrt/trace.h"
#include "packet.h"

namespace kdrt {
namespace {

/// The scalar "kernel": every valid ray alone.
template <bool AnyHit>
void trace_scalar(const KdTree& tree, const Ray* rays, size_t count, Hit* hits, uint8_t* occ,
                  bool count_work, detail::TraceCounters& counters) noexcept {
    for (size_t i = 0; i < count; ++i) {
        if constexpr (AnyHit) {
            occ[i] = (count_work ? detail::occluded_counted(tree, rays[i], counters)
                                 : occluded(tree, rays[i]))
                         ? 1
                         : 0;
        } else {
            hits[i] = count_work ? detail::intersect_counted(tree, rays[i], counters)
                                 : intersect(tree, rays[i]);
        }
    }
    counters.single_rays += count;
}

template <bool AnyHit>
void trace_block(const KdTree& tree, std::span<const Ray> rays, Hit* hits, uint8_t* occ,
                 const TraceOptions& options, detail::TraceCounters& counters) noexcept {
    const detail::PacketKernels* k = detail::packet_kernels_for(detail::resolve_isa(options.isa));
    if (k == nullptr) {
        trace_scalar<AnyHit>(tree, rays.data(), rays.size(), hits, occ, options.count_work,
                             counters);
    } else if constexpr (AnyHit) {
        (options.count_work ? k->occluded_counted : k->occluded)(
            tree, rays.data(), rays.size(), occ, detail::policy_for(options.mode), counters);
    } else {
        (options.count_work ? k->intersect_counted : k->intersect)(
            tree, rays.data(), rays.size(), hits, detail::policy_for(options.mode), counters);
    }
}

template <bool AnyHit>
void trace_batch(const KdTree& tree, std::span<const Ray> rays, Hit* hits, uint8_t* occ,
                 const TraceOptions& options, TraceStats* stats) noexcept {
    tbb::combinable<detail::TraceCounters> counters;
    // One kernel block per task at the finest: a batch of a few thousand rays still spreads over
    // the cores, and a task's sorting and tracing work dwarfs its scheduling.
    constexpr size_t kGrain = detail::kBlockRays;
    tbb::parallel_for(tbb::blocked_range<size_t>(0, rays.size(), kGrain),
                      [&](const tbb::blocked_range<size_t>& r) {
                          trace_block<AnyHit>(tree, rays.subspan(r.begin(), r.size()),
                                              hits ? hits + r.begin() : nullptr,
                                              occ ? occ + r.begin() : nullptr, options,
                                              counters.local());
                      });
    if (stats != nullptr) {
        *stats = TraceStats{};
        stats->isa = detail::resolve_isa(options.isa);
        stats->width = isa_width(stats->isa);
        stats->rays = rays.size();
        counters.combine_each([&](const detail::TraceCounters& c) {
            stats->packets += c.packets;
            stats->packet_rays += c.packet_rays;
            stats->single_rays += c.single_rays;
            stats->invalid_rays += c.invalid_rays;
            stats->sorted_rays += c.sorted_rays;
            stats->traversal_steps += c.steps;
            stats->leaves_visited += c.leaves;
            stats->triangle_tests += c.tri_tests;
            stats->triangle_repeats_skipped += c.tri_skips;
            stats->packet_visits += c.packet_visits;
            stats->packet_lanes += c.packet_lanes;
            stats->wide_visits += c.wide_visits;
        });
    }
}

}  // namespace

std::string_view trace_mode_name(TraceMode mode) noexcept {
    switch (mode) {
        case TraceMode::kAuto:
            return "auto";
        case TraceMode::kSingle:
            return "single";
        case TraceMode::kPacket:
            return "packet";
    }
    return "unknown";
}

std::optional<TraceMode> parse_trace_mode(std::string_view name) noexcept {
    for (TraceMode m : {TraceMode::kAuto, TraceMode::kSingle, TraceMode::kPacket})
        if (name == trace_mode_name(m)) return m;
    return std::nullopt;
}

void intersect(const KdTree& tree, std::span<const Ray> rays, std::span<Hit> hits,
               const TraceOptions& options, TraceStats* stats) noexcept {
    trace_batch<false>(tree, rays, hits.data(), nullptr, options, stats);
}

void occluded(const KdTree& tree, std::span<const Ray> rays, std::span<uint8_t> occluded_out,
              const TraceOptions& options, TraceStats* stats) noexcept {
    trace_batch<true>(tree, rays, nullptr, occluded_out.data(), options, stats);
}

void intersect_block(const KdTree& tree, std::span<const Ray> rays, std::span<Hit> hits,
                     const TraceOptions& options) noexcept {
    // A caller's blocks may be small and many (a scene's rounds give each instance's rays), so
    // the closest-hit packet mailbox's measure (mailbox_pays in packet_kernel.h) carries over
    // between a thread's calls instead of starting afresh, in its warm-up, at each. It is halved
    // past kMailCarried look-ups, so that it follows the meshes the thread traces now.
    constexpr uint64_t kMailCarried = uint64_t{1} << 16;
    thread_local detail::TraceCounters carried;
    detail::TraceCounters counters;
    counters.packets = carried.packets;
    counters.mail_looked = carried.mail_looked;
    counters.mail_skipped = carried.mail_skipped;
    trace_block<false>(tree, rays, hits.data(), nullptr, options, counters);
    carried.packets = counters.packets;
    carried.mail_looked = counters.mail_looked;
    carried.mail_skipped = counters.mail_skipped;
    if (carried.mail_looked > kMailCarried) {
        carried.mail_looked /= 2;
        carried.mail_skipped /= 2;
    }
}

void occluded_block(const KdTree& tree, std::span<const Ray> rays, std::span<uint8_t> occluded_out,
                    const TraceOptions& options) noexcept {
    detail::TraceCounters counters;
    trace_block<true>(tree, rays, nullptr, occluded_out.data(), options, counters);
}

}  // namespace kdrt
