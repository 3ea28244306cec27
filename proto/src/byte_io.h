#pragma once
// Internal: little-endian loads and stores. proto's one byte-order policy lives here: every wire
// format it reads or writes is little-endian, and so must the host be (as the engine's tree blob
// already requires), so records whose layout matches a host struct (KDRR rays, KDRH hits, raw
// mesh arrays) are copied with memcpy. The explicit loads and stores below serve the fields whose
// width or byte order differs from a host struct (headers, big-endian PLY).

#include <bit>
#include <cstddef>
#include <cstdint>
#include <cstring>

namespace kdrt::proto::detail {

static_assert(std::endian::native == std::endian::little,
              "proto copies little-endian wire records as host structs");

template <class U>
[[nodiscard]] inline U load_uint(const std::byte* p, bool big_endian) noexcept {
    static_assert(sizeof(U) <= 8);
    U v = 0;
    if (big_endian) {
        for (size_t i = 0; i < sizeof(U); ++i) v = static_cast<U>((v << 8) | static_cast<U>(p[i]));
    } else {
        for (size_t i = sizeof(U); i-- > 0;) v = static_cast<U>((v << 8) | static_cast<U>(p[i]));
    }
    return v;
}

template <class U>
inline void store_uint(std::byte* p, U v, bool big_endian) noexcept {
    for (size_t i = 0; i < sizeof(U); ++i) {
        const auto b = static_cast<std::byte>((v >> (8 * i)) & 0xFF);
        p[big_endian ? sizeof(U) - 1 - i : i] = b;
    }
}

[[nodiscard]] inline uint16_t load_le16(const std::byte* p) noexcept {
    return load_uint<uint16_t>(p, false);
}
[[nodiscard]] inline uint32_t load_le32(const std::byte* p) noexcept {
    return load_uint<uint32_t>(p, false);
}
[[nodiscard]] inline float load_le_f32(const std::byte* p) noexcept {
    return std::bit_cast<float>(load_uint<uint32_t>(p, false));
}
inline void store_le16(std::byte* p, uint16_t v) noexcept { store_uint(p, v, false); }
inline void store_le32(std::byte* p, uint32_t v) noexcept { store_uint(p, v, false); }
inline void store_le_f32(std::byte* p, float v) noexcept {
    store_uint(p, std::bit_cast<uint32_t>(v), false);
}

}  // namespace kdrt::proto::detail
