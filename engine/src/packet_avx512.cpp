// The packet kernels instantiated for avx512 (W = 16). Only the code after the pragma is compiled
// for that instruction set; see simd.h for why the kernel lives in an anonymous namespace.
#include <cstddef>
#include <cstdint>

#include <immintrin.h>

#include "kdrt/trace.h"
#include "packet.h"
#include "ray_prep.h"

#pragma GCC push_options
// Without avx512vl: the 16-lane packets need only 512-bit forms, and with VL GCC compiles the
// single-ray walk's 8-lane comparisons through k-masks (moved to vectors and general registers
// for each movemask), which ran the walks in turn 16% slower on an AMD family 1Ah
// (tests/bench/README.md, session 24). So the walk is the AVX2 unit's code here too.
#pragma GCC target("avx2,avx512f,avx512dq,avx512bw,popcnt")
#define KDRT_WIDE_AVX2 1  // wide_kernel.h: 8-lane permutes
#include "packet_kernel.h"
#pragma GCC pop_options

namespace kdrt::detail {

const PacketKernels* packet_kernels_avx512() noexcept {
    static constexpr PacketKernels kKernels{16,
                                            &intersect_rays<16, false>,
                                            &occluded_rays<16, false>,
                                            &intersect_rays<16, true>,
                                            &occluded_rays<16, true>,
                                            &all_hits_rays<16>,
                                            &wide_intersect,
                                            &wide_occluded,
                                            &wide_intersect_counted,
                                            &wide_occluded_counted};
    return &kKernels;
}

const LaneKernels* lane_kernels_avx512() noexcept {
    static constexpr LaneKernels kKernels{&lanes_intersect<8>, &lanes_occluded<8>};
    return &kKernels;
}

}  // namespace kdrt::detail
