// The memory of a tree's arrays. An incoherent ray's node and triangle loads land anywhere in
// tens of megabytes on a big scene; with 4 KiB pages most of them also miss the TLB (its reach is
// a few megabytes), so each is a page walk plus a cache miss. Arrays of 2 MiB or more therefore
// get a mapping of their own, 2 MiB aligned and a whole number of 2 MiB pages long, marked
// MADV_HUGEPAGE before anything touches it: Debian's default transparent-huge-page setting is
// "madvise", which backs exactly such ranges with 2 MiB pages at their first touch when it can.
//
// The advice must come first. Memory from the heap (operator new) may already be backed by 4 KiB
// pages, touched by an earlier allocation that was freed; advice given then only lets khugepaged
// collapse the range some time later, so a tree built after other work used the heap ran on small
// pages (measured: random rays on 16 bunnies 1.57 against 1.82 Mrays/s). Where the kernel cannot
// give huge pages (or THP is off) the advice is ignored and the memory works as usual.

#include <sys/mman.h>

#include <cstddef>
#include <cstdint>
#include <map>
#include <mutex>
#include <new>

#include <tbb/blocked_range.h>
#include <tbb/parallel_for.h>
#include <tbb/task_arena.h>

#include "build_common.h"
#include "kdrt/kdtree.h"

