// The memory of a tree's arrays. An incoherent ray's node and triangle loads land anywhere in
// tens of megabytes on a big scene; with 4 KiB pages most of them also miss the TLB (its reach is
// a few megabytes), so each is a page walk plus a cache miss. Arrays of 2 MiB or more are
// therefore 2 MiB aligned and marked MADV_HUGEPAGE: Debian's default transparent-huge-page
// setting is "madvise", which backs exactly such ranges with 2 MiB pages when it can. Where the
// kernel cannot (or THP is off) the advice is ignored and the memory works as usual.

#include <sys/mman.h>

#include <cstddef>
#include <new>

#include "kdrt/kdtree.h"

namespace kdrt {
namespace {

constexpr size_t kLine = 64;
constexpr size_t kHugePage = size_t{2} << 20;

size_t alignment_for(size_t bytes) noexcept { return bytes >= kHugePage ? kHugePage : kLine; }

}  // namespace

void* allocate_tree_memory(size_t bytes) {
    const size_t align = alignment_for(bytes);
    void* p = ::operator new (bytes, std::align_val_t{align});
    if (align == kHugePage) {
        // Advice only: a failure (no THP support) changes nothing but speed.
        (void)madvise(p, bytes / kHugePage * kHugePage, MADV_HUGEPAGE);
    }
    return p;
}

void free_tree_memory(void* p, size_t bytes) noexcept {
    ::operator delete (p, std::align_val_t{alignment_for(bytes)});
}

}  // namespace kdrt
