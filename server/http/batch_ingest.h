#pragma once
/// The ingest of one KDRR batch, free of HTTP: the body is decoded as it arrives straight into a
/// pooled ray buffer, batches of kStreamTraceRays and more are traced block by block while the
/// rest is still arriving, and the answer is traced into a pooled response buffer and encoded
/// there in place. Pooled buffers go back to the pool on every exit (RAII). The transport feeds
/// the body (feed(), or receive_rest() for a reader that can receive into the ray buffer itself)
/// and then asks finish() for the answer or the reason there is none. Not thread-safe (one
/// ingest per request); the pool, compute and tree must outlive it.

#include <cstddef>
#include <cstdint>
#include <functional>
#include <optional>
#include <span>

#include "core/buffer_pool.h"
#include "core/compute.h"
#include "kdrt/kdtree.h"
#include "kdrt/proto/ray_batch.h"
#include "kdrt/proto/result.h"

namespace kdrt::server {

/// A traced batch: its KDRH (hits) or KDRO (occlusion) body in the first `size` bytes of `body`.
struct BatchAnswer {
    PooledBuffer body;
    size_t size = 0;
    uint32_t count = 0;
    bool occlusion = false;
};

/// Why a batch got no answer.
struct IngestFailure {
    enum class Kind {
        kTooLarge,    ///< more than BatchIngest::limit() bytes arrived
        kRefused,     ///< the decoder refused the batch (`error`)
        kUnreadable,  ///< the transport failed before the body was complete
        kOverBudget,  ///< the Reserve hook refused the memory of the batch the header declares
    };
    Kind kind = Kind::kRefused;
    std::optional<proto::DecodeError> error;  ///< kRefused only
    /// The rest of the body was not consumed: the connection cannot carry another request.
    bool close_connection = false;
};

class BatchIngest {
public:
    /// Reads up to `size` (> 0) body bytes into `out`, like recv(): the count, 0 when the peer
    /// closed the connection, negative on an error or a timeout.
    using Receive = std::function<ptrdiff_t(std::byte* out, size_t size)>;

    /// Batches this large are traced while their body is still arriving; smaller ones are
    /// decoded first and traced in one go.
    static constexpr uint32_t kStreamTraceRays = 2 * StreamTrace::kBlockRays;
    /// receive_rest() asks for at most this much at a time, so tracing starts on the first rays
    /// early.
    static constexpr size_t kReceivePieceBytes = size_t{1} << 20;

    /// Asked, once the header is in, with the body size it declares (16 + 32 x count) before
    /// the ray and answer buffers for it are taken: false refuses the batch (kOverBudget)
    /// without taking them.
    using Reserve = std::function<bool(uint64_t body_bytes)>;

    /// `declared_bytes`: the body's size when known in advance (Content-Length), else nullopt
    /// (chunked; `reserve`, when set, admits the memory the header asks for). Rays with NaN/Inf
    /// fields are refused (DecodeLimits::reject_non_finite) unless `reject_non_finite` is false:
    /// then the engine answers them as misses.
    BatchIngest(Compute& compute, BufferPool& pool, const KdTree& tree, uint32_t max_rays,
                std::optional<uint64_t> declared_bytes, bool reject_non_finite = true,
                Reserve reserve = {});
    BatchIngest(const BatchIngest&) = delete;
    BatchIngest& operator=(const BatchIngest&) = delete;
    /// Waits for any blocks still tracing, then returns the buffers to the pool.
    ~BatchIngest() = default;

    /// Largest body accepted: a KDRR batch of max_rays rays.
    [[nodiscard]] uint64_t limit() const noexcept { return limit_; }
    /// The declared size is over limit(): refuse before reading anything.
    [[nodiscard]] bool declared_too_large() const noexcept {
        return declared_ && *declared_ > limit_;
    }
    /// Body bytes taken so far.
    [[nodiscard]] uint64_t received() const noexcept { return received_; }

    /// Takes the next piece of the body. False when reading should stop: the body is over the
    /// limit, or the batch was refused and the rest is not worth draining (drain-or-close: a
    /// refused body of known size up to kDrainBodyBytes is read to its end, so the connection
    /// stays usable).
    bool feed(std::span<const std::byte> piece);
    /// Reads the rest of a declared-size body from `receive`, the rays straight into the ray
    /// buffer. False as feed(), or when `receive` fails or the peer closes first.
    bool receive_rest(const Receive& receive);

    /// After the last piece; `read_ok`: the transport delivered every byte it was asked for (the
    /// feed calls returning false count as asked for). The answer, traced and encoded, or why
    /// there is none.
    [[nodiscard]] proto::Result<BatchAnswer, IngestFailure> finish(bool read_ok);

private:
    std::span<Ray> storage(uint32_t count, bool occlusion);
    bool take(std::span<const std::byte> piece, bool in_place);

    Compute& compute_;
    BufferPool& pool_;
    const KdTree& tree_;
    const uint64_t limit_;
    const std::optional<uint64_t> declared_;
    const Reserve reserve_;
    PooledBuffer ray_buffer_, answer_buffer_;
    std::span<Ray> rays_;
    proto::RayStreamDecoder decoder_;
    uint64_t received_ = 0;
    bool too_large_ = false, refused_ = false, over_budget_ = false;
    std::optional<StreamTrace> tracer_;  ///< declared last: stops before the buffers go back
};

}  // namespace kdrt::server
