#pragma once
// Internal: the binned levels' reference arrays, carved from a few big blocks that live as long
// as the build.
//
// Why: on this project's VM the first touch of a page costs far more than using it (the guest's
// fault and the host's backing: a fresh 4 KiB page ~0.33 GB/s, a fresh 2 MiB page ~0.55 GB/s,
// memory the process already touched at full speed; tests/bench/README.md, session 24). The
// binned levels' arrays were std::vectors, the big ones kept whole in a pool for reuse: one kept
// array served one later node however much bigger it was, so 64 bunnies faulted in 297 MB of
// pooled arrays and 135 MB for the root's, on 4 KiB pages. Here every array is a range of a
// block: a range given back is merged with its free neighbours, and a request takes the
// smallest free range that holds it (best fit), the rest staying free, so a big freed array
// serves several smaller ones (64 bunnies: 270 MB of blocks in all). A new block is made only
// when no free range holds the request: from the heap, or, from 32 MiB, a huge-page mapping
// (allocate_tree_memory) faulted in by parallel tasks, whose whole 2 MiB pages the block takes
// (the tail past the request is a free range). Nothing is zero-filled: the builder writes every
// element it reads. The blocks are freed with the arena.

#include <cstddef>
#include <cstdint>
#include <iterator>
#include <map>
#include <memory>
#include <mutex>
#include <new>
#include <type_traits>
#include <utility>
#include <vector>

#include "kdrt/kdtree.h"

namespace kdrt::detail {

/// Arrays of T (trivially default-constructible: their elements start uninitialised) carved from
/// blocks that are freed with the arena. Thread-safe: take and give lock.
template <typename T>
class ArrayArena {
    static_assert(std::is_trivially_default_constructible_v<T> &&
                  std::is_trivially_destructible_v<T>);

public:
    /// A range of one block: does not own its memory (give it back to the arena, or let the arena
    /// end). Moving leaves the source empty.
    class Array {
    public:
        Array() noexcept = default;
        Array(Array&& other) noexcept { *this = std::move(other); }
        Array& operator=(Array&& other) noexcept {
            data_ = other.data_;
            size_ = other.size_;
            length_ = other.length_;
            block_ = other.block_;
            other.data_ = nullptr;
            other.size_ = other.length_ = 0;
            return *this;
        }
        Array(const Array&) = delete;
        Array& operator=(const Array&) = delete;
        ~Array() = default;

        [[nodiscard]] T* data() noexcept { return data_; }
        [[nodiscard]] const T* data() const noexcept { return data_; }
        [[nodiscard]] size_t size() const noexcept { return size_; }
        [[nodiscard]] T& operator[](size_t i) noexcept { return data_[i]; }
        [[nodiscard]] const T& operator[](size_t i) const noexcept { return data_[i]; }
        [[nodiscard]] T* begin() noexcept { return data_; }
        [[nodiscard]] T* end() noexcept { return data_ + size_; }
        [[nodiscard]] const T* begin() const noexcept { return data_; }
        [[nodiscard]] const T* end() const noexcept { return data_ + size_; }
        /// Keeps only the first `n` elements (n <= size()); the whole range still goes back.
        void shrink(size_t n) noexcept { size_ = n < size_ ? n : size_; }

    private:
        friend class ArrayArena;
        T* data_ = nullptr;
        size_t size_ = 0;
        size_t length_ = 0;  ///< the range taken from the block (size_ may shrink below it)
        size_t block_ = 0;
    };

    /// An array of `n` elements, not written.
    Array take(size_t n) {
        Array a;
        if (n == 0) return a;
        const std::lock_guard<std::mutex> lock(mutex_);
        size_t best_block = blocks_.size(), best_at = 0, best_length = 0;
        for (size_t b = 0; b < blocks_.size(); ++b) {
            for (const auto& [at, length] : blocks_[b].free) {
                if (length >= n && (best_block == blocks_.size() || length < best_length)) {
                    best_block = b;
                    best_at = at;
                    best_length = length;
                }
            }
        }
        if (best_block == blocks_.size()) {
            // A block of kOwnMapping bytes and more is a huge-page mapping (allocate_tree_memory,
            // in whole 2 MiB pages, all faulted in: the block takes the whole mapping). glibc maps
            // such an allocation afresh anyway (its mmap threshold never exceeds 32 MiB), on 4 KiB
            // pages; smaller blocks come from the heap, which may hand back memory already
            // touched (an earlier build's, on small meshes).
            size_t bytes = n * sizeof(T);
            const bool own_mapping = bytes >= kOwnMapping;
            if (own_mapping) bytes = (bytes + kHugePage - 1) / kHugePage * kHugePage;
            const size_t capacity = bytes / sizeof(T);
            blocks_.push_back({BlockMemory(static_cast<T*>(own_mapping ? allocate_tree_memory(bytes)
                                                                       : ::operator new(bytes)),
                                           BlockFree{bytes, own_mapping}),
                               capacity,
                               {}});
            if (capacity > n) blocks_.back().free.emplace(n, capacity - n);
            block_elements_ += capacity;
            best_at = 0;
        } else {
            auto& free = blocks_[best_block].free;
            free.erase(best_at);
            if (best_length > n) free.emplace(best_at + n, best_length - n);
        }
        a.data_ = blocks_[best_block].data.get() + best_at;
        a.size_ = a.length_ = n;
        a.block_ = best_block;
        return a;
    }

    /// Gives `a`'s range back (merged with the free ranges next to it); `a` becomes empty.
    void give(Array&& a) {
        Array gone = std::move(a);
        if (gone.length_ == 0) return;
        const std::lock_guard<std::mutex> lock(mutex_);
        Block& block = blocks_[gone.block_];
        size_t at = static_cast<size_t>(gone.data_ - block.data.get()), length = gone.length_;
        auto next = block.free.lower_bound(at);
        if (next != block.free.end() && next->first == at + length) {
            length += next->second;
            next = block.free.erase(next);
        }
        if (next != block.free.begin()) {
            auto prev = std::prev(next);
            if (prev->first + prev->second == at) {
                at = prev->first;
                length += prev->second;
                block.free.erase(prev);
            }
        }
        block.free.emplace(at, length);
    }

    /// Elements in all blocks allocated so far (what the arena has cost in fresh memory).
    [[nodiscard]] size_t block_elements() const noexcept { return block_elements_; }

private:
    static constexpr size_t kHugePage = size_t{2} << 20;
    static constexpr size_t kOwnMapping = size_t{32} << 20;
    struct BlockFree {
        size_t bytes = 0;
        bool own_mapping = false;
        void operator()(T* p) const noexcept {
            if (own_mapping) {
                free_tree_memory(p, bytes);
            } else {
                ::operator delete(p);
            }
        }
    };
    using BlockMemory = std::unique_ptr<T, BlockFree>;
    struct Block {
        BlockMemory data;
        size_t capacity = 0;
        std::map<size_t, size_t> free;  ///< free ranges: start -> length, never adjacent
    };
    std::mutex mutex_;
    std::vector<Block> blocks_;
    size_t block_elements_ = 0;
};

}  // namespace kdrt::detail
