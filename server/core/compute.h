#pragma once
/// The process-wide oneTBB arena: every parallel build and trace runs inside it, so the engine
/// never oversubscribes the machine however many HTTP threads call it (STYLE §1). Thread-safe.
///
/// Fairness (server/README.md, "Compute"): a request's calling thread always gets a slot of its
/// own in the arena (one is reserved for each of `callers` threads), and inside run(),
/// intersect(), occluded() and build() it only runs tasks of its own request
/// (tbb::this_task_arena::isolate), while the `threads - 1` workers serve whichever requests
/// have tasks. So a long request of one kind (a distance batch of far points, a big render)
/// never keeps a small one waiting for a slot or running the long one's tasks: the small one
/// makes progress on its own thread from the moment it arrives.

#include <tbb/global_control.h>
#include <tbb/task_arena.h>
#include <tbb/task_group.h>

#include <cstdint>
#include <functional>
#include <memory>
#include <span>

#include "kdrt/kdtree.h"
#include "kdrt/mesh.h"
#include "kdrt/types.h"

namespace kdrt::server {

class Compute {
public:
    /// `threads` = workers + 1 (the arena's concurrency for one request); 0 = every core.
    /// `callers`: how many threads may call into the arena at once (the server's HTTP threads
    /// and its job thread), each of which gets a reserved slot.
    explicit Compute(unsigned threads, unsigned callers = 1);

    [[nodiscard]] unsigned threads() const noexcept { return threads_; }

    /// Builds the SAH tree inside the arena. Throws what build_kdtree throws (MeshError,
    /// bad_alloc).
    [[nodiscard]] KdTree build(const Mesh& mesh);

    /// Batch queries. Batches below kInlineRays run on the calling thread (a 1-ray request must
    /// not pay for entering the arena); larger ones run in parallel inside the arena.
    void intersect(const KdTree& tree, std::span<const Ray> rays, std::span<Hit> hits);
    void occluded(const KdTree& tree, std::span<const Ray> rays, std::span<uint8_t> occluded);

    /// Runs `f` inside the arena, isolated (the calling thread runs only tasks `f` spawns), and
    /// returns its result (renders, scans, every-hit and distance queries).
    template <class F>
    auto run(F&& f) {
        return arena_.execute([&] { return tbb::this_task_arena::isolate(f); });
    }

    /// Runs `f` on an arena worker later, without waiting (work after an answer). The caller
    /// keeps whatever `f` uses alive until it has run.
    void enqueue(std::function<void()> f) { arena_.enqueue(std::move(f)); }

    static constexpr size_t kInlineRays = 256;

private:
    friend class StreamTrace;
    unsigned threads_;
    std::unique_ptr<tbb::global_control> control_;
    tbb::task_arena arena_;
};

/// Traces a batch while it is still arriving (a KDRR body read from the network): advance(n)
/// hands the complete rays [0, n) to the arena in blocks of kBlockRays, which trace on the
/// arena's worker threads while the caller keeps reading; finish() traces the rest with the
/// calling thread helping, and waits. Answers are the same as Compute::intersect/occluded on the
/// whole batch. The spans must outlive the tracer; the destructor waits for blocks in flight
/// (so a refused batch never leaves tasks writing into a buffer that went back to a pool).
class StreamTrace {
public:
    StreamTrace(Compute& compute, const KdTree& tree, std::span<const Ray> rays,
                std::span<Hit> hits);
    StreamTrace(Compute& compute, const KdTree& tree, std::span<const Ray> rays,
                std::span<uint8_t> occluded);
    StreamTrace(const StreamTrace&) = delete;
    StreamTrace& operator=(const StreamTrace&) = delete;
    ~StreamTrace();

    /// Rays [0, ready) are complete: start tracing whole blocks of them.
    void advance(size_t ready);
    /// Traces every ray not started yet and waits for all of them.
    void finish();
    /// Waits for the blocks in flight without starting more (the batch was refused); advance()
    /// and finish() do nothing afterwards.
    void abandon();

    /// Rays per block: large enough that a block's tasks cost nothing next to its tracing, small
    /// enough that tracing starts soon after the first bytes arrive.
    static constexpr size_t kBlockRays = size_t{1} << 16;

private:
    void submit(size_t end);
    void wait();

    Compute& compute_;
    const KdTree& tree_;
    std::span<const Ray> rays_;
    std::span<Hit> hits_;
    std::span<uint8_t> occluded_;
    size_t submitted_ = 0;
    bool waited_ = false;
    tbb::task_group group_;
};

}  // namespace kdrt::server
