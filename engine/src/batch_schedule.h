#pragma once
// Internal: the batch scheduler under the packet kernels. It cuts a batch into blocks of
// kBlockRays rays, decides per block whether sorting pays (block_is_incoherent), orders the valid
// rays by octant (and, when sorting, by the Morton codes of origin and direction), answers the
// invalid rays as misses, and hands the kernel one octant run at a time. It only picks an order:
// every answer is written at the ray's own index, so answers come back in input order.
//
// Included by packet_kernel.h inside each per-ISA translation unit's `#pragma GCC target`, so,
// like the kernel, everything is in an anonymous namespace and uses compiler builtins rather than
// <cmath> (see simd.h). Nothing here needs more than SSE2, x86-64's baseline: tests include it
// directly.

#include <cstddef>
#include <cstdint>

#include <emmintrin.h>

#include "kdrt/kdtree.h"
#include "kdrt/types.h"
#include "packet.h"
#include "ray_prep.h"

namespace kdrt::detail {
namespace {

/// Octant of a valid ray: the sign bits of its direction (those of its reciprocal, too).
inline uint32_t octant(const Ray& r) {
    return (__builtin_signbit(r.dx) ? 1u : 0u) | (__builtin_signbit(r.dy) ? 2u : 0u) |
           (__builtin_signbit(r.dz) ? 4u : 0u);
}

/// The octant of a ray the kernels trace (0..7, as octant() gives it), or -1 for one they answer
/// as a miss (ray_is_valid false). The same test as ray_is_valid in a dozen SSE2 instructions
/// (x86-64's baseline, so tests compile it too): it runs once for every ray of every batch, where
/// ray_is_valid's chain of compares and branches cost more than a coherent ray's whole set-up.
inline int octant_or_invalid(const Ray& r) {
    const __m128 zero = _mm_setzero_ps();
    const __m128 origin = _mm_loadu_ps(&r.ox);  // ox oy oz tmin
    const __m128 dir = _mm_loadu_ps(&r.dx);     // dx dy dz tmax
    // x * 0 == 0 exactly when x is finite (inf * 0 and NaN * 0 are NaN); lanes 0..2 count.
    const int finite = _mm_movemask_ps(_mm_and_ps(_mm_cmpeq_ps(_mm_mul_ps(origin, zero), zero),
                                                  _mm_cmpeq_ps(_mm_mul_ps(dir, zero), zero)));
    const int nonzero = _mm_movemask_ps(_mm_cmpneq_ps(dir, zero));  // -0 == 0; NaN is caught above
    const bool valid = (finite & 7) == 7 && (nonzero & 7) != 0 && r.tmin <= r.tmax;
    return valid ? (_mm_movemask_ps(dir) & 7) : -1;  // the direction's sign bits
}

/// The auto policy: a group of `lanes` same-octant rays goes as one packet of `width` lanes when
/// at least two and at least half the lanes are alive; else as single rays. A packet with fewer
/// live lanes (an octant's tail) does less useful work per traversal step than the single-ray
/// kernel (tests/bench/README.md has the measurements).
inline bool packet_pays(int lanes, int width) { return lanes >= 2 && lanes * 2 >= width; }

// Sort keys of the rays of a block: the direction octant in the top bits, so a packet never
// mixes octants; below it, for blocks whose origins differ, the Morton code of the origin (4 bits
// per axis, relative to the block's origin bounds) and of the direction (2 bits per axis of
// |d_axis| / |d|). Rays that start near each other and go the same way end up side by side.
constexpr int kOriginShift = 6;
constexpr int kOctantShift = 18;
constexpr int kKeyBits = 21;
constexpr int kRadixBits = 7;  // 3 passes of 128 buckets: cheap for a 256-ray render tile too
// Blocks whose unit directions span less than this in every axis keep their input order.
constexpr float kSortSpread = 0.5f;
// Coherent blocks are traced in runs of this many rays, bucketed by octant: a run's rays and its
// buckets stay in L1.
constexpr int kCoherentRun = 256;
// Every kSampleStride-th valid ray of a block is looked at to decide whether to sort it; the
// origin quantization uses the sample's bounds too (rays outside them clamp to the edge levels).
constexpr int kSampleStride = 64;

/// Bits 0..3 of x spread to bits 0, 3, 6, 9.
constexpr uint32_t spread3(uint32_t x) {
    x &= 0xFu;
    x = (x | (x << 4)) & 0x0C3u;
    x = (x | (x << 2)) & 0x249u;
    return x;
}

constexpr uint32_t morton3(uint32_t x, uint32_t y, uint32_t z) {
    return spread3(x) | (spread3(y) << 1) | (spread3(z) << 2);
}

/// Level 0..levels-1 of v, clamped to [0, 1] (v = 1 lands in the top level).
inline uint32_t quantize(double v, uint32_t levels) {
    const double q = v * levels;
    if (!(q > 0.0)) return 0;
    return q < static_cast<double>(levels) ? static_cast<uint32_t>(q) : levels - 1;
}

/// One stable counting-sort pass over `bits` bits of the keys from `shift`.
inline void radix_pass(const uint32_t* key_in, const uint16_t* index_in, uint32_t* key_out,
                       uint16_t* index_out, int n, int shift, int bits) {
    uint16_t start[(1 << kRadixBits) + 1];
    const int buckets = 1 << bits;
    for (int b = 0; b <= buckets; ++b) start[b] = 0;
    const uint32_t mask = static_cast<uint32_t>(buckets - 1);
    for (int i = 0; i < n; ++i) ++start[((key_in[i] >> shift) & mask) + 1];
    for (int b = 0; b < buckets; ++b) start[b + 1] = static_cast<uint16_t>(start[b + 1] + start[b]);
    for (int i = 0; i < n; ++i) {
        const uint16_t at = start[(key_in[i] >> shift) & mask]++;
        key_out[at] = key_in[i];
        index_out[at] = index_in[i];
    }
}

/// Sorts the first `n` keys (the low `key_bits` bits, stably) with their indices by radix passes
/// between the two buffers; true when the sorted keys and indices end in key_tmp / index_tmp.
inline bool radix_sort(uint32_t* key, uint16_t* index, uint32_t* key_tmp, uint16_t* index_tmp,
                       int n, int key_bits) {
    bool in_tmp = false;
    for (int shift = 0; shift < key_bits; shift += kRadixBits) {
        if (in_tmp)
            radix_pass(key_tmp, index_tmp, key, index, n, shift, kRadixBits);
        else
            radix_pass(key, index, key_tmp, index_tmp, n, shift, kRadixBits);
        in_tmp = !in_tmp;
    }
    return in_tmp;
}

/// Traces sorted rays (block[sorted[0..n)], sorted_key their keys, the octant in the bits from
/// `octant_shift` up) as one run per octant.
template <class TraceRun>
[[gnu::always_inline]] inline void trace_octant_runs(const Ray* block, size_t base,
                                                     const uint32_t* sorted_key,
                                                     const uint16_t* sorted, int n,
                                                     int octant_shift, const TraceRun& trace_run) {
    for (int first = 0; first < n;) {
        const uint32_t oct = sorted_key[first] >> octant_shift;
        int end = first + 1;
        while (end < n && (sorted_key[end] >> octant_shift) == oct) ++end;
        trace_run(block, base, sorted + first, end - first);
        first = end;
    }
}

/// Whether a block is worth sorting, from a sample of its valid rays (a heuristic: it only
/// picks the order, never an answer): the origins differ and the unit directions spread by
/// kSortSpread or more in some axis. Pinhole cameras (one origin), shadow rays towards a light
/// and orthographic views (one direction) come in an image's order, as coherent as it gets.
/// Writes the sample's origin bounds, for the sort's origin levels.
inline bool block_is_incoherent(const Ray* block, int n, float lo[3], float hi[3]) {
    float dir_lo[3] = {2.0f, 2.0f, 2.0f}, dir_hi[3] = {-2.0f, -2.0f, -2.0f};
    for (int a = 0; a < 3; ++a) {
        lo[a] = __builtin_inff();
        hi[a] = -__builtin_inff();
    }
    for (int i = 0; i < n; i += kSampleStride) {
        const Ray& r = block[i];
        if (!ray_is_valid(r)) continue;
        const float o[3] = {r.ox, r.oy, r.oz};
        // |d| in double: the squares of finite floats cannot overflow there.
        const float inv_len = static_cast<float>(
            1.0 / __builtin_sqrt(double{r.dx} * r.dx + double{r.dy} * r.dy + double{r.dz} * r.dz));
        const float d[3] = {r.dx * inv_len, r.dy * inv_len, r.dz * inv_len};
        for (int a = 0; a < 3; ++a) {
            lo[a] = o[a] < lo[a] ? o[a] : lo[a];
            hi[a] = o[a] > hi[a] ? o[a] : hi[a];
            dir_lo[a] = d[a] < dir_lo[a] ? d[a] : dir_lo[a];
            dir_hi[a] = d[a] > dir_hi[a] ? d[a] : dir_hi[a];
        }
    }
    bool origins_differ = false;
    float spread = 0;
    for (int a = 0; a < 3; ++a) {
        origins_differ |= hi[a] > lo[a];
        spread = dir_hi[a] - dir_lo[a] > spread ? dir_hi[a] - dir_lo[a] : spread;
    }
    return origins_differ && spread >= kSortSpread;
}

/// Answers the ray at `at` as a miss (one the kernels do not trace).
template <bool AnyHit>
inline void answer_miss(size_t at, Hit* hits, uint8_t* occluded, TraceCounters& counters) {
    if constexpr (AnyHit)
        occluded[at] = 0;
    else
        hits[at] = Hit{};
    ++counters.invalid_rays;
}

/// Collects the valid rays of block[0, n) (indices into the block, keys with their octant) and
/// answers the invalid ones as misses. Returns how many are valid.
template <bool AnyHit>
inline int collect_valid(const KdTree& tree, const Ray* block, size_t base, int n, Hit* hits,
                         uint8_t* occluded, TraceCounters& counters, uint32_t* key,
                         uint16_t* index) {
    int valid = 0;
    const bool empty_tree = tree.bounds.empty();
    for (int i = 0; i < n; ++i) {
        const int oct = octant_or_invalid(block[i]);
        if (oct < 0 || empty_tree) {
            answer_miss<AnyHit>(base + static_cast<size_t>(i), hits, occluded, counters);
            continue;
        }
        index[valid] = static_cast<uint16_t>(i);
        key[valid] = static_cast<uint32_t>(oct) << kOctantShift;
        ++valid;
    }
    return valid;
}

/// Adds the origin and direction Morton codes to the octant keys of the valid rays and sorts
/// them (3 radix passes). The result is in key/index or in key_tmp/index_tmp: returns whether
/// it is in the latter.
inline bool sort_by_origin_and_direction(const Ray* block, int valid, const float lo[3],
                                         const float hi[3], uint32_t* key, uint16_t* index,
                                         uint32_t* key_tmp, uint16_t* index_tmp) {
    double extent = 0;  // in double: hi - lo of finite floats cannot overflow there
    for (int a = 0; a < 3; ++a) {
        const double e = static_cast<double>(hi[a]) - lo[a];
        extent = e > extent ? e : extent;
    }
    for (int j = 0; j < valid; ++j) {
        const Ray& r = block[index[j]];
        const double o[3] = {r.ox, r.oy, r.oz}, d[3] = {r.dx, r.dy, r.dz};
        const double len = __builtin_sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2]);
        uint32_t qo[3], qd[3];
        for (int a = 0; a < 3; ++a) {
            qo[a] = quantize((o[a] - lo[a]) / extent, 16);  // origins outside the sample clamp
            qd[a] = quantize(__builtin_fabs(d[a]) / len, 4);
        }
        key[j] |= (morton3(qo[0], qo[1], qo[2]) << kOriginShift) | morton3(qd[0], qd[1], qd[2]);
    }
    return radix_sort(key, index, key_tmp, index_tmp, valid, kKeyBits);
}

