#pragma once
/// Incremental KDRR decoding, for a body that arrives in pieces (an HTTP request read in chunks).

#include <cstddef>
#include <cstdint>
#include <functional>
#include <optional>
#include <span>

#include "kdrt/proto/ray_batch_header.h"
#include "kdrt/proto/result.h"
#include "kdrt/types.h"

namespace kdrt::proto {

/// Decodes a KDRR body piece by piece. The records are copied straight into storage the caller
/// provides once the header is known, so a batch is never held twice and never copied again, and
/// the caller may use the rays that have arrived (rays_ready()) before the rest of the body is in.
///
/// The verdict is the one decode_rays gives for the same bytes, with the same code and detail:
/// header checks as soon as its 16 bytes are in, then the length, then (with reject_non_finite)
/// the first refused ray by index. When the body's size is declared in advance (Content-Length),
/// a size that cannot match the header's count is refused right after the header, and a refused
/// ray as soon as it arrives; otherwise non-finite rays are remembered and reported by finish()
/// after the length check, like decode_rays. Not thread-safe (one decoder per body).
class RayStreamDecoder {
public:
    /// Asked once, when the header has passed its checks: storage for exactly `count` rays (a span
    /// of another size is a programming error: std::logic_error). May throw (std::bad_alloc); the
    /// exception propagates out of feed().
    using Storage = std::function<std::span<Ray>(uint32_t count, bool occlusion)>;

    RayStreamDecoder(DecodeLimits limits, Storage storage,
                     std::optional<uint64_t> declared_bytes = std::nullopt);

    /// Consumes the next piece of the body. False once the batch is refused whatever follows
    /// (error() says why; later pieces are only counted). Bytes past the header's length are
    /// counted, not stored.
    bool feed(std::span<const std::byte> piece);
    /// Where the next body bytes belong in the storage, for a caller that reads them there itself
    /// (then calls commit()): empty until the header is in and after the last record or a
    /// refusal.
    [[nodiscard]] std::span<std::byte> next_window() const noexcept;
    /// The first `n` bytes of next_window() were written: the same as feed() of those bytes,
    /// without the copy. `n` must not exceed next_window().size() (std::logic_error).
    bool commit(size_t n);
    /// After the last piece: the verdict on the whole body.
    [[nodiscard]] Result<void, DecodeError> finish();

    [[nodiscard]] bool header_done() const noexcept { return header_done_; }
    [[nodiscard]] uint32_t count() const noexcept { return count_; }
    [[nodiscard]] uint16_t flags() const noexcept { return flags_; }
    [[nodiscard]] bool occlusion() const noexcept { return (flags_ & kRayFlagOcclusion) != 0; }
    /// Records complete in the storage (and checked, with reject_non_finite): a prefix of it.
    [[nodiscard]] uint64_t rays_ready() const noexcept { return ready_; }
    /// Body bytes fed so far.
    [[nodiscard]] uint64_t bytes_seen() const noexcept { return seen_; }
    /// The refusal once feed() has returned false.
    [[nodiscard]] const std::optional<DecodeError>& error() const noexcept { return error_; }

private:
    bool fail(DecodeError error);
    bool take_header(const std::byte*& p, size_t& n, uint64_t& pos);
    void check_new_rays(uint64_t end);

    DecodeLimits limits_;
    Storage storage_;
    std::optional<uint64_t> declared_;
    std::byte header_[kBatchHeaderBytes] = {};
    bool header_done_ = false;
    uint16_t flags_ = 0;
    uint32_t count_ = 0;
    uint64_t expected_ = 0;  ///< 16 + 32 * count once the header is in
    Ray* records_ = nullptr;
    uint64_t seen_ = 0;
    uint64_t ready_ = 0;
    std::optional<uint64_t> first_refused_;  ///< first non-finite ray (undeclared size)
    std::optional<DecodeError> error_;
};

}  // namespace kdrt::proto
