// The renderer: images equal the brute-force oracle's, regions stitch and thread counts agree bit
// for bit, shading values match closed-form answers, and bad settings fail naming the field.

#include "kdrt/render.h"

#include <gtest/gtest.h>
#include <tbb/task_arena.h>

#include <algorithm>
#include <atomic>
#include <cmath>
#include <cstdio>
#include <cstring>
#include <fstream>
#include <set>
#include <stdexcept>
#include <string>
#include <unordered_map>
#include <vector>

#include "kdrt/proto/mesh_io.h"
#include "kdrt/trace.h"
#include "oracle.h"
#include "render_internal.h"
#include "test_util.h"

namespace kdrt::test {
namespace {

// ---------------------------------------------------------------------------------------------
// Helpers

const Mesh& bunny() {
    static const Mesh mesh = [] {
        auto loaded = proto::load_mesh_file(std::string(KDRT_TEST_DATA_DIR) + "/bunny00.off");
        if (!loaded) throw std::runtime_error(loaded.error().to_string());
        return std::move(loaded).value();
    }();
    return mesh;
}

const KdTree& bunny_tree() {
    static const KdTree tree = build_kdtree(bunny());
    return tree;
}

/// The quad [-1, 1]^2 in the plane z = 0, two triangles (ids 0 and 1), normal +z.
Mesh unit_quad(float z = 0.0f) {
    Mesh m;
    const uint32_t a = add_vertex(m, {-1, -1, z}), b = add_vertex(m, {1, -1, z}),
                   c = add_vertex(m, {1, 1, z}), d = add_vertex(m, {-1, 1, z});
    add_indices(m, a, b, c);
    add_indices(m, a, c, d);
    return m;
}

CameraSpec looking_down_z(Vec3 eye, float fov_deg = 40.0f) {
    CameraSpec spec;
    spec.eye = eye;
    spec.look_at = {eye.x, eye.y, eye.z - 1.0f};
    spec.up = {0, 1, 0};
    spec.fov_deg = fov_deg;
    return spec;
}

/// (x, y) pixel value, channel c.
float at(const Image& image, uint32_t x, uint32_t y, uint32_t c) {
    return image.pixels[(size_t{y} * image.width + x) * image.channels + c];
}

bool same_bits(const Image& a, const Image& b) {
    return a.width == b.width && a.height == b.height && a.channels == b.channels &&
           a.pixels.size() == b.pixels.size() &&
           std::memcmp(a.pixels.data(), b.pixels.data(), a.pixels.size() * sizeof(float)) == 0;
}

void expect_same_image(const Image& got, const Image& want) {
    ASSERT_EQ(got.width, want.width);
    ASSERT_EQ(got.height, want.height);
    ASSERT_EQ(got.channels, want.channels);
    ASSERT_EQ(got.pixels.size(), want.pixels.size());
    size_t differences = 0;
    for (size_t i = 0; i < got.pixels.size(); ++i) {
        if (std::memcmp(&got.pixels[i], &want.pixels[i], sizeof(float)) == 0) continue;
        if (++differences <= 5) {
            const size_t pixel = i / got.channels;
            ADD_FAILURE() << "pixel (" << pixel % got.width << ", " << pixel / got.width
                          << ") channel " << i % got.channels << ": " << got.pixels[i] << " vs "
                          << want.pixels[i];
        }
    }
    EXPECT_EQ(differences, 0u);
}

/// Asserts that render(settings) throws RenderError whose message names `field`.
void expect_render_error(const KdTree& tree, const RenderSettings& settings,
                         const std::string& field) {
    try {
        const Image image = render(tree, settings);
        ADD_FAILURE() << "no RenderError; expected one naming '" << field << "'";
    } catch (const RenderError& e) {
        EXPECT_NE(std::string(e.what()).find(field), std::string::npos)
            << "message '" << e.what() << "' does not name '" << field << "'";
    }
    // validate_render_settings agrees without a tree.
    EXPECT_THROW(validate_render_settings(settings), RenderError) << field;
}

/// The brute-force oracle behind the renderer's TraceFunctions hook. FilteredBruteForce gives
/// exactly brute_force_intersect's answers (OracleSelfCheck.FilteredBruteForceEqualsPlain), and an
/// occlusion query is "the closest hit exists within [tmin, tmax]" (brute_force_occluded's
/// answer). Answers already computed for a ray set (remember()) are looked up by the ray's bits,
/// so several renders of the same camera rays pay for the brute force once.
class BruteForce {
public:
    explicit BruteForce(const KdTree& tree) : tris_(triangles_by_id(tree)), filtered_(tris_) {}

    void remember(std::span<const Ray> rays, std::span<const Hit> hits) {
        for (size_t i = 0; i < rays.size(); ++i) known_.emplace(key(rays[i]), hits[i]);
    }
    [[nodiscard]] Hit intersect(const Ray& ray) const {
        const auto it = known_.find(key(ray));
        return it != known_.end() ? it->second : filtered_.intersect(ray);
    }
    [[nodiscard]] detail::TraceFunctions functions() const {
        return {this, &intersect_all, &occluded_all};
    }

private:
    static std::string key(const Ray& ray) {
        return std::string(reinterpret_cast<const char*>(&ray), sizeof ray);
    }
    static void intersect_all(const void* self, std::span<const Ray> rays,
                              std::span<Hit> hits) noexcept {
        const auto& oracle = *static_cast<const BruteForce*>(self);
        for (size_t i = 0; i < rays.size(); ++i) hits[i] = oracle.intersect(rays[i]);
    }
    static void occluded_all(const void* self, std::span<const Ray> rays,
                             std::span<uint8_t> out) noexcept {
        const auto& oracle = *static_cast<const BruteForce*>(self);
        for (size_t i = 0; i < rays.size(); ++i)
            out[i] = oracle.intersect(rays[i]).is_hit() ? 1 : 0;
    }