/// An incoherent block (block_is_incoherent; lo, hi its origins' sample bounds), sorted whole by
/// octant, origin and direction, and traced as one run per octant. The invalid rays are answered
/// as misses here.
template <bool AnyHit, class TraceRun>
[[gnu::always_inline]] inline void trace_sorted_block(const KdTree& tree, const Ray* block,
                                                      size_t base, int n, const float lo[3],
                                                      const float hi[3], Hit* hits,
                                                      uint8_t* occluded, TraceCounters& counters,
                                                      const TraceRun& trace_run) {
    uint32_t key[kBlockRays], key_tmp[kBlockRays];
    uint16_t index[kBlockRays], index_tmp[kBlockRays];
    const int valid =
        collect_valid<AnyHit>(tree, block, base, n, hits, occluded, counters, key, index);
    counters.sorted_rays += static_cast<uint64_t>(valid);
    const bool in_tmp =
        sort_by_origin_and_direction(block, valid, lo, hi, key, index, key_tmp, index_tmp);
    trace_octant_runs(block, base, in_tmp ? key_tmp : key, in_tmp ? index_tmp : index, valid,
                      kOctantShift, trace_run);
}

/// A coherent block (not block_is_incoherent), cut into runs of kCoherentRun rays, each only
/// split by octant, keeping the input order and a small working set; the invalid rays are
/// answered as misses here.
template <bool AnyHit, class TraceRun>
[[gnu::always_inline]] inline void trace_coherent_block(const Ray* block, size_t base, int n,
                                                        Hit* hits, uint8_t* occluded,
                                                        TraceCounters& counters,
                                                        const TraceRun& trace_run) {
    for (int first = 0; first < n; first += kCoherentRun) {
        const int m = n - first < kCoherentRun ? n - first : kCoherentRun;
        const Ray* run = block + first;
        const size_t run_base = base + static_cast<size_t>(first);
        // Bucket the valid rays by octant (input order inside each), then trace the buckets.
        uint16_t bucket[8][kCoherentRun];
        int bucket_size[8] = {0, 0, 0, 0, 0, 0, 0, 0};
        for (int i = 0; i < m; ++i) {
            const int o = octant_or_invalid(run[i]);
            if (o < 0) {
                answer_miss<AnyHit>(run_base + static_cast<size_t>(i), hits, occluded, counters);
                continue;
            }
            bucket[o][bucket_size[o]++] = static_cast<uint16_t>(i);
        }
        for (int o = 0; o < 8; ++o) {
            trace_run(run, run_base, bucket[o], bucket_size[o]);
        }
    }
}

