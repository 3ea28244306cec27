#include "kdrt/proto/ray_batch.h"

#include <gmock/gmock.h>
#include <gtest/gtest.h>

#include <bit>
#include <cmath>
#include <limits>
#include <random>

#include "proto_test_util.h"

namespace kdrt::proto {
namespace {

using test::append_le32;
using test::from_hex;
using ::testing::HasSubstr;

constexpr float kInf = std::numeric_limits<float>::infinity();

// ---- golden wire bytes (hand-written, independent of the encoder; also in proto/FORMATS.md) ----

// Ray 0: o = (0, 0, -5), tmin = 0, d = (0, 0, 1), tmax = 100: hits triangle 7 at t = 5.
// Ray 1: o = (1, 2, 3), tmin = 0.5, d = (-1, 0, 0), tmax = +inf: misses.
constexpr std::string_view kGoldenRays = R"(
    4b 44 52 52 | 01 00 | 00 00 | 02 00 00 00 | 00 00 00 00
    00 00 00 00  00 00 00 00  00 00 a0 c0  00 00 00 00
    00 00 00 00  00 00 00 00  00 00 80 3f  00 00 c8 42
    00 00 80 3f  00 00 00 40  00 00 40 40  00 00 00 3f
    00 00 80 bf  00 00 00 00  00 00 00 00  00 00 80 7f
)";
// The same two rays as an occlusion query: flags = 1.
constexpr std::string_view kGoldenOcclusionRays = R"(
    4b 44 52 52 | 01 00 | 01 00 | 02 00 00 00 | 00 00 00 00
    00 00 00 00  00 00 00 00  00 00 a0 c0  00 00 00 00
    00 00 00 00  00 00 00 00  00 00 80 3f  00 00 c8 42
    00 00 80 3f  00 00 00 40  00 00 40 40  00 00 00 3f
    00 00 80 bf  00 00 00 00  00 00 00 00  00 00 80 7f
)";
// Hit 0: t = 5, prim = 7, u = 0.25, v = 0.5. Hit 1: miss (t = +inf, prim = 0xFFFFFFFF, u = v = 0).
constexpr std::string_view kGoldenHits = R"(
    4b 44 52 48 | 01 00 | 00 00 | 02 00 00 00 | 00 00 00 00
    00 00 a0 40  07 00 00 00  00 00 80 3e  00 00 00 3f
    00 00 80 7f  ff ff ff ff  00 00 00 00  00 00 00 00
)";
// Ray 0 occluded, ray 1 not.
constexpr std::string_view kGoldenOcclusion = R"(
    4b 44 52 4f | 01 00 | 00 00 | 02 00 00 00 | 00 00 00 00
    01 00
)";

const Ray kRay0{0, 0, -5, 0, 0, 0, 1, 100};
const Ray kRay1{1, 2, 3, 0.5f, -1, 0, 0, kInf};

using RayBits = std::array<uint32_t, 8>;
using HitBits = std::array<uint32_t, 4>;

void expect_same_ray(const Ray& a, const Ray& b) {
    EXPECT_EQ(std::bit_cast<RayBits>(a), std::bit_cast<RayBits>(b));
}

TEST(RayBatchGolden, DecodesHandWrittenRays) {
    const auto body = from_hex(kGoldenRays);
    ASSERT_EQ(body.size(), 16u + 2 * 32);
    const auto batch = decode_rays(body);
    ASSERT_TRUE(batch.ok()) << batch.error().to_string();
    EXPECT_FALSE(batch->occlusion);
    EXPECT_EQ(batch->flags, 0);
    ASSERT_EQ(batch->rays.size(), 2u);
    expect_same_ray(batch->rays[0], kRay0);
    expect_same_ray(batch->rays[1], kRay1);

    const auto occlusion = decode_rays(from_hex(kGoldenOcclusionRays));
    ASSERT_TRUE(occlusion.ok()) << occlusion.error().to_string();
    EXPECT_TRUE(occlusion->occlusion);
    EXPECT_EQ(occlusion->flags, kRayFlagOcclusion);
    ASSERT_EQ(occlusion->rays.size(), 2u);
    expect_same_ray(occlusion->rays[1], kRay1);
}

TEST(RayBatchGolden, EncodesRaysToHandWrittenBytes) {
    const Ray rays[] = {kRay0, kRay1};
    EXPECT_EQ(encode_rays(rays, false), from_hex(kGoldenRays));
    EXPECT_EQ(encode_rays(rays, true), from_hex(kGoldenOcclusionRays));
}

