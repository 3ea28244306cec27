// kdrt-bench: builds kD-trees, generates ray sets and times batch tracing; one JSON line per run.
// Usage: kdrt-bench --help. Exit status: 0 success, 1 runtime failure, 2 usage error.

#include <sched.h>
#include <tbb/global_control.h>
#include <tbb/info.h>
#include <tbb/parallel_for.h>
#include <tbb/task_arena.h>
#include <tbb/task_scheduler_observer.h>

#include <algorithm>
#include <array>
#include <bit>
#include <charconv>
#include <chrono>
#include <cmath>
#include <cstdint>
#include <cstdio>
#include <ctime>
#include <exception>
#include <filesystem>
#include <iostream>
#include <limits>
#include <new>
#include <nlohmann/json.hpp>
#include <numeric>
#include <span>
#include <string>
#include <string_view>
#include <vector>

#include "bench_args.h"
#include "embree_compare.h"
#include "embree_scene.h"
#include "image_helper.h"
#include "kdrt/distance.h"
#include "kdrt/kdtree.h"
#include "kdrt/mesh.h"
#include "kdrt/proto/file_io.h"
#include "kdrt/proto/mesh_io.h"
#include "kdrt/proto/ray_batch.h"
#include "kdrt/query.h"
#include "kdrt/raygen.h"
#include "kdrt/render.h"
#include "kdrt/scene.h"
#include "kdrt/serialize.h"
#include "kdrt/trace.h"
#include "scenes.h"
#include "test_util.h"

namespace kdrt::bench {
namespace {

// Keys keep the order they are written in, so a line reads the same run after run.
using Json = nlohmann::ordered_json;
using Clock = std::chrono::steady_clock;

constexpr std::string_view kToolUsage = R"(usage: kdrt-bench <command> [options]

Builds kD-trees, writes deterministic ray sets and times batch tracing. Every command prints one
JSON line on stdout; errors go to stderr (exit 1: the run failed, exit 2: bad command line).

commands:
  build MESH    build the tree of a mesh and print its statistics and build time
  trace MESH RAYS.kdrr
                trace a KDRR ray batch (closest hit, or occlusion when the batch says so)
  rays MESH     write a deterministic KDRR ray set (primary, shadow, diffuse, random)
  scene KIND    write a generated benchmark scene (stadium, grid) as a mesh file, or time a
                two-level scene of instances (scene instances)
  render MESH   render the default view of a mesh, timed against its camera rays as a batch
  distance MESH time closest-point and signed-distance queries (kD search against brute force)

MESH is any mesh file kdrt reads, chosen by extension: .obj .ply .off .stl .raw/.kdrtmesh.
Run 'kdrt-bench <command> --help' for the options of a command.
)";

constexpr std::string_view kBuildUsage =
    R"(usage: kdrt-bench build MESH [--builder sah|middle] [--c-isect X] [--threads N] [--reps K]
                        [--out FILE]

Builds the kD-tree of MESH K times (default 1) and prints one JSON line:
  mesh, triangles, builder, c_isect, threads, reps, parse_ms, build_ms (median of the K builds),
  build_ms_min, cpu_util (process CPU seconds per wall second over the builds), node_bytes,
  nodes, leaves, empty_leaves, refs, max_depth, mean_leaf_depth, mean_tris_per_leaf, sah_cost,
  bytes, bytes_per_triangle

options:
  --builder sah|middle  tree builder (default sah)
  --c-isect X           SAH cost of a triangle test relative to a traversal step (default 0.3)
  --threads N           worker threads (default: all cores)
  --reps K              number of builds to time (default 1)
  --out FILE            write the last tree as a blob (kdrt::serialize_tree) with its build_ms
                        set to 0, so that equal trees give equal files (a build change that must
                        not change the tree is checked with cmp against the old binary's file)
)";

constexpr std::string_view kAllHitsUsage =
    R"(usage: kdrt-bench all-hits MESH RAYS.kdrr [--max-hits N] [--merge] [--mode single|packet|auto]
                           [--threads N] [--reps K]

Every hit along each ray (kdrt::intersect_all, kdrt/query.h) against closest hit on the same
rays. Builds the tree of MESH, then times K passes (default 5, after an untimed warm-up) of:
intersect_all with max_hits N (default 16) and count_intersections, both in --mode (default auto:
packets where they pay), the closest-hit batch tracer (auto mode) and the single-ray closest-hit
kernel (intersect_single, the same scalar traversal family as intersect_all's single rays).
Prints one JSON line: rays, threads, mode, max_hits, merge, hits_per_ray
(mean of all hits), kept_hits, and for each query its median seconds and mrays_per_s, and
all_vs_closest_single / all_vs_closest_auto (rays/s ratios).
)";

constexpr std::string_view kDistanceUsage =
    R"(usage: kdrt-bench distance MESH [--points N] [--brute N] [--threads N] [--reps K] [--seed S]
                            [--far D]

Distance queries (kdrt::closest_points, kdrt/distance.h) against the brute-force scan. Builds the
tree and the surface index of MESH, then makes N query points (default 100000): half uniform in
the mesh's bounding box grown by 10% (5% of each side's length on both sides), half near the
surface (area-uniform surface samples, each moved in a random direction by up to 1% of the
box's diagonal). Times K passes (default 5, after an untimed warm-up) of the kD search unsigned
and signed over each half, and one pass of brute_force_closest_point (signed) over a subset of the points
(--brute, default enough for about 1e8 triangle tests, at least 32, at most 4096; half from each
kind), in parallel over the same threads. Checks that the kD answers on the subset equal brute
force bit for bit (signed; unsigned but for the side, which is then unknown), and exits 1 if any
differs. Prints one JSON line:
  mesh, triangles, closed, threads, reps, points, build_ms, surface_ms (build_surface_index),
  kd_points_per_s (unsigned, all points, from the medians), kd_uniform_points_per_s,
  kd_near_points_per_s, signed_points_per_s, signed_uniform_points_per_s,
  signed_near_points_per_s, brute_points, brute_seconds, brute_points_per_s, ratio
  (kd_points_per_s / brute_points_per_s), cpu_util (process CPU seconds per wall second over the
  timed kD passes), matches_brute_force, mismatches.

options:
  --points N   query points (default 100000)
  --brute N    points checked and timed by brute force (default: see above)
  --threads N  worker threads (default: all cores)
  --reps K     timed passes of the kD search (default 5)
  --seed S     random seed of the points (default 1)
  --far D      the "uniform" half is instead on a sphere D box diagonals from the mesh's
               centre (far points: 1e6 is a point a million mesh sizes away); printed as far
)";

constexpr std::string_view kTraceUsage =
    R"(usage: kdrt-bench trace MESH RAYS.kdrr [--mode single|packet|auto|one] [--isa ISA] [--threads N]
                        [--reps K] [--out FILE] [--builder sah|middle] [--c-isect X]
                        [--compare embree] [--stats]

Builds the tree of MESH, then traces the rays of RAYS.kdrr K times (default 5) after one untimed
warm-up pass: closest hits, or occlusion when the batch has flag bit 0 set. Prints one JSON line:
  mesh, rays_file, rays, occlusion, mode, isa, packets, packet_rays, single_rays, sorted_rays
  (how the mode split the rays), threads, builder, c_isect, reps, parse_ms, build_ms,
  seconds (tracing only, median of the K passes), seconds_min, mrays_per_s (from the median),
  hits (rays that hit, or are occluded), cpu_util (process CPU seconds per wall second while
  tracing: near `threads` only when the workers had their cores; lower = a noisy measurement)
