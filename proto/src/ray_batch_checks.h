#pragma once
// Internal: the checks the whole-body codecs and the stream decoder share, so both refuse a batch
// with the same code and the same detail (ray_batch_header.cpp).

#include <cstddef>
#include <cstdint>
#include <span>
#include <string_view>

#include "kdrt/proto/ray_batch_header.h"
#include "kdrt/proto/result.h"
#include "kdrt/types.h"

namespace kdrt::proto::detail {

/// What distinguishes the three batch kinds.
struct BatchKind {
    std::string_view magic;
    size_t record_bytes;
    uint16_t known_flags;       ///< bits a decoder accepts
    std::string_view singular;  ///< record noun for details
    std::string_view plural;
};

inline constexpr BatchKind kRays{kRayMagic, kRayRecordBytes, kRayFlagsKnown, "ray", "rays"};
inline constexpr BatchKind kHits{kHitMagic, kHitRecordBytes, 0, "hit", "hits"};
inline constexpr BatchKind kOcclusion{kOcclusionMagic, kOcclusionRecordBytes, 0, "occlusion value",
                                      "occlusion values"};

/// The header fields a decoder keeps once they passed their checks.
struct CheckedHeader {
    uint16_t flags = 0;
    uint32_t count = 0;
};

/// kTooShort for a body of `size` bytes.
[[nodiscard]] DecodeError too_short(uint64_t size);
/// kLengthMismatch: the header's `count` records do not fit a body of `size` bytes.
[[nodiscard]] DecodeError length_mismatch(const BatchKind& kind, uint32_t count, uint64_t size);
/// Validates the 16 header bytes at `p` (everything but the body length).
[[nodiscard]] Result<CheckedHeader, DecodeError> check_header_fields(const std::byte* p,
                                                                     const BatchKind& kind,
                                                                     const DecodeLimits& limits);
/// Validates the header and the exact body length; nothing is allocated.
[[nodiscard]] Result<CheckedHeader, DecodeError> check_header(std::span<const std::byte> body,
                                                              const BatchKind& kind,
                                                              const DecodeLimits& limits);
/// True when DecodeLimits::reject_non_finite refuses `ray` (branch-free on the bit patterns: the
/// stream decoder runs it on every ray as it arrives).
[[nodiscard]] bool ray_refused(const Ray& ray) noexcept;
/// kNonFiniteRay naming ray `index` and its first refused field. Precondition: ray_refused(ray).
[[nodiscard]] DecodeError non_finite_error(uint64_t index, const Ray& ray);

}  // namespace kdrt::proto::detail