TEST(RayBatchGolden, HitsBothWays) {
    const Hit hits[] = {Hit{5.0f, 7, 0.25f, 0.5f}, Hit{}};
    EXPECT_EQ(encode_hits(hits), from_hex(kGoldenHits));
    const auto decoded = decode_hits(from_hex(kGoldenHits));
    ASSERT_TRUE(decoded.ok()) << decoded.error().to_string();
    ASSERT_EQ(decoded->size(), 2u);
    EXPECT_EQ((*decoded)[0].t, 5.0f);
    EXPECT_EQ((*decoded)[0].prim, 7u);
    EXPECT_EQ((*decoded)[0].u, 0.25f);
    EXPECT_EQ((*decoded)[0].v, 0.5f);
    EXPECT_TRUE((*decoded)[0].is_hit());
    EXPECT_EQ((*decoded)[1].t, kInf);
    EXPECT_EQ((*decoded)[1].prim, kNoHit);
    EXPECT_FALSE((*decoded)[1].is_hit());
    EXPECT_EQ((*decoded)[1].u, 0.0f);
    EXPECT_EQ((*decoded)[1].v, 0.0f);
}

TEST(RayBatchGolden, OcclusionBothWays) {
    const uint8_t occluded[] = {1, 0};
    EXPECT_EQ(encode_occlusion(occluded), from_hex(kGoldenOcclusion));
    const auto decoded = decode_occlusion(from_hex(kGoldenOcclusion));
    ASSERT_TRUE(decoded.ok()) << decoded.error().to_string();
    EXPECT_EQ(*decoded, (std::vector<uint8_t>{1, 0}));
}

// ---- round trips and edge cases ----

TEST(RayBatch, CountZeroBatchesAreValid) {
    const auto rays = decode_rays(encode_rays({}, true));
    ASSERT_TRUE(rays.ok());
    EXPECT_TRUE(rays->rays.empty());
    EXPECT_TRUE(rays->occlusion);
    EXPECT_EQ(encode_rays({}, false).size(), kBatchHeaderBytes);
    const auto hits = decode_hits(encode_hits({}));
    ASSERT_TRUE(hits.ok());
    EXPECT_TRUE(hits->empty());
    const auto occ = decode_occlusion(encode_occlusion({}));
    ASSERT_TRUE(occ.ok());
    EXPECT_TRUE(occ->empty());
}

TEST(RayBatch, RandomBitPatternsRoundTripExactly) {
    const uint64_t seed = test::test_seed();
    SCOPED_TRACE(testing::Message() << "seed=" << seed);
    std::mt19937_64 rng(seed);
    std::vector<Ray> rays(1000);
    std::vector<Hit> hits(1000);
    std::vector<uint8_t> occluded(1000);
    for (size_t i = 0; i < rays.size(); ++i) {
        RayBits ray_bits;
        for (uint32_t& b : ray_bits) b = static_cast<uint32_t>(rng());  // NaN payloads included
        rays[i] = std::bit_cast<Ray>(ray_bits);
        HitBits hit_bits;
        for (uint32_t& b : hit_bits) b = static_cast<uint32_t>(rng());
        hits[i] = std::bit_cast<Hit>(hit_bits);
        occluded[i] = static_cast<uint8_t>(rng() & 1);
    }
    const auto batch = decode_rays(encode_rays(rays, false));
    ASSERT_TRUE(batch.ok()) << batch.error().to_string();
    ASSERT_EQ(batch->rays.size(), rays.size());
    for (size_t i = 0; i < rays.size(); ++i) expect_same_ray(batch->rays[i], rays[i]);

    const auto decoded_hits = decode_hits(encode_hits(hits));
    ASSERT_TRUE(decoded_hits.ok());
    ASSERT_EQ(decoded_hits->size(), hits.size());
    for (size_t i = 0; i < hits.size(); ++i) {
        EXPECT_EQ(std::bit_cast<HitBits>((*decoded_hits)[i]), std::bit_cast<HitBits>(hits[i]));
    }
    const auto decoded_occ = decode_occlusion(encode_occlusion(occluded));
    ASSERT_TRUE(decoded_occ.ok());
    EXPECT_EQ(*decoded_occ, occluded);
}

TEST(RayBatch, OcclusionEncoderNormalisesNonzeroToOne) {
    const uint8_t occluded[] = {0, 2, 255, 1};
    const auto body = encode_occlusion(occluded);
    ASSERT_EQ(body.size(), 20u);
    EXPECT_EQ(body[16], std::byte{0});
    EXPECT_EQ(body[17], std::byte{1});
    EXPECT_EQ(body[18], std::byte{1});
    EXPECT_EQ(body[19], std::byte{1});
}