/// Rows of an image a packet's patch spans at most (trace_patch_block).
constexpr int kPatchRows = 4;
/// Blocks of one origin that go in input order, after one whose rows were not found (image_row),
/// before the search is tried again.
constexpr int kRowSearchGap = 32;

/// |a's direction - b's|, summed over the axes.
inline float direction_step(const Ray& a, const Ray& b) {
    return __builtin_fabsf(a.dx - b.dx) + __builtin_fabsf(a.dy - b.dy) +
           __builtin_fabsf(a.dz - b.dz);
}

inline bool same_origin(const Ray& a, const Ray& b) {
    return a.ox == b.ox && a.oy == b.oy && a.oz == b.oz;
}

/// Whether the first and the last valid rays of block[0, n) start at one point (false when none
/// is valid): a cheap first look for a camera's rays.
inline bool ends_share_origin(const Ray* block, int n) {
    int first = 0, last = n - 1;
    while (first < n && !ray_is_valid(block[first])) ++first;
    while (last > first && !ray_is_valid(block[last])) --last;
    return last > first && same_origin(block[first], block[last]);
}

/// Whether block[0, n) looks like an image's rows of `row` rays each from one point (a pinhole
/// camera's rays in image order), at a few samples k: ray k + row starts where ray k does, its
/// direction is nearer k's than those of rays k + row - 1 and k + row + 1 are (the ray below,
/// not one beside it), and at most twice as far as k + 1's (a row's end, whose step is a jump,
/// passes). Samples with an invalid ray are skipped; at least two must pass. A heuristic: it
/// only picks the order.
inline bool rows_of(const Ray* block, int n, int row) {
    if (row < 2 || 2 * row > n) return false;
    constexpr int kChecks = 5;
    int checked = 0;
    for (int c = 0; c < kChecks; ++c) {
        const int k = (n - row - 2) * c / (kChecks - 1);
        const Ray &a = block[k], &right = block[k + 1], &down = block[k + row];
        const Ray &down_left = block[k + row - 1], &down_right = block[k + row + 1];
        if (!ray_is_valid(a) || !ray_is_valid(right) || !ray_is_valid(down) ||
            !ray_is_valid(down_left) || !ray_is_valid(down_right))
            continue;
        if (!same_origin(a, down)) return false;
        const float below = direction_step(a, down);
        if (!(below <= 2.0f * direction_step(a, right) && below < direction_step(a, down_left) &&
              below < direction_step(a, down_right)))
            return false;
        ++checked;
    }
    return checked >= 2;
}

