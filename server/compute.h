#pragma once
/// The process-wide oneTBB arena: every parallel build and trace runs inside it, so the engine
/// never oversubscribes the machine however many HTTP threads call it (STYLE §1). Thread-safe.

#include <tbb/global_control.h>
#include <tbb/task_arena.h>

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

    /// Builds the SAH tree inside the arena. Throws what build_kdtree throws (MeshError, bad_alloc).
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
    unsigned threads_;
    std::unique_ptr<tbb::global_control> control_;
    tbb::task_arena arena_;
};

}  // namespace kdrt::server
