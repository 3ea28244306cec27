#include "core/compute.h"

#include <tbb/info.h>

#include <algorithm>

#include "kdrt/trace.h"

namespace kdrt::server {
namespace {

unsigned resolve_threads(unsigned requested) {
    const int cores = tbb::info::default_concurrency();
    return requested == 0 ? static_cast<unsigned>(cores > 0 ? cores : 1) : requested;
}

}  // namespace

Compute::Compute(unsigned threads, unsigned callers)
    : threads_(resolve_threads(threads)),
      // Caps oneTBB's worker pool at threads - 1: nothing else in the process may add threads.
      control_(std::make_unique<tbb::global_control>(tbb::global_control::max_allowed_parallelism,
                                                     threads_)),
      // threads - 1 worker slots, plus one slot reserved for each calling thread, so that a
      // caller never waits for a slot held by another request (a caller without a slot would
      // have its work queued until a worker ran out of the other requests' tasks).
      arena_(static_cast<int>(threads_ - 1 + std::max(callers, 1u)), std::max(callers, 1u)) {}

KdTree Compute::build(const Mesh& mesh) {
    return run([&] { return build_kdtree(mesh, BuildOptions{}); });
}

void Compute::intersect(const KdTree& tree, std::span<const Ray> rays, std::span<Hit> hits) {
    if (rays.size() < kInlineRays) {
        intersect_block(tree, rays, hits);
        return;
    }
    run([&] { kdrt::intersect(tree, rays, hits); });
}

void Compute::occluded(const KdTree& tree, std::span<const Ray> rays, std::span<uint8_t> occluded) {
    if (rays.size() < kInlineRays) {
        occluded_block(tree, rays, occluded);
        return;
    }
    run([&] { kdrt::occluded(tree, rays, occluded); });
}

StreamTrace::StreamTrace(Compute& compute, const KdTree& tree, std::span<const Ray> rays,
                         std::span<Hit> hits)
    : compute_(compute), tree_(tree), rays_(rays), hits_(hits) {}

StreamTrace::StreamTrace(Compute& compute, const KdTree& tree, std::span<const Ray> rays,
                         std::span<uint8_t> occluded)
    : compute_(compute), tree_(tree), rays_(rays), occluded_(occluded) {}

StreamTrace::~StreamTrace() { wait(); }

void StreamTrace::submit(size_t end) {
    const size_t begin = submitted_;
    if (waited_ || end <= begin) return;  // nothing starts after finish() or abandon()
    submitted_ = end;
    const size_t n = end - begin;
    // Enqueued without joining the arena: the calling thread goes back to reading the body.
    if (!hits_.empty()) {
        compute_.arena_.enqueue(group_.defer([this, begin, n] {
            kdrt::intersect(tree_, rays_.subspan(begin, n), hits_.subspan(begin, n));
        }));
    } else {
        compute_.arena_.enqueue(group_.defer([this, begin, n] {
            kdrt::occluded(tree_, rays_.subspan(begin, n), occluded_.subspan(begin, n));
        }));
    }
}

void StreamTrace::advance(size_t ready) {
    ready = std::min(ready, rays_.size());
    if (ready - submitted_ >= kBlockRays) submit(ready - ready % kBlockRays);
}

void StreamTrace::finish() {
    if (waited_) return;
    // The rest is traced by the calling thread (inside the arena) while the workers finish the
    // blocks already enqueued.
    const size_t begin = submitted_;
    submitted_ = rays_.size();
    const size_t n = rays_.size() - begin;
    compute_.arena_.execute([&] {
        if (n > 0) {
            if (!hits_.empty())
                kdrt::intersect(tree_, rays_.subspan(begin, n), hits_.subspan(begin, n));
            else
                kdrt::occluded(tree_, rays_.subspan(begin, n), occluded_.subspan(begin, n));
        }
        group_.wait();
    });
    waited_ = true;
}

void StreamTrace::abandon() { wait(); }

void StreamTrace::wait() {
    if (waited_) return;
    compute_.arena_.execute([&] { group_.wait(); });
    waited_ = true;
}

}  // namespace kdrt::server
