#pragma once
/// Reuses the large vectors of ray batches (request bodies, hit arrays, encoded answers) across
/// requests. A fresh 32 MiB vector costs ~8000 page faults and the kernel zeroing it, which on a
/// 1M-ray batch was a third of the server's time; a pooled one costs nothing after warm-up. The
/// pool keeps at most `max_bytes` of idle capacity (beyond that, returned vectors are freed), so
/// it never holds more than that in the idle server. Thread-safe.

#include <sys/mman.h>

#include <algorithm>
#include <cstddef>
#include <cstdlib>
#include <mutex>
#include <new>
#include <utility>
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
                if (it->capacity() >= count &&
                    (best == idle_.end() || it->capacity() < best->capacity()))
                    best = it;
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

/// Uninitialised, 64-byte-aligned storage for a ray batch's rays or its encoded answer. Ray and
/// Hit are implicit-lifetime types, so the block can be used as an array of them (C++20 implicit
/// object creation by the allocation). Move-only.
class AlignedBuffer {
public:
    static constexpr size_t kAlignment = 64;

    AlignedBuffer() = default;
    /// At least `bytes` of storage (rounded up to the alignment). Throws std::bad_alloc.
    explicit AlignedBuffer(size_t bytes)
        : capacity_((std::max<size_t>(bytes, 1) + kAlignment - 1) / kAlignment * kAlignment) {
        data_ = static_cast<std::byte*>(std::aligned_alloc(kAlignment, capacity_));
        if (!data_) throw std::bad_alloc();
        // Large batches: ask for transparent huge pages (fewer faults on first use, fewer TLB
        // misses while tracing); harmless where THP is off.
        if (capacity_ >= (4u << 20)) ::madvise(data_, capacity_, MADV_HUGEPAGE);
    }
    AlignedBuffer(AlignedBuffer&& other) noexcept
        : data_(std::exchange(other.data_, nullptr)),
          capacity_(std::exchange(other.capacity_, 0)) {}
    AlignedBuffer& operator=(AlignedBuffer&& other) noexcept {
        if (this != &other) {
            std::free(data_);
            data_ = std::exchange(other.data_, nullptr);
            capacity_ = std::exchange(other.capacity_, 0);
        }
        return *this;
    }
    AlignedBuffer(const AlignedBuffer&) = delete;
    AlignedBuffer& operator=(const AlignedBuffer&) = delete;
    ~AlignedBuffer() { std::free(data_); }

    [[nodiscard]] std::byte* data() const noexcept { return data_; }
    [[nodiscard]] size_t capacity() const noexcept { return capacity_; }
    [[nodiscard]] explicit operator bool() const noexcept { return data_ != nullptr; }

private:
    std::byte* data_ = nullptr;
    size_t capacity_ = 0;
};

/// Reuses AlignedBuffers across requests, like VectorPool: take() hands out the smallest idle
/// buffer that fits (or a new one), give() keeps a buffer for reuse while the idle total stays
/// within `max_bytes`. Small buffers are not pooled. Thread-safe.
class BufferPool {
public:
    explicit BufferPool(size_t max_bytes) : max_bytes_(max_bytes) {}

    /// A buffer of at least `bytes`. Pooled sizes are rounded up to whole MiB, so batches of
    /// similar sizes share buffers. Throws std::bad_alloc.
    [[nodiscard]] AlignedBuffer take(size_t bytes) {
        if (bytes < kMinPooledBytes) return AlignedBuffer(bytes);
        {
            std::lock_guard lock(mutex_);
            auto best = idle_.end();
            for (auto it = idle_.begin(); it != idle_.end(); ++it)
                if (it->capacity() >= bytes &&
                    (best == idle_.end() || it->capacity() < best->capacity()))
                    best = it;
            if (best != idle_.end()) {
                AlignedBuffer out = std::move(*best);
                idle_bytes_ -= out.capacity();
                idle_.erase(best);
                return out;
            }
        }
        constexpr size_t kMiB = size_t{1} << 20;
        return AlignedBuffer((bytes + kMiB - 1) / kMiB * kMiB);
    }

    /// Keeps `buffer` for reuse if it is large enough to pool and the idle total allows it.
    void give(AlignedBuffer buffer) {
        if (!buffer || buffer.capacity() < kMinPooledBytes) return;
        std::lock_guard lock(mutex_);
        if (idle_bytes_ + buffer.capacity() > max_bytes_) return;  // freed on return
        idle_bytes_ += buffer.capacity();
        idle_.push_back(std::move(buffer));
    }

    [[nodiscard]] size_t idle_bytes() const {
        std::lock_guard lock(mutex_);
        return idle_bytes_;
    }

    static constexpr size_t kMinPooledBytes = size_t{1} << 20;

private:
    const size_t max_bytes_;
    mutable std::mutex mutex_;
    std::vector<AlignedBuffer> idle_;
    size_t idle_bytes_ = 0;
};

/// A buffer taken from a BufferPool that goes back to it when destroyed or replaced, so every
/// exit of a request (answer sent, batch refused, exception) returns its storage. Move-only; a
/// default-constructed or moved-from PooledBuffer holds nothing.
class PooledBuffer {
public:
    PooledBuffer() = default;
    /// At least `bytes` from `pool` (which must outlive this). Throws std::bad_alloc.
    PooledBuffer(BufferPool& pool, size_t bytes) : pool_(&pool), buffer_(pool.take(bytes)) {}
    PooledBuffer(PooledBuffer&& other) noexcept
        : pool_(std::exchange(other.pool_, nullptr)), buffer_(std::move(other.buffer_)) {}
    PooledBuffer& operator=(PooledBuffer&& other) noexcept {
        if (this != &other) {
            give_back();
            pool_ = std::exchange(other.pool_, nullptr);
            buffer_ = std::move(other.buffer_);
        }
        return *this;
    }
    PooledBuffer(const PooledBuffer&) = delete;
    PooledBuffer& operator=(const PooledBuffer&) = delete;
    ~PooledBuffer() { give_back(); }

    [[nodiscard]] std::byte* data() const noexcept { return buffer_.data(); }
    [[nodiscard]] size_t capacity() const noexcept { return buffer_.capacity(); }
    [[nodiscard]] explicit operator bool() const noexcept { return static_cast<bool>(buffer_); }

private:
    void give_back() noexcept {
        // give() can only fail to allocate its bookkeeping; the buffer is then simply freed.
        try {
            if (pool_) pool_->give(std::move(buffer_));
        } catch (...) {
        }
        pool_ = nullptr;
        buffer_ = AlignedBuffer();
    }

    BufferPool* pool_ = nullptr;
    AlignedBuffer buffer_;
};

}  // namespace kdrt::server