/// The row length of block[0, n) when its rays are an image's rows from one point (rows_of), or
/// 0. `guess` (the last block's) is tried first; else the row ends are looked for, the steps
/// between neighbouring valid rays' directions more than 2.5 times the step before (a row
/// of w rays ends in a step about w times as long): the
/// distance between the first two (or the first, when there is one).
inline int image_row(const Ray* block, int n, int guess) {
    if (n < 4 || !ends_share_origin(block, n)) return 0;
    if (rows_of(block, n, guess)) return guess;
    // The step before the first: the shorter of the first two (one of them may be a row's end).
    float step = __builtin_inff();
    for (int j = 1, seen = 0; j < n && seen < 2; ++j) {
        if (!ray_is_valid(block[j - 1]) || !ray_is_valid(block[j])) continue;
        const float s = direction_step(block[j - 1], block[j]);
        step = s < step ? s : step;
        ++seen;
    }
    int end[2] = {0, 0}, ends = 0;
    for (int j = 1; j < n && ends < 2; ++j) {
        if (!ray_is_valid(block[j - 1]) || !ray_is_valid(block[j])) continue;
        const float s = direction_step(block[j - 1], block[j]);
        if (s > 2.5f * step)
            end[ends++] = j;
        else
            step = s;
    }
    const int row = ends == 2 ? end[1] - end[0] : end[0];
    return rows_of(block, n, row) ? row : 0;
}

