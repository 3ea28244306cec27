// BatchIngest in process, without HTTP: KDRR bodies fed in arbitrary pieces (or received in
// place, as from a socket) give the bytes of the non-streamed path (decode_rays, the engine,
// encode_hits / encode_occlusion); refusals carry decode_rays' error and the drain-or-close
// verdict; pooled buffers go back to the pool on every exit.

#include "http/batch_ingest.h"

#include <gtest/gtest.h>

#include <algorithm>
#include <cstring>
#include <limits>
#include <optional>
#include <vector>

#include "kdrt/trace.h"
#include "test_util.h"

namespace kdrt::server {
namespace {

using Kind = IngestFailure::Kind;

/// How a test delivers a body.
enum class Delivery {
    kWhole,    ///< one feed()
    kRandom,   ///< feed() in random pieces of 1..5000 bytes
    kBytes,    ///< feed() byte by byte (small bodies only)
    kReceive,  ///< first piece fed, the rest through receive_rest() in random sizes
};

class BatchIngestTest : public ::testing::Test {
protected:
    static void SetUpTestSuite() {
        test::Rng rng(5);
        tree_ = new KdTree(build_kdtree(test::random_soup(rng, 2000)));
        compute_ = new Compute(2);
    }
    static void TearDownTestSuite() {
        delete tree_;
        delete compute_;
    }

    /// The answer of the non-streamed path for a valid body.
    static std::vector<std::byte> expected(const std::vector<std::byte>& body) {
        auto batch = proto::decode_rays(body, {.reject_non_finite = true});
        EXPECT_TRUE(batch);
        if (batch->occlusion) {
            std::vector<uint8_t> occluded(batch->rays.size());
            compute_->occluded(*tree_, batch->rays, occluded);
            return proto::encode_occlusion(occluded);
        }
        std::vector<Hit> hits(batch->rays.size());
        compute_->intersect(*tree_, batch->rays, hits);
        return proto::encode_hits(hits);
    }

    struct Run {
        proto::Result<BatchAnswer, IngestFailure> result;
        uint64_t received;
    };

    /// Delivers `body` (cut after `available` bytes: the peer closes there) to an ingest, as the
    /// route does, declaring `declared` bytes (nullopt: chunked).
    Run ingest(const std::vector<std::byte>& body, Delivery delivery,
               std::optional<uint64_t> declared, uint32_t max_rays = 1u << 20,
               size_t available = std::numeric_limits<size_t>::max()) {
        available = std::min(available, body.size());
        BatchIngest in(*compute_, pool_, *tree_, max_rays, declared);
        test::Rng rng(17);
        size_t at = 0;
        bool read_ok = true;
        const auto piece_size = [&](size_t left) {
            if (delivery == Delivery::kWhole) return left;
            if (delivery == Delivery::kBytes) return size_t{1};
            return std::min<size_t>(left, 1 + rng.below(5000));
        };
        while (read_ok && at < available) {
            const size_t n = piece_size(available - at);
            read_ok = in.feed(std::span(body).subspan(at, n));
            at += n;
            if (delivery == Delivery::kReceive && read_ok && declared) {
                read_ok = in.receive_rest([&](std::byte* out, size_t size) -> ptrdiff_t {
                    const size_t n = std::min<size_t>({size, available - at, 1 + rng.below(70000)});
                    std::memcpy(out, body.data() + at, n);
                    at += n;
                    return static_cast<ptrdiff_t>(n);  // 0 once the peer "closed"
                });
                break;
            }
        }
        if (read_ok && at < body.size() && declared) read_ok = false;  // the peer closed early
        const uint64_t received = in.received();
        return {in.finish(read_ok), received};
    }