TEST(RayBatch, NonFiniteRaysPassByDefault) {
    const Ray rays[] = {Ray{std::nanf(""), 0, 0, 0, 1, 0, 0, kInf}};
    const auto batch = decode_rays(encode_rays(rays, false));
    ASSERT_TRUE(batch.ok());
    EXPECT_TRUE(std::isnan(batch->rays[0].ox));
}

TEST(RayBatch, ErrorCodeNamesAreStable) {
    EXPECT_EQ(decode_error_code_name(DecodeErrorCode::kTooShort), "too_short");
    EXPECT_EQ(decode_error_code_name(DecodeErrorCode::kBadMagic), "bad_magic");
    EXPECT_EQ(decode_error_code_name(DecodeErrorCode::kBadVersion), "bad_version");
    EXPECT_EQ(decode_error_code_name(DecodeErrorCode::kBadReserved), "bad_reserved");
    EXPECT_EQ(decode_error_code_name(DecodeErrorCode::kLengthMismatch), "length_mismatch");
    EXPECT_EQ(decode_error_code_name(DecodeErrorCode::kTooManyRays), "too_many_rays");
    EXPECT_EQ(decode_error_code_name(DecodeErrorCode::kBadFlags), "bad_flags");
    EXPECT_EQ(decode_error_code_name(DecodeErrorCode::kNonFiniteRay), "non_finite_ray");
    EXPECT_EQ(decode_error_code_name(DecodeErrorCode::kBadOcclusionValue), "bad_occlusion_value");
    EXPECT_EQ((DecodeError{DecodeErrorCode::kBadMagic, "x"}.to_string()), "bad_magic: x");
}

// ---- decode errors: each code, and the detail names the right thing ----

/// A header built byte by byte, independent of the encoder.
std::vector<std::byte> header(std::string_view magic, uint16_t version, uint16_t flags,
                              uint32_t count, uint32_t reserved) {
    std::vector<std::byte> out;
    for (char c : magic) out.push_back(static_cast<std::byte>(c));
    out.push_back(static_cast<std::byte>(version & 0xFF));
    out.push_back(static_cast<std::byte>(version >> 8));
    out.push_back(static_cast<std::byte>(flags & 0xFF));
    out.push_back(static_cast<std::byte>(flags >> 8));
    append_le32(out, count);
    append_le32(out, reserved);
    return out;
}

std::vector<std::byte> with_body(std::vector<std::byte> head, size_t body_bytes,
                                 std::byte fill = std::byte{0}) {
    head.resize(head.size() + body_bytes, fill);
    return head;
}

DecodeError ray_error(std::span<const std::byte> body, const DecodeLimits& limits = {}) {
    auto r = decode_rays(body, limits);
    EXPECT_FALSE(r.ok());
    return r.ok() ? DecodeError{} : r.error();
}

TEST(RayBatchDecodeError, TooShort) {
    for (size_t n : {0u, 1u, 4u, 15u}) {
        const auto e = ray_error(std::vector<std::byte>(n));
        EXPECT_EQ(e.code, DecodeErrorCode::kTooShort);
        EXPECT_EQ(e.detail,
                  "body has " + std::to_string(n) + " bytes, less than the 16-byte header");
    }
    const auto hits = decode_hits(std::vector<std::byte>(3));
    ASSERT_FALSE(hits.ok());
    EXPECT_EQ(hits.error().code, DecodeErrorCode::kTooShort);
}

TEST(RayBatchDecodeError, BadMagicQuotesBothMagics) {
    auto e = ray_error(header("ABCD", 1, 0, 0, 0));
    EXPECT_EQ(e.code, DecodeErrorCode::kBadMagic);
    EXPECT_EQ(e.detail, "bad magic \"ABCD\", expected \"KDRR\"");
    // Non-printable bytes are escaped.
    auto binary = header("KDR", 1, 0, 0, 0);
    binary.insert(binary.begin() + 3, std::byte{0x01});
    e = ray_error(binary);
    EXPECT_EQ(e.detail, "bad magic \"KDR\\x01\", expected \"KDRR\"");
    // A hit batch sent where rays are expected, and vice versa.
    EXPECT_THAT(ray_error(from_hex(kGoldenHits)).detail, HasSubstr("\"KDRH\", expected \"KDRR\""));
    const auto hits = decode_hits(from_hex(kGoldenRays));
    ASSERT_FALSE(hits.ok());
    EXPECT_EQ(hits.error().code, DecodeErrorCode::kBadMagic);
    EXPECT_EQ(hits.error().detail, "bad magic \"KDRR\", expected \"KDRH\"");
    const auto occ = decode_occlusion(from_hex(kGoldenHits));
    ASSERT_FALSE(occ.ok());
    EXPECT_EQ(occ.error().detail, "bad magic \"KDRH\", expected \"KDRO\"");
}