/// A coherent block of an image's rows (`row` rays each, image_row) traced in patches: bands of
/// up to kPatchRows rows, each cut into runs of kCoherentRun rays (the band's rows over a range
/// of columns), whose rays are ordered patch by patch (the band's rows by W / rows columns,
/// row by row), then bucketed by octant (that order inside each). So a packet of W rays is a
/// square patch of the image (4 x 4 at W = 16) rather than a strip of one row, and its rays stay
/// together longer: 16 and 64 bunnies' primary packets visit fewer nodes
/// (tests/bench/README.md). The rays past the last whole band go as trace_coherent_block does.
/// Only the order changes: every valid ray is traced once; the invalid ones are answered as
/// misses here.
template <int W, bool AnyHit, class TraceRun>
[[gnu::always_inline]] inline void trace_patch_block(const Ray* block, size_t base, int n, int row,
                                                     Hit* hits, uint8_t* occluded,
                                                     TraceCounters& counters,
                                                     const TraceRun& trace_run) {
    const int rows = n / row < kPatchRows ? n / row : kPatchRows;
    const int cols = W / rows > 0 ? W / rows : 1;  // a patch's columns
    const int run_cols = kCoherentRun / rows;
    const int band = rows * row;
    int first = 0;
    for (; first + band <= n; first += band) {
        for (int c0 = 0; c0 < row; c0 += run_cols) {
            const int c1 = c0 + run_cols < row ? c0 + run_cols : row;
            uint16_t bucket[8][kCoherentRun];
            int bucket_size[8] = {0, 0, 0, 0, 0, 0, 0, 0};
            for (int pc = c0; pc < c1; pc += cols) {
                const int pe = pc + cols < c1 ? pc + cols : c1;
                for (int r = 0; r < rows; ++r) {
                    for (int c = pc; c < pe; ++c) {
                        const int i = first + r * row + c;
                        const int o = octant_or_invalid(block[i]);
                        if (o < 0) {
                            answer_miss<AnyHit>(base + static_cast<size_t>(i), hits, occluded,
                                                counters);
                            continue;
                        }
                        bucket[o][bucket_size[o]++] = static_cast<uint16_t>(i);
                    }
                }
            }
            for (int o = 0; o < 8; ++o) trace_run(block, base, bucket[o], bucket_size[o]);
        }
    }
    if (first < n)
        trace_coherent_block<AnyHit>(block + first, base + static_cast<size_t>(first), n - first,
                                     hits, occluded, counters, trace_run);
}

