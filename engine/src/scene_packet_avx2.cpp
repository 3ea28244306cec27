// The top level's packet walk steps (scene_packet_steps.h) with a packet's eight lanes in one
// AVX2 register. Only the code after the pragma is compiled for AVX2.
#include <immintrin.h>

#include <cstdint>
#include <cstring>

#include "kdrt/trace.h"
#include "scene_internal.h"
#include "scene_packet.h"

#pragma GCC push_options
#pragma GCC target("avx2,popcnt")
#define KDRT_SCENE_STEPS_AVX2 1  // scene_packet_steps.h: the 8-lane register type
#include "scene_packet_steps.h"
#pragma GCC pop_options

namespace kdrt::detail {

const TopPacketOps& top_packet_ops_avx2() noexcept {
    static constexpr TopPacketOps kOps{&next_leaf_steps<F8>,   &reach_steps<F8>,
                                       &clip_steps<F8>,        &start_steps<F8>,
                                       &start_steps<F8, true>, &object_rays_steps};
    return kOps;
}

}  // namespace kdrt::detail
