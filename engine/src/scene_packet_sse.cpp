// The top level's packet walk steps (scene_packet_steps.h) with a packet's eight lanes in two SSE
// halves: the x86-64 baseline, for the sse4 and scalar ISAs.
#include "scene_packet_steps.h"

namespace kdrt::detail {

const TopPacketOps& top_packet_ops_sse() noexcept {
    static constexpr TopPacketOps kOps{&next_leaf_steps<Halves>,   &reach_steps<Halves>,
                                       &clip_steps<Halves>,        &start_steps<Halves>,
                                       &start_steps<Halves, true>, &object_rays_steps};
    return kOps;
}

}  // namespace kdrt::detail
