#pragma once
/// KDRR / KDRH / KDRO batch codecs: rays in, closest hits or occlusion bits out.
/// Byte layouts and worked hex examples: proto/FORMATS.md.
///
/// Every batch is a 16-byte little-endian header followed by fixed-size records:
///
///   offset size field
///        0    4 magic     "KDRR" (rays), "KDRH" (hits) or "KDRO" (occlusion)
///        4    2 version   u16, 1
///        6    2 flags     u16; KDRR: bit 0 = occlusion query, other bits 0; KDRH/KDRO: 0
///        8    4 count     u32, number of records
///       12    4 reserved  u32, 0
///       16    . records   KDRR: 32 B (8 x f32 ox oy oz tmin dx dy dz tmax = kdrt::Ray)
///                         KDRH: 16 B (f32 t, u32 prim, f32 u, f32 v = kdrt::Hit)
///                         KDRO:  1 B (0 = not occluded, 1 = occluded)
///
/// All functions are thread-safe (no shared state) and never throw on bad input; decoders return
/// a DecodeError naming the first problem. Encoders may throw std::bad_alloc only.

#include <cstddef>
#include <cstdint>
#include <functional>
#include <optional>
#include <span>
#include <string>
#include <string_view>
#include <vector>

#include "kdrt/proto/result.h"
#include "kdrt/types.h"

namespace kdrt::proto {

/// Size of the common batch header.
inline constexpr size_t kBatchHeaderBytes = 16;
/// Size of one record in each batch kind.
inline constexpr size_t kRayRecordBytes = 32;
inline constexpr size_t kHitRecordBytes = 16;
inline constexpr size_t kOcclusionRecordBytes = 1;
/// The only version this code reads and writes.
inline constexpr uint16_t kBatchVersion = 1;
/// KDRR flag bit 0: the rays are an occlusion (any-hit) query, answered with KDRO.
inline constexpr uint16_t kRayFlagOcclusion = 0x0001;
/// Every KDRR flag bit this version defines.
inline constexpr uint16_t kRayFlagsKnown = kRayFlagOcclusion;
/// Magics, 4 ASCII bytes at offset 0.
inline constexpr std::string_view kRayMagic = "KDRR";
inline constexpr std::string_view kHitMagic = "KDRH";
inline constexpr std::string_view kOcclusionMagic = "KDRO";

static_assert(sizeof(Ray) == kRayRecordBytes, "KDRR records are kdrt::Ray");
static_assert(sizeof(Hit) == kHitRecordBytes, "KDRH records are kdrt::Hit");

/// Why a batch was refused. Stable: the server maps these to HTTP statuses.
enum class DecodeErrorCode {
    kTooShort,           ///< fewer than 16 bytes: no complete header
    kBadMagic,           ///< bytes 0..3 are not the expected magic
    kBadVersion,         ///< version != 1
    kBadReserved,        ///< reserved field != 0
    kLengthMismatch,     ///< body size != 16 + count * record size (either direction)
    kTooManyRays,        ///< count > DecodeLimits::max_rays
    kBadFlags,           ///< a flag bit that this version does not define is set
    kNonFiniteRay,       ///< DecodeLimits::reject_non_finite and a ray has a NaN/Inf field
    kBadOcclusionValue,  ///< a KDRO byte other than 0 or 1
};

/// Stable snake_case name of a code ("too_short", "bad_magic", ...), e.g. for JSON error bodies.
[[nodiscard]] std::string_view decode_error_code_name(DecodeErrorCode code) noexcept;

/// A refused batch: the code plus a one-line, human-readable detail naming the offending field
/// and values, e.g. `bad magic "ABCD", expected "KDRR"`,
/// `header says 10 rays (336 bytes) but body has 300 bytes`, `ray 17: field dx is NaN`.
struct DecodeError {
    DecodeErrorCode code = DecodeErrorCode::kTooShort;
    std::string detail;

