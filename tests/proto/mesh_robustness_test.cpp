// Robustness: every prefix of a small valid file, and single/multi-byte mutations of it, must
// parse to a well-formed mesh or fail with an error - never crash, hang or read out of bounds
// (the sanitizer build runs these too).

#include <gtest/gtest.h>

#include <random>

#include "kdrt/proto/file_io.h"
#include "kdrt/proto/mesh_io.h"
#include "proto_test_util.h"

namespace kdrt::proto {
namespace {

using test::bytes_of;

struct Sample {
    std::string name;
    MeshFormat format;
    std::vector<std::byte> bytes;
};

std::vector<Sample> samples() {
    const Mesh tet = test::tetrahedron();
    std::vector<Sample> out;
    out.push_back(
        {"obj", MeshFormat::kObj,
         bytes_of("# sample\nv 0 0 0\nv 1 0 0\nv 0 1 0 1\nv 0 0 1.5\nvt 0 0\nvn 0 0 1\ng g\n"
                  "f 1/1/1 3/1/1 2/1/1\nf -4//-1 -3//-1 -1//-1\nf 1 4 3 \\\n 2\n")});
    out.push_back({"off", MeshFormat::kOff,
                   bytes_of("OFF\n# c\n4 3 6\n0 0 0\n1 0 0\n0 1 0\n0 0 1.5\n3 0 2 1\n4 0 1 3 2\n3 "
                            "1 2 3 255 0 0\n")});
    out.push_back(
        {"ply_ascii", MeshFormat::kPly,
         bytes_of("ply\nformat ascii 1.0\nelement vertex 4\nproperty float x\nproperty float y\n"
                  "property float z\nproperty list uchar int extra\nelement face 2\n"
                  "property list uchar int vertex_indices\nend_header\n"
                  "0 0 0 0\n1 0 0 1 5\n0 1 0 0\n0 0 1.5 2 1 2\n3 0 2 1\n4 0 1 3 2\n")});
    out.push_back(
        {"ply_le", MeshFormat::kPly, write_mesh(tet, MeshFormat::kPly, {.binary = true})});
    out.push_back({"ply_be", MeshFormat::kPly,
                   write_mesh(tet, MeshFormat::kPly, {.binary = true, .big_endian = true})});
    out.push_back(
        {"stl_ascii", MeshFormat::kStl, write_mesh(tet, MeshFormat::kStl, {.binary = false})});
    out.push_back(
        {"stl_binary", MeshFormat::kStl, write_mesh(tet, MeshFormat::kStl, {.binary = true})});
    out.push_back({"raw", MeshFormat::kRaw, write_mesh(tet, MeshFormat::kRaw)});
    return out;
}

class MeshRobustness : public ::testing::TestWithParam<Sample> {};

TEST_P(MeshRobustness, FullFileParses) {
    const Sample& s = GetParam();
    const auto r = parse_mesh(s.bytes, s.format);
    ASSERT_TRUE(r.ok()) << r.error().message;
    test::expect_well_formed(*r);
    EXPECT_GE(r->triangle_count(), 3u);
}

TEST_P(MeshRobustness, EveryPrefixIsAnErrorOrAWellFormedMesh) {
    const Sample& s = GetParam();
    size_t errors = 0;
    for (size_t n = 0; n < s.bytes.size(); ++n) {
        // Copy, so that ASan sees reads past the prefix as heap overflows.
        const std::vector<std::byte> prefix(s.bytes.begin(),
                                            s.bytes.begin() + static_cast<ptrdiff_t>(n));
        const auto r = parse_mesh(prefix, s.format);
        if (r.ok()) {
            test::expect_well_formed(*r);
        } else {
            ++errors;
            EXPECT_FALSE(r.error().message.empty()) << "prefix " << n;
        }
    }
    // Most prefixes cut a record or a count and must be refused.
    EXPECT_GT(errors, s.bytes.size() / 2);
}

TEST_P(MeshRobustness, EverySingleByteMutation) {
    const Sample& s = GetParam();
    constexpr unsigned char kValues[] = {0x00, 0xFF, 0x80, '0',  '9', '-', '+', '.',
                                         'e',  'n',  ' ',  '\n', '/', '#', 0x7F};
    std::vector<std::byte> mutated = s.bytes;
    for (size_t i = 0; i < mutated.size(); ++i) {
        const std::byte original = mutated[i];
        for (unsigned char v : kValues) {
            mutated[i] = static_cast<std::byte>(v);
            const auto r = parse_mesh(mutated, s.format);
            if (r.ok()) test::expect_well_formed(*r);
        }
        mutated[i] = original;
    }
}

TEST_P(MeshRobustness, RandomMultiByteMutations) {
    const Sample& s = GetParam();
    const uint64_t seed = test::test_seed();
    SCOPED_TRACE(testing::Message() << "seed=" << seed);
    std::mt19937_64 rng(seed);
    for (int round = 0; round < 2000; ++round) {
        std::vector<std::byte> mutated = s.bytes;
        const int edits = 1 + static_cast<int>(rng() % 8);
        for (int k = 0; k < edits && !mutated.empty(); ++k) {
            const size_t at = rng() % mutated.size();
            switch (rng() % 3) {
                case 0:
                    mutated[at] = static_cast<std::byte>(rng());
                    break;
                case 1:
                    mutated.erase(mutated.begin() + static_cast<ptrdiff_t>(at));
                    break;
                default:
                    mutated.insert(mutated.begin() + static_cast<ptrdiff_t>(at),
                                   static_cast<std::byte>(rng()));
                    break;
            }
        }
        const auto r = parse_mesh(mutated, s.format);
        if (r.ok()) test::expect_well_formed(*r);
    }
}

INSTANTIATE_TEST_SUITE_P(AllFormats, MeshRobustness, ::testing::ValuesIn(samples()),
                         [](const ::testing::TestParamInfo<Sample>& info) {
                             return info.param.name;
                         });

TEST(MeshRobustnessBunny, TruncatedBunnyNamesTheEndOfFile) {
    const auto bytes = read_file_bytes(test::test_data("bunny00.off"));
    ASSERT_TRUE(bytes.ok()) << bytes.error();
    // Lines: 1 "OFF", 2 counts, 3 blank, vertices from line 4. Keep the header and 1000 vertices.
    size_t cut = 0;
    for (int newlines = 0; newlines < 3 + 1000; ++cut)
        newlines += (*bytes)[cut] == std::byte{'\n'} ? 1 : 0;
    const auto e = test::parse_error(std::span(*bytes).first(cut), MeshFormat::kOff);
    EXPECT_EQ(e.line, 3u + 1000 + 1);
    EXPECT_EQ(e.message, "line 1004: unexpected end of file: expected 37706 vertices, found 1000");

    const uint64_t seed = test::test_seed();
    SCOPED_TRACE(testing::Message() << "seed=" << seed);
    std::mt19937_64 rng(seed);
    for (int i = 0; i < 20; ++i) {
        const size_t n = rng() % (bytes->size() - 1);  // any cut but the final newline
        const auto r = parse_mesh(std::span(*bytes).first(n), MeshFormat::kOff);
        EXPECT_FALSE(r.ok()) << "cut at " << n;
    }
}

}  // namespace
}  // namespace kdrt::proto