    /// Checks that `body` is answered with the non-streamed path's bytes, every way it arrives.
    void expect_answer(const std::vector<std::byte>& body, const std::string& what) {
        SCOPED_TRACE(what);
        const std::vector<std::byte> want = expected(body);
        for (const Delivery d :
             {Delivery::kWhole, Delivery::kRandom, Delivery::kBytes, Delivery::kReceive}) {
            if (d == Delivery::kBytes && body.size() > 20000) continue;
            for (const bool declare : {true, false}) {
                if (d == Delivery::kReceive && !declare) continue;
                SCOPED_TRACE(testing::Message()
                             << "delivery " << static_cast<int>(d) << " declared " << declare);
                Run run =
                    ingest(body, d, declare ? std::optional<uint64_t>(body.size()) : std::nullopt);
                ASSERT_TRUE(run.result) << run.result.error().error->detail;
                EXPECT_EQ(run.received, body.size());
                const BatchAnswer& a = *run.result;
                EXPECT_EQ(a.count, (body.size() - 16) / 32);
                ASSERT_EQ(a.size, want.size());
                EXPECT_TRUE(std::equal(want.begin(), want.end(), a.body.data()));
            }
        }
    }

    /// Checks that `body` is refused as decode_rays refuses it, with the drain-or-close verdict.
    void expect_refused(const std::vector<std::byte>& body, std::optional<uint64_t> declared,
                        Delivery delivery, bool close, const std::string& what) {
        SCOPED_TRACE(what);
        auto want = proto::decode_rays(body, {.max_rays = 1000, .reject_non_finite = true});
        ASSERT_FALSE(want);
        Run run = ingest(body, delivery, declared, 1000);
        ASSERT_FALSE(run.result);
        EXPECT_EQ(run.result.error().kind, Kind::kRefused);
        ASSERT_TRUE(run.result.error().error);
        EXPECT_EQ(run.result.error().error->code, want.error().code);
        EXPECT_EQ(run.result.error().error->detail, want.error().detail);
        EXPECT_EQ(run.result.error().close_connection, close);
    }

