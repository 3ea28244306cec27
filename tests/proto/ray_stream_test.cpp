// The incremental KDRR decoder and the in-place answers: RayStreamDecoder gives decode_rays'
// verdict (same code, same detail) for every body however it is cut into pieces, fed or read in
// place; write_answer_in_place gives encode_hits' / encode_occlusion's bytes.

#include <gtest/gtest.h>

#include <bit>
#include <cmath>
#include <cstring>
#include <limits>
#include <optional>
#include <vector>

#include "kdrt/proto/ray_batch.h"
#include "test_util.h"

namespace kdrt::proto {
namespace {

/// How a test cuts a body into pieces.
enum class Cut { kWhole, kBytes, kOdd, kRandom };

struct Outcome {
    bool ok = false;
    DecodeErrorCode code{};
    std::string detail;
    std::vector<Ray> rays;
    bool occlusion = false;
};

/// Decodes `body` with a stream decoder, fed in pieces (or read in place into its window after
/// the header when `in_place`), optionally told the body's size in advance.
Outcome stream_decode(const std::vector<std::byte>& body, Cut cut, bool declare, bool in_place,
                      uint64_t seed,
                      DecodeLimits limits = {.max_rays = 1u << 20, .reject_non_finite = true}) {
    std::vector<Ray> storage;
    Outcome out;
    RayStreamDecoder decoder(
        limits,
        [&](uint32_t count, bool) {
            storage.assign(count, Ray{});
            return std::span<Ray>(storage);
        },
        declare ? std::optional<uint64_t>(body.size()) : std::nullopt);
    kdrt::test::Rng rng(seed);
    size_t at = 0;
    while (at < body.size()) {
        size_t n = body.size() - at;
        if (cut == Cut::kBytes) n = 1;
        if (cut == Cut::kOdd) n = std::min<size_t>(n, 37);
        if (cut == Cut::kRandom) n = std::min<size_t>(n, 1 + rng.below(5000));
        const std::span<std::byte> window = decoder.next_window();
        if (in_place && !window.empty()) {
            n = std::min(n, window.size());
            std::memcpy(window.data(), body.data() + at, n);
            if (!decoder.commit(n)) break;
        } else if (!decoder.feed(std::span(body).subspan(at, n))) {
            break;
        }
        EXPECT_LE(decoder.rays_ready(), decoder.count());
        at += n;
    }
    auto verdict = decoder.finish();
    if (at < body.size()) {
        EXPECT_FALSE(verdict) << "feed refused but finish accepted";
    }
    out.ok = static_cast<bool>(verdict);
    if (!verdict) {
        out.code = verdict.error().code;
        out.detail = verdict.error().detail;
    } else {
        EXPECT_EQ(decoder.rays_ready(), decoder.count());
        out.rays = storage;
        out.occlusion = decoder.occlusion();
    }
    return out;
}

/// Every way of streaming `body` agrees with decode_rays on it. (A refusal found early, with the
/// size declared, may name the same problem before the rest arrives: same code and detail.)
void expect_like_decode_rays(const std::vector<std::byte>& body, const std::string& what) {
    SCOPED_TRACE(what);
    const DecodeLimits limits{.max_rays = 1u << 20, .reject_non_finite = true};
    auto want = decode_rays(body, limits);
    for (const Cut cut : {Cut::kWhole, Cut::kBytes, Cut::kOdd, Cut::kRandom}) {
        if (cut == Cut::kBytes && body.size() > 20000) continue;
        for (const bool declare : {false, true}) {
            for (const bool in_place : {false, true}) {
                SCOPED_TRACE(testing::Message() << "cut " << static_cast<int>(cut) << " declare "
                                                << declare << " in_place " << in_place);
                const Outcome got = stream_decode(body, cut, declare, in_place, 7, limits);
                ASSERT_EQ(got.ok, static_cast<bool>(want)) << got.detail;
                if (!want) {
                    EXPECT_EQ(got.code, want.error().code);
                    EXPECT_EQ(got.detail, want.error().detail);
                } else {
                    EXPECT_EQ(got.occlusion, want->occlusion);
                    ASSERT_EQ(got.rays.size(), want->rays.size());
                    if (!got.rays.empty()) {
                        EXPECT_EQ(std::memcmp(got.rays.data(), want->rays.data(),
                                              got.rays.size() * sizeof(Ray)),
                                  0);
                    }
                }
            }
        }
    }
}

TEST(RayStreamDecoder, AgreesWithDecodeRaysOnValidBatches) {
    for (const size_t count : {size_t{0}, size_t{1}, size_t{3}, size_t{1000}}) {
        const std::vector<Ray> rays = kdrt::test::rays_towards_unit_cube(count, count + 1);
        expect_like_decode_rays(encode_rays(rays, false), std::to_string(count) + " rays");
        expect_like_decode_rays(encode_rays(rays, true), std::to_string(count) + " occlusion rays");
    }
}

TEST(RayStreamDecoder, AgreesWithDecodeRaysOnEveryRefusal) {
    const std::vector<Ray> rays = kdrt::test::rays_towards_unit_cube(50, 3);
    const std::vector<std::byte> good = encode_rays(rays, false);
    auto with = [&](size_t offset, std::initializer_list<uint8_t> bytes) {
        std::vector<std::byte> b = good;
        for (uint8_t v : bytes) b[offset++] = std::byte{v};
        return b;
    };
    expect_like_decode_rays({}, "empty");
    expect_like_decode_rays(std::vector<std::byte>(good.begin(), good.begin() + 15), "15 bytes");
    expect_like_decode_rays(with(0, {'A', 'B', 'C', 'D'}), "bad magic");
    expect_like_decode_rays(with(4, {2, 0}), "bad version");
    expect_like_decode_rays(with(6, {3, 0}), "bad flags");
    expect_like_decode_rays(with(12, {7}), "bad reserved");
    expect_like_decode_rays(with(8, {0xff, 0xff, 0xff, 0xff}), "too many rays");
    expect_like_decode_rays(std::vector<std::byte>(good.begin(), good.end() - 1), "one byte short");
    std::vector<std::byte> longer = good;
    longer.resize(good.size() + 33);
    expect_like_decode_rays(longer, "33 bytes too long");
    // Non-finite rays: the first one by index is named, whichever field.
    const char* fields[] = {"ox", "oy", "oz", "tmin", "dx", "dy", "dz", "tmax"};
    for (int field = 0; field < 8; ++field) {
        std::vector<Ray> bad = rays;
        float* f = reinterpret_cast<float*>(&bad[17]);
        f[field] = std::numeric_limits<float>::quiet_NaN();
        reinterpret_cast<float*>(&bad[40])[0] = std::numeric_limits<float>::infinity();
        const std::vector<std::byte> body = encode_rays(bad, false);
        expect_like_decode_rays(body, std::string("NaN in ") + fields[field]);
        auto want = decode_rays(body, {.reject_non_finite = true});
        ASSERT_FALSE(want);
        EXPECT_EQ(want.error().detail, "ray 17: field " + std::string(fields[field]) + " is NaN");
    }
    // Infinite tmin/tmax stay legal; an infinite direction does not.
    std::vector<Ray> inf = rays;
    inf[5].tmax = std::numeric_limits<float>::infinity();
    inf[6].tmin = -std::numeric_limits<float>::infinity();
    expect_like_decode_rays(encode_rays(inf, false), "infinite range");
    inf[9].dz = -std::numeric_limits<float>::infinity();
    expect_like_decode_rays(encode_rays(inf, false), "infinite direction");
    // A refused ray and a wrong length: the length is reported, as decode_rays does.
    std::vector<Ray> nan_rays = rays;
    nan_rays[2].dx = std::numeric_limits<float>::quiet_NaN();
    std::vector<std::byte> nan_short = encode_rays(nan_rays, false);
    nan_short.pop_back();
    expect_like_decode_rays(nan_short, "NaN and short");
}

TEST(RayStreamDecoder, ADeclaredSizeRefusesEarly) {
    const std::vector<std::byte> body =
        encode_rays(kdrt::test::rays_towards_unit_cube(100, 5), false);
    RayStreamDecoder decoder(
        {},
        [](uint32_t, bool) -> std::span<Ray> {
            ADD_FAILURE() << "no storage for a refused batch";
            return {};
        },
        body.size() + 32);
    EXPECT_FALSE(decoder.feed(std::span(body).first(16)));
    ASSERT_TRUE(decoder.error());
    EXPECT_EQ(decoder.error()->code, DecodeErrorCode::kLengthMismatch);
    EXPECT_EQ(decoder.error()->detail, "header says 100 rays (3216 bytes) but body has 3248 bytes");
    EXPECT_FALSE(decoder.feed(std::span(body).subspan(16)));  // later pieces only counted
    EXPECT_EQ(decoder.bytes_seen(), body.size());
}

TEST(RayStreamDecoder, StorageOfTheWrongSizeIsAProgrammingError) {
    const std::vector<std::byte> body =
        encode_rays(kdrt::test::rays_towards_unit_cube(4, 5), false);
    std::vector<Ray> storage(3);
    RayStreamDecoder decoder({}, [&](uint32_t, bool) { return std::span<Ray>(storage); });
    EXPECT_THROW((void)decoder.feed(body), std::logic_error);
}

TEST(RayBatchAnswers, WrittenInPlaceTheyEqualTheEncoders) {
    kdrt::test::Rng rng(11);
    for (const uint32_t count : {0u, 1u, 5u, 1000u}) {
        std::vector<Hit> hits(count);
        std::vector<uint8_t> occluded(count);
        for (uint32_t i = 0; i < count; ++i) {
            hits[i] = i % 3 ? Hit{rng.uniform(), i * 7, rng.uniform(), rng.uniform()} : Hit{};
            occluded[i] =
                static_cast<uint8_t>(rng.below(3));  // 2: any nonzero value is 1 on the wire
        }
        // Storage aligned for Hit records after the 16-byte header, as the server's buffers are.
        std::vector<Hit> storage(1 + size_t{count});
        std::byte* body = reinterpret_cast<std::byte*>(storage.data());
        ASSERT_EQ(answer_body_size(AnswerKind::kHits, count), 16 + 16 * uint64_t{count});
        const std::span<Hit> records = answer_hit_records(body, count);
        ASSERT_EQ(records.size(), count);
        EXPECT_EQ(reinterpret_cast<std::byte*>(records.data()), body + kBatchHeaderBytes);
        std::copy(hits.begin(), hits.end(), records.begin());
        size_t size = write_answer_in_place(body, AnswerKind::kHits, count);
        EXPECT_EQ(std::vector<std::byte>(body, body + size), encode_hits(hits));
        const std::span<uint8_t> flags = answer_occlusion_records(body, count);
        std::copy(occluded.begin(), occluded.end(), flags.begin());
        size = write_answer_in_place(body, AnswerKind::kOcclusion, count);
        EXPECT_EQ(size, answer_body_size(AnswerKind::kOcclusion, count));
        EXPECT_EQ(std::vector<std::byte>(body, body + size), encode_occlusion(occluded));
    }
}

TEST(RayBatchSizes, NameTheKdrrArithmetic) {
    EXPECT_EQ(kdrr_body_size(0), 16u);
    EXPECT_EQ(kdrr_body_size(3), 16u + 3 * 32);
    EXPECT_EQ(kdrr_body_size(0xffffffffu), 16 + 32 * uint64_t{0xffffffffu});
    EXPECT_EQ(answer_record_size(AnswerKind::kHits), kHitRecordBytes);
    EXPECT_EQ(answer_record_size(AnswerKind::kOcclusion), kOcclusionRecordBytes);
    EXPECT_EQ(answer_body_size(AnswerKind::kOcclusion, 5), 21u);
    EXPECT_EQ(encode_rays(std::vector<Ray>(7), false).size(), kdrr_body_size(7));
}

}  // namespace
}  // namespace kdrt::proto
