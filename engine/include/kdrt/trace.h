#pragma once
/// Single-ray queries against a KdTree, and a brute-force reference.

#include <cstdint>
#include <optional>
#include <span>
#include <string_view>

#include "kdrt/kdtree.h"
#include "kdrt/types.h"

namespace kdrt {

/// Closest hit of `ray` in `tree` with tmin <= t <= tmax. Among hits at exactly equal t the lowest
/// triangle id wins, so the answer does not depend on traversal order. Watertight (Woop, Benthin
/// & Wald 2013): a ray through a shared edge or vertex of a closed mesh always hits one triangle.
/// A ray with NaN/Inf components, a zero direction or tmin > tmax is a miss. Thread-safe.
[[nodiscard]] Hit intersect(const KdTree& tree, const Ray& ray) noexcept;

/// True when any triangle is hit with tmin <= t <= tmax. Stops at the first hit found.
[[nodiscard]] bool occluded(const KdTree& tree, const Ray& ray) noexcept;

/// The same answers as intersect/occluded, by testing every triangle: the oracle for tests.
[[nodiscard]] Hit brute_force_intersect(std::span<const TriVerts> tris, const Ray& ray) noexcept;
[[nodiscard]] bool brute_force_occluded(std::span<const TriVerts> tris, const Ray& ray) noexcept;

/// Pre-processed triangles of a mesh (what KdTree::tris holds), for brute_force_*. Degenerate
/// (zero-area) triangles are collapsed to a point, so no ray ever hits them.
[[nodiscard]] std::vector<TriVerts> make_tri_verts(const Mesh& mesh);

/// SIMD instruction sets the packet kernels exist for, narrowest first.
enum class Isa : uint32_t {
    kScalar = 0,  ///< no packets: the single-ray kernel only
    kSse4 = 1,    ///< SSE4.2, 4 rays per packet
    kAvx2 = 2,    ///< AVX2, 8 rays per packet
    kAvx512 = 3,  ///< AVX-512 (F, DQ, VL, BW), 16 rays per packet
};

/// "scalar", "sse4", "avx2", "avx512".
[[nodiscard]] std::string_view isa_name(Isa isa) noexcept;
[[nodiscard]] std::optional<Isa> parse_isa(std::string_view name) noexcept;
/// Rays per packet: 1, 4, 8, 16.
[[nodiscard]] int isa_width(Isa isa) noexcept;
/// True when this CPU can run the kernels of `isa`.
[[nodiscard]] bool isa_supported(Isa isa) noexcept;
/// The instruction set batch queries use by default: the widest the CPU supports (but AVX2 where
/// 512-bit vectors run as two 256-bit halves, AMD family 19h, whose 8-lane packets are faster
/// there), or the one named by the environment variable KDRT_ISA (scalar|sse4|avx2|avx512) if
/// the CPU supports it.
/// Decided once, at first use; thread-safe.
[[nodiscard]] Isa default_isa() noexcept;
/// Why default_isa() is what it is, e.g. "widest supported" or "KDRT_ISA=sse4", or a warning
/// when KDRT_ISA names an unknown or unsupported set (which is then ignored).
[[nodiscard]] std::string_view default_isa_reason() noexcept;

/// How a batch traces: packets where the rays are coherent and single rays elsewhere (auto),
/// or one way only. Every mode gives the same answers, bit for bit.
enum class TraceMode : uint32_t { kAuto = 0, kSingle = 1, kPacket = 2 };
[[nodiscard]] std::string_view trace_mode_name(TraceMode mode) noexcept;
[[nodiscard]] std::optional<TraceMode> parse_trace_mode(std::string_view name) noexcept;

struct TraceOptions {
    TraceMode mode = TraceMode::kAuto;
    std::optional<Isa> isa;  ///< default: default_isa(); an unsupported one falls back to it
    /// Count the work done into TraceStats (traversal steps, leaves, triangle tests, packet lane
    /// use). Uses counting copies of the kernels: the same answers, somewhat slower.
    bool count_work = false;
};

/// What a batch did: how the auto policy split the work.
struct TraceStats {
    Isa isa = Isa::kScalar;
    uint64_t rays = 0;
    uint64_t packets = 0;
    uint64_t packet_rays = 0;
    uint64_t single_rays = 0;
    uint64_t invalid_rays = 0;
    /// Valid rays of blocks the tracer found incoherent and sorted by origin and direction before
    /// cutting packets (the rest keep their input order, split only by octant).
    uint64_t sorted_rays = 0;
    /// The work done, with TraceOptions::count_work only (else 0). Summed over rays: a packet's
    /// node visit or triangle test counts once per live lane, so the means per ray compare across
    /// modes and instruction sets.
    uint64_t traversal_steps = 0;  ///< inner nodes visited
    uint64_t leaves_visited = 0;   ///< leaves visited (empty ones too)
    uint64_t triangle_tests = 0;   ///< ray-triangle tests
    uint64_t packet_visits = 0;    ///< nodes (inner and leaf) visited by packets
    uint64_t packet_lanes = 0;     ///< live lanes summed over those visits
    /// Wide nodes (3-level treelets, KdTree::wide_nodes) visited by the single-ray kernel; each
    /// stands for up to 7 of traversal_steps, at one dependent load.
    uint64_t wide_visits = 0;
    /// Of triangle_tests, the lanes of closest-hit packet tests skipped because every active
    /// lane had tested that triangle already in an earlier leaf (the packet's mailbox).
    uint64_t triangle_repeats_skipped = 0;
    int width = 1;  ///< lanes per packet (isa_width): utilisation is
                    ///< packet_lanes / (packet_visits * width)
};

/// Batch queries for arbitrary input, over all threads of the current oneTBB arena. Answers come
/// back in input order; `hits` / `occluded_out` must have rays.size() elements (1 = occluded).
/// Rays are sorted by octant, origin and direction inside blocks of 4096 and traced as SIMD
/// packets when the policy says so. No allocation; per-thread scratch only.
void intersect(const KdTree& tree, std::span<const Ray> rays, std::span<Hit> hits,
               const TraceOptions& options = {}, TraceStats* stats = nullptr) noexcept;
void occluded(const KdTree& tree, std::span<const Ray> rays, std::span<uint8_t> occluded_out,
              const TraceOptions& options = {}, TraceStats* stats = nullptr) noexcept;

/// The same, on the calling thread only (no tasks spawned): for callers that already run in
/// parallel over small blocks, such as the renderer's tiles.
void intersect_block(const KdTree& tree, std::span<const Ray> rays, std::span<Hit> hits,
                     const TraceOptions& options = {}) noexcept;
void occluded_block(const KdTree& tree, std::span<const Ray> rays, std::span<uint8_t> occluded_out,
                    const TraceOptions& options = {}) noexcept;

/// Batch queries with the single-ray kernel only (the baseline that packets are measured against).
void intersect_single(const KdTree& tree, std::span<const Ray> rays, std::span<Hit> hits) noexcept;
void occluded_single(const KdTree& tree, std::span<const Ray> rays,
                     std::span<uint8_t> occluded_out) noexcept;

}  // namespace kdrt
