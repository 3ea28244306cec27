// KDRP / KDRD codecs: round trips bit for bit, each decoder refusal naming the field and point,
// the distance query parameters, query points as text and the CSV writer.

#include <gtest/gtest.h>

#include <bit>
#include <cmath>
#include <cstring>
#include <string>

#include "kdrt/proto/distance.h"

namespace kdrt::proto {
namespace {

uint32_t float_bits(float f) { return std::bit_cast<uint32_t>(f); }

std::vector<ClosestPoint> sample_answers() {
    std::vector<ClosestPoint> out(3);
    out[0] = {2.5f, 7, 0.25f, 0.125f, {1, 2, 3}, Feature::kFace, Side::kInside};
    out[1] = {0x1p-30f, 0xABCDEFu, 1.0f, 0.0f, {-4, 5.5f, 6}, Feature::kVertex1, Side::kOutside};
    // out[2]: nothing found (the default record)
    return out;
}

TEST(DistanceCodec, PointsRoundTrip) {
    const std::vector<Vec3> points = {{1, 2, 3}, {-0.0f, 0x1p-149f, 1e30f}};
    const std::vector<std::byte> body = encode_points(points);
    EXPECT_EQ(body.size(), kdrp_body_size(2));
    auto back = decode_points(body, {.reject_non_finite = true});
    ASSERT_TRUE(back) << back.error().to_string();
    ASSERT_EQ(back->size(), 2u);
    for (size_t i = 0; i < 2; ++i)
        for (int a = 0; a < 3; ++a) EXPECT_EQ(float_bits((*back)[i][a]), float_bits(points[i][a]));
    EXPECT_TRUE(decode_points(encode_points({}))) << "an empty batch is valid";
}

TEST(DistanceCodec, PointDecoderRefusals) {
    std::vector<std::byte> body = encode_points(std::vector<Vec3>{{1, 2, 3}, {4, NAN, 6}});
    // Non-finite points pass unless refused, and the refusal names the point and field.
    EXPECT_TRUE(decode_points(body));
    auto refused = decode_points(body, {.reject_non_finite = true});
    ASSERT_FALSE(refused);
    EXPECT_EQ(refused.error().code, DecodeErrorCode::kNonFinitePoint);
    EXPECT_EQ(refused.error().detail, "point 1: field y is NaN");
    EXPECT_EQ(decode_error_code_name(DecodeErrorCode::kNonFinitePoint), "non_finite_point");
    body = encode_points(std::vector<Vec3>{{INFINITY, 0, 0}});
    EXPECT_NE(decode_points(body, {.reject_non_finite = true}).error().detail.find("field x"),
              std::string::npos);

    body = encode_points(std::vector<Vec3>{{1, 2, 3}});
    EXPECT_EQ(decode_points(std::span(body).first(10)).error().code, DecodeErrorCode::kTooShort);
    EXPECT_EQ(decode_points(std::span(body).first(body.size() - 1)).error().code,
              DecodeErrorCode::kLengthMismatch);
    EXPECT_EQ(decode_points(body, {.max_rays = 0}).error().code, DecodeErrorCode::kTooManyRays);
    EXPECT_NE(decode_points(body, {.max_rays = 0}).error().detail.find("1 point"),
              std::string::npos);
    auto changed = [&](size_t at, std::byte value) {
        std::vector<std::byte> b = body;
        b[at] = value;
        return decode_points(b).error().code;
    };
    EXPECT_EQ(changed(3, std::byte{'R'}), DecodeErrorCode::kBadMagic);
    EXPECT_EQ(changed(4, std::byte{2}), DecodeErrorCode::kBadVersion);
    EXPECT_EQ(changed(6, std::byte{1}), DecodeErrorCode::kBadFlags);
    EXPECT_EQ(changed(12, std::byte{1}), DecodeErrorCode::kBadReserved);
}

TEST(DistanceCodec, DistancesRoundTripBitForBit) {
    const std::vector<ClosestPoint> answers = sample_answers();
    for (const bool signed_query : {false, true}) {
        const std::vector<std::byte> body = encode_distances(answers, signed_query);
        EXPECT_EQ(body.size(), kdrd_body_size(answers.size()));
        auto back = decode_distances(body);
        ASSERT_TRUE(back) << back.error().to_string();
        EXPECT_EQ(back->signed_query, signed_query);
        ASSERT_EQ(back->points.size(), answers.size());
        for (size_t i = 0; i < answers.size(); ++i) {
            const ClosestPoint &a = answers[i], &b = back->points[i];
            EXPECT_EQ(float_bits(a.distance), float_bits(b.distance));
            EXPECT_EQ(a.prim, b.prim);
            EXPECT_EQ(float_bits(a.u), float_bits(b.u));
            EXPECT_EQ(float_bits(a.v), float_bits(b.v));
            for (int k = 0; k < 3; ++k) EXPECT_EQ(float_bits(a.point[k]), float_bits(b.point[k]));
            EXPECT_EQ(a.feature, b.feature);
            EXPECT_EQ(a.side, b.side);
        }
    }
}

TEST(DistanceCodec, DistanceDecoderRefusals) {
    const std::vector<std::byte> body = encode_distances(sample_answers(), true);
    auto changed = [&](size_t at, std::byte value) {
        std::vector<std::byte> b = body;
        b[at] = value;
        return decode_distances(b);
    };
    EXPECT_EQ(changed(6, std::byte{2}).error().code, DecodeErrorCode::kBadFlags);
    EXPECT_NE(changed(6, std::byte{2}).error().detail.find("signed"), std::string::npos);
    const size_t record1 = kBatchHeaderBytes + kDistanceRecordBytes;
    auto bad_feature = changed(record1 + 28, std::byte{8});
    ASSERT_FALSE(bad_feature);
    EXPECT_EQ(bad_feature.error().code, DecodeErrorCode::kBadRecord);
    EXPECT_EQ(bad_feature.error().detail.rfind("point 1: feature 8", 0), 0u);
    EXPECT_EQ(changed(record1 + 29, std::byte{3}).error().code, DecodeErrorCode::kBadRecord);
    EXPECT_EQ(changed(record1 + 31, std::byte{1}).error().code, DecodeErrorCode::kBadRecord);
    EXPECT_EQ(decode_distances(std::span(body).first(body.size() - 4)).error().code,
              DecodeErrorCode::kLengthMismatch);
    EXPECT_EQ(changed(0, std::byte{'X'}).error().code, DecodeErrorCode::kBadMagic);
}

TEST(DistanceQueryParams, ParseAndPrint) {
    auto parse = [](std::map<std::string, std::string> params) {
        return parse_distance_query([&](std::string_view name) -> std::optional<std::string> {
            auto it = params.find(std::string(name));
            if (it == params.end()) return std::nullopt;
            return it->second;
        });
    };
    auto none = parse({});
    ASSERT_TRUE(none);
    EXPECT_EQ(*none, DistanceQuery{});
    auto q = parse({{"max_distance", "0.5"}, {"signed", "true"}});
    ASSERT_TRUE(q);
    EXPECT_EQ(q->max_distance, 0.5f);
    EXPECT_TRUE(q->signed_query);
    EXPECT_EQ(parse({{"max_distance", "inf"}})->max_distance, INFINITY);
    EXPECT_EQ(parse({{"max_distance", "0"}})->max_distance, 0.0f);
    for (const char* bad : {"-1", "nan", "abc", "", "1e99", "1.5x"}) {
        auto r = parse({{"max_distance", bad}});
        ASSERT_FALSE(r) << bad;
        EXPECT_NE(r.error().find("max_distance"), std::string::npos);
    }
    auto bad_sign = parse({{"signed", "yes"}});
    ASSERT_FALSE(bad_sign);
    EXPECT_NE(bad_sign.error().find("signed is \"yes\""), std::string::npos);
    for (const DistanceQuery& d :
         {DistanceQuery{}, DistanceQuery{0.125f, true}, DistanceQuery{3.1f, false}}) {
        const std::string s = distance_query_string(d);
        std::map<std::string, std::string> params;
        size_t start = 0;
        while (start < s.size()) {
            size_t amp = s.find('&', start);
            if (amp == std::string::npos) amp = s.size();
            const std::string kv = s.substr(start, amp - start);
            params[kv.substr(0, kv.find('='))] = kv.substr(kv.find('=') + 1);
            start = amp + 1;
        }
        EXPECT_EQ(*parse(params), d) << s;
    }
}

TEST(PointsText, XyzCsvAndErrors) {
    auto p = parse_points_text("x,y,z\n1,2,3\n\n# comment\n  4 5 6 0 0 1\r\n7\t8\t9");
    ASSERT_TRUE(p) << p.error();
    ASSERT_EQ(p->size(), 3u);
    EXPECT_EQ((*p)[0], (Vec3{1, 2, 3}));
    EXPECT_EQ((*p)[1], (Vec3{4, 5, 6}));
    EXPECT_EQ((*p)[2], (Vec3{7, 8, 9}));
    EXPECT_TRUE(parse_points_text("")->empty());
    auto short_line = parse_points_text("1 2 3\n4 5\n");
    ASSERT_FALSE(short_line);
    EXPECT_EQ(short_line.error().rfind("line 2:", 0), 0u);
    EXPECT_FALSE(parse_points_text("1 2 3\nx y z\n")) << "only a first line may be a header";
    EXPECT_FALSE(parse_points_text("1 2x 3\n"));
    auto nan = parse_points_text("1 nan 3\n");
    ASSERT_FALSE(nan);
    EXPECT_NE(nan.error().find("coordinate y is not finite"), std::string::npos);
}

TEST(DistancesCsv, OneLinePerPointAndEmptyFieldsWhereUnknown) {
    const std::vector<ClosestPoint> answers = sample_answers();
    const std::vector<Vec3> queries = {{0, 0, 0}, {1, 1, 1}, {2, 2, 2}};
    const std::string csv = distances_csv(queries, answers);
    EXPECT_EQ(csv,
              "x,y,z,distance,signed_distance,side,prim,u,v,px,py,pz,feature\n"
              "0,0,0,2.5,-2.5,inside,7,0.25,0.125,1,2,3,face\n"
              "1,1,1,9.313226e-10,9.313226e-10,outside,11259375,1,0,-4,5.5,6,vertex1\n"
              "2,2,2,inf,,unknown,,,,,,,none\n");
}

}  // namespace
}  // namespace kdrt::proto