TEST(RayBatchDecodeError, BadVersion) {
    for (uint16_t version : {uint16_t{0}, uint16_t{2}, uint16_t{0x0100}}) {
        const auto e = ray_error(header("KDRR", version, 0, 0, 0));
        EXPECT_EQ(e.code, DecodeErrorCode::kBadVersion);
        EXPECT_EQ(e.detail, "unsupported version " + std::to_string(version) + ", expected 1");
    }
}

TEST(RayBatchDecodeError, BadFlags) {
    auto e = ray_error(header("KDRR", 1, 0x0003, 0, 0));
    EXPECT_EQ(e.code, DecodeErrorCode::kBadFlags);
    EXPECT_THAT(e.detail, HasSubstr("unknown flag bits 0x0002"));
    EXPECT_THAT(e.detail, HasSubstr("only bit 0, occlusion"));
    e = ray_error(header("KDRR", 1, 0x8000, 0, 0));
    EXPECT_THAT(e.detail, HasSubstr("0x8000"));
    // KDRH and KDRO define no flags at all.
    const auto hits = decode_hits(header("KDRH", 1, 0x0001, 0, 0));
    ASSERT_FALSE(hits.ok());
    EXPECT_EQ(hits.error().code, DecodeErrorCode::kBadFlags);
    EXPECT_THAT(hits.error().detail, HasSubstr("no flags are defined for KDRH"));
    const auto occ = decode_occlusion(header("KDRO", 1, 0x0001, 0, 0));
    ASSERT_FALSE(occ.ok());
    EXPECT_EQ(occ.error().code, DecodeErrorCode::kBadFlags);
}

TEST(RayBatchDecodeError, BadReserved) {
    const auto e = ray_error(header("KDRR", 1, 0, 0, 7));
    EXPECT_EQ(e.code, DecodeErrorCode::kBadReserved);
    EXPECT_EQ(e.detail, "reserved header field is 0x00000007, expected 0");
    const auto hits = decode_hits(header("KDRH", 1, 0, 0, 0x80000000u));
    ASSERT_FALSE(hits.ok());
    EXPECT_EQ(hits.error().code, DecodeErrorCode::kBadReserved);
    EXPECT_THAT(hits.error().detail, HasSubstr("0x80000000"));
}

TEST(RayBatchDecodeError, BodyShorterThanCount) {
    const auto e = ray_error(with_body(header("KDRR", 1, 0, 10, 0), 300 - 16));
    EXPECT_EQ(e.code, DecodeErrorCode::kLengthMismatch);
    EXPECT_EQ(e.detail, "header says 10 rays (336 bytes) but body has 300 bytes");
}

TEST(RayBatchDecodeError, BodyLongerThanCount) {
    auto e = ray_error(with_body(header("KDRR", 1, 0, 1, 0), 33));
    EXPECT_EQ(e.code, DecodeErrorCode::kLengthMismatch);
    EXPECT_EQ(e.detail, "header says 1 ray (48 bytes) but body has 49 bytes");
    e = ray_error(with_body(header("KDRR", 1, 0, 0, 0), 32));
    EXPECT_EQ(e.detail, "header says 0 rays (16 bytes) but body has 48 bytes");
    const auto hits = decode_hits(with_body(header("KDRH", 1, 0, 2, 0), 31));
    ASSERT_FALSE(hits.ok());
    EXPECT_EQ(hits.error().code, DecodeErrorCode::kLengthMismatch);
    EXPECT_EQ(hits.error().detail, "header says 2 hits (48 bytes) but body has 47 bytes");
    const auto occ = decode_occlusion(with_body(header("KDRO", 1, 0, 2, 0), 3));
    ASSERT_FALSE(occ.ok());
    EXPECT_EQ(occ.error().detail,
              "header says 2 occlusion values (18 bytes) but body has 19 bytes");
}

