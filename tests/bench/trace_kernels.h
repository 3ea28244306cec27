#pragma once
/// The batch tracers kdrt-bench can time, one per --mode. A new traversal (packets, a new ISA)
/// joins by returning its functions from trace_kernel(); nothing else in the tool changes.

#include <cstdint>
#include <optional>
#include <span>
#include <string_view>

#include "kdrt/kdtree.h"
#include "kdrt/types.h"

namespace kdrt::bench {

enum class TraceMode { kSingle, kPacket, kAuto };

/// "single", "packet", "auto" -> mode; anything else -> nullopt.
[[nodiscard]] std::optional<TraceMode> parse_trace_mode(std::string_view name) noexcept;
[[nodiscard]] std::string_view trace_mode_name(TraceMode mode) noexcept;

/// Batch entry points with the contract of kdrt::intersect_single / occluded_single: results in
/// input order, parallel over the calling thread's oneTBB arena.
using IntersectBatchFn = void (*)(const KdTree&, std::span<const Ray>, std::span<Hit>) noexcept;
using OccludedBatchFn = void (*)(const KdTree&, std::span<const Ray>, std::span<uint8_t>) noexcept;

struct TraceKernel {
    std::string_view isa;  ///< instruction set the kernel runs on: "scalar", "sse4", "avx2", ...
    IntersectBatchFn intersect = nullptr;
    OccludedBatchFn occluded = nullptr;
};

/// The kernel that implements `mode` in this build, or nullopt when the engine does not have it.
[[nodiscard]] std::optional<TraceKernel> trace_kernel(TraceMode mode) noexcept;

}  // namespace kdrt::bench
