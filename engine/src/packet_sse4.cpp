// The packet kernels instantiated for sse4 (W = 4). Only the code after the pragma is compiled
// for that instruction set; see simd.h for why the kernel lives in an anonymous namespace.
#include <cstddef>
#include <cstdint>

#include <immintrin.h>

#include "kdrt/trace.h"
#include "packet.h"
#include "ray_prep.h"

#pragma GCC push_options
#pragma GCC target("sse4.2,popcnt")
#include "packet_kernel.h"
#pragma GCC pop_options

namespace kdrt::detail {

const PacketKernels* packet_kernels_sse4() noexcept {
    static constexpr PacketKernels kKernels{4,
                                            &intersect_rays<4, false>,
                                            &occluded_rays<4, false>,
                                            &intersect_rays<4, true>,
                                            &occluded_rays<4, true>,
                                            &all_hits_rays<4>,
                                            &wide_intersect,
                                            &wide_occluded,
                                            &wide_intersect_counted,
                                            &wide_occluded_counted};
    return &kKernels;
}

const LaneKernels* lane_kernels_sse4() noexcept {
    static constexpr LaneKernels kKernels{&lanes_intersect<4>, &lanes_occluded<4>};
    return &kKernels;
}

}  // namespace kdrt::detail
