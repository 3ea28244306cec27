#pragma once
// Embree 4 or 3 through their public headers (CMake passes the major version it found as
// KDRT_EMBREE_MAJOR), and what differs between them for a query: Embree 4 replaced the intersect
// context (rtcInitIntersectContext, passed before the rays) by optional argument structs passed
// after them, and dropped the ray-stream calls (rtc*1M). QueryArgs holds what a query call needs;
// query() and query_packet() pass it where the API version wants it.

#if KDRT_EMBREE_MAJOR >= 4
#include <embree4/rtcore.h>
#else
#include <embree3/rtcore.h>
#endif

namespace kdrt::bench {

#if RTC_VERSION_MAJOR >= 4
inline constexpr bool kHasRayStreams = false;

class QueryArgs {
public:
    explicit QueryArgs(bool coherent) {
        rtcInitIntersectArguments(&intersect_);
        rtcInitOccludedArguments(&occluded_);
        const RTCRayQueryFlags flags =
            coherent ? RTC_RAY_QUERY_FLAG_COHERENT : RTC_RAY_QUERY_FLAG_INCOHERENT;
        intersect_.flags = flags;
        occluded_.flags = flags;
    }
    RTCIntersectArguments* intersect_args() noexcept { return &intersect_; }
    RTCOccludedArguments* occluded_args() noexcept { return &occluded_; }

private:
    RTCIntersectArguments intersect_;
    RTCOccludedArguments occluded_;
};

template <typename Fn, typename Rays, typename Args>
void query(Fn fn, RTCScene scene, Rays* rays, Args* args) {
    fn(scene, rays, args);
}
template <typename Fn, typename Rays, typename Args>
void query_packet(Fn fn, const int* valid, RTCScene scene, Rays* rays, Args* args) {
    fn(valid, scene, rays, args);
}
#else
inline constexpr bool kHasRayStreams = true;

class QueryArgs {
public:
    explicit QueryArgs(bool coherent) {
        rtcInitIntersectContext(&context_);
        context_.flags =
            coherent ? RTC_INTERSECT_CONTEXT_FLAG_COHERENT : RTC_INTERSECT_CONTEXT_FLAG_INCOHERENT;
    }
    RTCIntersectContext* intersect_args() noexcept { return &context_; }
    RTCIntersectContext* occluded_args() noexcept { return &context_; }

private:
    RTCIntersectContext context_;
};

template <typename Fn, typename Rays, typename Args>
void query(Fn fn, RTCScene scene, Rays* rays, Args* args) {
    fn(scene, args, rays);
}
template <typename Fn, typename Rays, typename Args>
void query_packet(Fn fn, const int* valid, RTCScene scene, Rays* rays, Args* args) {
    fn(valid, scene, args, rays);
}
#endif

}  // namespace kdrt::bench
