#pragma once
// Internal: what a scene's distance search shares with the mesh's (distance.cpp): the
// nearest-triangle search of one point with its work counted, and a batch's work limit, poll and
// cancellation (DistanceControl), so both batch forms stop by the same rules.

#include <atomic>
#include <cstdint>
#include <mutex>
#include <vector>

#include "kdrt/distance.h"

namespace kdrt::detail {

/// Points per task of a distance batch: small, so a batch of costly points (far away, where every
/// triangle's rounded distance ties) leaves the arena's workers free for other requests often.
inline constexpr size_t kDistanceBlockPoints = 16;

/// Work between two calls of DistanceControl::poll (about a millisecond of one thread).
inline constexpr uint64_t kDistancePollWork = uint64_t{1} << 16;

/// One thread's nearest-triangle searches: the heap of cells waiting (kept across its points, so
/// it is allocated once) and the work done. Not thread-safe: one per thread.
class NearestSearch {
public:
    /// closest_point(tree, index, p, options) (kdrt/distance.h), its work (cells visited plus
    /// triangles tested) added to work. Throws std::bad_alloc (the heap).
    [[nodiscard]] ClosestPoint run(const KdTree& tree, const SurfaceIndex& index, Vec3 p,
                                   const DistanceOptions& options);
    uint64_t work = 0;

    /// A cell waiting in the best-first search: its node, its box and its squared distance.
    struct Cell {
        double d2;
        uint32_t node;
        float lo[3], hi[3];
    };

private:
    std::vector<Cell> heap_;
};

/// A batch's progress against its DistanceControl, shared by the batch's threads (thread-safe).
/// The status is the first stop seen (cancel or work); once stopped, it stays stopped.
class DistanceBatch {
public:
    explicit DistanceBatch(const DistanceControl& control) noexcept;
    /// True once the batch must stop: it stopped already, or control.cancel is set (the status
    /// becomes kCancelled).
    [[nodiscard]] bool stopped() noexcept;
    /// Counts `work` more units. False when the batch's total passes control.max_work (the status
    /// becomes kOverWork). Calls control.poll (one thread at a time) when the total crosses a
    /// multiple of kDistancePollWork.
    [[nodiscard]] bool charge(uint64_t work);
    /// The work counted and the status.
    [[nodiscard]] DistanceStats stats() const noexcept;

private:
    void stop(DistanceStatus status) noexcept;

    const DistanceControl& control_;
    const uint64_t max_work_;
    std::atomic<uint64_t> work_{0};
    std::atomic<int> status_{static_cast<int>(DistanceStatus::kDone)};
    std::mutex poll_mutex_;
};

}  // namespace kdrt::detail