TEST(RayBatchDecodeError, TooManyRaysBeforeAnyAllocation) {
    // The count says 4 billion rays but only the header exists: refused on the count alone.
    auto e = ray_error(header("KDRR", 1, 0, 0xFFFFFFFFu, 0));
    EXPECT_EQ(e.code, DecodeErrorCode::kTooManyRays);
    EXPECT_EQ(e.detail, "header says 4294967295 rays, limit is 67108864");
    DecodeLimits small;
    small.max_rays = 2;
    const Ray rays[] = {kRay0, kRay1, kRay0};
    e = ray_error(encode_rays(rays, false), small);
    EXPECT_EQ(e.code, DecodeErrorCode::kTooManyRays);
    EXPECT_EQ(e.detail, "header says 3 rays, limit is 2");
    EXPECT_TRUE(decode_rays(encode_rays(std::span(rays, 2), false), small).ok());
    const auto hits = decode_hits(header("KDRH", 1, 0, 3, 0), small);
    ASSERT_FALSE(hits.ok());
    EXPECT_EQ(hits.error().code, DecodeErrorCode::kTooManyRays);
    const auto occ = decode_occlusion(header("KDRO", 1, 0, 3, 0), small);
    ASSERT_FALSE(occ.ok());
    EXPECT_EQ(occ.error().code, DecodeErrorCode::kTooManyRays);
}

TEST(RayBatchDecodeError, NonFiniteRejectedOnRequestNamingRayAndField) {
    DecodeLimits strict;
    strict.reject_non_finite = true;
    const char* names[] = {"ox", "oy", "oz", "tmin", "dx", "dy", "dz", "tmax"};
    for (int field = 0; field < 8; ++field) {
        std::vector<Ray> rays(20, kRay0);
        auto bits = std::bit_cast<std::array<float, 8>>(rays[17]);
        bits[static_cast<size_t>(field)] = std::nanf("");
        rays[17] = std::bit_cast<Ray>(bits);
        bits[static_cast<size_t>(field)] = std::nanf("");
        rays[19] = std::bit_cast<Ray>(bits);  // a later bad ray is not the one reported
        const auto e = ray_error(encode_rays(rays, false), strict);
        EXPECT_EQ(e.code, DecodeErrorCode::kNonFiniteRay);
        EXPECT_EQ(e.detail, std::string("ray 17: field ") + names[field] + " is NaN");
    }
    std::vector<Ray> rays = {kRay0, kRay0};
    rays[1].dy = -kInf;
    EXPECT_EQ(ray_error(encode_rays(rays, false), strict).detail, "ray 1: field dy is -inf");
    rays[1].dy = 0;
    rays[1].ox = kInf;
    EXPECT_EQ(ray_error(encode_rays(rays, false), strict).detail, "ray 1: field ox is +inf");
}

TEST(RayBatchDecodeError, InfiniteRangeBoundsAreNotNonFiniteRays) {
    // tmax = +inf is the ordinary unbounded ray; the engine traces it.
    DecodeLimits strict;
    strict.reject_non_finite = true;
    Ray r = kRay1;
    r.tmin = -kInf;
    const Ray rays[] = {kRay1, r};
    const auto batch = decode_rays(encode_rays(rays, true), strict);
    ASSERT_TRUE(batch.ok()) << batch.error().to_string();
    EXPECT_EQ(batch->rays[0].tmax, kInf);
}

TEST(RayBatchDecodeError, OcclusionBytesMustBeZeroOrOne) {
    auto body = from_hex(kGoldenOcclusion);
    body[17] = std::byte{2};
    const auto occ = decode_occlusion(body);
    ASSERT_FALSE(occ.ok());
    EXPECT_EQ(occ.error().code, DecodeErrorCode::kBadOcclusionValue);
    EXPECT_EQ(occ.error().detail, "ray 1: occlusion value 2, expected 0 or 1");
}

TEST(RayBatchDecodeError, ChecksRunInHeaderOrder) {
    // Every field wrong at once: the magic is reported first, then version, flags, reserved,
    // count, length.
    EXPECT_EQ(ray_error(header("XXXX", 9, 4, 0xFFFFFFFF, 1)).code, DecodeErrorCode::kBadMagic);
    EXPECT_EQ(ray_error(header("KDRR", 9, 4, 0xFFFFFFFF, 1)).code, DecodeErrorCode::kBadVersion);
    EXPECT_EQ(ray_error(header("KDRR", 1, 4, 0xFFFFFFFF, 1)).code, DecodeErrorCode::kBadFlags);
    EXPECT_EQ(ray_error(header("KDRR", 1, 1, 0xFFFFFFFF, 1)).code, DecodeErrorCode::kBadReserved);
    EXPECT_EQ(ray_error(header("KDRR", 1, 1, 0xFFFFFFFF, 0)).code, DecodeErrorCode::kTooManyRays);
    EXPECT_EQ(ray_error(header("KDRR", 1, 1, 5, 0)).code, DecodeErrorCode::kLengthMismatch);
}

}  // namespace
}  // namespace kdrt::proto