/// Bits 0..15 of x spread to the even bits 0..30.
constexpr uint32_t spread2(uint32_t x) {
    x &= 0xFFFFu;
    x = (x | (x << 8)) & 0x00FF00FFu;
    x = (x | (x << 4)) & 0x0F0F0F0Fu;
    x = (x | (x << 2)) & 0x33333333u;
    x = (x | (x << 1)) & 0x55555555u;
    return x;
}
static_assert(spread2(0x1FFu) == 0x15555u && spread2(0x100u) == 0x10000u);

/// Bits per axis of a sorted coherent run's 2D origin key (trace_origin_sorted_block), and the
/// key's bits below the octant.
constexpr int kPlaneAxisBits = 9;
constexpr int kPlaneBits = 2 * kPlaneAxisBits;
/// Rays per sorted coherent run: a whole block. Runs of 1024 rays (keys and indices in 12 KiB)
/// made packets that split more, not less: 16 bunnies' shadow packets visited 314k nodes against
/// 245k sorted by blocks and 291k unsorted (tests/bench/README.md).
constexpr int kSortedRun = static_cast<int>(kBlockRays);

/// A coherent block whose rays start at different points and go nearly the same way (shadow rays
/// from the surface points of an image towards a light), in runs of kSortedRun rays, each sorted
/// by octant and the Morton code of the origin in the plane across the rays (the two axes other
/// than the run's first valid ray's dominant one, kPlaneAxisBits each over the run's origin
/// bounds), so that a packet's rays run side by side in a narrow bundle (a small patch of the
/// image, not a strip of one row). Each run is traced as one run per octant; the invalid rays are
/// answered as misses here.
template <bool AnyHit, class TraceRun>
[[gnu::always_inline]] inline void trace_origin_sorted_block(const KdTree& tree, const Ray* block,
                                                             size_t base, int n, Hit* hits,
                                                             uint8_t* occluded,
                                                             TraceCounters& counters,
                                                             const TraceRun& trace_run) {
    for (int first_ray = 0; first_ray < n; first_ray += kSortedRun) {
        const int m = n - first_ray < kSortedRun ? n - first_ray : kSortedRun;
        const Ray* run = block + first_ray;
        const size_t run_base = base + static_cast<size_t>(first_ray);
        uint32_t key[kSortedRun], key_tmp[kSortedRun];
        uint16_t index[kSortedRun], index_tmp[kSortedRun];
        const int valid =
            collect_valid<AnyHit>(tree, run, run_base, m, hits, occluded, counters, key, index);
        if (valid == 0) continue;
        const Ray& first = run[index[0]];
        const float d0[3] = {__builtin_fabsf(first.dx), __builtin_fabsf(first.dy),
                             __builtin_fabsf(first.dz)};
        const int major = d0[0] >= d0[1] ? (d0[0] >= d0[2] ? 0 : 2) : (d0[1] >= d0[2] ? 1 : 2);
        const int axis_u = major == 0 ? 1 : 0, axis_v = major == 2 ? 1 : 2;
        float lo[2] = {__builtin_inff(), __builtin_inff()};
        float hi[2] = {-__builtin_inff(), -__builtin_inff()};
        for (int j = 0; j < valid; ++j) {
            const float* o = &run[index[j]].ox;
            lo[0] = o[axis_u] < lo[0] ? o[axis_u] : lo[0];
            hi[0] = o[axis_u] > hi[0] ? o[axis_u] : hi[0];
            lo[1] = o[axis_v] < lo[1] ? o[axis_v] : lo[1];
            hi[1] = o[axis_v] > hi[1] ? o[axis_v] : hi[1];
        }
        // One scale for both axes, so the cells are square (in double: hi - lo of finite floats
        // cannot overflow there).
        const double eu = static_cast<double>(hi[0]) - lo[0];
        const double ev = static_cast<double>(hi[1]) - lo[1];
        const double extent = eu > ev ? eu : ev;
        const double scale = extent > 0.0 ? 1.0 / extent : 0.0;  // one origin: input order
        for (int j = 0; j < valid; ++j) {
            const float* o = &run[index[j]].ox;
            const uint32_t qu = quantize((o[axis_u] - lo[0]) * scale, 1u << kPlaneAxisBits);
            const uint32_t qv = quantize((o[axis_v] - lo[1]) * scale, 1u << kPlaneAxisBits);
            key[j] = (key[j] >> kOctantShift << kPlaneBits) | spread2(qu) | (spread2(qv) << 1);
        }
        const bool in_tmp = radix_sort(key, index, key_tmp, index_tmp, valid, kPlaneBits + 3);
        trace_octant_runs(run, run_base, in_tmp ? key_tmp : key, in_tmp ? index_tmp : index, valid,
                          kPlaneBits, trace_run);
    }
}