namespace kdrt {
namespace {

constexpr size_t kLine = 64;
constexpr size_t kHugePage = size_t{2} << 20;

bool own_mapping(size_t bytes) noexcept { return bytes >= kHugePage; }

/// A big array's mapping length: whole 2 MiB pages.
size_t mapping_bytes(size_t bytes) noexcept {
    return (bytes + kHugePage - 1) / kHugePage * kHugePage;
}

/// Faults in every 2 MiB page of a fresh mapping, in parallel (oneTBB) when it has several: a
/// fresh huge page is zeroed at its first touch, and on this project's VM that ran at 300-380 MB/s
/// (the host backs the memory at that touch), so a big array's first pass spent most of its time
/// there, on the one thread that writes it (make_wide_nodes' 46 MB on 64 bunnies). The writes put
/// in the zeros the page already holds; a core with nothing else to do takes a share of them.
void prefault(void* p, size_t len) {
    auto* const bytes = static_cast<volatile unsigned char*>(p);
    const size_t pages = len / kHugePage;
    if (pages < 2) {
        for (size_t i = 0; i < pages; ++i) bytes[i * kHugePage] = 0;
        return;
    }
    // Isolated: while it waits, this thread runs only these tasks, never another task of the
    // arena that might want a lock the allocating caller holds.
    tbb::this_task_arena::isolate([&] {
        tbb::parallel_for(tbb::blocked_range<size_t>(0, pages, 1),
                          [&](const tbb::blocked_range<size_t>& range) {
                              for (size_t i = range.begin(); i < range.end(); ++i)
                                  bytes[i * kHugePage] = 0;
                          });
    });
}

void* map_huge(size_t bytes) {
    const size_t len = mapping_bytes(bytes);
    if (len < bytes) throw std::bad_alloc();  // wrapped around
    // One huge page more than needed, then the unaligned head and the tail are unmapped.
    void* raw =
        mmap(nullptr, len + kHugePage, PROT_READ | PROT_WRITE, MAP_PRIVATE | MAP_ANONYMOUS, -1, 0);
    if (raw == MAP_FAILED) throw std::bad_alloc();
    const auto start = reinterpret_cast<uintptr_t>(raw);
    const uintptr_t aligned = (start + kHugePage - 1) / kHugePage * kHugePage;
    if (aligned > start) munmap(raw, aligned - start);
    const size_t tail = start + len + kHugePage - (aligned + len);
    if (tail > 0) munmap(reinterpret_cast<void*>(aligned + len), tail);
    void* p = reinterpret_cast<void*>(aligned);
    // Advice only: a failure (no THP support) changes nothing but speed.
    (void)madvise(p, len, MADV_HUGEPAGE);
    prefault(p, len);
    return p;
}

/// The mappings freed while a build runs (detail::RecycleTreeMappings), kept to serve the
/// mappings asked for later in the build: on 64 bunnies the binned levels' arena frees ~270 MB of
/// huge pages just before the tree's final arrays (~180 MB) are made, and a fresh huge page costs
/// its zeroing by the host at its first touch (0.3-0.6 GB/s on this project's VM), a kept one
/// nothing. Ranges are 2 MiB aligned, whole 2 MiB pages, advised MADV_HUGEPAGE and touched.
///
/// Kept memory is outside every budget the caller keeps (a server's tree cache counts its trees,
/// not this), so it is capped: at most the sum of the live builds' own limits. Without the cap a
/// freed tree (a cache eviction, a replaced mesh) was kept whole while any build ran, and with
/// builds overlapping it was never given back.
struct Recycled {
    std::mutex mutex;
    int builds = 0;                  ///< live RecycleTreeMappings objects
    size_t limit = 0;                ///< the sum of their limits
    std::map<uintptr_t, size_t> at;  ///< kept ranges: start -> length
    size_t bytes = 0;                ///< their total length
};
/// Never destroyed: a tree array may be freed by a static object's destructor at exit.
Recycled& recycled() {
    static auto* const r = new Recycled;
    return *r;
}

/// A kept range of `len` bytes (the smallest that holds them; what is left of it stays kept),
/// or null.
void* take_recycled(size_t len) {
    Recycled& r = recycled();
    const std::lock_guard<std::mutex> lock(r.mutex);
    auto best = r.at.end();
    for (auto it = r.at.begin(); it != r.at.end(); ++it)
        if (it->second >= len && (best == r.at.end() || it->second < best->second)) best = it;
    if (best == r.at.end()) return nullptr;
    const uintptr_t start = best->first;
    const size_t rest = best->second - len;
    r.at.erase(best);
    if (rest > 0) r.at.emplace(start + len, rest);
    r.bytes -= len;
    return reinterpret_cast<void*>(start);
}

/// Keeps as much of the range as the live builds' limit leaves room for (whole 2 MiB pages, its
/// start); returns the bytes kept: the caller unmaps the rest.
size_t keep_recycled(void* p, size_t len) {
    Recycled& r = recycled();
    const std::lock_guard<std::mutex> lock(r.mutex);
    if (r.builds == 0 || r.bytes >= r.limit) return 0;
    const size_t room = (r.limit - r.bytes) / kHugePage * kHugePage;
    const size_t kept = len < room ? len : room;
    if (kept == 0) return 0;
    r.at.emplace(reinterpret_cast<uintptr_t>(p), kept);
    r.bytes += kept;
    return kept;
}

}  // namespace

void* allocate_tree_memory(size_t bytes) {
    if (own_mapping(bytes)) {
        const size_t len = mapping_bytes(bytes);
        if (len >= bytes) {
            if (void* p = take_recycled(len)) return p;
        }
        return map_huge(bytes);
    }
    return ::operator new (bytes, std::align_val_t{kLine});
}

void free_tree_memory(void* p, size_t bytes) noexcept {
    if (own_mapping(bytes)) {
        const size_t len = mapping_bytes(bytes);
        size_t kept = 0;
        try {
            kept = keep_recycled(p, len);
        } catch (...) {  // no room for the map's entry: unmapped as before
        }
        if (kept < len) (void)munmap(static_cast<unsigned char*>(p) + kept, len - kept);
        return;
    }
    ::operator delete (p, std::align_val_t{kLine});
}

namespace detail {

RecycleTreeMappings::RecycleTreeMappings(size_t limit) : limit_(limit) {
    Recycled& r = recycled();
    const std::lock_guard<std::mutex> lock(r.mutex);
    ++r.builds;
    r.limit += limit_;
}

RecycleTreeMappings::~RecycleTreeMappings() {
    Recycled& r = recycled();
    std::map<uintptr_t, size_t> gone;
    {
        const std::lock_guard<std::mutex> lock(r.mutex);
        r.limit -= limit_;
        if (--r.builds == 0) {
            gone.swap(r.at);
            r.bytes = 0;
        } else {
            // The builds still running keep no more than their own limits: the biggest ranges go
            // first (the fewest unmaps), a range is cut to whole pages where part of it fits.
            while (r.bytes > r.limit) {
                auto big = r.at.begin();
                for (auto it = r.at.begin(); it != r.at.end(); ++it)
                    if (it->second > big->second) big = it;
                const size_t over = mapping_bytes(r.bytes - r.limit);
                const size_t cut = over < big->second ? over : big->second;
                gone.emplace(big->first + big->second - cut, cut);
                r.bytes -= cut;
                if (cut == big->second) {
                    r.at.erase(big);
                } else {
                    big->second -= cut;
                }
            }
        }
    }
    for (const auto& [start, len] : gone) (void)munmap(reinterpret_cast<void*>(start), len);
}

void* take_kept_tree_memory(size_t bytes) {
    const size_t len = mapping_bytes(bytes);
    return own_mapping(bytes) && len >= bytes ? take_recycled(len) : nullptr;
}

size_t recycled_tree_bytes() {
    Recycled& r = recycled();
    const std::lock_guard<std::mutex> lock(r.mutex);
    return r.bytes;
}

}  // namespace detail

}  // namespace kdrt