With --compare embree it also traces the rays with Embree 4 or 3 (RTC_BUILD_QUALITY_HIGH), in two
scenes: default flags (Embree's fast, non-watertight triangle test) and RTC_SCENE_FLAG_ROBUST
(watertight, as kdrt's), each through rtcIntersect1/4/8/16 and, with Embree 3, 1M (rtcOccluded*
for occlusion), incoherent and coherent, and adds
  embree_mrays_per_s, embree_best_mode and embree_best_flags (default or robust: the fastest of
  all those), ratio (mrays_per_s divided by embree_mrays_per_s), embree_default_mrays_per_s,
  embree_robust_mrays_per_s, embree_robust_best_mode and ratio_robust (each flag's own best),
  embree_build_ms and embree_robust_build_ms, embree_bytes_per_triangle (memory the default
  scene keeps after the build), embree_version (major), differences (rays whose answer differs in the best mode: another prim, or t off by
  more than 1e-4 relative and 1e-7 of the scene diagonal; for occlusion another bit), ties (of those, rays where both hit at
  the same t on triangles that share a corner, or that kdrt's test hits too: both answers
  right), kdrt_matches_oracle (of the other differences, rays where kdrt's answer is the
  brute-force oracle's), the same three counts for the robust scene's best mode
  (embree_robust_differences, embree_robust_ties, embree_robust_kdrt_matches_oracle) and
  embree_modes (Mrays/s of every mode; the robust scene's prefixed robust_), and
  embree_1_mrays_per_s, embree_1_mode and ratio_1: Embree's fastest one-ray-at-a-time mode
  (rtcIntersect1 or rtcOccluded1, either flag), the yardstick of --mode one.
With --stats it traces once more, untimed, with the counting kernels and adds the work per ray:
  steps_per_ray (inner nodes visited), leaves_per_ray, tri_tests_per_ray (a packet's visit or
  test counts once per live lane), tri_skips_per_ray (of those, packet tests of a triangle that
  every active lane had tested already, skipped), packet_visits (node visits by packets) and lane_utilisation
  (live lanes per packet node visit, divided by the packet width).

options:
  --mode single|packet|auto  traversal (default auto: packets where rays are coherent)
  --mode one                 one ray at a time (kdrt::intersect_single / occluded_single, on the
                             default ISA's kernel: KDRT_ISA sets it), the counterpart of
                             rtcIntersect1 / rtcOccluded1; --stats counts --mode single's walks
  --isa scalar|sse4|avx2|avx512  packet instruction set (default: the engine's default_isa(), or KDRT_ISA)
  --threads N                worker threads (default: all cores)
  --reps K                   timed passes (default 5)
  --out FILE                 write the answers as KDRH (hits) or KDRO (occlusion) to FILE
  --builder sah|middle       tree builder (default sah)
  --c-isect X                SAH cost of a triangle test relative to a traversal step (default 0.3)
  --compare embree           also trace with Embree (default and robust) and compare speed and answers
  --stats                    also count the work per ray (an extra, untimed pass)
)";

constexpr std::string_view kRaysUsage =
    R"(usage: kdrt-bench rays MESH --kind primary|shadow|diffuse|random --out FILE
                       [--res R] [--seed S] [--eye X,Y,Z --look-at X,Y,Z] [--threads N]

Writes a deterministic KDRR ray set for MESH (the same bytes on any machine and thread count):
  primary  R x R camera rays through the pixel centres of the default view of the mesh (or of
           the camera at --eye looking at --look-at: up +y, 40 degree field of view)
  shadow   one occlusion ray per primary hit, towards a point light (flag bit 0 set)
  diffuse  one cosine-weighted ray per primary hit, into the hemisphere facing the camera
  random   R x R rays, origins uniform in the mesh bounds, directions uniform on the sphere
Prints one JSON line: mesh, kind, res, seed, rays, occlusion, out, bytes, generate_ms, camera
("default", or "eye X,Y,Z look_at X,Y,Z").

options:
  --kind K       ray set (required)
  --out FILE     output KDRR file (required)
  --res R        image resolution R x R (default 1024)
  --seed S       random seed for diffuse and random (default 1)
  --eye X,Y,Z    camera position for primary, shadow and diffuse (with --look-at)
  --look-at X,Y,Z  the point the camera looks at (with --eye)
  --threads N    worker threads (default: all cores)
)";

constexpr std::string_view kRenderUsage =
    R"(usage: kdrt-bench render MESH [--shading MODE] [--res R] [--spp S] [--tile 8|16]
                         [--threads N] [--reps K] [--seed S] [--ao-samples K] [--bounces B]
                         [--builder sah|middle] [--c-isect X] [--out FILE] [--compare embree]

Renders the default view of MESH (R x R pixels into a linear float buffer, kdrt::render) K times
(default 5) after one untimed warm-up render. Then traces the render's own camera rays (sample 0)
as one batch with kdrt::intersect (default mode and ISA, as the renderer), K times: the render
loop's overhead is the difference. Prints one JSON line:
  mesh, triangles, shading, width, height, spp, tile, isa, threads, builder, c_isect, reps, parse_ms,
  build_ms, pixels, rays (traced per frame: camera, AO, shadow and bounce rays), seconds (per
  frame, median of the K renders), seconds_min, fps (from the median), mrays_per_s (rays per frame
  / median), cpu_util, batch_rays, batch_seconds (median), batch_mrays_per_s, and for shadings
  that trace camera rays only (normals, eyelight, depth, primid) overhead = seconds / (spp *
  batch_seconds) - 1: what tiling, ray generation and shading add to tracing the same rays
With --compare embree the same camera rays also go through Embree (as in `trace --compare
embree`, both scene flags), adding embree_fps (camera rays of a frame at Embree's best speed) and
the speed and answer keys of `trace --compare embree` (ratio is mrays_per_s / embree_mrays_per_s).

options:
  --shading MODE    normals, eyelight, depth, primid, ao, diffuse (default eyelight)
  --res R           image width and height in pixels (default 1024)
  --spp S           samples per pixel (default 1)
  --tile 8|16       tile edge in pixels (default 16)
  --threads N       worker threads (default: all cores)
  --reps K          timed renders and batch passes (default 5)
  --seed S          random seed (default 1)
  --ao-samples K    ao: occlusion rays per sample (default 16)
  --bounces B       diffuse: indirect bounces (default 0)
  --builder sah|middle  tree builder (default sah)
  --c-isect X       SAH cost of a triangle test relative to a traversal step (default 0.3)
  --out FILE        write the last image: .png/.jpg/.jpeg (8-bit sRGB) or .exr (linear half),
                    through the kdrt-image helper built next to kdrt-bench (kdrt-bench itself
                    does not load OpenImageIO, which would add ~0.2 s to every start)
  --compare embree  also trace the camera rays with Embree (default and robust)
)";

double ms_since(Clock::time_point start) {
    return std::chrono::duration<double, std::milli>(Clock::now() - start).count();
}

double median(std::vector<double> values) {
    std::sort(values.begin(), values.end());
    const size_t mid = values.size() / 2;
    return values.size() % 2 == 1 ? values[mid] : 0.5 * (values[mid - 1] + values[mid]);
}

/// `value` rounded to `digits` decimals, so the JSON shows measurement precision, not noise.
double rounded(double value, int digits) {
    const double scale = std::pow(10.0, digits);
    return std::round(value * scale) / scale;
}

/// CPU time of the whole process (all threads), in seconds.
double process_cpu_seconds() {
    timespec ts{};
    clock_gettime(CLOCK_PROCESS_CPUTIME_ID, &ts);
    return static_cast<double>(ts.tv_sec) + 1e-9 * static_cast<double>(ts.tv_nsec);
}

void print_json(const Json& line) { std::cout << line.dump() << '\n' << std::flush; }

unsigned thread_count(const Args& args) {
    const auto cores = static_cast<uint64_t>(tbb::info::default_concurrency());
    return static_cast<unsigned>(args.get_uint("threads", cores, 1, 4096));
}

/// Under a real-time policy (`chrt -f 50`, as tests/bench/run.sh runs), pins the i-th thread of
/// the arena to the i-th allowed core while it is in the arena. Linux never preempts a SCHED_FIFO
/// thread for another of the same priority, and here a core that went from other work to idle did
/// not pull a queued real-time thread. So a oneTBB worker woken while the other core is briefly
/// busy (back to back runs leave the kernel's reserve for ordinary threads due) is queued behind
/// the calling thread, which never blocks while it finds every task still its own: a whole timed
/// pass loop then runs on one thread (cpu_util 1.0; tests/bench/README.md, session 18). A pinned
/// worker is always woken on its own core. The calling thread gets its old mask back in the
/// destructor.
class RealtimePinning final : public tbb::task_scheduler_observer {
public:
    RealtimePinning(tbb::task_arena& arena, unsigned threads)
        : tbb::task_scheduler_observer(arena) {
        const int policy = sched_getscheduler(0);
        if (policy != SCHED_FIFO && policy != SCHED_RR) return;
        if (sched_getaffinity(0, sizeof(caller_mask_), &caller_mask_) != 0) return;
        for (int cpu = 0; cpu < CPU_SETSIZE; ++cpu)
            if (CPU_ISSET(cpu, &caller_mask_)) cpus_.push_back(cpu);
        if (cpus_.size() < threads) return;  // more threads than cores: leave placement alone
        observe(true);
    }
    ~RealtimePinning() override {
        if (!is_observing()) return;
        observe(false);
        sched_setaffinity(0, sizeof(caller_mask_), &caller_mask_);
    }
    RealtimePinning(const RealtimePinning&) = delete;
    RealtimePinning& operator=(const RealtimePinning&) = delete;

    void on_scheduler_entry(bool /*is_worker*/) override {
        const int index = tbb::this_task_arena::current_thread_index();
        if (index < 0 || static_cast<size_t>(index) >= cpus_.size()) return;
        cpu_set_t one;
        CPU_ZERO(&one);
        CPU_SET(cpus_[static_cast<size_t>(index)], &one);
        sched_setaffinity(0, sizeof(one), &one);
    }

private:
    cpu_set_t caller_mask_{};
    std::vector<int> cpus_;
};

/// Runs `body` with at most `threads` oneTBB workers: its own arena of that size, and a global
/// cap so nothing it calls can run wider; under a real-time policy its threads are pinned.
template <typename Body>
void with_threads(unsigned threads, Body&& body) {
    const tbb::global_control cap(tbb::global_control::max_allowed_parallelism, threads);
    tbb::task_arena arena(static_cast<int>(threads));
    arena.initialize();
    RealtimePinning pinning(arena, threads);
    arena.execute(body);
}

BuildOptions parse_build_options(const Args& args) {
    BuildOptions options;
    const std::string name = args.get("builder").value_or("sah");
    if (name == "sah") {
        options.builder = Builder::kSah;
    } else if (name == "middle") {
        options.builder = Builder::kMiddle;
    } else {
        throw UsageError("option '--builder': '" + name + "' is not one of sah, middle");
    }
    // Only their ratio matters (kdtree.h): C_trav stays 1 and C_isect is the knob.
    options.intersection_cost =
        args.get_float("c-isect", options.intersection_cost, 0.001f, 1000.0f);
    return options;
}

std::string_view builder_name(Builder builder) {
    return builder == Builder::kMiddle ? "middle" : "sah";
}

struct LoadedMesh {
    Mesh mesh;
    double parse_ms = 0;
};

LoadedMesh load_mesh(const std::string& path) {
    const auto start = Clock::now();
    auto mesh = proto::load_mesh_file(path);
    if (!mesh) {
        const proto::ParseError& error = mesh.error();
        // to_string() starts with the path already when the parser knows it.
        throw BenchError("cannot load mesh: " +
                         (error.source.empty() ? path + ": " : std::string()) + error.to_string());
    }
    return {std::move(*mesh), ms_since(start)};
}

KdTree build_tree(const Mesh& mesh, const BuildOptions& options, double& build_ms) {
    const auto start = Clock::now();
    KdTree tree = build_kdtree(mesh, options);
    build_ms = ms_since(start);
    return tree;
}

void write_output(const std::string& path, std::span<const std::byte> bytes) {
    auto written = proto::write_file_bytes(path, bytes);
    if (!written) throw BenchError(written.error());
}

/// The keys both --compare embree outputs end with: how the answers compare, and every mode's
/// speed.
void put_embree_answers(Json& line, const EmbreeReport& embree) {
    const EmbreeSceneReport& best = embree.best();
    line["differences"] = best.differences;
    line["ties"] = best.ties;
    line["kdrt_matches_oracle"] = best.kdrt_matches_oracle;
    line["embree_robust_differences"] = embree.robust.differences;
    line["embree_robust_ties"] = embree.robust.ties;
    line["embree_robust_kdrt_matches_oracle"] = embree.robust.kdrt_matches_oracle;
    line["embree_version"] = embree.version_major;
    Json modes = Json::object();
    for (const EmbreeSceneReport* scene : {&embree.standard, &embree.robust})
        for (const EmbreeModeTiming& m : scene->modes) modes[m.name] = rounded(m.mrays_per_s, 3);
    line["embree_modes"] = modes;
}

/// The speed keys both --compare embree outputs share: Embree's best over both scene flags (the
/// yardstick of `ratio`), then each flag's own best, and the default scene's build.
void put_embree_speeds(Json& line, const EmbreeReport& embree, double mrays_per_s) {
    const EmbreeSceneReport& best = embree.best();
    auto ratio = [&](double embree_mrays) {
        return embree_mrays > 0 ? rounded(mrays_per_s / embree_mrays, 4) : 0.0;
    };
    line["embree_mrays_per_s"] = rounded(best.best_mrays_per_s, 3);
    line["embree_best_mode"] = best.best_mode;
    line["embree_best_flags"] = embree.best_flags();
    line["ratio"] = ratio(best.best_mrays_per_s);
    line["embree_default_mrays_per_s"] = rounded(embree.standard.best_mrays_per_s, 3);
    line["embree_robust_mrays_per_s"] = rounded(embree.robust.best_mrays_per_s, 3);
    line["embree_robust_best_mode"] = embree.robust.best_mode;
    line["ratio_robust"] = ratio(embree.robust.best_mrays_per_s);
    line["embree_build_ms"] = rounded(embree.standard.build_ms, 3);
    line["embree_robust_build_ms"] = rounded(embree.robust.build_ms, 3);
}

int run_build(const Args& args) {
    static constexpr std::array<std::string_view, 1> kNames = {"MESH"};
    args.expect_positional(kNames);
    const std::string& mesh_path = args.positional()[0];
    const BuildOptions build_options = parse_build_options(args);
    const unsigned threads = thread_count(args);
    const auto reps = static_cast<int>(args.get_uint("reps", 1, 1, 1000));

    const LoadedMesh loaded = load_mesh(mesh_path);
    KdTree tree;
    std::vector<double> build_ms;
    double cpu_seconds = 0;
    with_threads(threads, [&] {
        for (int rep = 0; rep < reps; ++rep) {
            double ms = 0;
            const double cpu_start = process_cpu_seconds();
            tree = build_tree(loaded.mesh, build_options, ms);
            cpu_seconds += process_cpu_seconds() - cpu_start;
            build_ms.push_back(ms);
        }
    });
    double wall_ms = 0;
    for (const double ms : build_ms) wall_ms += ms;

    const TreeStats& s = tree.stats;
    Json line;
    line["command"] = "build";
    line["mesh"] = std::filesystem::path(mesh_path).filename().string();
    line["triangles"] = s.triangles;
    line["builder"] = builder_name(build_options.builder);
    line["c_isect"] = build_options.intersection_cost;
    line["threads"] = threads;
    line["reps"] = reps;
    line["parse_ms"] = rounded(loaded.parse_ms, 3);
    line["build_ms"] = rounded(median(build_ms), 3);
    line["build_ms_min"] = rounded(*std::min_element(build_ms.begin(), build_ms.end()), 3);
    line["cpu_util"] = rounded(wall_ms > 0 ? 1e3 * cpu_seconds / wall_ms : 0.0, 2);
    line["node_bytes"] = sizeof(KdNode);
    line["nodes"] = s.nodes;
    line["leaves"] = s.leaves;
    line["empty_leaves"] = s.empty_leaves;
    line["refs"] = s.refs;
    line["max_depth"] = s.max_depth;
    line["mean_leaf_depth"] = rounded(s.mean_leaf_depth, 3);
    line["mean_tris_per_leaf"] = rounded(s.mean_tris_per_leaf, 3);
    line["sah_cost"] = rounded(s.sah_cost, 3);
    line["bytes"] = s.bytes;
    line["bytes_per_triangle"] = rounded(s.bytes_per_triangle, 2);
    if (const auto out_path = args.get("out")) {
        tree.stats.build_ms = 0;  // the only field that differs between builds of one tree
        write_output(*out_path, serialize_tree(tree));
    }
    print_json(line);
    return 0;
}

proto::RayBatch load_rays(const std::string& path) {
    auto bytes = proto::read_file_bytes(path);
    if (!bytes) throw BenchError(bytes.error());
    proto::DecodeLimits limits;
    limits.max_rays = std::numeric_limits<uint32_t>::max();  // a local file: no network limit
    auto batch = proto::decode_rays(*bytes, limits);
    if (!batch)
        throw BenchError("cannot read rays from " + path + ": " + batch.error().to_string());
    return std::move(*batch);
}

int run_trace(const Args& args) {
    static constexpr std::array<std::string_view, 2> kNames = {"MESH", "RAYS.kdrr"};
    args.expect_positional(kNames);
    const std::string& mesh_path = args.positional()[0];
    const std::string& rays_path = args.positional()[1];
    const std::string mode_text = args.get("mode").value_or("auto");
    // "one": kdrt::intersect_single / occluded_single, one ray at a time (as rtcIntersect1).
    const bool one_at_a_time = mode_text == "one";
    const auto mode =
        one_at_a_time ? std::optional(TraceMode::kSingle) : parse_trace_mode(mode_text);
    if (!mode)
        throw UsageError("option '--mode': '" + mode_text +
                         "' is not one of single, packet, auto, one");
    TraceOptions trace_options{*mode, default_isa()};
    if (const auto isa_text = args.get("isa")) {
        const auto isa = parse_isa(*isa_text);
        if (!isa)
            throw UsageError("option '--isa': '" + *isa_text +
                             "' is not one of scalar, sse4, avx2, avx512");
        if (!isa_supported(*isa))
            throw BenchError("--isa " + *isa_text + " is not supported by this CPU");
        if (one_at_a_time && *isa != default_isa())
            throw UsageError("option '--isa': --mode one runs the default ISA's kernel (" +
                             std::string(isa_name(default_isa())) + "; KDRT_ISA sets it)");
        trace_options.isa = *isa;
    }
    const BuildOptions build_options = parse_build_options(args);
    const unsigned threads = thread_count(args);
    const auto reps = static_cast<int>(args.get_uint("reps", 5, 1, 1000));
    const auto out_path = args.get("out");
    const auto compare = args.get("compare");
    if (compare && *compare != "embree") {
        throw UsageError("option '--compare': '" + *compare + "' is not embree");
    }
    if (compare && !kEmbreeAvailable) {
        throw BenchError(
            "--compare embree is not available in this build (neither Embree 4 nor 3 was found "
            "when it was configured)");
    }

    const LoadedMesh loaded = load_mesh(mesh_path);
    const proto::RayBatch batch = load_rays(rays_path);
    const std::span<const Ray> rays = batch.rays;

    KdTree tree;
    double build_ms = 0;
    std::vector<double> seconds;
    double cpu_seconds = 0;
    std::vector<Hit> hits;
    std::vector<uint8_t> occluded;
    std::optional<EmbreeReport> embree;
    TraceStats stats, work;
    with_threads(threads, [&] {
        tree = build_tree(loaded.mesh, build_options, build_ms);
        if (batch.occlusion) {
            occluded.resize(rays.size());
        } else {
            hits.resize(rays.size());
        }
        // Pass 0 warms caches and starts the workers; it is not timed.
        for (int pass = 0; pass <= reps; ++pass) {
            const double cpu_start = process_cpu_seconds();
            const auto start = Clock::now();
            if (one_at_a_time) {
                if (batch.occlusion) {
                    kdrt::occluded_single(tree, rays, occluded);
                } else {
                    kdrt::intersect_single(tree, rays, hits);
                }
            } else if (batch.occlusion) {
                kdrt::occluded(tree, rays, occluded, trace_options, &stats);
            } else {
                kdrt::intersect(tree, rays, hits, trace_options, &stats);
            }
            const double elapsed = std::chrono::duration<double>(Clock::now() - start).count();
            if (pass > 0) {
                seconds.push_back(elapsed);
                cpu_seconds += process_cpu_seconds() - cpu_start;
            }
        }
        if (args.flag("stats")) {
            TraceOptions counting = trace_options;
            counting.count_work = true;
            if (batch.occlusion) {
                kdrt::occluded(tree, rays, occluded, counting, &work);
            } else {
                kdrt::intersect(tree, rays, hits, counting, &work);
            }
        }
        if (compare) {
            embree = compare_with_embree(loaded.mesh, batch, hits, occluded, EmbreeOptions{reps});
        }
    });

    uint64_t answered = 0;
    if (batch.occlusion) {
        answered = static_cast<uint64_t>(
            std::count_if(occluded.begin(), occluded.end(), [](uint8_t o) { return o != 0; }));
        if (out_path) write_output(*out_path, proto::encode_occlusion(occluded));
    } else {
        answered = static_cast<uint64_t>(
            std::count_if(hits.begin(), hits.end(), [](const Hit& h) { return h.is_hit(); }));
        if (out_path) write_output(*out_path, proto::encode_hits(hits));
    }

    const double median_seconds = median(seconds);
    const double mrays_per_s =
        median_seconds > 0 ? static_cast<double>(rays.size()) / median_seconds / 1e6 : 0.0;
    Json line;
    line["command"] = "trace";
    line["mesh"] = std::filesystem::path(mesh_path).filename().string();
    line["rays_file"] = std::filesystem::path(rays_path).filename().string();
    line["rays"] = rays.size();
    line["occlusion"] = batch.occlusion;
    line["mode"] = one_at_a_time ? std::string_view("one") : trace_mode_name(*mode);
    line["isa"] = isa_name(*trace_options.isa);
    line["packets"] = stats.packets;
    line["packet_rays"] = stats.packet_rays;
    line["single_rays"] = stats.single_rays;
    line["sorted_rays"] = stats.sorted_rays;
    line["threads"] = threads;
    line["builder"] = builder_name(build_options.builder);
    line["c_isect"] = build_options.intersection_cost;
    line["reps"] = reps;
    line["parse_ms"] = rounded(loaded.parse_ms, 3);
    line["build_ms"] = rounded(build_ms, 3);
    line["seconds"] = rounded(median_seconds, 9);
    line["seconds_min"] = rounded(*std::min_element(seconds.begin(), seconds.end()), 9);
    line["mrays_per_s"] = rounded(mrays_per_s, 3);
    line["hits"] = answered;
    if (args.flag("stats")) {
        const auto per_ray = [&](uint64_t n) {
            return rounded(
                rays.empty() ? 0.0 : static_cast<double>(n) / static_cast<double>(rays.size()), 3);
        };
        line["steps_per_ray"] = per_ray(work.traversal_steps);
        line["leaves_per_ray"] = per_ray(work.leaves_visited);
        line["tri_tests_per_ray"] = per_ray(work.triangle_tests);
        line["tri_skips_per_ray"] = per_ray(work.triangle_repeats_skipped);
        line["packet_visits"] = work.packet_visits;
        // Wide-node visits per single-traced ray (the dependent node loads of the single-ray
        // kernel), and the share of rays traced as single rays.
        line["wide_visits_per_single_ray"] = rounded(
            work.single_rays == 0
                ? 0.0
                : static_cast<double>(work.wide_visits) / static_cast<double>(work.single_rays),
            3);
        line["single_ray_share"] = rounded(
            rays.empty() ? 0.0
                         : static_cast<double>(work.single_rays) / static_cast<double>(rays.size()),
            3);
        line["lane_utilisation"] = rounded(
            work.packet_visits == 0 ? 0.0
                                    : static_cast<double>(work.packet_lanes) /
                                          (static_cast<double>(work.packet_visits) * work.width),
            3);
    }
    // CPU seconds per wall second while tracing: close to `threads` only when the workers had
    // their cores to themselves; lower means other load (or a VM host) took CPU time.
    const double wall_total = std::accumulate(seconds.begin(), seconds.end(), 0.0);
    line["cpu_util"] = rounded(wall_total > 0 ? cpu_seconds / wall_total : 0.0, 2);
    if (embree) {
        put_embree_speeds(line, *embree, mrays_per_s);
        // One ray at a time against one ray at a time: Embree's fastest rtcIntersect1 /
        // rtcOccluded1 (either scene flag, incoherent or coherent).
        const std::string one_name = batch.occlusion ? "occluded1" : "intersect1";
        const EmbreeModeTiming* one = nullptr;
        for (const EmbreeSceneReport* scene : {&embree->standard, &embree->robust})
            for (const EmbreeModeTiming& m : scene->modes)
                if ((m.name.ends_with(one_name) || m.name.ends_with(one_name + "_coherent")) &&
                    (one == nullptr || m.mrays_per_s > one->mrays_per_s))
                    one = &m;
        if (one != nullptr) {
            line["embree_1_mrays_per_s"] = rounded(one->mrays_per_s, 3);
            line["embree_1_mode"] = one->name;
            line["ratio_1"] =
                one->mrays_per_s > 0 ? rounded(mrays_per_s / one->mrays_per_s, 4) : 0.0;
        }
        line["embree_bytes_per_triangle"] = rounded(embree->standard.bytes_per_triangle, 2);
        put_embree_answers(line, *embree);
    }
    print_json(line);
    return 0;
}

int run_all_hits(const Args& args) {
    static constexpr std::array<std::string_view, 2> kNames = {"MESH", "RAYS.kdrr"};
    args.expect_positional(kNames);
    const std::string& mesh_path = args.positional()[0];
    const std::string& rays_path = args.positional()[1];
    const unsigned threads = thread_count(args);
    const auto reps = static_cast<int>(args.get_uint("reps", 5, 1, 1000));
    const auto max_hits = static_cast<uint32_t>(args.get_uint("max-hits", 16, 1, kMaxHitsPerRay));
    const bool merge = args.flag("merge");
    const std::string mode_text = args.get("mode").value_or("auto");
    const auto mode = parse_trace_mode(mode_text);
    if (!mode)
        throw UsageError("option '--mode': '" + mode_text + "' is not one of single, packet, auto");
    AllHitsOptions options;
    options.max_hits = max_hits;
    options.merge_coincident = merge;
    options.mode = *mode;
    const LoadedMesh loaded = load_mesh(mesh_path);
    const proto::RayBatch batch = load_rays(rays_path);
    const std::span<const Ray> rays = batch.rays;
    KdTree tree;
    double build_ms = 0;
    std::vector<double> all_s, count_s, auto_s, single_s;
    uint64_t total_hits = 0, kept = 0;
    with_threads(threads, [&] {
        tree = build_tree(loaded.mesh, BuildOptions{}, build_ms);
        std::vector<Hit> hits(rays.size());
        std::vector<uint32_t> counts(rays.size());
        const auto timed = [&](std::vector<double>& out, auto&& f) {
            for (int pass = 0; pass <= reps; ++pass) {
                const auto start = Clock::now();
                f();
                const double elapsed = std::chrono::duration<double>(Clock::now() - start).count();
                if (pass > 0) out.push_back(elapsed);
            }
        };
        timed(all_s, [&] {
            const AllHits all = intersect_all(tree, rays, options);
            kept = all.hits.size();
            total_hits = std::accumulate(all.counts.begin(), all.counts.end(), uint64_t{0});
        });
        timed(count_s, [&] { count_intersections(tree, rays, options, counts); });
        timed(auto_s, [&] { kdrt::intersect(tree, rays, hits); });
        timed(single_s, [&] { intersect_single(tree, rays, hits); });
    });
    const auto mrays = [&](const std::vector<double>& s) {
        const double m = median(s);
        return m > 0 ? static_cast<double>(rays.size()) / m / 1e6 : 0.0;
    };
    Json line;
    line["command"] = "all-hits";
    line["mesh"] = std::filesystem::path(mesh_path).filename().string();
    line["rays_file"] = std::filesystem::path(rays_path).filename().string();
    line["rays"] = rays.size();
    line["threads"] = threads;
    line["reps"] = reps;
    line["mode"] = trace_mode_name(*mode);
    line["max_hits"] = max_hits;
    line["merge"] = merge;
    line["build_ms"] = rounded(build_ms, 3);
    line["hits_per_ray"] = rounded(
        rays.empty() ? 0.0 : static_cast<double>(total_hits) / static_cast<double>(rays.size()), 3);
    line["kept_hits"] = kept;
    line["all_seconds"] = rounded(median(all_s), 6);
    line["all_mrays_per_s"] = rounded(mrays(all_s), 3);
    line["count_mrays_per_s"] = rounded(mrays(count_s), 3);
    line["closest_auto_mrays_per_s"] = rounded(mrays(auto_s), 3);
    line["closest_single_mrays_per_s"] = rounded(mrays(single_s), 3);
    line["all_vs_closest_single"] =
        mrays(single_s) > 0 ? rounded(mrays(all_s) / mrays(single_s), 3) : 0.0;
    line["all_vs_closest_auto"] =
        mrays(auto_s) > 0 ? rounded(mrays(all_s) / mrays(auto_s), 3) : 0.0;
    print_json(line);
    return 0;
}

/// The query points of `kdrt-bench distance`: `count` uniform in the mesh's box grown by 10%
/// (or, when `far` > 0, on the sphere `far` diagonals from its centre), and `count` near the
/// surface (area-uniform samples moved by up to 1% of the diagonal).
float norm(Vec3 v) { return std::sqrt(dot(v, v)); }

void distance_query_points(const Mesh& mesh, size_t count, uint64_t seed, float far,
                           std::vector<Vec3>& uniform, std::vector<Vec3>& near) {
    test::Rng rng(seed);
    Aabb box = mesh_bounds(mesh);
    const Vec3 extent = box.hi - box.lo;
    const Vec3 centre = (box.lo + box.hi) * 0.5f;
    box.lo = box.lo - extent * 0.05f;
    box.hi = box.hi + extent * 0.05f;
    const float jitter = 0.01f * norm(extent);
    uniform.resize(count);
    for (Vec3& p : uniform)
        p = far > 0 ? centre + rng.on_sphere() * (far * norm(extent)) : rng.in_box(box);
    std::vector<double> area(mesh.triangle_count());
    double total = 0;
    for (size_t t = 0; t < area.size(); ++t) {
        total += 0.5 * static_cast<double>(norm(cross(mesh.corner(t, 1) - mesh.corner(t, 0),
                                                      mesh.corner(t, 2) - mesh.corner(t, 0))));
        area[t] = total;
    }
    near.resize(count);
    for (Vec3& p : near) {
        const double pick = static_cast<double>(rng.uniform()) * total;
        const size_t t = std::min<size_t>(
            static_cast<size_t>(std::upper_bound(area.begin(), area.end(), pick) - area.begin()),
            area.size() - 1);
        float u = rng.uniform(), v = rng.uniform();
        if (u + v > 1.0f) {  // fold the far half of the square back onto the triangle
            u = 1.0f - u;
            v = 1.0f - v;
        }
        const Vec3 a = mesh.corner(t, 0), b = mesh.corner(t, 1), c = mesh.corner(t, 2);
        p = a + (b - a) * u + (c - a) * v + rng.on_sphere() * (jitter * rng.uniform());
    }
}

bool same_closest_point(const ClosestPoint& a, const ClosestPoint& b) {
    const auto same = [](float x, float y) {
        return std::bit_cast<uint32_t>(x) == std::bit_cast<uint32_t>(y);
    };
    return same(a.distance, b.distance) && a.prim == b.prim && same(a.u, b.u) && same(a.v, b.v) &&
           same(a.point.x, b.point.x) && same(a.point.y, b.point.y) && same(a.point.z, b.point.z) &&
           a.feature == b.feature && a.side == b.side;
}

int run_distance(const Args& args) {
    static constexpr std::array<std::string_view, 1> kNames = {"MESH"};
    args.expect_positional(kNames);
    const std::string& mesh_path = args.positional()[0];
    const unsigned threads = thread_count(args);
    const auto reps = static_cast<int>(args.get_uint("reps", 5, 1, 1000));
    const auto points = static_cast<size_t>(args.get_uint("points", 100000, 2, 1u << 26));
    const uint64_t seed = args.get_uint("seed", 1, 0, std::numeric_limits<uint64_t>::max());
    const float far = args.get_float("far", 0.0f, 0.0f, 1e30f);
    const LoadedMesh loaded = load_mesh(mesh_path);
    const size_t triangles = std::max<size_t>(1, loaded.mesh.triangle_count());
    const auto brute_default = static_cast<uint64_t>(
        std::clamp<double>(1e8 / static_cast<double>(triangles), 32.0, 4096.0));
    const size_t half = points / 2;  // of each kind (an odd --points loses one)
    const auto brute = static_cast<size_t>(
        args.get_uint("brute", std::min<uint64_t>(brute_default, 2 * half), 2, 2 * half));

    std::vector<Vec3> uniform, near;
    distance_query_points(loaded.mesh, half, seed, far, uniform, near);
    // The brute-force subset: its first half from each kind.
    std::vector<Vec3> subset(uniform.begin(),
                             uniform.begin() + static_cast<std::ptrdiff_t>(brute / 2));
    subset.insert(subset.end(), near.begin(),
                  near.begin() + static_cast<std::ptrdiff_t>(brute - brute / 2));

    KdTree tree;
    SurfaceIndex index;
    double build_ms = 0, surface_ms = 0, brute_seconds = 0, cpu_seconds = 0, wall_seconds = 0;
    std::vector<double> kd_uniform, kd_near, signed_uniform, signed_near;
    uint64_t mismatches = 0;
    with_threads(threads, [&] {
        tree = build_tree(loaded.mesh, BuildOptions{}, build_ms);
        auto start = Clock::now();
        index = build_surface_index(tree);
        surface_ms = ms_since(start);
        std::vector<ClosestPoint> out(uniform.size());
        const auto timed = [&](std::vector<double>& seconds, std::span<const Vec3> query,
                               bool sign) {
            for (int pass = 0; pass <= reps; ++pass) {
                const double cpu0 = process_cpu_seconds();
                const auto t0 = Clock::now();
                closest_points(tree, index, query, std::span(out).first(query.size()),
                               {INFINITY, sign});
                const double elapsed = std::chrono::duration<double>(Clock::now() - t0).count();
                if (pass == 0) continue;
                seconds.push_back(elapsed);
                wall_seconds += elapsed;
                cpu_seconds += process_cpu_seconds() - cpu0;
            }
        };
        timed(kd_uniform, uniform, false);
        timed(kd_near, near, false);
        timed(signed_uniform, uniform, true);
        timed(signed_near, near, true);

        // Brute force over the subset (signed: the side costs one dot product), and the kD
        // answers to compare: signed ones equal to it, unsigned ones too but for the side.
        const std::vector<TriVerts> tris = triangles_by_id(tree);
        std::vector<ClosestPoint> truth(subset.size());
        start = Clock::now();
        tbb::parallel_for(size_t{0}, subset.size(), [&](size_t i) {
            truth[i] = brute_force_closest_point(tris, index, subset[i], {INFINITY, true});
        });
        brute_seconds = std::chrono::duration<double>(Clock::now() - start).count();
        std::vector<ClosestPoint> kd(subset.size()), kd_signed(subset.size());
        closest_points(tree, index, subset, kd, {INFINITY, false});
        closest_points(tree, index, subset, kd_signed, {INFINITY, true});
        for (size_t i = 0; i < subset.size(); ++i) {
            ClosestPoint unsigned_truth = truth[i];
            unsigned_truth.side = Side::kUnknown;
            mismatches += same_closest_point(kd[i], unsigned_truth) ? 0 : 1;
            mismatches += same_closest_point(kd_signed[i], truth[i]) ? 0 : 1;
        }
    });
    const auto rate = [](size_t count, double seconds) {
        return seconds > 0 ? static_cast<double>(count) / seconds : 0.0;
    };
    const double kd_rate = rate(uniform.size() + near.size(), median(kd_uniform) + median(kd_near));
    const double signed_rate =
        rate(uniform.size() + near.size(), median(signed_uniform) + median(signed_near));
    const double brute_rate = rate(subset.size(), brute_seconds);
    Json line;
    line["command"] = "distance";
    line["mesh"] = std::filesystem::path(mesh_path).filename().string();
    line["triangles"] = loaded.mesh.triangle_count();
    line["closed"] = index.closed;
    line["threads"] = threads;
    line["reps"] = reps;
    line["points"] = uniform.size() + near.size();
    line["far"] = far;
    line["build_ms"] = rounded(build_ms, 3);
    line["surface_ms"] = rounded(surface_ms, 3);
    line["kd_points_per_s"] = rounded(kd_rate, 0);
    line["kd_uniform_points_per_s"] = rounded(rate(uniform.size(), median(kd_uniform)), 0);
    line["kd_near_points_per_s"] = rounded(rate(near.size(), median(kd_near)), 0);
    line["signed_points_per_s"] = rounded(signed_rate, 0);
    line["signed_uniform_points_per_s"] = rounded(rate(uniform.size(), median(signed_uniform)), 0);
    line["signed_near_points_per_s"] = rounded(rate(near.size(), median(signed_near)), 0);
    line["brute_points"] = subset.size();
    line["brute_seconds"] = rounded(brute_seconds, 4);
    line["brute_points_per_s"] = rounded(brute_rate, 1);
    line["ratio"] = brute_rate > 0 ? rounded(kd_rate / brute_rate, 1) : 0.0;
    line["cpu_util"] = rounded(wall_seconds > 0 ? cpu_seconds / wall_seconds : 0.0, 2);
    line["matches_brute_force"] = mismatches == 0;
    line["mismatches"] = mismatches;
    print_json(line);
    if (mismatches != 0) {
        std::cerr << "kdrt-bench distance: error: " << mismatches << " of " << 2 * subset.size()
                  << " kD answers differ from brute force\n";
        return 1;
    }
    return 0;
}

/// "X,Y,Z": three finite numbers.
Vec3 parse_vec3(std::string_view option, const std::string& text) {
    Vec3 v;
    const char* p = text.data();
    const char* const end = text.data() + text.size();
    for (int a = 0; a < 3; ++a) {
        const auto [next, ec] = std::from_chars(p, end, v[a]);
        const bool separator_ok = a < 2 ? (next != end && *next == ',') : next == end;
        if (ec != std::errc() || !separator_ok || !std::isfinite(v[a])) {
            throw UsageError("option '--" + std::string(option) + "': '" + text +
                             "' is not X,Y,Z (three finite numbers)");
        }
        p = next + 1;
    }
    return v;
}

int run_rays(const Args& args) {
    static constexpr std::array<std::string_view, 1> kNames = {"MESH"};
    args.expect_positional(kNames);
    const std::string& mesh_path = args.positional()[0];
    const std::string kind_text = args.require("kind");
    const auto kind = parse_ray_kind(kind_text);
    if (!kind) {
        throw UsageError("option '--kind': '" + kind_text +
                         "' is not one of primary, shadow, diffuse, random");
    }
    const std::string out_path = args.require("out");
    RayGenOptions options;
    options.kind = *kind;
    options.res = static_cast<uint32_t>(args.get_uint("res", 1024, 1, 65535));
    options.seed = args.get_uint("seed", 1, 0, std::numeric_limits<uint64_t>::max());
    const auto eye = args.get("eye"), look_at = args.get("look-at");
    if (eye.has_value() != look_at.has_value()) {
        throw UsageError(std::string("option '--") + (eye ? "look-at" : "eye") +
                         "' is required with '--" + (eye ? "eye" : "look-at") + "'");
    }
    std::string camera_text = "default";
    if (eye) {
        CameraSpec spec;
        spec.eye = parse_vec3("eye", *eye);
        spec.look_at = parse_vec3("look-at", *look_at);
        // Checked here, before the mesh is loaded: a bad camera is a command-line error.
        try {
            (void)Camera(spec, 1, 1);
        } catch (const CameraError& e) {
            throw UsageError(std::string("options '--eye'/'--look-at': ") + e.what());
        }
        options.camera = spec;
        camera_text = "eye " + *eye + " look_at " + *look_at;
    }
    const unsigned threads = thread_count(args);

    const LoadedMesh loaded = load_mesh(mesh_path);
    std::vector<Ray> rays;
    double generate_ms = 0;
    with_threads(threads, [&] {
        const KdTree tree = build_kdtree(loaded.mesh);
        const auto start = Clock::now();
        rays = generate_rays(tree, options);
        generate_ms = ms_since(start);
    });
    const bool occlusion = *kind == RayKind::kShadow;
    const std::vector<std::byte> bytes = proto::encode_rays(rays, occlusion);
    write_output(out_path, bytes);

    Json line;
    line["command"] = "rays";
    line["mesh"] = std::filesystem::path(mesh_path).filename().string();
    line["kind"] = ray_kind_name(*kind);
    line["res"] = options.res;
    line["seed"] = options.seed;
    line["rays"] = rays.size();
    line["occlusion"] = occlusion;
    line["out"] = out_path;
    line["bytes"] = bytes.size();
    line["generate_ms"] = rounded(generate_ms, 3);
    line["camera"] = camera_text;
    print_json(line);
    return 0;
}

/// Instance transforms of `copies` copies of a mesh with bounds `b` on replicate_grid's grid
/// (the same translations, so the merged mesh holds the same triangles), each moved up by
/// `lift` (a pose change).
std::vector<Affine3x4> grid_transforms(const Aabb& b, uint32_t copies, float lift) {
    uint32_t side = 1;
    while (side * side < copies) ++side;
    const Vec3 e = b.extent();
    std::vector<Affine3x4> out(copies);
    for (uint32_t c = 0; c < copies; ++c) {
        out[c].m[0][3] = 1.1f * e.x * static_cast<float>(c % side);
        out[c].m[1][3] = lift;
        out[c].m[2][3] = 1.1f * e.z * static_cast<float>(c / side);
    }
    return out;
}

template <typename F>
double median_seconds(int reps, F&& f) {
    std::vector<double> s;
    for (int r = 0; r < reps; ++r) {
        const auto start = Clock::now();
        f();
        s.push_back(std::chrono::duration<double>(Clock::now() - start).count());
    }
    return median(s);
}

/// Answers that differ between two scene answers of the same ray (geometry or triangle, or t
/// beyond 1e-4 relative): the merged mesh and Embree compute the same triangles in other
/// arithmetic, so a few rays through edges differ.
bool differs(const SceneHit& a, const SceneHit& b) {
    if (a.is_hit() != b.is_hit()) return true;
    if (!a.is_hit()) return false;
    return a.geom != b.geom || a.prim != b.prim ||
           std::fabs(static_cast<double>(a.t) - b.t) > 1e-4 * std::fabs(static_cast<double>(a.t));
}

int run_scene_instances(const Args& args) {
    const std::string from = args.require("from");
    const auto copies = static_cast<uint32_t>(args.get_uint("copies", 16, 1, kMaxSceneInstances));
    const auto res = static_cast<uint32_t>(args.get_uint("res", 512, 16, 4096));
    const int reps = static_cast<int>(args.get_uint("reps", 5, 1, 1000));
    const bool embree = args.get("compare").has_value();
    if (embree && *args.get("compare") != "embree")
        throw UsageError("option '--compare': only 'embree' is supported");
    if (embree && !kEmbreeAvailable)
        throw UsageError("option '--compare': this kdrt-bench was built without Embree");
    // The ray kinds to time, in this order (--kinds primary,shadow: a profile of two of them).
    std::vector<RayKind> ray_kinds;
    const std::string kinds_text = args.get("kinds").value_or("primary,shadow,diffuse,random");
    for (size_t at = 0; at <= kinds_text.size();) {
        const size_t comma = std::min(kinds_text.find(',', at), kinds_text.size());
        const std::string name = kinds_text.substr(at, comma - at);
        const auto kind = parse_ray_kind(name);
        if (!kind)
            throw UsageError("option '--kinds': '" + name +
                             "' is not one of primary, shadow, diffuse, random");
        ray_kinds.push_back(*kind);
        at = comma + 1;
    }
    const Mesh mesh =
        from == "sphere" ? test::uv_sphere({0, 0, 0}, 1.0f, 24, 48) : load_mesh(from).mesh;
    Json line;
    line["command"] = "scene";
    line["kind"] = "instances";
    line["from"] = from;
    line["triangles_per_instance"] = mesh.triangle_count();
    line["instances"] = copies;
    line["threads"] = thread_count(args);
    with_threads(thread_count(args), [&] {
        const Aabb bounds = mesh_bounds(mesh);
        auto start = Clock::now();
        auto tree = std::make_shared<const KdTree>(build_kdtree(mesh));
        line["mesh_build_ms"] = rounded(ms_since(start), 3);
        const std::vector<Affine3x4> poses = grid_transforms(bounds, copies, 0.0f);
        std::vector<SceneInstance> list;
        for (const Affine3x4& t : poses) list.push_back({tree, t, nullptr, nullptr});
        const Scene scene = build_scene(std::move(list));
        line["scene_build_ms"] = rounded(scene.stats().build_ms, 3);
        line["top_nodes"] = scene.stats().nodes;
        line["top_refs"] = scene.stats().refs;
        line["top_depth"] = scene.stats().max_depth;
        line["bytes_per_instance"] = rounded(scene.stats().bytes_per_instance, 1);
        // Every instance moved (alternately up and back), only the top level rebuilt.
        const std::vector<Affine3x4> moved =
            grid_transforms(bounds, copies, 0.01f * bounds.extent().y);
        std::vector<InstancePose> updates(copies);
        for (uint32_t g = 0; g < copies; ++g) updates[g] = {g, moved[g]};
        double pose_ms = 1e3 * median_seconds(std::max(reps, 5), [&] {
                             const Scene next = scene.with_transforms(updates);
                             if (next.size() != copies)
                                 throw BenchError("pose update lost instances");
                         });
        line["pose_update_ms"] = rounded(pose_ms, 4);

        start = Clock::now();
        const Mesh merged = test::replicate_grid(mesh, copies);
        const KdTree merged_tree = build_kdtree(merged);
        line["merged_build_ms"] = rounded(ms_since(start), 3);
        line["merged_bytes"] = merged_tree.stats.bytes;

        std::unique_ptr<EmbreeInstanceScene> em;
        if (embree) {
            em = std::make_unique<EmbreeInstanceScene>(mesh, poses);
            line["embree_blas_build_ms"] = rounded(em->blas_build_ms(), 3);
            line["embree_top_build_ms"] = rounded(em->top_build_ms(), 3);
            line["embree_pose_update_ms"] = rounded(
                1e3 * median_seconds(std::max(reps, 5), [&] { em->set_transforms(moved); }), 4);
            em->set_transforms(poses);
        }
        Json kinds = Json::array();
        for (const RayKind kind : ray_kinds) {
            RayGenOptions gen;
            gen.kind = kind;
            gen.res = res;
            const std::vector<Ray> rays = generate_rays(merged_tree, gen);
            const bool occlusion = kind == RayKind::kShadow;
            const double n = static_cast<double>(rays.size());
            std::vector<Hit> mh(rays.size());
            std::vector<SceneHit> sh(rays.size()), eh(rays.size());
            std::vector<uint8_t> mo(rays.size()), so(rays.size()), eo(rays.size());
            const auto merged_pass = [&] {
                if (occlusion)
                    occluded(merged_tree, rays, mo);
                else
                    intersect(merged_tree, rays, mh);
            };
            const auto scene_pass = [&] {
                if (occlusion)
                    occluded(scene, rays, so);
                else
                    intersect(scene, rays, sh);
            };
            merged_pass();
            scene_pass();
            const double cpu_start = process_cpu_seconds();
            const auto wall_start = Clock::now();
            const double merged_mrays = n / median_seconds(reps, merged_pass) / 1e6;
            const double scene_mrays = n / median_seconds(reps, scene_pass) / 1e6;
            const double wall = std::chrono::duration<double>(Clock::now() - wall_start).count();
            const double cpu_util = (process_cpu_seconds() - cpu_start) / wall;
            SceneTraceStats stats;
            if (occlusion)
                occluded(scene, rays, so, {}, &stats);
            else
                intersect(scene, rays, sh, {}, &stats);
            Json k;
            k["kind"] = std::string(ray_kind_name(kind));
            k["rays"] = rays.size();
            k["merged_mrays_per_s"] = rounded(merged_mrays, 3);
            k["scene_mrays_per_s"] = rounded(scene_mrays, 3);
            k["ratio_vs_merged"] = rounded(scene_mrays / merged_mrays, 3);
            k["cpu_util"] = rounded(cpu_util, 2);  // CPU seconds per wall second, kdrt passes
            k["instance_visits_per_ray"] =
                rounded(static_cast<double>(stats.instance_visits) / n, 3);
            k["batched_calls"] = stats.instance_batches;
            // The merged mesh's triangle ids: instance g's triangle p is g * T + p.
            const uint64_t tri_count = mesh.triangle_count();
            uint64_t merged_diff = 0;
            for (size_t i = 0; i < rays.size(); ++i) {
                if (occlusion) {
                    merged_diff += mo[i] != so[i];
                } else {
                    const Hit& h = mh[i];
                    const SceneHit m =
                        h.is_hit() ? SceneHit{h.t, static_cast<uint32_t>(h.prim % tri_count), h.u,
                                              h.v, static_cast<uint32_t>(h.prim / tri_count)}
                                   : SceneHit{};
                    merged_diff += differs(m, sh[i]);
                }
            }
            k["differences_vs_merged"] = merged_diff;
            if (em) {
                const EmbreeSceneTiming et = em->trace(rays, occlusion, reps, eh, eo);
                k["embree_mrays_per_s"] = rounded(et.best_mrays_per_s, 3);
                k["embree_best_mode"] = et.best_mode;
                Json modes = Json::object();  // every Embree mode's Mrays/s
                for (const auto& [name, mrays] : et.modes) modes[name] = rounded(mrays, 3);
                k["embree_modes"] = modes;
                k["ratio_vs_embree"] = rounded(scene_mrays / et.best_mrays_per_s, 3);
                uint64_t ediff = 0;
                for (size_t i = 0; i < rays.size(); ++i)
                    ediff += occlusion ? eo[i] != so[i] : differs(eh[i], sh[i]);
                k["differences_vs_embree"] = ediff;
            }
            kinds.push_back(k);
        }
        line["kinds"] = kinds;
    });
    print_json(line);
    return 0;
}

/// scene_latency.py's layout at frame `frame`: instance k on a ring grid around the origin
/// (spacing 3), turned about z by 0.01 frame + 0.37 k, scale 1.5; in double, rounded to float as
/// the server decodes the Python client's poses.
std::vector<Affine3x4> ring_poses(uint32_t n, int frame) {
    const auto side = static_cast<uint32_t>(std::ceil(std::sqrt(static_cast<double>(n))));
    std::vector<Affine3x4> out(n);
    for (uint32_t k = 0; k < n; ++k) {
        const double x = (static_cast<double>(k % side) - side / 2.0) * 3.0;
        const double y = (static_cast<double>(k / side) - side / 2.0) * 3.0;
        const double a = 0.01 * frame + 0.37 * k;
        const double c = std::cos(a) * 1.5, s = std::sin(a) * 1.5;
        Affine3x4& t = out[k];
        t.m[0][0] = static_cast<float>(c), t.m[0][1] = static_cast<float>(-s);
        t.m[0][3] = static_cast<float>(x);
        t.m[1][0] = static_cast<float>(s), t.m[1][1] = static_cast<float>(c);
        t.m[1][3] = static_cast<float>(y);
        t.m[2][2] = 1.5f;
    }
    return out;
}

/// `scene lidar`: scene_latency.py's scan in process (the engine's scan_lidar only).
int run_scene_lidar(const Args& args) {
    const std::string from = args.require("from");
    const auto copies = static_cast<uint32_t>(args.get_uint("copies", 1000, 1, kMaxSceneInstances));
    const auto azimuth = static_cast<uint32_t>(args.get_uint("azimuth", 2048, 1, 1u << 16));
    const auto channels = static_cast<uint32_t>(args.get_uint("channels", 64, 1, 1024));
    const auto returns = static_cast<uint32_t>(args.get_uint("returns", 1, 1, kMaxHitsPerRay));
    const int reps = static_cast<int>(args.get_uint("reps", 7, 1, 1000));
    const int frame = static_cast<int>(args.get_uint("frame", 1, 0, 1000000));
    const Mesh mesh = load_mesh(from).mesh;
    Json line;
    line["command"] = "scene";
    line["kind"] = "lidar";
    line["from"] = from;
    line["instances"] = copies;
    line["beams"] = uint64_t{channels} * azimuth;
    line["returns_per_beam"] = returns;
    line["threads"] = thread_count(args);
    with_threads(thread_count(args), [&] {
        auto tree = std::make_shared<const KdTree>(build_kdtree(mesh));
        // The tree's HitClearance, shared by every instance (as the server's scene cache gives
        // it): single returns skip the windows it rules out. --no-clearance leaves it out.
        std::shared_ptr<const HitClearance> clearance;
        if (!args.flag("no-clearance")) {
            const auto start = Clock::now();
            clearance = std::make_shared<const HitClearance>(build_hit_clearance(*tree));
            line["clearance_ms"] = rounded(ms_since(start), 3);
            line["clearance_bytes"] = clearance->bytes();
        }
        std::vector<SceneInstance> list;
        for (const Affine3x4& t : ring_poses(copies, frame))
            list.push_back({tree, t, nullptr, clearance});
        const Scene scene = build_scene(std::move(list));
        LidarSpec spec;
        spec.elevation_deg = lidar_elevations(-25.0, 15.0, channels);
        spec.azimuth_steps = azimuth;
        spec.max_range = 120.0f;
        spec.returns = returns;
        spec.pose.m = {1, 0, 0, 0.7, 0, 1, 0, 0.3, 0, 0, 1, 0.2, 0, 0, 0, 1};
        ScenePointCloud cloud = scan_lidar(scene, spec);
        line["scan_ms"] =
            rounded(1e3 * median_seconds(reps, [&] { cloud = scan_lidar(scene, spec); }), 3);
        // The pose update's engine part: every instance moved to frame F + 1, the top level
        // rebuilt (Scene::with_transforms, as the server's pose update runs it).
        std::vector<InstancePose> poses;
        for (const Affine3x4& t : ring_poses(copies, frame + 1))
            poses.push_back({static_cast<uint32_t>(poses.size()), t});
        line["pose_ms"] = rounded(
            1e3 * median_seconds(reps, [&] { (void)scene.with_transforms(poses).size(); }), 3);
        // FNV-1a over the points and geometry ids: equal answers print equal hashes.
        uint64_t hash = 1469598103934665603ull;
        const auto mix = [&](const void* data, size_t bytes) {
            const auto* p = static_cast<const unsigned char*>(data);
            for (size_t i = 0; i < bytes; ++i) hash = (hash ^ p[i]) * 1099511628211ull;
        };
        mix(cloud.cloud.points.data(), cloud.cloud.points.size() * sizeof(LidarPoint));
        mix(cloud.geom.data(), cloud.geom.size() * sizeof(uint32_t));
        line["points"] = cloud.cloud.points.size();
        line["answer_fnv1a"] = hash;
    });
    print_json(line);
    return 0;
}

constexpr std::string_view kSceneUsage =
    R"(usage: kdrt-bench scene stadium --out FILE [--size S]
       kdrt-bench scene grid --from MESH --copies N --out FILE
       kdrt-bench scene instances --from MESH|sphere --copies N [--res R] [--reps K]
                                  [--threads T] [--compare embree] [--kinds K1,K2,...]
       kdrt-bench scene lidar --from MESH [--copies N] [--azimuth A] [--channels C]
                              [--returns R] [--frame F] [--reps K] [--threads T]
                              [--no-clearance]

Writes a generated scene; the format follows the extension of FILE (.ply is binary PLY).
  stadium  a closed box of side S (default 1000) around a finely tessellated unit sphere
           (180 x 360 segments, ~130k triangles): the "teapot in a stadium"
  grid     N copies of MESH (default 16) on a square grid: 16 bunnies are 1.2M triangles
Prints one JSON line: kind, triangles, vertices, out, bytes.

  instances  times a two-level scene (kdrt/scene.h) of N instances of MESH (or a generated
           2,256-triangle sphere) on the grid layout, against the same triangles merged into one
           mesh (grid) traced by the mesh kernel, and with --compare embree against Embree's
           instancing (RTC_GEOMETRY_TYPE_INSTANCE over one BLAS). Ray sets of the merged mesh
           (primary, shadow, diffuse, random, or those --kinds lists; R x R, default 512), K passes
           each (median, default 5). Prints one JSON line: build times, bytes_per_instance,
           pose_update_ms (every instance moved, the top level rebuilt), and per ray kind the
           Mrays/s of each tracer, ratio_vs_merged, ratio_vs_embree, the answers that differ and
           instance_visits_per_ray (the scene's, shadow rays included).
  lidar    scene_latency.py's scan in process: N instances of MESH (default 1,000) on its ring
           grid at frame F (default 1), a lidar of C channels (default 64, -25..15 degrees) x A
           azimuth steps (default 2048), R returns, from (0.7, 0.3, 0.2) to range 120; K scans
           (median, default 7), every instance carrying the mesh tree's HitClearance (built once:
           clearance_ms, clearance_bytes; --no-clearance: none, every single return gets its
           every-hit window, the same answers). Prints scan_ms, pose_ms (Scene::with_transforms
           moving every instance to frame F + 1: the top level rebuilt), points and answer_fnv1a
           (a hash of the points and geometry ids: equal answers, equal hashes).
)";

int run_scene(const Args& args) {
    static constexpr std::array<std::string_view, 1> kNames = {"KIND"};
    args.expect_positional(kNames);
    const std::string& kind = args.positional()[0];
    if (kind == "instances") return run_scene_instances(args);
    if (kind == "lidar") return run_scene_lidar(args);
    const std::string out_path = args.require("out");
    const auto format = proto::mesh_format_from_path(out_path);
    if (!format)
        throw UsageError("option '--out': cannot tell the mesh format from the extension of '" +
                         out_path + "'");
    Mesh mesh;
    if (kind == "stadium") {
        const auto size = static_cast<float>(args.get_uint("size", 1000, 4, 1000000));
        mesh = test::teapot_in_stadium(size, 180, 360);
    } else if (kind == "grid") {
        const LoadedMesh loaded = load_mesh(args.require("from"));
        mesh = test::replicate_grid(loaded.mesh,
                                    static_cast<uint32_t>(args.get_uint("copies", 16, 1, 4096)));
    } else {
        throw UsageError("scene kind '" + kind + "' is not one of stadium, grid");
    }
    const std::vector<std::byte> bytes = proto::write_mesh(mesh, *format);
    write_output(out_path, bytes);
    Json line;
    line["command"] = "scene";
    line["kind"] = kind;
    line["triangles"] = mesh.triangle_count();
    line["vertices"] = mesh.vertex_count();
    line["out"] = out_path;
    line["bytes"] = bytes.size();
    print_json(line);
    return 0;
}

int run_render(const Args& args) {
    static constexpr std::array<std::string_view, 1> kNames = {"MESH"};
    args.expect_positional(kNames);
    const std::string& mesh_path = args.positional()[0];
    RenderSettings settings;
    const std::string shading_text = args.get("shading").value_or("eyelight");
    const auto shading = parse_shading(shading_text);
    if (!shading) {
        throw UsageError("option '--shading': '" + shading_text +
                         "' is not one of normals, eyelight, depth, primid, ao, diffuse");
    }
    settings.shading = *shading;
    settings.width = settings.height =
        static_cast<uint32_t>(args.get_uint("res", 1024, 1, kMaxImageSize));
    settings.spp = static_cast<uint32_t>(args.get_uint("spp", 1, 1, kMaxSamplesPerPixel));
    settings.tile_size = static_cast<uint32_t>(args.get_uint("tile", 16, 8, 16));
    if (settings.tile_size != 8 && settings.tile_size != 16) {
        throw UsageError("option '--tile': '" + std::to_string(settings.tile_size) +
                         "' is not 8 or 16");
    }
    settings.seed = args.get_uint("seed", 1, 0, std::numeric_limits<uint64_t>::max());
    settings.ao_samples = static_cast<uint32_t>(args.get_uint("ao-samples", 16, 1, kMaxAoSamples));
    settings.bounces = static_cast<uint32_t>(args.get_uint("bounces", 0, 0, kMaxBounces));
    const BuildOptions build_options = parse_build_options(args);
    const unsigned threads = thread_count(args);
    const auto reps = static_cast<int>(args.get_uint("reps", 5, 1, 1000));
    const auto out_path = args.get("out");
    const auto compare = args.get("compare");
    if (compare && *compare != "embree")
        throw UsageError("option '--compare': '" + *compare + "' is not embree");
    if (compare && !kEmbreeAvailable) {
        throw BenchError(
            "--compare embree is not available in this build (neither Embree 4 nor 3 was found "
            "when it was configured)");
    }
    const bool camera_rays_only =
        settings.shading != Shading::kAo && settings.shading != Shading::kDiffuse;

    const LoadedMesh loaded = load_mesh(mesh_path);
    KdTree tree;
    double build_ms = 0;
    Image image;
    RenderStats stats;
    std::vector<double> seconds, batch_seconds;
    double cpu_seconds = 0;
    std::vector<Ray> rays;
    std::vector<Hit> hits;
    std::optional<EmbreeReport> embree;
    with_threads(threads, [&] {
        tree = build_tree(loaded.mesh, build_options, build_ms);
        // Render 0 warms caches and starts the workers; it is not timed.
        for (int rep = 0; rep <= reps; ++rep) {
            const double cpu_start = process_cpu_seconds();
            const auto start = Clock::now();
            image = render(tree, settings, {}, &stats);
            const double elapsed = std::chrono::duration<double>(Clock::now() - start).count();
            if (rep > 0) {
                seconds.push_back(elapsed);
                cpu_seconds += process_cpu_seconds() - cpu_start;
            }
        }
        rays = render_camera_rays(tree, settings, 0);
        hits.resize(rays.size());
        for (int pass = 0; pass <= reps; ++pass) {
            const auto start = Clock::now();
            kdrt::intersect(tree, rays, hits);
            const double elapsed = std::chrono::duration<double>(Clock::now() - start).count();
            if (pass > 0) batch_seconds.push_back(elapsed);
        }
        if (compare) {
            proto::RayBatch batch;
            batch.rays = rays;
            embree = compare_with_embree(loaded.mesh, batch, hits, {}, EmbreeOptions{reps});
        }
    });
    if (out_path) write_image_with_helper(*out_path, image);

    const double median_seconds = median(seconds);
    const double median_batch = median(batch_seconds);
    const double mrays_per_s =
        median_seconds > 0 ? static_cast<double>(stats.rays) / median_seconds / 1e6 : 0.0;
    Json line;
    line["command"] = "render";
    line["mesh"] = std::filesystem::path(mesh_path).filename().string();
    line["triangles"] = tree.stats.triangles;
    line["shading"] = shading_name(settings.shading);
    line["width"] = settings.width;
    line["height"] = settings.height;
    line["spp"] = settings.spp;
    line["tile"] = settings.tile_size;
    line["isa"] = isa_name(default_isa());
    line["threads"] = threads;
    line["builder"] = builder_name(build_options.builder);
    line["c_isect"] = build_options.intersection_cost;
    line["reps"] = reps;
    line["parse_ms"] = rounded(loaded.parse_ms, 3);
    line["build_ms"] = rounded(build_ms, 3);
    line["pixels"] = stats.pixels;
    line["rays"] = stats.rays;
    line["seconds"] = rounded(median_seconds, 9);
    line["seconds_min"] = rounded(*std::min_element(seconds.begin(), seconds.end()), 9);
    line["fps"] = rounded(median_seconds > 0 ? 1.0 / median_seconds : 0.0, 3);
    line["mrays_per_s"] = rounded(mrays_per_s, 3);
    const double wall_total = std::accumulate(seconds.begin(), seconds.end(), 0.0);
    line["cpu_util"] = rounded(wall_total > 0 ? cpu_seconds / wall_total : 0.0, 2);
    line["batch_rays"] = rays.size();
    line["batch_seconds"] = rounded(median_batch, 9);
    line["batch_mrays_per_s"] =
        rounded(median_batch > 0 ? static_cast<double>(rays.size()) / median_batch / 1e6 : 0.0, 3);
    if (camera_rays_only && median_batch > 0) {
        line["overhead"] = rounded(median_seconds / (settings.spp * median_batch) - 1.0, 4);
    }
    if (embree) {
        put_embree_speeds(line, *embree, mrays_per_s);
        line["embree_fps"] = rounded(
            embree->best().best_mrays_per_s * 1e6 / static_cast<double>(stats.primary_rays), 3);
        put_embree_answers(line, *embree);
    }
    if (out_path) line["out"] = *out_path;
    print_json(line);
    return 0;
}

struct Command {
    std::string_view name;
    std::string_view usage;
    std::span<const std::string_view> options;
    int (*run)(const Args&);
    std::span<const std::string_view> flags = {};
};

constexpr std::array<std::string_view, 5> kBuildOptions = {"builder", "c-isect", "threads", "reps",
                                                           "out"};
constexpr std::array<std::string_view, 8> kTraceOptions = {"mode", "isa",     "threads", "reps",
                                                           "out",  "builder", "c-isect", "compare"};
constexpr std::array<std::string_view, 1> kTraceFlags = {"stats"};
constexpr std::array<std::string_view, 7> kRaysOptions = {"kind", "res",     "seed",   "out",
                                                          "eye",  "look-at", "threads"};
constexpr std::array<std::string_view, 13> kSceneOptions = {
    "out",     "size",    "from",     "copies",  "res",   "reps", "threads",
    "compare", "azimuth", "channels", "returns", "frame", "kinds"};
constexpr std::array<std::string_view, 1> kSceneFlags = {"no-clearance"};
constexpr std::array<std::string_view, 13> kRenderOptions = {
    "shading",    "res",     "spp",     "tile",    "threads", "reps",   "seed",
    "ao-samples", "bounces", "builder", "c-isect", "out",     "compare"};
constexpr std::array<std::string_view, 4> kAllHitsOptions = {"max-hits", "mode", "threads", "reps"};
constexpr std::array<std::string_view, 1> kAllHitsFlags = {"merge"};
constexpr std::array<std::string_view, 6> kDistanceOptions = {"points", "brute", "threads",
                                                              "reps",   "seed",  "far"};
constexpr std::array<Command, 7> kCommands = {{
    {"build", kBuildUsage, kBuildOptions, &run_build},
    {"trace", kTraceUsage, kTraceOptions, &run_trace, kTraceFlags},
    {"all-hits", kAllHitsUsage, kAllHitsOptions, &run_all_hits, kAllHitsFlags},
    {"rays", kRaysUsage, kRaysOptions, &run_rays},
    {"scene", kSceneUsage, kSceneOptions, &run_scene, kSceneFlags},
    {"render", kRenderUsage, kRenderOptions, &run_render},
    {"distance", kDistanceUsage, kDistanceOptions, &run_distance},
}};

int run_main(int argc, char** argv) {
    const std::span<char* const> all(argv + 1, static_cast<size_t>(std::max(argc - 1, 0)));
    if (all.empty()) {
        std::cerr << kToolUsage;
        return 2;
    }
    const std::string_view first = all[0];
    if (first == "--help" || first == "-h" || first == "help") {
        std::cout << kToolUsage;
        return 0;
    }
    const auto command = std::find_if(kCommands.begin(), kCommands.end(),
                                      [&](const Command& c) { return c.name == first; });
    if (command == kCommands.end()) {
        std::cerr << "kdrt-bench: unknown command '" << first << "'\n\n" << kToolUsage;
        return 2;
    }
    try {
        const Args args(all.subspan(1), command->options, command->flags);
        if (args.help()) {
            std::cout << command->usage;
            return 0;
        }
        return command->run(args);
    } catch (const UsageError& e) {
        std::cerr << "kdrt-bench " << command->name << ": " << e.what() << "\n"
                  << "Run 'kdrt-bench " << command->name << " --help' for usage.\n";
        return 2;
    } catch (const std::bad_alloc&) {
        std::cerr << "kdrt-bench " << command->name << ": error: out of memory\n";
        return 1;
    } catch (const std::exception& e) {
        // BenchError, MeshError, CameraError, RenderError, EmbreeError, ...: the run itself failed.
        std::cerr << "kdrt-bench " << command->name << ": error: " << e.what() << "\n";
        return 1;
    }
}

}  // namespace
}  // namespace kdrt::bench

int main(int argc, char** argv) { return kdrt::bench::run_main(argc, argv); }
