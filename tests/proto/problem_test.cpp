#include "kdrt/proto/problem.h"

#include <gtest/gtest.h>

#include <set>

namespace kdrt::proto {
namespace {

TEST(Problem, EncodesRfc9457Members) {
    Problem p;
    p.kind = ProblemKind::kMeshParseError;
    p.detail = "line 4: face \"x\"\n";
    p.instance = "/v1/meshes";
    p.line = 4;
    p.request_id = "00000000000000ff";
    EXPECT_EQ(encode_problem(p),
              "{\"type\":\"urn:kdrt:problem:mesh-parse-error\",\"title\":\"Mesh parse "
              "error\",\"status\":422,"
              "\"detail\":\"line 4: face \\\"x\\\"\\n\",\"instance\":\"/v1/meshes\",\"line\":4,"
              "\"request_id\":\"00000000000000ff\"}");
}

TEST(Problem, RoundTripsEveryKind) {
    std::set<std::string_view> types;
    for (int k = 0; k <= static_cast<int>(kLastProblemKind); ++k) {
        Problem p;
        p.kind = static_cast<ProblemKind>(k);
        p.detail = "detail " + std::to_string(k);
        p.code.assign(1, 'c');  // (operator=("c") trips a GCC 12 -Wrestrict false positive)
        p.byte_offset = 12;
        p.limit = 99;
        p.retry_after = 1;
        auto back = decode_problem(encode_problem(p));
        ASSERT_TRUE(back) << back.error();
        EXPECT_EQ(back->kind, p.kind);
        EXPECT_EQ(back->detail, p.detail);
        EXPECT_EQ(back->code, "c");
        EXPECT_EQ(back->byte_offset, 12u);
        EXPECT_EQ(back->limit, 99u);
        EXPECT_EQ(back->retry_after, 1u);
        EXPECT_FALSE(back->line.has_value());
        types.insert(problem_type(p.kind));
        EXPECT_GE(problem_status(p.kind), 400);
    }
    EXPECT_EQ(types.size(), static_cast<size_t>(kLastProblemKind) + 1);  // unique types
}

TEST(Problem, StatusesMatchTheApi) {
    EXPECT_EQ(problem_status(ProblemKind::kBadRayBatch), 400);
    EXPECT_EQ(problem_status(ProblemKind::kUnauthorized), 401);
    EXPECT_EQ(problem_status(ProblemKind::kUnknownMesh), 404);
    EXPECT_EQ(problem_status(ProblemKind::kMethodNotAllowed), 405);
    EXPECT_EQ(problem_status(ProblemKind::kRequestTimeout), 408);
    EXPECT_EQ(problem_status(ProblemKind::kHeadersTooLarge), 431);
    EXPECT_EQ(problem_status(ProblemKind::kJobNotDone), 409);
    EXPECT_EQ(problem_status(ProblemKind::kPayloadTooLarge), 413);
    EXPECT_EQ(problem_status(ProblemKind::kUnsupportedMediaType), 415);
    EXPECT_EQ(problem_status(ProblemKind::kMeshParseError), 422);
    EXPECT_EQ(problem_status(ProblemKind::kInternal), 500);
    EXPECT_EQ(problem_status(ProblemKind::kOverCapacity), 503);
}

TEST(Problem, DecodeRefusesOtherDocuments) {
    EXPECT_FALSE(decode_problem("nope"));
    EXPECT_FALSE(decode_problem("[]"));
    EXPECT_FALSE(decode_problem("{\"type\":\"about:blank\",\"status\":400,\"detail\":\"x\"}"));
    EXPECT_FALSE(decode_problem(
        "{\"type\":\"urn:kdrt:problem:unknown-mesh\",\"status\":400,\"detail\":\"x\"}"));
    EXPECT_FALSE(decode_problem("{\"type\":\"urn:kdrt:problem:unknown-mesh\",\"status\":404}"));
}

}  // namespace
}  // namespace kdrt::proto
