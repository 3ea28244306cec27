#pragma once
/// A rendered image as linear floats: what render() returns and proto encodes. Value type only.

#include <sys/mman.h>

#include <cstddef>
#include <cstdint>
#include <memory>
#include <new>
#include <type_traits>
#include <vector>

#include "kdrt/uninitialized.h"

namespace kdrt {

namespace detail {

inline constexpr size_t kPixelHugePage = size_t{2} << 20;

/// A mapping of its own for `bytes` (2 MiB or more): 2 MiB aligned, whole 2 MiB pages, advised
/// MADV_HUGEPAGE before anything touches it. Null when the length wraps or mmap fails.
inline void* map_pixels(size_t bytes) noexcept {
    const size_t len = (bytes + kPixelHugePage - 1) / kPixelHugePage * kPixelHugePage;
    if (len < bytes || len + kPixelHugePage < len) return nullptr;
    void* raw = mmap(nullptr, len + kPixelHugePage, PROT_READ | PROT_WRITE,
                     MAP_PRIVATE | MAP_ANONYMOUS, -1, 0);
    if (raw == MAP_FAILED) return nullptr;
    const auto start = reinterpret_cast<uintptr_t>(raw);
    const uintptr_t aligned = (start + kPixelHugePage - 1) / kPixelHugePage * kPixelHugePage;
    if (aligned > start) (void)munmap(raw, aligned - start);
    const size_t tail = start + len + kPixelHugePage - (aligned + len);
    if (tail > 0) (void)munmap(reinterpret_cast<void*>(aligned + len), tail);
    void* p = reinterpret_cast<void*>(aligned);
    (void)madvise(p, len, MADV_HUGEPAGE);  // advice only: without THP the pages are 4 KiB
    return p;
}

inline void unmap_pixels(void* p, size_t bytes) noexcept {
    (void)munmap(p, (bytes + kPixelHugePage - 1) / kPixelHugePage * kPixelHugePage);
}

}  // namespace detail

/// The allocator of an image's pixels. A buffer of 2 MiB or more (a 1024^2 RGB frame is 12 MiB)
/// is a mapping of its own on transparent huge pages where the kernel gives them (its "madvise"
/// setting, Debian's default): a fresh frame then costs a few page faults instead of one per
/// 4 KiB (on this project's VM a 4 KiB fault took ~15 us, 50-90 ms for such a frame, a 2 MiB one
/// ~0.1 ms). Smaller buffers are std::allocator's. A pixel constructed from Uninitialized is left
/// unwritten (every other construction initialises as usual): a renderer sizes its frame so
/// (uninitialized_pixels) and its tiles write every pixel, so the frame's memory is first touched
/// by the threads that render it, not in a serial pass before them.
template <class T>
struct PixelAllocator {
    using value_type = T;
    PixelAllocator() noexcept = default;
    template <class U>
    PixelAllocator(const PixelAllocator<U>&) noexcept {}  // NOLINT(google-explicit-constructor)
    [[nodiscard]] T* allocate(size_t n) {
        if (n > SIZE_MAX / sizeof(T)) throw std::bad_array_new_length();
        if (n * sizeof(T) < detail::kPixelHugePage) return std::allocator<T>().allocate(n);
        void* p = detail::map_pixels(n * sizeof(T));
        if (p == nullptr) throw std::bad_alloc();
        return static_cast<T*>(p);
    }
    void deallocate(T* p, size_t n) noexcept {
        if (n * sizeof(T) < detail::kPixelHugePage) {
            std::allocator<T>().deallocate(p, n);
        } else {
            detail::unmap_pixels(p, n * sizeof(T));
        }
    }
    template <class U>
    void construct(U* p, Uninitialized /*tag*/) noexcept {
        static_assert(std::is_trivially_default_constructible_v<U>);
        ::new (static_cast<void*>(p)) U;
    }
    friend bool operator==(const PixelAllocator&, const PixelAllocator&) noexcept { return true; }
};

/// An image's pixel values.
using Pixels = std::vector<float, PixelAllocator<float>>;

/// `n` unwritten pixel values (see Uninitialized): every one must be written before it is read.
[[nodiscard]] inline Pixels uninitialized_pixels(size_t n) {
    return Pixels(detail::UninitializedTags{0}, detail::UninitializedTags{n});
}

/// A linear float image, row-major, top row first, `channels` interleaved floats per pixel:
/// 3 = RGB, 4 = RGBA. pixels.size() == width * height * channels.
struct Image {
    uint32_t width = 0;
    uint32_t height = 0;
    uint32_t channels = 0;
    Pixels pixels;
};

}  // namespace kdrt