    /// "<code name>: <detail>".
    [[nodiscard]] std::string to_string() const;
};

/// Limits a decoder enforces before allocating anything.
struct DecodeLimits {
    /// Largest accepted record count (rays, hits or occlusion bytes). Larger -> kTooManyRays.
    uint32_t max_rays = 1u << 26;
    /// KDRR only. When false (default) rays are decoded as sent and the engine treats invalid ones
    /// as misses. When true, a ray is refused (kNonFiniteRay, detail names the first ray index and
    /// field among ox oy oz tmin dx dy dz tmax) if any origin or direction component is NaN or
    /// +-inf, or tmin or tmax is NaN. tmin/tmax = +-inf stay accepted: tmax = +inf is the usual
    /// unbounded ray and the engine traces it.
    bool reject_non_finite = false;
};

/// A decoded KDRR batch.
struct RayBatch {
    std::vector<Ray> rays;
    /// Flag bit 0: answer with occlusion bytes (KDRO) instead of closest hits (KDRH).
    bool occlusion = false;
    /// The raw flags field (only kRayFlagsKnown bits can be set in a decoded batch).
    uint16_t flags = 0;
};

/// Decodes a KDRR body. Checks, in order: size >= 16 (kTooShort), magic, version, flags (only
/// bit 0), reserved == 0, count <= limits.max_rays, size == 16 + 32 * count exactly, and, if
/// requested, finiteness. A count-0 batch is valid. Ray values are bit-exact copies of the wire.
[[nodiscard]] Result<RayBatch, DecodeError> decode_rays(std::span<const std::byte> body,
                                                        const DecodeLimits& limits = {});

/// Which answer a KDRR batch gets.
enum class AnswerKind { kHits, kOcclusion };

/// In-place encoding of an answer, for callers that trace straight into their response buffer:
/// `out` has 16 bytes of room for the header followed by `count` records as the engine wrote them
/// (kdrt::Hit, or one uint8_t per ray for occlusion). Writes the header and turns the records
/// into their wire form in place (byte order on big-endian hosts, any nonzero occlusion value to
/// 1), giving the same bytes as encode_hits / encode_occlusion. Returns the body size,
/// 16 + count x record size. `out` must be suitably aligned for Hit records at out + 16.
size_t write_answer_in_place(std::byte* out, AnswerKind kind, uint32_t count) noexcept;

/// Incremental KDRR decoding, for a body that arrives in pieces (an HTTP request read in chunks).
/// The records are copied straight into storage the caller provides once the header is known, so
/// a batch is never held twice and never copied again, and the caller may use the rays that have
/// arrived (rays_ready()) before the rest of the body is in.
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
    void check_new_rays(uint64_t end);

    DecodeLimits limits_;
    Storage storage_;
    std::optional<uint64_t> declared_;
    std::byte header_[kBatchHeaderBytes] = {};
    bool header_done_ = false;
    uint16_t flags_ = 0;
    uint32_t count_ = 0;
    uint64_t expected_ = 0;  ///< 16 + 32 * count once the header is in
    std::byte* records_ = nullptr;
    uint64_t seen_ = 0;
    uint64_t ready_ = 0;
    std::optional<uint64_t> first_refused_;  ///< first non-finite ray (undeclared size)
    std::optional<DecodeError> error_;
};

/// Encodes rays as a KDRR body (flags = 1 if `occlusion`). Values are copied bit-exactly,
/// NaN payloads included. Precondition: rays.size() < 2^32 (else std::length_error).
[[nodiscard]] std::vector<std::byte> encode_rays(std::span<const Ray> rays, bool occlusion);

/// Encodes closest hits as a KDRH body (flags = 0), bit-exactly.
/// Precondition: hits.size() < 2^32 (else std::length_error).
[[nodiscard]] std::vector<std::byte> encode_hits(std::span<const Hit> hits);

/// Decodes a KDRH body: magic, version, flags == 0, reserved == 0, count <= limits.max_rays,
/// exact size. Hit values are not interpreted (any t/prim/u/v bit pattern is accepted).
[[nodiscard]] Result<std::vector<Hit>, DecodeError> decode_hits(std::span<const std::byte> body,
                                                                const DecodeLimits& limits = {});

/// Encodes occlusion answers as a KDRO body (flags = 0): one byte per ray, any nonzero input
/// byte is written as 1. Precondition: occluded.size() < 2^32 (else std::length_error).
[[nodiscard]] std::vector<std::byte> encode_occlusion(std::span<const uint8_t> occluded);

/// Decodes a KDRO body: magic, version, flags == 0, reserved == 0, count <= limits.max_rays,
/// exact size, every byte 0 or 1 (else kBadOcclusionValue naming the ray index and value).
[[nodiscard]] Result<std::vector<uint8_t>, DecodeError> decode_occlusion(
    std::span<const std::byte> body, const DecodeLimits& limits = {});

}  // namespace kdrt::proto
