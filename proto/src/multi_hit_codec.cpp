// KDRM (every hit, CSR) and KDRC (hit counts) codecs.

#include <charconv>
#include <cstring>
#include <limits>
#include <stdexcept>
#include <string>

#include "byte_io.h"
#include "kdrt/proto/multi_hit.h"
#include "kdrt/proto/text.h"
#include "ray_batch_checks.h"

namespace kdrt::proto {
namespace {

constexpr detail::BatchKind kCounts{kHitCountMagic, kHitCountRecordBytes, 0, "count", "counts"};

DecodeError make(DecodeErrorCode code, std::string detail) {
    return DecodeError{code, std::move(detail)};
}

void store_le64(std::byte* p, uint64_t v) noexcept { detail::store_uint(p, v, false); }
uint64_t load_le64(const std::byte* p) noexcept { return detail::load_uint<uint64_t>(p, false); }

void store_vec(std::byte* p, Vec3 v) noexcept {
    detail::store_le_f32(p, v.x);
    detail::store_le_f32(p + 4, v.y);
    detail::store_le_f32(p + 8, v.z);
}
Vec3 load_vec(const std::byte* p) noexcept {
    return {detail::load_le_f32(p), detail::load_le_f32(p + 4), detail::load_le_f32(p + 8)};
}

uint16_t layout_flags(HitLayout layout, bool merged) noexcept {
    return static_cast<uint16_t>(
        static_cast<uint16_t>(layout.fields) | (layout.normal ? kMultiHitFlagNormal : 0) |
        (layout.point ? kMultiHitFlagPoint : 0) | (merged ? kMultiHitFlagMerged : 0));
}

}  // namespace

std::string_view hit_fields_name(HitFields fields) noexcept {
    switch (fields) {
        case HitFields::kFull:
            return "full";
        case HitFields::kT:
            return "t";
        case HitFields::kTPrim:
            return "t_prim";
    }
    return "full";
}

std::optional<HitFields> parse_hit_fields(std::string_view name) noexcept {
    for (HitFields f : {HitFields::kFull, HitFields::kT, HitFields::kTPrim})
        if (name == hit_fields_name(f)) return f;
    return std::nullopt;
}

std::vector<std::byte> encode_multi_hits(const MultiHitsView& a) {
    const size_t rays = a.counts.size();
    if (rays > std::numeric_limits<uint32_t>::max())
        throw std::length_error("KDRM answer of " + std::to_string(rays) +
                                " rays exceeds the u32 count field");
    if (a.offsets.size() != rays + 1 || a.offsets.back() != a.hits.size() ||
        (a.layout.normal && a.normals.size() != a.hits.size()) ||
        (a.layout.point && a.points.size() != a.hits.size()))
        throw std::invalid_argument("encode_multi_hits: offsets, normals or points do not match");
    const uint32_t record = hit_record_bytes(a.layout);
    std::vector<std::byte> out(kdrm_body_size(rays, a.hits.size(), a.layout));
    std::byte* p = out.data();
    std::memcpy(p, kMultiHitMagic.data(), 4);
    detail::store_le16(p + 4, kBatchVersion);
    detail::store_le16(p + 6, layout_flags(a.layout, a.merged));
    detail::store_le32(p + 8, static_cast<uint32_t>(rays));
    detail::store_le32(p + 12, record);
    store_le64(p + 16, a.hits.size());
    detail::store_le32(p + 24, a.max_hits);
    detail::store_le32(p + 28, 0);
    p += kMultiHitHeaderBytes;
    for (uint64_t o : a.offsets) {
        store_le64(p, o);
        p += 8;
    }
    for (uint32_t c : a.counts) {
        detail::store_le32(p, c);
        p += 4;
    }
    for (size_t i = 0; i < a.hits.size(); ++i) {
        const Hit& h = a.hits[i];
        detail::store_le_f32(p, h.t);
        size_t at = 4;
        if (a.layout.fields != HitFields::kT) {
            detail::store_le32(p + 4, h.prim);
            at = 8;
        }
        if (a.layout.fields == HitFields::kFull) {
            detail::store_le_f32(p + 8, h.u);
            detail::store_le_f32(p + 12, h.v);
            at = 16;
        }
        if (a.layout.normal) {
            store_vec(p + at, a.normals[i]);
            at += 12;
        }
        if (a.layout.point) store_vec(p + at, a.points[i]);
        p += record;
    }
    return out;
}

Result<MultiHits, DecodeError> decode_multi_hits(std::span<const std::byte> body,
                                                 const DecodeLimits& limits) {
    if (body.size() < kMultiHitHeaderBytes) {
        return Err{make(DecodeErrorCode::kTooShort,
                        "body has " + std::to_string(body.size()) + " bytes, less than the " +
                            std::to_string(kMultiHitHeaderBytes) + "-byte KDRM header")};
    }
    const std::byte* p = body.data();
    if (std::memcmp(p, kMultiHitMagic.data(), 4) != 0)
        return Err{make(DecodeErrorCode::kBadMagic, "bad magic, expected \"KDRM\"")};
    const uint16_t version = detail::load_le16(p + 4);
    if (version != kBatchVersion) {
        return Err{make(DecodeErrorCode::kBadVersion,
                        "unsupported version " + std::to_string(version) + ", expected 1")};
    }
    const uint16_t flags = detail::load_le16(p + 6);
    const uint16_t fields = flags & kMultiHitFieldsMask;
    if ((flags & ~kMultiHitFlagsKnown) != 0 || fields > 2) {
        return Err{make(DecodeErrorCode::kBadFlags,
                        "flags " + std::to_string(flags) +
                            " set unknown bits or a fields value above 2 (bits 0-1 fields, 2 "
                            "normal, 3 point, 4 merged)")};
    }
    MultiHits out;
    out.layout = {static_cast<HitFields>(fields), (flags & kMultiHitFlagNormal) != 0,
                  (flags & kMultiHitFlagPoint) != 0};
    out.merged = (flags & kMultiHitFlagMerged) != 0;
    const uint32_t rays = detail::load_le32(p + 8);
    const uint32_t record = detail::load_le32(p + 12);
    const uint64_t hits = load_le64(p + 16);
    out.max_hits = detail::load_le32(p + 24);
    const uint32_t reserved = detail::load_le32(p + 28);
    if (record != hit_record_bytes(out.layout)) {
        return Err{make(DecodeErrorCode::kBadFlags,
                        "record size " + std::to_string(record) + " does not match the flags' " +
                            std::to_string(hit_record_bytes(out.layout)))};
    }
    if (reserved != 0)
        return Err{make(DecodeErrorCode::kBadReserved, "reserved header field is not 0")};
    if (rays > limits.max_rays) {
        return Err{make(DecodeErrorCode::kTooManyRays, "header says " + std::to_string(rays) +
                                                           " rays, limit is " +
                                                           std::to_string(limits.max_rays))};
    }
    const uint64_t fixed = kdrm_body_size(rays, 0, out.layout);
    if (body.size() < fixed || (body.size() - fixed) / record < hits ||
        kdrm_body_size(rays, hits, out.layout) != body.size()) {
        return Err{make(DecodeErrorCode::kLengthMismatch,
                        "header says " + std::to_string(rays) + " rays and " +
                            std::to_string(hits) + " hits of " + std::to_string(record) +
                            " bytes but body has " + std::to_string(body.size()) + " bytes")};
    }
    p += kMultiHitHeaderBytes;
    out.offsets.resize(size_t{rays} + 1);
    for (uint64_t& o : out.offsets) {
        o = load_le64(p);
        p += 8;
    }
    out.counts.resize(rays);
    for (uint32_t& c : out.counts) {
        c = detail::load_le32(p);
        p += 4;
    }
    if (out.offsets[0] != 0 || out.offsets[rays] != hits)
        return Err{
            make(DecodeErrorCode::kBadOffsets,
                 "offsets must start at 0 and end at the hit count " + std::to_string(hits))};
    for (uint32_t i = 0; i < rays; ++i) {
        if (out.offsets[i + 1] < out.offsets[i] ||
            out.offsets[i + 1] - out.offsets[i] > out.counts[i])
            return Err{make(DecodeErrorCode::kBadOffsets,
                            "ray " + std::to_string(i) +
                                ": offsets decrease or keep more hits than its count")};
    }
    out.hits.resize(hits);
    for (HitRecord& h : out.hits) {
        h.t = detail::load_le_f32(p);
        size_t at = 4;
        if (out.layout.fields != HitFields::kT) {
            h.prim = detail::load_le32(p + 4);
            at = 8;
        }
        if (out.layout.fields == HitFields::kFull) {
            h.u = detail::load_le_f32(p + 8);
            h.v = detail::load_le_f32(p + 12);
            at = 16;
        }
        if (out.layout.normal) {
            h.normal = load_vec(p + at);
            at += 12;
        }
        if (out.layout.point) h.point = load_vec(p + at);
        p += record;
    }
    return out;
}

std::vector<std::byte> encode_hit_counts(std::span<const uint32_t> counts) {
    if (counts.size() > std::numeric_limits<uint32_t>::max())
        throw std::length_error("KDRC batch exceeds the u32 count field");
    std::vector<std::byte> out(kdrc_body_size(counts.size()));
    std::memcpy(out.data(), kHitCountMagic.data(), 4);
    detail::store_le16(out.data() + 4, kBatchVersion);
    detail::store_le16(out.data() + 6, 0);
    detail::store_le32(out.data() + 8, static_cast<uint32_t>(counts.size()));
    detail::store_le32(out.data() + 12, 0);
    for (size_t i = 0; i < counts.size(); ++i)
        detail::store_le32(out.data() + kBatchHeaderBytes + 4 * i, counts[i]);
    return out;
}

Result<std::vector<uint32_t>, DecodeError> decode_hit_counts(std::span<const std::byte> body,
                                                             const DecodeLimits& limits) {
    auto header = detail::check_header(body, kCounts, limits);
    if (!header) return Err{std::move(header).error()};
    std::vector<uint32_t> counts(header->count);
    for (size_t i = 0; i < counts.size(); ++i)
        counts[i] = detail::load_le32(body.data() + kBatchHeaderBytes + 4 * i);
    return counts;
}

std::vector<std::byte> encode_hit_points_ply(const MultiHits& a) {
    if (!a.layout.point) throw std::invalid_argument("encode_hit_points_ply needs hit points");
    const bool normals = a.layout.normal;
    std::string header =
        "ply\nformat binary_little_endian 1.0\ncomment hit points written by "
        "kdrt (every hit along each ray)\nelement vertex " +
        std::to_string(a.hits.size()) +
        "\nproperty float x\nproperty float y\nproperty float z\n"
        "property float t\nproperty uint ray\nproperty uint prim\n";
    if (normals) header += "property float nx\nproperty float ny\nproperty float nz\n";
    header += "end_header\n";
    const size_t record = normals ? 36 : 24;
    std::vector<std::byte> out(header.size() + record * a.hits.size());
    std::memcpy(out.data(), header.data(), header.size());
    std::byte* p = out.data() + header.size();
    for (size_t ray = 0; ray + 1 < a.offsets.size(); ++ray) {
        for (uint64_t k = a.offsets[ray]; k < a.offsets[ray + 1]; ++k) {
            const HitRecord& h = a.hits[k];
            store_vec(p, h.point);
            detail::store_le_f32(p + 12, h.t);
            detail::store_le32(p + 16, static_cast<uint32_t>(ray));
            detail::store_le32(p + 20, h.prim);
            if (normals) store_vec(p + 24, h.normal);
            p += record;
        }
    }
    return out;
}

Result<MultiHitQuery, std::string> parse_multi_hit_query(
    const std::function<std::optional<std::string>(std::string_view)>& param,
    uint32_t max_hits_limit) {
    MultiHitQuery q;
    q.max_hits = std::min(kDefaultMaxHits, max_hits_limit);
    auto quoted = [](const std::string& v) { return quote_value(v); };
    if (auto v = param(kQueryMaxHits)) {
        uint64_t n = 0;
        const auto [end, ec] = std::from_chars(v->data(), v->data() + v->size(), n);
        if (ec != std::errc{} || end != v->data() + v->size() || v->empty() || n < 1 ||
            n > max_hits_limit) {
            return Err{"query parameter max_hits is " + quoted(*v) + " (expected an integer 1 .. " +
                       std::to_string(max_hits_limit) + ", the server's max_hits_per_ray)"};
        }
        q.max_hits = static_cast<uint32_t>(n);
    }
    std::string error;
    auto flag = [&](std::string_view name, bool& out) {
        auto v = param(name);
        if (!v) return;
        if (*v == "true" || *v == "1") {
            out = true;
        } else if (*v == "false" || *v == "0") {
            out = false;
        } else if (error.empty()) {
            error = "query parameter " + std::string(name) + " is " + quoted(*v) +
                    " (expected true or false)";
        }
    };
    flag(kQueryMerge, q.merge_coincident);
    flag(kQueryCountOnly, q.count_only);
    flag(kQueryNormal, q.layout.normal);
    flag(kQueryPoint, q.layout.point);
    if (!error.empty()) return Err{std::move(error)};
    if (auto v = param(kQueryFields)) {
        auto f = parse_hit_fields(*v);
        if (!f) {
            return Err{"query parameter fields is " + quoted(*v) + " (expected full, t or t_prim)"};
        }
        q.layout.fields = *f;
    }
    return q;
}

std::string multi_hit_query_string(const MultiHitQuery& q) {
    auto b = [](bool v) { return v ? "true" : "false"; };
    return std::string(kQueryMaxHits) + "=" + std::to_string(q.max_hits) + "&" +
           std::string(kQueryMerge) + "=" + b(q.merge_coincident) + "&" +
           std::string(kQueryCountOnly) + "=" + b(q.count_only) + "&" + std::string(kQueryFields) +
           "=" + std::string(hit_fields_name(q.layout.fields)) + "&" + std::string(kQueryNormal) +
           "=" + b(q.layout.normal) + "&" + std::string(kQueryPoint) + "=" + b(q.layout.point);
}

}  // namespace kdrt::proto