/// Schedules `count` rays, block by block (kBlockRays), as runs of one octant each:
/// `trace_run(block, base, order, run_count)` traces the rays block[order[0..run_count)], whose
/// answers belong at hits / occluded [base + order[i]] (run_count may be 0). An incoherent block
/// (block_is_incoherent) is sorted whole by octant, origin and direction (trace_sorted_block), or
/// handed whole to `trace_run.incoherent_block(block, base, n, lo, hi)` when the kernel has one
/// (which then answers every ray of the block, the invalid ones included); a coherent one goes in
/// runs of packets (trace_coherent_block), or whole to `trace_run.coherent_block(block, base, n)`
/// when the kernel has one (which then answers every ray of the block). Every valid ray is in
/// exactly one run; the invalid ones (and every ray of a tree with an empty root) are answered as
/// misses here. The kernels make every lane's single-ray decisions, so the grouping changes the
/// speed, never an answer.
template <bool AnyHit, class TraceRun>
[[gnu::always_inline]] inline void schedule_rays(const KdTree& tree, const Ray* rays, size_t count,
                                                 Hit* hits, uint8_t* occluded,
                                                 TraceCounters& counters,
                                                 const TraceRun& trace_run) {
    if (tree.bounds.empty()) {  // nothing to hit: every ray is answered as a miss
        for (size_t i = 0; i < count; ++i) answer_miss<AnyHit>(i, hits, occluded, counters);
        return;
    }
    for (size_t base = 0; base < count; base += kBlockRays) {
        const int n = static_cast<int>(count - base < kBlockRays ? count - base : kBlockRays);
        const Ray* block = rays + base;
        float lo[3], hi[3];
        if (block_is_incoherent(block, n, lo, hi)) {
            // A kernel may choose how to trace it (the auto policy); else sorted runs.
            if constexpr (requires { trace_run.incoherent_block(block, base, n, lo, hi); })
                trace_run.incoherent_block(block, base, n, lo, hi);
            else
                trace_sorted_block<AnyHit>(tree, block, base, n, lo, hi, hits, occluded, counters,
                                           trace_run);
            continue;
        }
        // A kernel may choose how to trace it (the auto policy); else runs of packets.
        if constexpr (requires { trace_run.coherent_block(block, base, n); })
            trace_run.coherent_block(block, base, n);
        else
            trace_coherent_block<AnyHit>(block, base, n, hits, occluded, counters, trace_run);
    }
}

}  // namespace
}  // namespace kdrt::detail
