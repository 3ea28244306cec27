// The incremental KDRR decoder: the header is collected and checked as soon as its 16 bytes are
// in, the records go straight into the caller's storage (host structs in wire order, byte_io.h).

#include "kdrt/proto/ray_stream_decoder.h"

#include <algorithm>
#include <cstring>
#include <stdexcept>
#include <string>

#include "ray_batch_checks.h"

namespace kdrt::proto {

RayStreamDecoder::RayStreamDecoder(DecodeLimits limits, Storage storage,
                                   std::optional<uint64_t> declared_bytes)
    : limits_(limits), storage_(std::move(storage)), declared_(declared_bytes) {}

bool RayStreamDecoder::fail(DecodeError error) {
    error_ = std::move(error);
    return false;
}

void RayStreamDecoder::check_new_rays(uint64_t end) {
    if (limits_.reject_non_finite && !first_refused_) {
        for (uint64_t i = ready_; i < end; ++i) {
            if (!detail::ray_refused(records_[i])) continue;
            first_refused_ = i;
            // With the size known to match, nothing that follows can change the verdict.
            if (declared_) fail(detail::non_finite_error(i, records_[i]));
            break;
        }
    }
    ready_ = end;
}

/// Collects header bytes from the piece (`p`, `n`, at body offset `pos`, all advanced past what
/// it takes); once all 16 are in, checks them and asks for the storage. False on a refusal.
bool RayStreamDecoder::take_header(const std::byte*& p, size_t& n, uint64_t& pos) {
    const size_t take = std::min<size_t>(n, kBatchHeaderBytes - pos);
    if (take > 0) std::memcpy(header_ + pos, p, take);
    pos += take;
    p += take;
    n -= take;
    if (pos < kBatchHeaderBytes) return true;
    auto header = detail::check_header_fields(header_, detail::kRays, limits_);
    if (!header) return fail(std::move(header).error());
    flags_ = header->flags;
    count_ = header->count;
    expected_ = kdrr_body_size(count_);
    header_done_ = true;
    if (declared_ && *declared_ != expected_)
        return fail(detail::length_mismatch(detail::kRays, count_, *declared_));
    const std::span<Ray> storage = storage_(count_, occlusion());
    if (storage.size() != count_)
        throw std::logic_error("RayStreamDecoder: storage for " + std::to_string(storage.size()) +
                               " rays, the header says " + std::to_string(count_));
    records_ = storage.data();
    return true;
}

bool RayStreamDecoder::feed(std::span<const std::byte> piece) {
    uint64_t pos = seen_;
    seen_ += piece.size();
    if (error_) return false;
    const std::byte* p = piece.data();
    size_t n = piece.size();
    if (!header_done_ && !take_header(p, n, pos)) return false;
    if (n > 0 && pos < expected_) {
        const size_t take = static_cast<size_t>(std::min<uint64_t>(n, expected_ - pos));
        std::memcpy(reinterpret_cast<std::byte*>(records_) + (pos - kBatchHeaderBytes), p, take);
        pos += take;
        check_new_rays((pos - kBatchHeaderBytes) / kRayRecordBytes);
    }
    return !error_;
}

std::span<std::byte> RayStreamDecoder::next_window() const noexcept {
    if (!header_done_ || error_ || seen_ >= expected_) return {};
    return {reinterpret_cast<std::byte*>(records_) + (seen_ - kBatchHeaderBytes),
            static_cast<size_t>(expected_ - seen_)};
}

bool RayStreamDecoder::commit(size_t n) {
    if (n > next_window().size())
        throw std::logic_error("RayStreamDecoder::commit: " + std::to_string(n) +
                               " bytes, more than the window");
    seen_ += n;
    check_new_rays((seen_ - kBatchHeaderBytes) / kRayRecordBytes);
    return !error_;
}

Result<void, DecodeError> RayStreamDecoder::finish() {
    if (error_) return Err{*error_};
    if (!header_done_) return Err{detail::too_short(seen_)};
    if (seen_ != expected_) return Err{detail::length_mismatch(detail::kRays, count_, seen_)};
    if (first_refused_)
        return Err{detail::non_finite_error(*first_refused_, records_[*first_refused_])};
    return {};
}

}  // namespace kdrt::proto