    static KdTree* tree_;
    static Compute* compute_;
    BufferPool pool_{size_t{1} << 30};
};
KdTree* BatchIngestTest::tree_ = nullptr;
Compute* BatchIngestTest::compute_ = nullptr;

TEST_F(BatchIngestTest, AnswersEqualTheNonStreamedPathHoweverTheBodyArrives) {
    for (const size_t count : {size_t{0}, size_t{1}, size_t{3}, size_t{1000}}) {
        const std::vector<Ray> rays = test::rays_towards_unit_cube(count, count + 1);
        expect_answer(proto::encode_rays(rays, false), std::to_string(count) + " rays");
        expect_answer(proto::encode_rays(rays, true), std::to_string(count) + " occlusion rays");
    }
    // Traced while arriving (BatchIngest::kStreamTraceRays and more), with a ragged tail.
    const std::vector<Ray> many =
        test::rays_towards_unit_cube(BatchIngest::kStreamTraceRays + 1234, 9);
    expect_answer(proto::encode_rays(many, false), "streamed trace");
    expect_answer(proto::encode_rays(many, true), "streamed occlusion trace");
}

TEST_F(BatchIngestTest, RefusalsCarryDecodeRaysErrorAndTheDrainVerdict) {
    const std::vector<std::byte> good =
        proto::encode_rays(test::rays_towards_unit_cube(50, 3), false);
    const auto with = [&](size_t offset, std::initializer_list<uint8_t> bytes) {
        std::vector<std::byte> b = good;
        for (uint8_t v : bytes) b[offset++] = std::byte{v};
        return b;
    };
    const std::optional<uint64_t> sized = good.size();
    // A small refused body of known size is drained: the connection stays usable.
    expect_refused(with(0, {'A', 'B', 'C', 'D'}), sized, Delivery::kRandom, false, "bad magic");
    expect_refused(with(4, {2, 0}), sized, Delivery::kBytes, false, "bad version");
    expect_refused(with(6, {3, 0}), sized, Delivery::kWhole, false, "bad flags");
    expect_refused(with(12, {7}), sized, Delivery::kReceive, false, "bad reserved");
    expect_refused(with(8, {0xe9, 0x03, 0, 0}), std::nullopt, Delivery::kRandom, true,
                   "1001 rays over max_rays 1000, chunked: not drained");
    // NaN rays: named by index, at arrival (declared size) or at the end (chunked).
    std::vector<Ray> nan_rays = test::rays_towards_unit_cube(50, 3);
    nan_rays[17].dy = std::numeric_limits<float>::quiet_NaN();
    nan_rays[30].ox = std::numeric_limits<float>::infinity();
    const std::vector<std::byte> nan_body = proto::encode_rays(nan_rays, false);
    expect_refused(nan_body, nan_body.size(), Delivery::kReceive, false, "NaN, declared");
    expect_refused(nan_body, std::nullopt, Delivery::kRandom, false, "NaN, chunked");
    // A chunked body that ends short of its header's count: a length mismatch.
    const std::vector<std::byte> short_body(good.begin(), good.end() - 5);
    expect_refused(short_body, std::nullopt, Delivery::kRandom, false, "chunked, short");
    // A declared size that cannot match the header's count is refused after the header.
    Run longer = ingest(good, Delivery::kBytes, good.size() + 32, 1000);
    ASSERT_FALSE(longer.result);
    EXPECT_EQ(longer.result.error().error->code, proto::DecodeErrorCode::kLengthMismatch);
    EXPECT_EQ(longer.result.error().error->detail,
              "header says 50 rays (1616 bytes) but body has 1648 bytes");
    // A refused body too large to drain: reading stops, the connection must close.
    Run big = ingest(with(0, {'X'}), Delivery::kBytes, uint64_t{100} << 20, 4u << 20);
    ASSERT_FALSE(big.result);
    EXPECT_EQ(big.result.error().kind, Kind::kRefused);
    EXPECT_TRUE(big.result.error().close_connection);
    EXPECT_EQ(big.received, 16u);  // nothing read past the refusal
}

TEST_F(BatchIngestTest, TruncatedAndOverLimitBodies) {
    const std::vector<std::byte> body =
        proto::encode_rays(test::rays_towards_unit_cube(500, 4), false);
    // The peer closes before the declared size: unreadable, close.
    for (const Delivery d : {Delivery::kRandom, Delivery::kReceive}) {
        Run cut = ingest(body, d, body.size(), 1u << 20, body.size() - 100);
        ASSERT_FALSE(cut.result);
        EXPECT_EQ(cut.result.error().kind, Kind::kUnreadable);
        EXPECT_TRUE(cut.result.error().close_connection);
        EXPECT_EQ(cut.received, body.size() - 100);
    }
    // Fewer than 16 bytes in a chunked body: too short.
    Run tiny = ingest(std::vector<std::byte>(body.begin(), body.begin() + 9), Delivery::kBytes,
                      std::nullopt);
    ASSERT_FALSE(tiny.result);
    EXPECT_EQ(tiny.result.error().error->code, proto::DecodeErrorCode::kTooShort);
    // More bytes than a batch of max_rays may have (chunked): too large, close.
    std::vector<std::byte> longer = body;
    longer.resize(proto::kdrr_body_size(500) + 1);
    Run over = ingest(longer, Delivery::kRandom, std::nullopt, 500);
    ASSERT_FALSE(over.result);
    EXPECT_EQ(over.result.error().kind, Kind::kTooLarge);
    EXPECT_TRUE(over.result.error().close_connection);
    // A declared size over the limit is seen before anything is read.
    BatchIngest in(*compute_, pool_, *tree_, 500, proto::kdrr_body_size(500) + 1);
    EXPECT_EQ(in.limit(), proto::kdrr_body_size(500));
    EXPECT_TRUE(in.declared_too_large());
}

TEST_F(BatchIngestTest, AChunkedBodyAsksForItsMemoryWhenItsHeaderArrives) {
    // Reserve is asked once, with the size the header declares, before the buffers are taken;
    // a refusal stops the body there (kOverBudget) and takes no buffer.
    const std::vector<std::byte> body =
        proto::encode_rays(test::rays_towards_unit_cube(300, 4), false);
    for (const bool admit : {true, false}) {
        SCOPED_TRACE(admit ? "admitted" : "refused");
        std::vector<uint64_t> asked;
        const size_t idle = pool_.idle_bytes();
        BatchIngest in(*compute_, pool_, *tree_, 1u << 20, std::nullopt, true,
                       [&](uint64_t body_bytes) {
                           asked.push_back(body_bytes);
                           EXPECT_EQ(pool_.idle_bytes(), idle) << "no buffer taken yet";
                           return admit;
                       });
        bool read_ok = true;
        size_t at = 0;
        for (; read_ok && at < body.size(); at += 7)
            read_ok = in.feed(std::span(body).subspan(at, std::min<size_t>(7, body.size() - at)));
        EXPECT_EQ(asked, std::vector<uint64_t>{body.size()});
        auto answer = in.finish(read_ok);
        if (admit) {
            ASSERT_TRUE(answer);
            const std::vector<std::byte> want = expected(body);
            ASSERT_EQ(answer->size, want.size());
            EXPECT_TRUE(std::equal(want.begin(), want.end(), answer->body.data()));
        } else {
            EXPECT_LE(at, 21u) << "reading stops at the header";
            ASSERT_FALSE(answer);
            EXPECT_EQ(answer.error().kind, Kind::kOverBudget);
            EXPECT_TRUE(answer.error().close_connection);
        }
    }
}

TEST_F(BatchIngestTest, BuffersGoBackToThePoolOnEveryExit) {
    // Large enough that both buffers are pooled (>= 1 MiB each) and the trace streams.
    const std::vector<Ray> rays = test::rays_towards_unit_cube(BatchIngest::kStreamTraceRays, 6);
    const std::vector<std::byte> body = proto::encode_rays(rays, false);
    const std::optional<uint64_t> sized = body.size();
    { Run warm = ingest(body, Delivery::kReceive, sized, 1u << 20); }
    const size_t idle = pool_.idle_bytes();
    ASSERT_GE(idle, body.size());  // the ray buffer and the answer buffer
    const auto expect_all_back = [&](const char* what) {
        EXPECT_EQ(pool_.idle_bytes(), idle) << what;
    };
    {
        Run ok = ingest(body, Delivery::kRandom, sized, 1u << 20);
        ASSERT_TRUE(ok.result);
        EXPECT_LT(pool_.idle_bytes(), idle) << "the answer holds its buffer";
    }
    expect_all_back("after an answer");
    std::vector<Ray> bad = rays;
    bad[rays.size() - 10].dz = std::numeric_limits<float>::quiet_NaN();
    const std::vector<std::byte> nan_body = proto::encode_rays(bad, false);
    { Run r = ingest(nan_body, Delivery::kReceive, sized, 1u << 20); }
    expect_all_back("after a refused ray (declared)");
    { Run r = ingest(nan_body, Delivery::kRandom, std::nullopt, 1u << 20); }
    expect_all_back("after a refused ray (chunked)");
    { Run r = ingest(body, Delivery::kReceive, sized, 1u << 20, body.size() / 2); }
    expect_all_back("after a body cut short");
    std::vector<std::byte> longer = body;
    longer.resize(body.size() + 64);
    { Run r = ingest(longer, Delivery::kRandom, std::nullopt, static_cast<uint32_t>(rays.size())); }
    expect_all_back("after a body over the limit");
    {
        // Destroyed without finish() (an exception in the route).
        BatchIngest in(*compute_, pool_, *tree_, 1u << 20, sized);
        EXPECT_TRUE(in.feed(std::span(body).first(body.size() / 2)));
    }
    expect_all_back("after an abandoned ingest");
}

}  // namespace
}  // namespace kdrt::server
