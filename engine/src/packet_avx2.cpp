// The packet kernels instantiated for avx2 (W = 8). Only the code after the pragma is compiled
// for that instruction set; see simd.h for why the kernel lives in an anonymous namespace.
#include <cstddef>
#include <cstdint>

#include <immintrin.h>

#include "kdrt/trace.h"
#include "packet.h"
#include "ray_prep.h"

#pragma GCC push_options
#pragma GCC target("avx2,popcnt")
#define KDRT_WIDE_AVX2 1  // wide_kernel.h: 8-lane permutes
#include "packet_kernel.h"
#pragma GCC pop_options

namespace kdrt::detail {

const PacketKernels* packet_kernels_avx2() noexcept {
    static constexpr PacketKernels kKernels{8,
                                            &intersect_rays<8, false>,
                                            &occluded_rays<8, false>,
                                            &intersect_rays<8, true>,
                                            &occluded_rays<8, true>,
                                            &all_hits_rays<8>,
                                            &wide_intersect,
                                            &wide_occluded,
                                            &wide_intersect_counted,
                                            &wide_occluded_counted};
    return &kKernels;
}

const LaneKernels* lane_kernels_avx2() noexcept {
    static constexpr LaneKernels kKernels{&lanes_intersect<8>, &lanes_occluded<8>};
    return &kKernels;
}

}  // namespace kdrt::detail
