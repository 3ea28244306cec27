// The instruction sets: what the CPU supports, which one the engine uses (KDRT_ISA), and the
// packet kernels of each.

#include <cpuid.h>

#include <cstdlib>
#include <cstring>
#include <optional>
#include <string>
#include <string_view>

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

/// AMD family 19h (Zen 4) runs each 512-bit operation as two 256-bit halves, so a 16-lane packet
/// costs what two 8-lane ones do, with wider masks and emptier lanes on top: there the AVX2
/// kernels are faster on every kind of ray (tests/bench/README.md has the measurements).
bool splits_512_bit_vectors() noexcept {
    unsigned a = 0, b = 0, c = 0, d = 0;
    if (__get_cpuid(0, &a, &b, &c, &d) == 0) return false;
    char vendor[12];
    std::memcpy(vendor, &b, 4);
    std::memcpy(vendor + 4, &d, 4);
    std::memcpy(vendor + 8, &c, 4);
    if (std::memcmp(vendor, "AuthenticAMD", 12) != 0) return false;
    if (__get_cpuid(1, &a, &b, &c, &d) == 0) return false;
    const unsigned base = (a >> 8) & 0xFu;
    const unsigned family = base == 0xFu ? base + ((a >> 20) & 0xFFu) : base;
    return family == 0x19u;
}

/// The default without KDRT_ISA: the widest set the CPU supports, but the 8-lane one where
/// 512-bit vectors run as two halves.
IsaChoice preferred_supported() {
    const Isa widest = widest_supported();
    if (widest == Isa::kAvx512 && splits_512_bit_vectors())
        return IsaChoice{Isa::kAvx2,
                         "AMD family 19h runs 512-bit vectors as two 256-bit halves: 8-lane "
                         "packets are faster (KDRT_ISA=avx512 overrides)"};
    return IsaChoice{widest, "widest supported"};
}

const IsaChoice& choice() noexcept {
    static const IsaChoice c = [] {
        const IsaChoice preferred = preferred_supported();
        const Isa widest = preferred.isa;
        const char* env = std::getenv("KDRT_ISA");
        if (env == nullptr || *env == '\0') return preferred;
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

namespace detail {

Isa resolve_isa(const std::optional<Isa>& isa) noexcept {
    if (isa && isa_supported(*isa)) return *isa;
    return default_isa();
}

Policy policy_for(TraceMode mode) noexcept {
    switch (mode) {
        case TraceMode::kSingle:
            return Policy::kSingle;
        case TraceMode::kPacket:
            return Policy::kPacket;
        case TraceMode::kAuto:
            break;
    }
    return Policy::kAuto;
}

const PacketKernels* single_ray_kernels() noexcept {
    static const PacketKernels* const kernels = packet_kernels_for(default_isa());
    return kernels;
}

const PacketKernels* packet_kernels_for(Isa isa) noexcept {
    switch (isa) {
        case Isa::kSse4:
            return packet_kernels_sse4();
        case Isa::kAvx2:
            return packet_kernels_avx2();
        case Isa::kAvx512:
            return packet_kernels_avx512();
        case Isa::kScalar:
            break;
    }
    return nullptr;
}

const LaneKernels* lane_kernels_for(Isa isa) noexcept {
    switch (isa) {
        case Isa::kSse4:
            return lane_kernels_sse4();
        case Isa::kAvx2:
            return lane_kernels_avx2();
        case Isa::kAvx512:
            return lane_kernels_avx512();
        case Isa::kScalar:
            break;
    }
    return nullptr;
}

}  // namespace detail
}  // namespace kdrt
