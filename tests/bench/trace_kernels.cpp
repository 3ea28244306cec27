#include "trace_kernels.h"

#include "kdrt/trace.h"

namespace kdrt::bench {

std::optional<TraceMode> parse_trace_mode(std::string_view name) noexcept {
    if (name == "single") return TraceMode::kSingle;
    if (name == "packet") return TraceMode::kPacket;
    if (name == "auto") return TraceMode::kAuto;
    return std::nullopt;
}

std::string_view trace_mode_name(TraceMode mode) noexcept {
    switch (mode) {
        case TraceMode::kSingle:
            return "single";
        case TraceMode::kPacket:
            return "packet";
        case TraceMode::kAuto:
            return "auto";
    }
    return "unknown";
}

std::optional<TraceKernel> trace_kernel(TraceMode mode) noexcept {
    switch (mode) {
        case TraceMode::kSingle:
            return TraceKernel{"scalar", &intersect_single, &occluded_single};
        case TraceMode::kPacket:
        case TraceMode::kAuto:
            // The engine has no packet traversal yet; the caller reports the mode as unavailable.
            return std::nullopt;
    }
    return std::nullopt;
}

}  // namespace kdrt::bench
