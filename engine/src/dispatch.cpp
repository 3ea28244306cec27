// Run-time choice of the packet kernels, and the parallel batch tracer on top of them.

#include <cstdlib>
#include <string>

#include <tbb/blocked_range.h>
#include <tbb/combinable.h>
#include <tbb/parallel_for.h>

#include "kdrt/trace.h"
#include "packet.h"

namespace kdrt {
namespace {

struct IsaChoice {
    Isa isa;
    std::string reason;
};

Isa widest_supported() noexcept {
    for (Isa isa : {Isa::kAvx512, Isa::kAvx2, Isa::kSse4})
        if (isa_supported(isa)) return isa;
    return Isa::kScalar;
}

const IsaChoice& choice() noexcept {
    static const IsaChoice c = [] {
        const Isa widest = widest_supported();
        const char* env = std::getenv("KDRT_ISA");
        if (env == nullptr || *env == '\0') return IsaChoice{widest, "widest supported"};
        const std::optional<Isa> named = parse_isa(env);
        if (!named)
            return IsaChoice{widest, std::string("KDRT_ISA=") + env +
                                         " is not one of scalar|sse4|avx2|avx512; ignored"};
        if (!isa_supported(*named))
            return IsaChoice{
                widest, std::string("KDRT_ISA=") + env + " is not supported by this CPU; ignored"};
        return IsaChoice{*named, std::string("KDRT_ISA=") + env};
    }();
    return c;
}

const detail::PacketKernels* kernels_for(Isa isa) noexcept {
    switch (isa) {
        case Isa::kSse4:
            return detail::packet_kernels_sse4();
        case Isa::kAvx2:
            return detail::packet_kernels_avx2();
        case Isa::kAvx512:
            return detail::packet_kernels_avx512();
        case Isa::kScalar:
            break;
    }
    return nullptr;
}

Isa resolve(const TraceOptions& options) noexcept {
    if (options.isa && isa_supported(*options.isa)) return *options.isa;
    return default_isa();
}

detail::Policy policy_for(TraceMode mode) noexcept {
    switch (mode) {
        case TraceMode::kSingle:
            return detail::Policy::kSingle;
        case TraceMode::kPacket:
            return detail::Policy::kPacket;
        case TraceMode::kAuto:
            break;
    }
    return detail::Policy::kAuto;
}

/// The scalar "kernel": every valid ray alone.
template <bool AnyHit>
void trace_scalar(const KdTree& tree, const Ray* rays, size_t count, Hit* hits, uint8_t* occ,
                  detail::TraceCounters& counters) noexcept {
    for (size_t i = 0; i < count; ++i) {
        if constexpr (AnyHit)
            occ[i] = occluded(tree, rays[i]) ? 1 : 0;
        else
            hits[i] = intersect(tree, rays[i]);
    }
    counters.single_rays += count;
}

template <bool AnyHit>
void trace_block(const KdTree& tree, std::span<const Ray> rays, Hit* hits, uint8_t* occ,
                 const TraceOptions& options, detail::TraceCounters& counters) noexcept {
    const detail::PacketKernels* k = kernels_for(resolve(options));
    if (k == nullptr) {
        trace_scalar<AnyHit>(tree, rays.data(), rays.size(), hits, occ, counters);
    } else if constexpr (AnyHit) {
        k->occluded(tree, rays.data(), rays.size(), occ, policy_for(options.mode), counters);
    } else {
        k->intersect(tree, rays.data(), rays.size(), hits, policy_for(options.mode), counters);
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
        stats->isa = resolve(options);
        stats->rays = rays.size();
        counters.combine_each([&](const detail::TraceCounters& c) {
            stats->packets += c.packets;
            stats->packet_rays += c.packet_rays;
            stats->single_rays += c.single_rays;
            stats->invalid_rays += c.invalid_rays;
            stats->sorted_rays += c.sorted_rays;
        });
    }
}

}  // namespace

std::string_view isa_name(Isa isa) noexcept {
    switch (isa) {
        case Isa::kScalar:
            return "scalar";
        case Isa::kSse4:
            return "sse4";
        case Isa::kAvx2:
            return "avx2";
        case Isa::kAvx512:
            return "avx512";
    }
    return "unknown";
}

std::optional<Isa> parse_isa(std::string_view name) noexcept {
    for (Isa isa : {Isa::kScalar, Isa::kSse4, Isa::kAvx2, Isa::kAvx512})
        if (name == isa_name(isa)) return isa;
    return std::nullopt;
}

int isa_width(Isa isa) noexcept {
    switch (isa) {
        case Isa::kSse4:
            return 4;
        case Isa::kAvx2:
            return 8;
        case Isa::kAvx512:
            return 16;
        case Isa::kScalar:
            break;
    }
    return 1;
}

bool isa_supported(Isa isa) noexcept {
    __builtin_cpu_init();
    switch (isa) {
        case Isa::kScalar:
            return true;
        case Isa::kSse4:
            return __builtin_cpu_supports("sse4.2") && __builtin_cpu_supports("popcnt");
        case Isa::kAvx2:
            return __builtin_cpu_supports("avx2") && __builtin_cpu_supports("popcnt");
        case Isa::kAvx512:
            return __builtin_cpu_supports("avx512f") && __builtin_cpu_supports("avx512dq") &&
                   __builtin_cpu_supports("avx512vl") && __builtin_cpu_supports("avx512bw");
    }
    return false;
}

Isa default_isa() noexcept { return choice().isa; }

std::string_view default_isa_reason() noexcept { return choice().reason; }

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
    detail::TraceCounters counters;
    trace_block<false>(tree, rays, hits.data(), nullptr, options, counters);
}

void occluded_block(const KdTree& tree, std::span<const Ray> rays, std::span<uint8_t> occluded_out,
                    const TraceOptions& options) noexcept {
    detail::TraceCounters counters;
    trace_block<true>(tree, rays, nullptr, occluded_out.data(), options, counters);
}

}  // namespace kdrt
