#pragma once
/// The process-wide oneTBB arena: every parallel build and trace runs inside it, so the engine
/// never oversubscribes the machine however many HTTP threads call it (STYLE §1). Thread-safe.

#include <tbb/global_control.h>
#include <tbb/task_arena.h>
#include <tbb/task_group.h>

#include <cstdint>
#include <memory>
#include <span>

#include "kdrt/kdtree.h"
#include "kdrt/mesh.h"
#include "kdrt/types.h"

namespace kdrt::server {

class Compute {
public:
    /// `threads` = arena concurrency; 0 = every core.
    explicit Compute(unsigned threads);

    [[nodiscard]] unsigned threads() const noexcept { return threads_; }

    /// Builds the SAH tree inside the arena. Throws what build_kdtree throws (MeshError,
    /// bad_alloc).
    [[nodiscard]] KdTree build(const Mesh& mesh);

    /// Batch queries. Batches below kInlineRays run on the calling thread (a 1-ray request must
    /// not pay for entering the arena); larger ones run in parallel inside the arena.
    void intersect(const KdTree& tree, std::span<const Ray> rays, std::span<Hit> hits);
    void occluded(const KdTree& tree, std::span<const Ray> rays, std::span<uint8_t> occluded);

    /// Runs `f` inside the arena and returns its result (for the renderer).
    template <class F>
    auto run(F&& f) {
        return arena_.execute(std::forward<F>(f));
    }

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