    std::vector<TriVerts> tris_;  // by mesh id; filtered_ refers to it
    FilteredBruteForce filtered_;
    std::unordered_map<std::string, Hit> known_;
};

Image render_brute_force(const KdTree& tree, const RenderSettings& settings) {
    const BruteForce oracle(tree);
    return detail::render_with(tree, settings, oracle.functions());
}

/// Pixels whose camera ray (`rays`, with the oracle's answers `want`) has an exact tie at its
/// closest t, broken differently by the tree and the oracle (both legitimate: see
/// expect_same_hits in oracle.h). The only accepted difference.
std::set<size_t> tie_pixels(const KdTree& tree, std::span<const Ray> rays,
                            std::span<const Hit> want) {
    std::set<size_t> ties;
    std::vector<Hit> hits(rays.size());
    intersect_single(tree, rays, hits);
    for (size_t i = 0; i < rays.size(); ++i) {
        if (hits[i].prim == want[i].prim || hits[i].t != want[i].t || !hits[i].is_hit()) continue;
        const Hit alone =
            brute_force_intersect(std::span(&tree.triangle(hits[i].prim), 1), rays[i]);
        if (alone.t == hits[i].t) ties.insert(i);
    }
    return ties;
}

/// The tree render equals the oracle render bit for bit, except at the exact-tie pixels `ties`.
/// Returns the number of pixels the camera rays hit (so callers can check the image is not
/// trivial).
size_t expect_matches_oracle(const KdTree& tree, const RenderSettings& settings,
                             const BruteForce& oracle, const std::set<size_t>& ties) {
    const Image got = render(tree, settings);
    const Image want = detail::render_with(tree, settings, oracle.functions());
    EXPECT_EQ(got.width, want.width);
    EXPECT_EQ(got.height, want.height);
    EXPECT_EQ(got.channels, want.channels);
    if (got.pixels.size() != want.pixels.size()) return 0;
    size_t mismatches = 0, tie_mismatches = 0, hit_pixels = 0;
    const size_t pixels = size_t{got.width} * got.height;
    for (size_t p = 0; p < pixels; ++p) {
        const float* a = &got.pixels[p * got.channels];
        const float* b = &want.pixels[p * want.channels];
        if (got.channels == 4) hit_pixels += a[3] > 0.0f;
        if (std::memcmp(a, b, got.channels * sizeof(float)) == 0) continue;
        if (ties.count(p)) {
            ++tie_mismatches;
            continue;
        }
        if (++mismatches <= 5) {
            ADD_FAILURE() << "pixel (" << p % got.width << ", " << p / got.width << "): (" << a[0]
                          << ", " << a[1] << ", " << a[2] << ") vs brute force (" << b[0] << ", "
                          << b[1] << ", " << b[2] << ")";
        }
    }
    EXPECT_EQ(mismatches, 0u) << "of " << pixels << " pixels";
    if (tie_mismatches)
        std::printf("    %zu pixels had an exact tie broken differently\n", tie_mismatches);
    return hit_pixels;
}

RenderSettings bunny_settings(Shading shading, uint32_t res) {
    RenderSettings s;
    s.width = res;
    s.height = res;
    s.shading = shading;
    s.alpha = true;
    return s;
}

// ---------------------------------------------------------------------------------------------
// Oracle

TEST(RenderOracle, BunnyNormalsDepthPrimIdEqualBruteForce) {
    const KdTree& tree = bunny_tree();
    // One camera ray per pixel through its centre: the three modes trace the same rays, so the
    // brute force runs once for all of them, and the ties are the same.
    const uint32_t res = scaled_res(128);
    const std::vector<Ray> rays = render_camera_rays(tree, bunny_settings(Shading::kNormals, res));
    const std::vector<Hit> want = brute_force_all(triangles_by_id(tree), rays);
    BruteForce oracle(tree);
    oracle.remember(rays, want);
    const std::set<size_t> ties = tie_pixels(tree, rays, want);
    for (Shading shading : {Shading::kNormals, Shading::kDepth, Shading::kPrimId}) {
        SCOPED_TRACE(shading_name(shading));
        const size_t hit_pixels =
            expect_matches_oracle(tree, bunny_settings(shading, res), oracle, ties);
        EXPECT_GT(hit_pixels, res * res / 5)
            << "the default camera should fill the frame with the bunny";
        EXPECT_LT(hit_pixels, res * res) << "and show some background";
    }
}

TEST(RenderOracle, BunnyEyelightWithJitterEqualsBruteForce) {
    RenderSettings s = bunny_settings(Shading::kEyelight, scaled_res(64, 24));
    s.spp = 3;
    s.seed = test_seed();
    SCOPED_TRACE(testing::Message() << "seed=" << s.seed);
    // Ties are looked up for sample 0 only; with jitter they are vanishingly rare anyway.
    const Image got = render(bunny_tree(), s);
    const Image want = render_brute_force(bunny_tree(), s);
    expect_same_image(got, want);
}

TEST(RenderOracle, BunnyAoCloseToBruteForceWithTheSameSeed) {
    const KdTree& tree = bunny_tree();
    RenderSettings s = bunny_settings(Shading::kAo, scaled_res(128));
    s.ao_samples = 4;
    s.seed = test_seed();
    SCOPED_TRACE(testing::Message() << "seed=" << s.seed);
    const Image got = render(tree, s);
    const Image want = render_brute_force(tree, s);
    ASSERT_EQ(got.pixels.size(), want.pixels.size());
    double squared = 0;
    size_t exact = 0, occluded_somewhere = 0;
    const size_t pixels = size_t{got.width} * got.height;
    for (size_t p = 0; p < pixels; ++p) {
        const double d = double{got.pixels[p * 4]} - want.pixels[p * 4];
        squared += d * d;
        exact += d == 0.0;
        occluded_somewhere += want.pixels[p * 4 + 3] > 0.0f && want.pixels[p * 4] < 1.0f;
    }
    const double rmse = std::sqrt(squared / static_cast<double>(pixels));
    EXPECT_LT(rmse, 0.01);
    EXPECT_GT(exact, pixels * 99 / 100)
        << "the same rays should almost always give the same answers";
    EXPECT_GT(occluded_somewhere, pixels / 20) << "the bunny occludes itself in places";
}

TEST(RenderOracle, DiffuseWithBouncesEqualsBruteForceOnASoup) {
    Rng rng(test_seed() + 7);
    SCOPED_TRACE(testing::Message() << "seed=" << test_seed() + 7);
    const KdTree tree = build_kdtree(random_soup(rng, 400, 0.3f));
    RenderSettings s;
    s.width = 40;
    s.height = 30;
    s.spp = 2;
    s.shading = Shading::kDiffuse;
    s.bounces = 4;
    s.sky = 0.5f;
    s.seed = test_seed();
    const Image got = render(tree, s);
    const Image want = render_brute_force(tree, s);
    expect_same_image(got, want);
}

// ---------------------------------------------------------------------------------------------
// Determinism: regions, tiles, threads, seeds

RenderSettings noisy_settings(Shading shading) {
    RenderSettings s;
    s.width = 70;
    s.height = 53;
    s.spp = 5;
    s.shading = shading;
    s.ao_samples = 3;
    s.bounces = 3;
    s.sky = 0.3f;
    s.alpha = true;
    s.seed = test_seed();
    return s;
}

TEST(RenderDeterminism, FourRegionsStitchIntoTheFullFrameBitExactly) {
    for (Shading shading : {Shading::kEyelight, Shading::kAo, Shading::kDiffuse}) {
        SCOPED_TRACE(shading_name(shading));
        const RenderSettings full = noisy_settings(shading);
        const Image frame = render(bunny_tree(), full);
        // Uneven split points, off the tile grid: tiles inside a region start elsewhere.
        const uint32_t split_x = 29, split_y = 19;
        Image stitched{full.width, full.height, frame.channels, Pixels(frame.pixels.size(), -1.0f)};
        const PixelRegion regions[4] = {
            {0, 0, split_x, split_y},
            {split_x, 0, full.width - split_x, split_y},
            {0, split_y, split_x, full.height - split_y},
            {split_x, split_y, full.width - split_x, full.height - split_y}};
        for (const PixelRegion& r : regions) {
            RenderSettings part = full;
            part.region = r;
            const Image piece = render(bunny_tree(), part);
            ASSERT_EQ(piece.width, r.width);
            ASSERT_EQ(piece.height, r.height);
            for (uint32_t y = 0; y < r.height; ++y) {
                std::memcpy(&stitched.pixels[(size_t{r.y + y} * full.width + r.x) * frame.channels],
                            &piece.pixels[size_t{y} * r.width * frame.channels],
                            size_t{r.width} * frame.channels * sizeof(float));
            }
        }
        expect_same_image(stitched, frame);
    }
}

TEST(RenderDeterminism, OneThreadEqualsTwoThreadsBitExactly) {
    for (Shading shading : {Shading::kNormals, Shading::kAo, Shading::kDiffuse}) {
        SCOPED_TRACE(shading_name(shading));
        const RenderSettings s = noisy_settings(shading);
        Image one, two;
        RenderStats stats_one, stats_two;
        tbb::task_arena(1).execute([&] { one = render(bunny_tree(), s, {}, &stats_one); });
        tbb::task_arena(2).execute([&] { two = render(bunny_tree(), s, {}, &stats_two); });
        expect_same_image(one, two);
        EXPECT_EQ(stats_one.rays, stats_two.rays);
    }
}

TEST(RenderDeterminism, EveryPixelIsWrittenOverUsedMemory) {
    // render() sizes its frame without writing it (uninitialized_pixels), so every pixel must be
    // written by its tile. The frame is rendered into memory that held a marker just before:
    // a block of the frame's size is filled with the marker and freed, and the heap hands it back
    // to the next allocation of that size (checked: the frame's address). Frames of partial
    // tiles (tile 16), alpha and not.
    size_t reused = 0;
    for (const bool alpha : {true, false}) {
        for (const Shading shading : {Shading::kEyelight, Shading::kNormals}) {
            SCOPED_TRACE(testing::Message() << shading_name(shading) << " alpha=" << alpha);
            RenderSettings s = bunny_settings(shading, 40);
            s.height = 23;
            s.alpha = alpha;
            const Image want = render_brute_force(bunny_tree(), s);
            const size_t n = want.pixels.size();
            const float* old = nullptr;
            {
                Pixels used = uninitialized_pixels(n);
                const uint32_t marker = 0x7fc0dead;  // a quiet NaN no shading makes
                for (float& v : used) std::memcpy(&v, &marker, sizeof v);
                old = used.data();
            }
            const Image got = render(bunny_tree(), s);
            reused += got.pixels.data() == old ? 1 : 0;
            expect_same_image(got, want);
        }
    }
#if !defined(__SANITIZE_ADDRESS__)
    // ASan keeps freed memory out of use for a while; glibc's heap reuses the block at once.
    EXPECT_GT(reused, 0u) << "no frame was rendered into the marked memory: the test saw nothing";
#endif
}

/// The VmFlags line of the mapping holding `p` in /proc/self/smaps ("" if none).
std::string vm_flags_at(const void* p) {
    std::ifstream smaps("/proc/self/smaps");
    const auto at = reinterpret_cast<uintptr_t>(p);
    bool inside = false;
    for (std::string line; std::getline(smaps, line);) {
        unsigned long lo = 0, hi = 0;
        if (std::sscanf(line.c_str(), "%lx-%lx ", &lo, &hi) == 2 && line.find('-') < 17) {
            inside = lo <= at && at < hi;
        } else if (inside && line.rfind("VmFlags:", 0) == 0) {
            return line;
        }
    }
    return "";
}

TEST(RenderMemory, BigPixelBuffersAreHugePageMappingsAndInitialiseAsAsked) {
    constexpr size_t kHuge = size_t{2} << 20;
    const size_t n = 3 * kHuge / sizeof(float) + 5;  // 6 MiB and a little: four huge pages
    // Value-initialising constructions still zero every pixel; the tagged one writes nothing.
    Pixels zeros(n);
    EXPECT_EQ(reinterpret_cast<uintptr_t>(zeros.data()) % kHuge, 0u) << "a mapping of its own";
    EXPECT_TRUE(std::all_of(zeros.begin(), zeros.end(), [](float v) { return v == 0.0f; }));
    Pixels frame = uninitialized_pixels(n);
    ASSERT_EQ(frame.size(), n);
    EXPECT_EQ(reinterpret_cast<uintptr_t>(frame.data()) % kHuge, 0u);
    for (size_t i = 0; i < n; ++i) frame[i] = static_cast<float>(i % 1000);
    const Pixels copy = frame;
    EXPECT_EQ(copy, frame);
    frame.resize(n + kHuge, 7.0f);  // grows into a new mapping, keeps the values
    EXPECT_EQ(frame[n - 1], static_cast<float>((n - 1) % 1000));
    EXPECT_EQ(frame.back(), 7.0f);
    // Advised for transparent huge pages ("hg") wherever the kernel has them.
    if (std::ifstream("/sys/kernel/mm/transparent_hugepage/enabled")) {
        EXPECT_NE(vm_flags_at(copy.data()).find(" hg"), std::string::npos)
            << vm_flags_at(copy.data());
    }
    // Small buffers stay on the heap (no mapping of their own each).
    const Pixels small(1000, 1.0f);
    EXPECT_EQ(vm_flags_at(small.data()).find(" hg"), std::string::npos);
}

TEST(RenderDeterminism, TileSizeDoesNotChangeTheImage) {
    RenderSettings s = noisy_settings(Shading::kDiffuse);
    s.tile_size = 8;
    const Image small_tiles = render(bunny_tree(), s);
    s.tile_size = 16;
    expect_same_image(small_tiles, render(bunny_tree(), s));
}

TEST(RenderDeterminism, SeedDecidesTheNoise) {
    RenderSettings s = noisy_settings(Shading::kAo);
    const Image a = render(bunny_tree(), s);
    EXPECT_TRUE(same_bits(a, render(bunny_tree(), s))) << "same seed, same image";
    s.seed += 1;
    EXPECT_FALSE(same_bits(a, render(bunny_tree(), s))) << "another seed should move the AO noise";
}

// ---------------------------------------------------------------------------------------------
// Samples and camera rays

TEST(RenderSamples, OneSampleGoesThroughThePixelCentre) {
    RenderSettings s;
    s.width = 9;
    s.height = 7;
    s.camera = looking_down_z({0, 0, 5});
    const Camera camera(*s.camera, s.width, s.height);
    const std::vector<Ray> rays = render_camera_rays(bunny_tree(), s);
    ASSERT_EQ(rays.size(), 63u);
    for (uint32_t y = 0; y < s.height; ++y) {
        for (uint32_t x = 0; x < s.width; ++x) {
            const Ray want = camera.ray(static_cast<float>(x) + 0.5f, static_cast<float>(y) + 0.5f);
            EXPECT_EQ(std::memcmp(&rays[y * s.width + x], &want, sizeof(Ray)), 0) << x << "," << y;
        }
    }
}

TEST(RenderSamples, SamplesAreStratifiedOneToACell) {
    // An orthographic camera at the origin whose image plane maps pixel (px, py) to the ray
    // origin (px - W/2, H/2 - py, 0), so each sample's position in its pixel can be read back.
    constexpr uint32_t kSize = 6;
    for (uint32_t spp : {2u, 4u, 5u, 9u, 10u}) {
        SCOPED_TRACE(testing::Message() << "spp=" << spp);
        RenderSettings s;
        s.width = s.height = kSize;
        s.spp = spp;
        s.seed = test_seed();
        CameraSpec spec = looking_down_z({0, 0, 0});
        spec.projection = Projection::kOrthographic;
        spec.ortho_height = static_cast<float>(kSize);
        s.camera = spec;
        uint32_t columns = 1;
        while (columns * columns < spp) ++columns;
        const uint32_t rows = (spp + columns - 1) / columns;
        std::vector<std::vector<Ray>> samples;
        for (uint32_t k = 0; k < spp; ++k)
            samples.push_back(render_camera_rays(bunny_tree(), s, k));
        size_t on_a_boundary = 0;
        for (uint32_t y = 0; y < kSize; ++y) {
            for (uint32_t x = 0; x < kSize; ++x) {
                std::set<uint32_t> cells;
                bool ambiguous = false;
                for (uint32_t k = 0; k < spp; ++k) {
                    const Ray& r = samples[k][y * kSize + x];
                    const double fx = r.ox + kSize / 2.0 - x,
                                 fy = kSize / 2.0 - r.oy - y;  // in [0, 1]
                    ASSERT_GE(fx, -1e-5) << x << "," << y;
                    ASSERT_LE(fx, 1.0 + 1e-5) << x << "," << y;
                    ASSERT_GE(fy, -1e-5) << x << "," << y;
                    ASSERT_LE(fy, 1.0 + 1e-5) << x << "," << y;
                    // A sample within rounding of a cell border cannot be assigned reliably.
                    const double gx = fx * columns, gy = fy * rows;
                    ambiguous = ambiguous || std::fabs(gx - std::round(gx)) < 1e-4 ||
                                std::fabs(gy - std::round(gy)) < 1e-4;
                    const auto cx = std::min(columns - 1, static_cast<uint32_t>(gx));
                    const auto cy = std::min(rows - 1, static_cast<uint32_t>(gy));
                    cells.insert(cy * columns + cx);
                }
                on_a_boundary += ambiguous;
                if (!ambiguous) {
                    EXPECT_EQ(cells.size(), spp)
                        << "pixel " << x << "," << y << ": two samples share a cell";
                }
            }
        }
        EXPECT_LT(on_a_boundary, 3u);
    }
}

TEST(RenderSamples, RegionRaysAreTheFullFrameRays) {
    RenderSettings s = noisy_settings(Shading::kEyelight);
    const std::vector<Ray> full = render_camera_rays(bunny_tree(), s, 3);
    s.region = PixelRegion{11, 7, 20, 13};
    const std::vector<Ray> part = render_camera_rays(bunny_tree(), s, 3);
    ASSERT_EQ(part.size(), 260u);
    for (uint32_t y = 0; y < 13; ++y)
        for (uint32_t x = 0; x < 20; ++x)
            ASSERT_EQ(
                std::memcmp(&part[y * 20 + x], &full[(y + 7) * s.width + x + 11], sizeof(Ray)), 0);
    EXPECT_THROW((void)render_camera_rays(bunny_tree(), s, s.spp), RenderError);
}

// ---------------------------------------------------------------------------------------------
// Shading values

TEST(RenderShading, DepthIsTheDistanceAlongTheCameraRay) {
    const KdTree tree = build_kdtree(unit_quad());
    RenderSettings s;
    s.width = 5;
    s.height = 5;
    s.shading = Shading::kDepth;
    s.camera = looking_down_z({0, 0, 4}, 20.0f);
    const Image image = render(tree, s);
    const std::vector<Ray> rays = render_camera_rays(tree, s);
    for (uint32_t i = 0; i < 25; ++i) {
        const Ray& r = rays[i];
        const float want = 4.0f / -r.dz;  // unit direction: t is the distance to z = 0
        EXPECT_NEAR(image.pixels[i * 3], want, 1e-5f) << i;
        EXPECT_EQ(image.pixels[i * 3], image.pixels[i * 3 + 2]);
    }
    EXPECT_NEAR(at(image, 2, 2, 0), 4.0f, 1e-5f);

    // Orthographic: every ray travels the same distance to a plane facing the camera.
    CameraSpec ortho = looking_down_z({0.1f, -0.2f, 3});
    ortho.projection = Projection::kOrthographic;
    ortho.ortho_height = 1.0f;
    s.camera = ortho;
    const Image flat = render(tree, s);
    for (size_t i = 0; i < flat.pixels.size(); ++i) EXPECT_FLOAT_EQ(flat.pixels[i], 3.0f) << i;
}

TEST(RenderShading, NormalsFaceTheCamera) {
    const KdTree tree = build_kdtree(unit_quad());
    RenderSettings s;
    s.width = s.height = 4;
    s.shading = Shading::kNormals;
    s.camera = looking_down_z({0, 0, 3});
    const Image front = render(tree, s);
    CameraSpec back;
    back.eye = {0, 0, -3};
    back.look_at = {0, 0, 0};
    s.camera = back;
    const Image behind = render(tree, s);
    for (uint32_t i = 0; i < 16; ++i) {
        EXPECT_EQ(front.pixels[i * 3 + 0], 0.5f);
        EXPECT_EQ(front.pixels[i * 3 + 1], 0.5f);
        EXPECT_EQ(front.pixels[i * 3 + 2], 1.0f) << "+z normal seen from +z";
        EXPECT_EQ(behind.pixels[i * 3 + 2], 0.0f) << "the same face seen from -z shows -z";
    }
}

TEST(RenderShading, EyelightIsTheCosineToTheView) {
    const KdTree tree = build_kdtree(unit_quad());
    RenderSettings s;
    s.width = s.height = 1;
    // Looking at the quad's centre from 60 degrees off its normal: cos = 0.5.
    CameraSpec spec;
    spec.eye = {0, 3.0f * std::sqrt(3.0f) / 2.0f, 1.5f};
    spec.look_at = {0, 0, 0};
    s.camera = spec;
    const Image image = render(tree, s);
    ASSERT_EQ(image.pixels.size(), 3u);
    EXPECT_NEAR(image.pixels[0], 0.5f, 1e-5f);
}

TEST(RenderShading, PrimIdColourIsFixedPerTriangle) {
    const KdTree tree = build_kdtree(unit_quad());
    RenderSettings s;
    s.width = s.height = 16;
    s.shading = Shading::kPrimId;
    s.camera = looking_down_z({0, 0, 2}, 40.0f);
    const Image image = render(tree, s);
    const std::vector<Ray> rays = render_camera_rays(tree, s);
    std::vector<Hit> hits(rays.size());
    intersect_single(tree, rays, hits);
    std::vector<std::array<float, 3>> colour_of(2, {-1, -1, -1});
    for (size_t i = 0; i < rays.size(); ++i) {
        ASSERT_TRUE(hits[i].is_hit()) << "the quad fills the view";
        const std::array<float, 3> c{image.pixels[i * 3], image.pixels[i * 3 + 1],
                                     image.pixels[i * 3 + 2]};
        for (float v : c) {
            EXPECT_GE(v, 0.0f);
            EXPECT_LE(v, 1.0f);
        }
        auto& known = colour_of[hits[i].prim];
        if (known[0] < 0) known = c;
        EXPECT_EQ(known, c) << "pixel " << i << " of triangle " << hits[i].prim;
    }
    EXPECT_NE(colour_of[0], colour_of[1]);
}

TEST(RenderShading, AoIsOneInTheOpenAndZeroInsideAClosedMesh) {
    RenderSettings s;
    s.width = s.height = 8;
    s.shading = Shading::kAo;
    s.ao_samples = 8;
    s.camera = looking_down_z({0, 0, 2}, 40.0f);  // the quad fills the view
    const Image open = render(build_kdtree(unit_quad()), s);
    for (size_t i = 0; i < open.pixels.size(); ++i) EXPECT_EQ(open.pixels[i], 1.0f) << i;

    // Inside a sphere every AO ray of 2 scene diagonals hits the far wall.
    s.camera = looking_down_z({0, 0, 0}, 60.0f);
    s.ao_distance = 2.0f;
    const Image closed = render(build_kdtree(uv_sphere({0, 0, 0}, 1.0f, 24, 48)), s);
    for (size_t i = 0; i < closed.pixels.size(); ++i) EXPECT_EQ(closed.pixels[i], 0.0f) << i;
}

TEST(RenderShading, DiffuseDirectLightAndHardShadow) {
    Mesh scene = unit_quad();
    // A small occluder above the quad's right half, between it and a light straight above.
    const uint32_t a = add_vertex(scene, {0.2f, -2, 1}), b = add_vertex(scene, {2, -2, 1}),
                   c = add_vertex(scene, {2, 2, 1}), d = add_vertex(scene, {0.2f, 2, 1});
    add_indices(scene, a, b, c);
    add_indices(scene, a, c, d);
    const KdTree tree = build_kdtree(scene);
    RenderSettings s;
    s.width = 8;
    s.height = 1;
    s.shading = Shading::kDiffuse;
    s.albedo = 0.5f;
    s.light.intensity = 2.0f;
    s.light.direction = {0, 0, 10};
    // An orthographic camera between the quad and the occluder, looking down at the quad.
    CameraSpec spec;
    spec.eye = {0, 0, 0.5f};
    spec.look_at = {0, 0, 0};
    spec.up = {0, 1, 0};
    spec.projection = Projection::kOrthographic;
    spec.ortho_height = 0.25f;
    s.camera = spec;
    // Ortho width = 0.25 * 8 = 2: pixel centres at x = -0.875 .. 0.875.
    const Image lit = render(tree, s);
    for (uint32_t x = 0; x < 8; ++x) {
        const float px = -0.875f + 0.25f * static_cast<float>(x);
        const float want = px < 0.2f ? 0.5f * 2.0f : 0.0f;  // albedo * intensity * cos 0, or shadow
        EXPECT_NEAR(at(lit, x, 0, 0), want, 1e-6f) << "x=" << px;
    }

    // Light 60 degrees off the normal: cos = 0.5.
    s.light.direction = {0, std::sqrt(3.0f), 1};
    const Image slanted = render(tree, s);
    EXPECT_NEAR(at(slanted, 0, 0, 0), 0.5f * 2.0f * 0.5f, 1e-6f);

    // A point light 2 units above the left half: intensity / d^2.
    s.light.kind = LightKind::kPoint;
    s.light.position = {-0.875f, 0, 2};
    const Image point = render(tree, s);
    EXPECT_NEAR(at(point, 0, 0, 0), 0.5f * 2.0f / 4.0f, 1e-4f);
}

TEST(RenderShading, DiffuseBounceSeesTheSky) {
    // An open quad under a sky of radiance 1 and no light: the first bounce always escapes, so
    // every pixel is albedo * sky exactly, however many bounces are allowed.
    RenderSettings s;
    s.width = s.height = 6;
    s.shading = Shading::kDiffuse;
    s.camera = looking_down_z({0, 0, 2}, 40.0f);
    s.light.intensity = 0.0f;
    s.sky = 1.0f;
    s.albedo = 0.6f;
    const KdTree tree = build_kdtree(unit_quad());
    s.bounces = 0;
    const Image direct_only = render(tree, s);
    for (float v : direct_only.pixels) EXPECT_EQ(v, 0.0f);
    s.bounces = 5;
    const Image bounced = render(tree, s);
    for (float v : bounced.pixels) EXPECT_FLOAT_EQ(v, 0.6f);
}

TEST(RenderShading, PathTracerConvergesInsideALitSphere) {
    // Inside a closed sphere of radius R with a point light at its centre, every surface point
    // gets direct radiance a * I / R^2, and each bounce lands on the sphere again: after B bounces
    // the radiance is a * I / R^2 * (1 + a + ... + a^B). Russian roulette (from bounce 2) must not
    // bias it. The eye sits inside the mesh, at the light.
    const KdTree tree = build_kdtree(uv_sphere({0, 0, 0}, 1.0f, 48, 96));
    RenderSettings s;
    s.width = s.height = 12;
    s.shading = Shading::kDiffuse;
    s.camera = looking_down_z({0, 0, 0}, 90.0f);
    s.light.kind = LightKind::kPoint;
    s.light.position = {0, 0, 0};
    s.light.intensity = 1.0f;
    s.albedo = 0.5f;
    s.seed = test_seed();
    SCOPED_TRACE(testing::Message() << "seed=" << s.seed);

    s.bounces = 2;  // no roulette yet: every path gives the same value
    const Image exact = render(tree, s);
    for (float v : exact.pixels) EXPECT_NEAR(v, 0.5f * (1.0f + 0.5f + 0.25f), 0.01f);

    s.bounces = 10;
    s.spp = 64;
    RenderStats stats;
    const Image image = render(tree, s, {}, &stats);
    double mean = 0;
    for (float v : image.pixels) mean += v;
    mean /= static_cast<double>(image.pixels.size());
    const double want = 0.5 * (1.0 - std::pow(0.5, 11)) / (1.0 - 0.5);
    EXPECT_NEAR(mean, want, 0.02 * want);
    // Roulette ends paths early: fewer rays than the full 11 vertices x 2 rays per path.
    EXPECT_LT(stats.rays, stats.primary_rays * 10);
    EXPECT_GT(stats.rays, stats.primary_rays * 5);
}

TEST(RenderShading, EyeInsideTheMeshSeesItsInside) {
    const KdTree tree = build_kdtree(uv_sphere({0, 0, 0}, 2.0f, 32, 64));
    RenderSettings s;
    s.width = s.height = 9;
    s.alpha = true;
    s.camera = looking_down_z({0, 0, 0}, 60.0f);
    const Image eyelight = render(tree, s);
    for (uint32_t i = 0; i < 81; ++i)
        EXPECT_EQ(eyelight.pixels[i * 4 + 3], 1.0f) << "every ray hits the wall";
    EXPECT_NEAR(at(eyelight, 4, 4, 0), 1.0f, 0.01f)
        << "looking at the wall head-on from the centre";
    s.shading = Shading::kDepth;
    const Image depth = render(tree, s);
    for (uint32_t i = 0; i < 81; ++i) EXPECT_NEAR(depth.pixels[i * 4], 2.0f, 0.02f);
}

TEST(RenderShading, AlphaIsCoverageAndMissesShowTheBackground) {
    const KdTree tree = build_kdtree(unit_quad());
    RenderSettings s;
    s.width = 16;
    s.height = 8;
    s.spp = 16;
    s.alpha = true;
    s.background = {0.25f, 0.5f, 0.75f};
    s.camera = looking_down_z({0, 0, 3}, 40.0f);  // the quad covers the middle of the frame
    const Image image = render(tree, s);
    ASSERT_EQ(image.channels, 4u);
    EXPECT_EQ(at(image, 8, 4, 3), 1.0f);
    EXPECT_EQ(at(image, 0, 0, 3), 0.0f);
    EXPECT_EQ(at(image, 0, 0, 0), 0.25f);
    EXPECT_EQ(at(image, 0, 0, 2), 0.75f);
    size_t partial = 0;
    for (uint32_t y = 0; y < 8; ++y)
        for (uint32_t x = 0; x < 16; ++x)
            partial += at(image, x, y, 3) > 0.0f && at(image, x, y, 3) < 1.0f;
    EXPECT_GT(partial, 0u) << "pixels on the quad's edge are partly covered";

    s.alpha = false;
    EXPECT_EQ(render(tree, s).channels, 3u);
}

TEST(RenderShading, EmptySceneIsAllBackground) {
    const KdTree tree = build_kdtree(Mesh{});
    RenderSettings s;
    s.width = 5;
    s.height = 3;
    s.alpha = true;
    s.background = {0.1f, 0.2f, 0.3f};
    RenderStats stats;
    const Image image = render(tree, s, {}, &stats);
    for (uint32_t i = 0; i < 15; ++i) {
        EXPECT_EQ(image.pixels[i * 4 + 1], 0.2f);
        EXPECT_EQ(image.pixels[i * 4 + 3], 0.0f);
    }
    EXPECT_EQ(stats.pixels, 15u);
    EXPECT_EQ(stats.rays, 15u);
}

// ---------------------------------------------------------------------------------------------
// Control and statistics

TEST(RenderControl, ProgressRisesAndEndsAtOne) {
    RenderSettings s = noisy_settings(Shading::kEyelight);
    s.width = s.height = 200;
    s.tile_size = 8;  // 625 tiles
    std::vector<double> reports;
    RenderControl control;
    control.progress = [&](double f) { reports.push_back(f); };  // calls never overlap
    (void)render(bunny_tree(), s, control);
    ASSERT_GE(reports.size(), 2u);
    for (size_t i = 1; i < reports.size(); ++i) EXPECT_GT(reports[i], reports[i - 1]) << i;
    EXPECT_GT(reports.front(), 0.0);
    EXPECT_EQ(reports.back(), 1.0);
    EXPECT_LE(reports.size(), 260u) << "reports are throttled to about 1/256 steps";
}

TEST(RenderControl, CancelBeforeStartThrowsAndReportsNoCompletion) {
    std::atomic<bool> cancel{true};
    bool finished = false;
    RenderControl control;
    control.cancel = &cancel;
    control.progress = [&](double f) { finished = finished || f == 1.0; };
    EXPECT_THROW((void)render(bunny_tree(), noisy_settings(Shading::kEyelight), control),
                 RenderCancelled);
    EXPECT_FALSE(finished);
}

TEST(RenderControl, CancelDuringTheRenderStopsIt) {
    RenderSettings s = noisy_settings(Shading::kAo);
    s.width = s.height = 256;
    s.tile_size = 8;  // 1024 tiles
    std::atomic<bool> cancel{false};
    std::atomic<int> calls{0};
    RenderControl control;
    control.cancel = &cancel;
    control.progress = [&](double f) {
        ++calls;
        if (f > 0.1) cancel = true;
    };
    RenderStats stats;
    EXPECT_THROW((void)render(bunny_tree(), s, control, &stats), RenderCancelled);
    EXPECT_GE(calls.load(), 1);
    EXPECT_EQ(stats.pixels, 0u) << "no statistics for a cancelled render";
}

TEST(RenderControl, ProgressCallbackExceptionPropagates) {
    RenderSettings s = noisy_settings(Shading::kEyelight);
    s.width = s.height = 128;
    s.tile_size = 8;
    RenderControl control;
    control.progress = [](double) { throw std::runtime_error("client went away"); };
    EXPECT_THROW((void)render(bunny_tree(), s, control), std::runtime_error);
}

TEST(RenderStatsTest, CountsPixelsTilesAndRays) {
    RenderSettings s;
    s.width = 40;
    s.height = 20;
    s.spp = 3;
    s.tile_size = 16;
    s.region = PixelRegion{5, 2, 33, 17};
    RenderStats stats;
    (void)render(bunny_tree(), s, {}, &stats);
    EXPECT_EQ(stats.pixels, 33u * 17u);
    EXPECT_EQ(stats.tiles, 3u * 2u);
    EXPECT_EQ(stats.primary_rays, 33u * 17u * 3u);
    EXPECT_EQ(stats.rays, stats.primary_rays) << "eyelight traces camera rays only";
    EXPECT_GT(stats.seconds, 0.0);

    // AO: one occlusion ray per AO sample at every camera hit.
    s.shading = Shading::kAo;
    s.ao_samples = 5;
    s.alpha = true;
    const Image ao = render(bunny_tree(), s, {}, &stats);
    double hits = 0;
    for (size_t p = 0; p < size_t{ao.width} * ao.height; ++p) hits += ao.pixels[p * 4 + 3] * 3.0;
    EXPECT_EQ(stats.rays, stats.primary_rays + static_cast<uint64_t>(std::lround(hits)) * 5u);
}

// ---------------------------------------------------------------------------------------------
// Settings validation

TEST(RenderSettingsTest, ShadingNamesRoundTrip) {
    for (Shading shading : {Shading::kNormals, Shading::kEyelight, Shading::kDepth,
                            Shading::kPrimId, Shading::kAo, Shading::kDiffuse}) {
        EXPECT_EQ(parse_shading(shading_name(shading)), shading);
    }
    EXPECT_EQ(parse_shading("Eyelight"), std::nullopt);
    EXPECT_EQ(parse_shading(""), std::nullopt);
    EXPECT_EQ(shading_name(static_cast<Shading>(99)), "unknown");
}

TEST(RenderSettingsTest, BadSizesAndCountsNameTheField) {
    const KdTree& tree = bunny_tree();
    auto with = [](auto change) {
        RenderSettings s;
        s.width = s.height = 32;
        change(s);
        return s;
    };
    expect_render_error(tree, with([](RenderSettings& s) { s.width = 0; }), "width");
    expect_render_error(tree, with([](RenderSettings& s) { s.height = 0; }), "height");
    expect_render_error(tree, with([](RenderSettings& s) { s.width = kMaxImageSize + 1; }),
                        "width");
    expect_render_error(tree, with([](RenderSettings& s) {
                            s.region = PixelRegion{0, 0, 0, 4};
                        }),
                        "region");
    expect_render_error(tree, with([](RenderSettings& s) {
                            s.region = PixelRegion{30, 0, 3, 4};
                        }),
                        "region");
    expect_render_error(tree, with([](RenderSettings& s) {
                            s.region = PixelRegion{0xFFFFFFFFu, 0, 2, 2};
                        }),
                        "region");
    expect_render_error(tree, with([](RenderSettings& s) { s.spp = 0; }), "spp");
    expect_render_error(tree, with([](RenderSettings& s) { s.spp = kMaxSamplesPerPixel + 1; }),
                        "spp");
    expect_render_error(tree, with([](RenderSettings& s) { s.tile_size = 12; }), "tile_size");
    expect_render_error(tree, with([](RenderSettings& s) { s.ao_samples = 0; }), "ao_samples");
    expect_render_error(tree, with([](RenderSettings& s) { s.ao_distance = 0.0f; }), "ao_distance");
    expect_render_error(tree, with([](RenderSettings& s) { s.ao_distance = NAN; }), "ao_distance");
    expect_render_error(tree, with([](RenderSettings& s) { s.albedo = 1.5f; }), "albedo");
    expect_render_error(tree, with([](RenderSettings& s) { s.bounces = kMaxBounces + 1; }),
                        "bounces");
    expect_render_error(tree, with([](RenderSettings& s) { s.sky = -1.0f; }), "sky");
    expect_render_error(tree, with([](RenderSettings& s) {
                            s.background = {0, INFINITY, 0};
                        }),
                        "background");
    expect_render_error(tree, with([](RenderSettings& s) { s.light.intensity = NAN; }),
                        "light.intensity");
    expect_render_error(tree, with([](RenderSettings& s) {
                            s.light.direction = {0, 0, 0};
                        }),
                        "light.direction");
    expect_render_error(tree, with([](RenderSettings& s) {
                            s.light.direction = {1e30f, 1e30f, 0};
                        }),
                        "light.direction");
    expect_render_error(tree, with([](RenderSettings& s) {
                            s.light.kind = LightKind::kPoint;
                            s.light.position = {NAN, 0, 0};
                        }),
                        "light.position");
    expect_render_error(tree,
                        with([](RenderSettings& s) { s.light.kind = static_cast<LightKind>(5); }),
                        "light.kind");
    expect_render_error(tree, with([](RenderSettings& s) { s.shading = static_cast<Shading>(42); }),
                        "shading");
    // The error type is an invalid_argument, as the server maps it to 400.
    EXPECT_THROW((void)render(tree, with([](RenderSettings& s) { s.spp = 0; })),
                 std::invalid_argument);
}

TEST(RenderSettingsTest, CameraEdgeCasesGiveClearErrors) {
    const KdTree& tree = bunny_tree();
    auto with_camera = [](auto change) {
        RenderSettings s;
        s.width = s.height = 16;
        CameraSpec spec;
        spec.eye = {0, 0, 3};
        change(spec);
        s.camera = spec;
        return s;
    };
    for (float fov : {0.0f, -10.0f, 180.0f, 200.0f, NAN}) {
        expect_render_error(tree, with_camera([fov](CameraSpec& c) { c.fov_deg = fov; }), "fov");
    }
    expect_render_error(tree, with_camera([](CameraSpec& c) { c.look_at = c.eye; }), "look_at");
    // Looking straight down the up vector: no basis can be formed.
    expect_render_error(tree, with_camera([](CameraSpec& c) {
                            c.eye = {0, 5, 0};
                            c.look_at = {0, 0, 0};
                            c.up = {0, 1, 0};
                        }),
                        "parallel");
    expect_render_error(tree, with_camera([](CameraSpec& c) { c.up = {0, 0, 0}; }), "up");
    expect_render_error(tree, with_camera([](CameraSpec& c) {
                            c.projection = Projection::kOrthographic;
                            c.ortho_height = 0.0f;
                        }),
                        "ortho_height");
    expect_render_error(tree, with_camera([](CameraSpec& c) { c.eye = {INFINITY, 0, 0}; }), "eye");
}

TEST(RenderSettingsTest, OnePixelFramesAndStripsRender) {
    const KdTree tree = build_kdtree(unit_quad());
    RenderSettings s;
    s.camera = looking_down_z({0, 0, 2});
    s.shading = Shading::kDepth;
    for (auto [w, h] : {std::pair{1u, 1u}, std::pair{1u, 7u}, std::pair{9u, 1u}}) {
        s.width = w;
        s.height = h;
        const Image image = render(tree, s);
        ASSERT_EQ(image.width, w);
        ASSERT_EQ(image.height, h);
        ASSERT_EQ(image.pixels.size(), size_t{w} * h * 3);
        // The middle pixel of an odd size looks straight at the quad's centre.
        EXPECT_NEAR(at(image, w / 2, h / 2, 0), 2.0f, 1e-5f) << w << "x" << h;
    }
}

TEST(RenderSettingsTest, DefaultCameraFramesTheScene) {
    RenderSettings s;
    s.width = 96;
    s.height = 48;  // wide frame: the default camera adapts to the aspect
    s.alpha = true;
    const Image image = render(bunny_tree(), s);
    // The bunny touches neither the outermost rows nor the outermost columns, yet fills a good
    // share of the frame.
    size_t covered = 0;
    for (uint32_t y = 0; y < s.height; ++y) {
        for (uint32_t x = 0; x < s.width; ++x) {
            const bool hit = at(image, x, y, 3) > 0.0f;
            covered += hit;
            if (x == 0 || y == 0 || x + 1 == s.width || y + 1 == s.height) {
                EXPECT_FALSE(hit) << x << "," << y;
            }
        }
    }
    EXPECT_GT(covered, size_t{s.width} * s.height / 10);
}

}  // namespace
}  // namespace kdrt::test
