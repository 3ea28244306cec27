// KDRM / KDRC codecs: round trips in every layout, every layout's fields bit-identical to the
// full record's, and each decoder refusal.

#include <gtest/gtest.h>

#include <bit>
#include <cstring>
#include <map>
#include <optional>
#include <stdexcept>
#include <string>

#include "kdrt/proto/multi_hit.h"

namespace kdrt::proto {
namespace {

struct HitSample {
    std::vector<uint64_t> offsets{0, 2, 2, 3};
    std::vector<uint32_t> counts{5, 0, 1};
    std::vector<Hit> hits{Hit{1.5f, 7, 0.25f, 0.125f}, Hit{2.75f, 3, 0.5f, 0.0f},
                          Hit{0x1p-20f, 0xABCDEFu, 0.1f, 0.7f}};
    std::vector<Vec3> normals{{0, 0, 1}, {0.6f, 0.8f, 0}, {-1, 0, 0}};
    std::vector<Vec3> points{{1, 2, 3}, {-4, 5.5f, 6}, {7, 8, 9.25f}};

    MultiHitsView view(HitLayout layout, bool merged = false) const {
        return {layout, merged, 2, offsets, counts, hits, normals, points};
    }
};

std::vector<HitLayout> all_layouts() {
    std::vector<HitLayout> out;
    for (HitFields f : {HitFields::kFull, HitFields::kT, HitFields::kTPrim})
        for (bool n : {false, true})
            for (bool p : {false, true}) out.push_back({f, n, p});
    return out;
}

uint32_t bits(float f) { return std::bit_cast<uint32_t>(f); }

TEST(MultiHitCodec, RoundTripsEveryLayoutBitIdentical) {
    const HitSample s;
    for (const HitLayout layout : all_layouts()) {
        SCOPED_TRACE(testing::Message() << hit_fields_name(layout.fields) << " n=" << layout.normal
                                        << " p=" << layout.point);
        const auto body = encode_multi_hits(s.view(layout, true));
        EXPECT_EQ(body.size(), kdrm_body_size(3, 3, layout));
        auto decoded = decode_multi_hits(body);
        ASSERT_TRUE(decoded) << decoded.error().to_string();
        EXPECT_EQ(decoded->layout, layout);
        EXPECT_TRUE(decoded->merged);
        EXPECT_EQ(decoded->max_hits, 2u);
        EXPECT_EQ(decoded->offsets, s.offsets);
        EXPECT_EQ(decoded->counts, s.counts);
        ASSERT_EQ(decoded->hits.size(), 3u);
        for (size_t i = 0; i < 3; ++i) {
            const HitRecord& r = decoded->hits[i];
            EXPECT_EQ(bits(r.t), bits(s.hits[i].t));
            EXPECT_EQ(r.prim, layout.fields == HitFields::kT ? kNoHit : s.hits[i].prim);
            const bool full = layout.fields == HitFields::kFull;
            EXPECT_EQ(bits(r.u), full ? bits(s.hits[i].u) : 0u);
            EXPECT_EQ(bits(r.v), full ? bits(s.hits[i].v) : 0u);
            EXPECT_EQ(r.normal, layout.normal ? s.normals[i] : Vec3{});
            EXPECT_EQ(r.point, layout.point ? s.points[i] : Vec3{});
        }
    }
}

TEST(MultiHitCodec, FullRecordsAreKdrhRecords) {
    const HitSample s;
    const auto body = encode_multi_hits(s.view({}));
    const size_t records = kdrm_body_size(3, 0, {});
    ASSERT_EQ(body.size(), records + 3 * 16);
    EXPECT_EQ(std::memcmp(body.data() + records, s.hits.data(), 3 * sizeof(Hit)), 0);
}

TEST(MultiHitCodec, FieldNames) {
    for (HitFields f : {HitFields::kFull, HitFields::kT, HitFields::kTPrim})
        EXPECT_EQ(parse_hit_fields(hit_fields_name(f)), f);
    EXPECT_FALSE(parse_hit_fields("u"));
    EXPECT_FALSE(parse_hit_fields(""));
}

DecodeErrorCode code_of(const std::vector<std::byte>& body, const DecodeLimits& limits = {}) {
    auto r = decode_multi_hits(body, limits);
    EXPECT_FALSE(r);
    return r ? DecodeErrorCode::kTooShort : r.error().code;
}

TEST(MultiHitCodec, RefusesBadBodies) {
    const HitSample s;
    const auto good = encode_multi_hits(s.view({HitFields::kTPrim, true, false}));
    auto body = good;
    body.resize(31);
    EXPECT_EQ(code_of(body), DecodeErrorCode::kTooShort);
    body = good;
    body[3] = std::byte{'X'};
    EXPECT_EQ(code_of(body), DecodeErrorCode::kBadMagic);
    body = good;
    body[4] = std::byte{2};
    EXPECT_EQ(code_of(body), DecodeErrorCode::kBadVersion);
    body = good;
    body[6] = std::byte{0x23};  // unknown bit 5
    EXPECT_EQ(code_of(body), DecodeErrorCode::kBadFlags);
    body = good;
    body[6] = std::byte{0x07};  // fields 3
    EXPECT_EQ(code_of(body), DecodeErrorCode::kBadFlags);
    body = good;
    body[12] = std::byte{16};  // record bytes not what the flags say (20)
    EXPECT_EQ(code_of(body), DecodeErrorCode::kBadFlags);
    body = good;
    body[28] = std::byte{1};
    EXPECT_EQ(code_of(body), DecodeErrorCode::kBadReserved);
    EXPECT_EQ(code_of(good, DecodeLimits{.max_rays = 2}), DecodeErrorCode::kTooManyRays);
    body = good;
    body.pop_back();
    EXPECT_EQ(code_of(body), DecodeErrorCode::kLengthMismatch);
    body = good;
    body[16 + 7] = std::byte{0x80};  // H = 2^63 + 3: no overflow into a "matching" size
    EXPECT_EQ(code_of(body), DecodeErrorCode::kLengthMismatch);
    // Offsets: ray 1 ends before it starts.
    body = good;
    body[32 + 16] = std::byte{1};
    EXPECT_EQ(code_of(body), DecodeErrorCode::kBadOffsets);
    // Ray 0 keeps 2 hits but counts 1.
    body = good;
    body[32 + 32] = std::byte{1};
    EXPECT_EQ(code_of(body), DecodeErrorCode::kBadOffsets);
    // offsets[0] != 0.
    body = good;
    body[32] = std::byte{1};
    EXPECT_EQ(code_of(body), DecodeErrorCode::kBadOffsets);
    EXPECT_EQ(decode_error_code_name(DecodeErrorCode::kBadOffsets), "bad_offsets");
}

TEST(MultiHitCodec, EmptyAnswer) {
    const std::vector<uint64_t> offsets{0};
    MultiHitsView view;
    view.offsets = offsets;
    const auto body = encode_multi_hits(view);
    EXPECT_EQ(body.size(), 40u);
    auto decoded = decode_multi_hits(body);
    ASSERT_TRUE(decoded);
    EXPECT_TRUE(decoded->counts.empty());
    EXPECT_TRUE(decoded->hits.empty());
}

TEST(MultiHitCodec, HitPointsAsPly) {
    const HitSample s;
    auto decoded = decode_multi_hits(encode_multi_hits(s.view({HitFields::kTPrim, true, true})));
    ASSERT_TRUE(decoded);
    const std::vector<std::byte> ply = encode_hit_points_ply(*decoded);
    const std::string text(reinterpret_cast<const char*>(ply.data()), ply.size());
    const size_t end = text.find("end_header\n");
    ASSERT_NE(end, std::string::npos);
    EXPECT_NE(text.find("element vertex 3\n"), std::string::npos);
    EXPECT_NE(text.find("property uint ray\n"), std::string::npos);
    const size_t data = end + 11;
    ASSERT_EQ(ply.size(), data + 3 * 36);
    // The third vertex belongs to ray 2 (offsets 0, 2, 2, 3), its point first.
    float xyz[3];
    uint32_t ray = 0, prim = 0;
    std::memcpy(xyz, ply.data() + data + 2 * 36, 12);
    std::memcpy(&ray, ply.data() + data + 2 * 36 + 16, 4);
    std::memcpy(&prim, ply.data() + data + 2 * 36 + 20, 4);
    EXPECT_EQ((Vec3{xyz[0], xyz[1], xyz[2]}), s.points[2]);
    EXPECT_EQ(ray, 2u);
    EXPECT_EQ(prim, s.hits[2].prim);
    decoded->layout.point = false;
    EXPECT_THROW((void)encode_hit_points_ply(*decoded), std::invalid_argument);
}

TEST(HitCountCodec, RoundTripAndRefusals) {
    const std::vector<uint32_t> counts{0, 1, 0xFFFFFFFFu, 42};
    const auto body = encode_hit_counts(counts);
    EXPECT_EQ(body.size(), kdrc_body_size(4));
    auto decoded = decode_hit_counts(body);
    ASSERT_TRUE(decoded);
    EXPECT_EQ(*decoded, counts);
    auto shorter = body;
    shorter.pop_back();
    auto r = decode_hit_counts(shorter);
    ASSERT_FALSE(r);
    EXPECT_EQ(r.error().code, DecodeErrorCode::kLengthMismatch);
    auto flags = body;
    flags[6] = std::byte{1};
    ASSERT_FALSE(decode_hit_counts(flags));
    EXPECT_EQ(decode_hit_counts(flags).error().code, DecodeErrorCode::kBadFlags);
    auto magic = body;
    magic[3] = std::byte{'H'};
    EXPECT_EQ(decode_hit_counts(magic).error().code, DecodeErrorCode::kBadMagic);
}

std::optional<MultiHitQuery> parse(const std::map<std::string, std::string>& params, uint32_t limit,
                                   std::string* error = nullptr) {
    auto r = parse_multi_hit_query(
        [&](std::string_view name) -> std::optional<std::string> {
            auto it = params.find(std::string(name));
            if (it == params.end()) return std::nullopt;
            return it->second;
        },
        limit);
    if (!r) {
        if (error) *error = r.error();
        return std::nullopt;
    }
    return *r;
}

TEST(MultiHitQuery, DefaultsAndRoundTrip) {
    auto q = parse({}, 1024);
    ASSERT_TRUE(q);
    EXPECT_EQ(q->max_hits, kDefaultMaxHits);
    EXPECT_FALSE(q->merge_coincident);
    EXPECT_EQ(parse({}, 4)->max_hits, 4u);  // the default never exceeds the limit
    MultiHitQuery want{7, true, false, {HitFields::kTPrim, true, false}};
    std::map<std::string, std::string> params;
    const std::string text = multi_hit_query_string(want);
    size_t start = 0;
    while (start < text.size()) {
        const size_t amp = std::min(text.find('&', start), text.size());
        const std::string kv = text.substr(start, amp - start);
        params[kv.substr(0, kv.find('='))] = kv.substr(kv.find('=') + 1);
        start = amp + 1;
    }
    EXPECT_EQ(parse(params, 1024), want);
}

TEST(MultiHitQuery, RefusalsNameTheParameter) {
    std::string error;
    EXPECT_FALSE(parse({{"max_hits", "0"}}, 1024, &error));
    EXPECT_NE(error.find("max_hits is \"0\""), std::string::npos) << error;
    EXPECT_FALSE(parse({{"max_hits", "1025"}}, 1024, &error));
    EXPECT_NE(error.find("max_hits"), std::string::npos) << error;
    EXPECT_NE(error.find("1024"), std::string::npos) << error;
    EXPECT_FALSE(parse({{"max_hits", "3x"}}, 1024, &error));
    EXPECT_FALSE(parse({{"max_hits", ""}}, 1024, &error));
    EXPECT_FALSE(parse({{"max_hits", "-1"}}, 1024, &error));
    EXPECT_TRUE(parse({{"max_hits", "1024"}}, 1024));
    EXPECT_FALSE(parse({{"merge_coincident", "yes"}}, 1024, &error));
    EXPECT_NE(error.find("merge_coincident"), std::string::npos) << error;
    EXPECT_FALSE(parse({{"normal", "2"}}, 1024, &error));
    EXPECT_NE(error.find("normal"), std::string::npos) << error;
    EXPECT_FALSE(parse({{"fields", "uv"}}, 1024, &error));
    EXPECT_NE(error.find("fields"), std::string::npos) << error;
}

}  // namespace
}  // namespace kdrt::proto
