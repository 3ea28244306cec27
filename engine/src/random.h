#pragma once
// Internal: counter-based random numbers for ray-set generation (raygen.cpp) and the renderer
// (render_frame.h, render_shading.h). A stream is keyed by what it is for (a ray, a pixel sample),
// never by a shared sequence, so results do not depend on threads, tiles or evaluation order.

#include <algorithm>
#include <bit>
#include <cstdint>

#include "kdrt/raygen.h"

namespace kdrt::detail {

/// splitmix64 finaliser (Steele, Lea & Flood 2014): a bijection on 64 bits with good avalanche.
constexpr uint64_t mix64(uint64_t x) noexcept {
    x += 0x9E3779B97F4A7C15ull;
    x = (x ^ (x >> 30)) * 0xBF58476D1CE4E5B9ull;
    x = (x ^ (x >> 27)) * 0x94D049BB133111EBull;
    return x ^ (x >> 31);
}

/// A random stream from a 64-bit key: a Weyl sequence (the key plus multiples of the golden
/// ratio) finalised by mix64. The keying functions below give each use its own keys.
class CounterRng {
public:
    explicit constexpr CounterRng(uint64_t key) noexcept : state_(key) {}

    /// 32 random bits.
    uint32_t bits() noexcept {
        state_ += 0x9E3779B97F4A7C15ull;
        return static_cast<uint32_t>(mix64(state_) >> 32);
    }
    /// Uniform in [0, 1): 24 random bits, so every value is an exact float.
    float uniform() noexcept { return static_cast<float>(bits() >> 8) * 0x1.0p-24f; }
    /// Uniform in [-1, 1).
    float symmetric() noexcept { return 2.0f * uniform() - 1.0f; }

private:
    uint64_t state_;
};

/// The stream of ray `index` of a generated ray set: depends only on (seed, kind, index), so a
/// ray set is the same at any thread count.
inline CounterRng ray_set_rng(uint64_t seed, RayKind kind, uint64_t index) noexcept {
    return CounterRng(mix64(mix64(seed ^ (static_cast<uint64_t>(kind) << 56)) ^ index));
}

/// What a pixel's random stream is used for; part of its key, so streams never overlap.
enum class PixelStream : uint32_t {
    kStrata = 0,  ///< the pixel's permutation of the stratification cells
    kJitter = 1,  ///< position of one camera sample inside its cell
    kAo = 2,      ///< one AO ray (index = AO ray number)
    kBounce = 3,  ///< one bounce of a path (index = bounce number): roulette, direction
};

/// The stream keyed by (seed, full-frame pixel, sample, purpose, index): the same values whichever
/// thread, tile or region computes the pixel.
inline CounterRng pixel_rng(uint64_t seed, uint32_t x, uint32_t y, uint32_t sample,
                            PixelStream stream, uint32_t index) noexcept {
    return CounterRng(mix64(
        mix64(mix64(seed) ^ ((uint64_t{y} << 32) | x)) ^
        ((uint64_t{sample} << 32) | (uint64_t{static_cast<uint32_t>(stream)} << 28) | index)));
}

/// A permutation of [0, count) chosen by `key`, evaluated at `index` < count: a keyed bijection
/// of [0, 2^k) (xor, odd multiplications and xorshifts, all mod 2^k), repeated until the value
/// lands below count ("cycle walking"; it ends because index itself is below count).
inline uint32_t permute(uint32_t index, uint32_t count, uint32_t key) noexcept {
    const uint32_t mask = std::bit_ceil(count) - 1u;
    const int shift = std::max(1, std::popcount(mask) / 2);
    uint32_t i = index;
    do {
        i = (i ^ key) & mask;
        i = (i * 0x2C1B3C6Du) & mask;
        i ^= i >> shift;
        i = (i + (key >> 16)) & mask;
        i = (i * 0x297A2D39u) & mask;
        i ^= i >> shift;
    } while (i >= count);
    return i;
}

}  // namespace kdrt::detail
