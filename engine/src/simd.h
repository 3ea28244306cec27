#pragma once
// Internal: the SIMD vocabulary of the packet kernels, on GCC/Clang vector extensions.
//
// Include this only from a per-ISA translation unit, after its `#pragma GCC target`: everything
// here lives in an anonymous namespace, so each ISA file gets its own copy compiled for its own
// instruction set and no copy can leak into code that runs on a CPU without it.

#include <immintrin.h>

#include <cstdint>

namespace kdrt::simd {
namespace {

template <int W>
struct Types;
template <>
struct Types<4> {
    using F = float __attribute__((vector_size(16)));
    using I = int32_t __attribute__((vector_size(16)));
    using U = uint32_t __attribute__((vector_size(16)));
};
template <>
struct Types<8> {
    using F = float __attribute__((vector_size(32)));
    using I = int32_t __attribute__((vector_size(32)));
    using U = uint32_t __attribute__((vector_size(32)));
};
template <>
struct Types<16> {
    using F = float __attribute__((vector_size(64)));
    using I = int32_t __attribute__((vector_size(64)));
    using U = uint32_t __attribute__((vector_size(64)));
};

/// W floats, W signed ints (masks: -1 true, 0 false, as comparisons produce), W unsigned ints.
template <int W>
using Float = typename Types<W>::F;
template <int W>
using Mask = typename Types<W>::I;
template <int W>
using UInt = typename Types<W>::U;

template <int W>
inline Float<W> broadcast(float x) {
    return Float<W>{} + x;
}
template <int W>
inline UInt<W> broadcast_u(uint32_t x) {
    return UInt<W>{} + x;
}
template <int W>
inline Mask<W> broadcast_i(int32_t x) {
    return Mask<W>{} + x;
}
template <int W>
inline Float<W> load(const float* p) {
    Float<W> v;
    __builtin_memcpy(&v, p, sizeof v);
    return v;
}
template <int W>
inline void store(float* p, Float<W> v) {
    __builtin_memcpy(p, &v, sizeof v);
}

/// Lane-wise m ? a : b.
template <int W, class V>
inline V select(Mask<W> m, V a, V b) {
    return m ? a : b;
}
/// Lane-wise minimum/maximum with the scalar kernel's NaN behaviour: a < b ? a : b.
template <int W>
inline Float<W> min(Float<W> a, Float<W> b) {
    return a < b ? a : b;
}
template <int W>
inline Float<W> max(Float<W> a, Float<W> b) {
    return a > b ? a : b;
}

/// One bit per lane (movemask): bit i set when lane i of the mask is true.
template <int W>
inline uint32_t bits(Mask<W> m) {
    if constexpr (W == 4) {
        return static_cast<uint32_t>(_mm_movemask_ps(reinterpret_cast<__m128>(m)));
    } else if constexpr (W == 8) {
        return static_cast<uint32_t>(_mm256_movemask_ps(reinterpret_cast<__m256>(m)));
    } else {
        return static_cast<uint32_t>(_mm512_movepi32_mask(reinterpret_cast<__m512i>(m)));
    }
}
template <int W>
inline bool any(Mask<W> m) {
    return bits<W>(m) != 0;
}
template <int W>
inline bool none(Mask<W> m) {
    return bits<W>(m) == 0;
}

}  // namespace
}  // namespace kdrt::simd
