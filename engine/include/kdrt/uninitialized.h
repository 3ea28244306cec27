#pragma once
/// Arrays sized without writing their elements first: a tag whose construction leaves an element
/// unwritten, and iterators over it to size a vector in one step. Header only (engine types).

#include <cstddef>
#include <iterator>

namespace kdrt {

/// Constructing an element from this tag leaves it uninitialised (kdtree.h's TreeAllocator,
/// image.h's PixelAllocator): for arrays that are written in full right after they are sized, where
/// value-initialising them first is one more pass over memory (a big mesh's triangles: 36 bytes
/// each, on one thread). Other constructions (resize, a size, a value) initialise as usual.
struct Uninitialized {};

namespace detail {
/// A forward iterator over tags (uninitialized_tree_array, uninitialized_pixels): a vector built
/// from a range of them sizes itself once and constructs each element from a tag through its
/// allocator.
struct UninitializedTags {
    using iterator_category = std::forward_iterator_tag;
    using value_type = Uninitialized;
    using difference_type = std::ptrdiff_t;
    using pointer = const Uninitialized*;
    using reference = Uninitialized;
    size_t i = 0;
    Uninitialized operator*() const noexcept { return {}; }
    UninitializedTags& operator++() noexcept {
        ++i;
        return *this;
    }
    UninitializedTags operator++(int) noexcept {
        UninitializedTags old = *this;
        ++i;
        return old;
    }
    bool operator==(const UninitializedTags&) const noexcept = default;
};
}  // namespace detail

}  // namespace kdrt
