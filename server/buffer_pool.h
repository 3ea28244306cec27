#pragma once
/// Reuses the large vectors of ray batches (request bodies, hit arrays, encoded answers) across
/// requests. A fresh 32 MiB vector costs ~8000 page faults and the kernel zeroing it, which on a
/// 1M-ray batch was a third of the server's time; a pooled one costs nothing after warm-up. The
/// pool keeps at most `max_bytes` of idle capacity (beyond that, returned vectors are freed), so
/// it never holds more than that in the idle server. Thread-safe.

#include <algorithm>
#include <cstddef>
#include <mutex>
#include <vector>

namespace kdrt::server {

template <class T>
class VectorPool {
public:
    explicit VectorPool(size_t max_bytes) : max_bytes_(max_bytes) {}

    /// An empty vector with capacity >= `count`: for large counts the smallest idle one that fits,
    /// else (and for small counts) a new one.
    [[nodiscard]] std::vector<T> take(size_t count) {
        if (count * sizeof(T) >= kMinPooledBytes) {
            std::lock_guard lock(mutex_);
            auto best = idle_.end();
            for (auto it = idle_.begin(); it != idle_.end(); ++it)
                if (it->capacity() >= count && (best == idle_.end() || it->capacity() < best->capacity())) best = it;
            if (best != idle_.end()) {
                std::vector<T> out = std::move(*best);
                idle_bytes_ -= out.capacity() * sizeof(T);
                idle_.erase(best);
                return out;
            }
        }
        std::vector<T> out;
        out.reserve(count);
        return out;
    }

    /// Returns a vector for reuse (its contents are dropped). Small vectors are not kept.
    void give(std::vector<T>&& v) {
        const size_t bytes = v.capacity() * sizeof(T);
        if (bytes < kMinPooledBytes) return;
        v.clear();
        std::lock_guard lock(mutex_);
        if (idle_bytes_ + bytes > max_bytes_) return;  // v is freed on return
        idle_bytes_ += bytes;
        idle_.push_back(std::move(v));
    }

    [[nodiscard]] size_t idle_bytes() const {
        std::lock_guard lock(mutex_);
        return idle_bytes_;
    }

    /// Vectors below this size are cheap to allocate and not worth pooling.
    static constexpr size_t kMinPooledBytes = 1u << 20;

private:
    const size_t max_bytes_;
    mutable std::mutex mutex_;
    std::vector<std::vector<T>> idle_;
    size_t idle_bytes_ = 0;
};

}  // namespace kdrt::server
