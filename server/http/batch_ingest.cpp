#include "http/batch_ingest.h"

#include <algorithm>
#include <utility>
#include <vector>

#include "http/request_body.h"

namespace kdrt::server {
namespace {

/// Header bytes, and the rest of a refused body being drained, are received in pieces of this.
constexpr size_t kScratchBytes = size_t{64} << 10;

/// Thrown by the decoder's storage callback when Reserve refuses the batch's memory: the decoder
/// then stops in feed() (its contract lets storage throw), and take() turns it into kOverBudget.
struct OverBudget {};

}  // namespace

BatchIngest::BatchIngest(Compute& compute, BufferPool& pool, const KdTree& tree, uint32_t max_rays,
                         std::optional<uint64_t> declared_bytes, bool reject_non_finite,
                         Reserve reserve)
    : compute_(compute),
      pool_(pool),
      tree_(tree),
      limit_(proto::kdrr_body_size(max_rays)),
      declared_(declared_bytes),
      reserve_(std::move(reserve)),
      decoder_(
          {.max_rays = max_rays, .reject_non_finite = reject_non_finite},
          [this](uint32_t count, bool occlusion) { return storage(count, occlusion); },
          declared_bytes) {}

std::span<Ray> BatchIngest::storage(uint32_t count, bool occlusion) {
    if (reserve_ && !reserve_(proto::kdrr_body_size(count))) throw OverBudget{};
    const auto kind = occlusion ? proto::AnswerKind::kOcclusion : proto::AnswerKind::kHits;
    ray_buffer_ = PooledBuffer(pool_, size_t{count} * sizeof(Ray));
    answer_buffer_ = PooledBuffer(pool_, proto::answer_body_size(kind, count));
    // Ray is an implicit-lifetime type: the aligned buffer holds the array.
    rays_ = std::span<Ray>(reinterpret_cast<Ray*>(ray_buffer_.data()), count);
    if (count >= kStreamTraceRays) {
        if (occlusion)
            tracer_.emplace(compute_, tree_, rays_,
                            proto::answer_occlusion_records(answer_buffer_.data(), count));
        else
            tracer_.emplace(compute_, tree_, rays_,
                            proto::answer_hit_records(answer_buffer_.data(), count));
    }
    return rays_;
}

bool BatchIngest::take(std::span<const std::byte> piece, bool in_place) {
    if (over_budget_) return false;
    received_ += piece.size();
    if (received_ > limit_) {
        too_large_ = true;
        return false;
    }
    bool ok = false;
    try {
        ok = in_place ? decoder_.commit(piece.size()) : decoder_.feed(piece);
    } catch (const OverBudget&) {
        over_budget_ = true;
        return false;
    }
    if (!ok) {
        if (!refused_ && tracer_) tracer_->abandon();
        refused_ = true;
        return declared_ && *declared_ <= kDrainBodyBytes;
    }
    if (tracer_) tracer_->advance(decoder_.rays_ready());
    return true;
}

bool BatchIngest::feed(std::span<const std::byte> piece) { return take(piece, false); }

bool BatchIngest::receive_rest(const Receive& receive) {
    std::vector<std::byte> scratch;
    bool ok = true;
    while (ok && declared_ && received_ < *declared_) {
        const size_t left = static_cast<size_t>(*declared_ - received_);
        const std::span<std::byte> window = decoder_.next_window();
        ptrdiff_t n = 0;
        if (!window.empty()) {
            n = receive(window.data(), std::min({window.size(), left, kReceivePieceBytes}));
            if (n > 0) ok = take(window.first(static_cast<size_t>(n)), true);
        } else {
            scratch.resize(kScratchBytes);
            n = receive(scratch.data(), std::min(scratch.size(), left));
            if (n > 0) ok = take(std::span(scratch).first(static_cast<size_t>(n)), false);
        }
        if (n <= 0) ok = false;
    }
    return ok;
}

proto::Result<BatchAnswer, IngestFailure> BatchIngest::finish(bool read_ok) {
    using Kind = IngestFailure::Kind;
    if (too_large_) return proto::Err{IngestFailure{Kind::kTooLarge, std::nullopt, true}};
    if (over_budget_) return proto::Err{IngestFailure{Kind::kOverBudget, std::nullopt, true}};
    if (refused_) return proto::Err{IngestFailure{Kind::kRefused, decoder_.error(), !read_ok}};
    if (!read_ok) return proto::Err{IngestFailure{Kind::kUnreadable, std::nullopt, true}};
    if (auto verdict = decoder_.finish(); !verdict)
        return proto::Err{IngestFailure{Kind::kRefused, std::move(verdict).error(), false}};

    const uint32_t count = decoder_.count();
    const bool occlusion = decoder_.occlusion();
    std::byte* body = answer_buffer_.data();
    if (tracer_)
        tracer_->finish();
    else if (occlusion)
        compute_.occluded(tree_, rays_, proto::answer_occlusion_records(body, count));
    else
        compute_.intersect(tree_, rays_, proto::answer_hit_records(body, count));
    tracer_.reset();
    ray_buffer_ = PooledBuffer();  // back to the pool before the answer is sent
    const auto kind = occlusion ? proto::AnswerKind::kOcclusion : proto::AnswerKind::kHits;
    const size_t size = proto::write_answer_in_place(body, kind, count);
    return BatchAnswer{std::move(answer_buffer_), size, count, occlusion};
}

}  // namespace kdrt::server
