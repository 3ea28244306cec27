#pragma once
/// A rendered image as linear floats: what render() returns and proto encodes. Value type only.

#include <cstddef>
#include <cstdint>
#include <memory>
#include <new>
#include <type_traits>
#include <vector>

#include "kdrt/uninitialized.h"

namespace kdrt {

/// The allocator of an image's pixels: std::allocator's memory, and a pixel constructed from
/// Uninitialized is left unwritten (every other construction initialises as usual). A renderer
/// sizes its frame so (uninitialized_pixels) and its tiles write every pixel: the frame's memory
/// is first touched by the threads that render it, not in a serial pass before them (on a fresh
/// 1024^2 RGB frame that pass, its page faults included, took longer than the frame's tracing).
template <class T>
struct PixelAllocator {
    using value_type = T;
    PixelAllocator() noexcept = default;
    template <class U>
    PixelAllocator(const PixelAllocator<U>&) noexcept {}  // NOLINT(google-explicit-constructor)
    [[nodiscard]] T* allocate(size_t n) { return std::allocator<T>().allocate(n); }
    void deallocate(T* p, size_t n) noexcept { std::allocator<T>().deallocate(p, n); }
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
