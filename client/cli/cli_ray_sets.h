#pragma once
/// The ray sets of kdrt rays, trace and bench-remote: read from a KDRR file, generated from a
/// mesh file as kdrt-bench rays does, or primary rays from the bounds the server reports; the
/// point sets of the distance commands; and the options and outputs the mesh and scene commands
/// share (internal to the CLI). Every function that fails has already printed why
/// and returns the exit code as its error.

#include <algorithm>
#include <chrono>
#include <cstddef>
#include <cstdint>
#include <optional>
#include <span>
#include <string>
#include <string_view>
#include <type_traits>
#include <vector>

#include "cli_context.h"
#include "kdrt/distance_types.h"
#include "kdrt/proto/multi_hit.h"
#include "kdrt/raygen.h"
#include "kdrt/types.h"

namespace kdrt::cli {

using Clock = std::chrono::steady_clock;

/// Seconds from `start` to now.
[[nodiscard]] double seconds_since(Clock::time_point start);

/// A ray set and where it came from.
struct RaySet {
    std::vector<Ray> rays;
    bool occlusion = false;
    std::string kind;    ///< primary, shadow, diffuse, random, or "file"
    std::string source;  ///< "mesh", "bounds" or "rays"
};

/// --kind, --res, --seed (defaults primary, 1024, 1). Returns an exit code on a usage error.
[[nodiscard]] proto::Result<RayGenOptions, int> ray_options(const Context& ctx);

/// --connections and --chunk-rays on top of the global client options.
[[nodiscard]] proto::Result<ClientOptions, int> trace_client_options(const Context& ctx);

/// Loads a mesh file and generates `options` rays from its tree. With `expected_id`, the file's
/// mesh id must match it.
[[nodiscard]] proto::Result<RaySet, int> rays_from_mesh_file(const Context& ctx,
                                                             const std::string& path,
                                                             const RayGenOptions& options,
                                                             const std::string& expected_id = {});

/// Reads a KDRR file.
[[nodiscard]] proto::Result<RaySet, int> rays_from_file(const Context& ctx,
                                                        const std::string& path);

/// res x res camera rays through the pixel centres of the default view of `bounds` (what
/// generate_rays' primary set does with the tree's padded bounds).
[[nodiscard]] proto::Result<RaySet, int> primary_rays_from_bounds(const Context& ctx,
                                                                  const Aabb& bounds, uint32_t res);

/// The query points of `path` (kdrt distance, kdrt scene distance): a KDRP batch when the file
/// starts with its magic, else text (proto::parse_points_text).
[[nodiscard]] proto::Result<std::vector<Vec3>, int> points_from_file(const Context& ctx,
                                                                     const std::string& path);
/// --max-distance and --signed.
[[nodiscard]] proto::Result<DistanceQuery, int> distance_query_options(const Context& ctx);
/// --chunk-points on top of the global client options.
[[nodiscard]] proto::Result<ClientOptions, int> distance_client_options(const Context& ctx);
/// The output of a distance command, by the path's extension: .csv or .kdrd.
enum class DistanceOutput { kCsv, kKdrd };
[[nodiscard]] std::optional<DistanceOutput> distance_output(std::string_view path);
/// -o OUT of a distance command with its format (distance_output); a usage error when -o is
/// missing or its extension is neither.
struct DistanceOutputFile {
    std::string path;
    DistanceOutput kind;
};
[[nodiscard]] proto::Result<DistanceOutputFile, int> distance_output_option(const Context& ctx);

/// Closest points found, and of those the ones inside and outside.
struct SideCounts {
    uint64_t found = 0, inside = 0, outside = 0;
};
[[nodiscard]] SideCounts count_sides(std::span<const ClosestPoint> points);

/// --max-hits, --fields, --merge, --count-only, --normal, --point (kdrt hits, kdrt scene hits).
[[nodiscard]] proto::Result<proto::MultiHitQuery, int> multi_hit_options(const Context& ctx);
/// The KDRM bytes of every-hit answers joined from several requests: what one request for the
/// whole batch would have answered (kdrt hits, kdrt scene hits).
[[nodiscard]] std::vector<std::byte> multi_hits_bytes(const proto::MultiHits& all);

/// The hits among closest-hit answers, or the occluded rays among occlusion bytes.
template <class T>
uint64_t count_answers(const std::vector<T>& answers) {
    if constexpr (std::is_same_v<T, Hit>) {
        return static_cast<uint64_t>(
            std::count_if(answers.begin(), answers.end(), [](const Hit& h) { return h.is_hit(); }));
    } else {
        return static_cast<uint64_t>(std::count(answers.begin(), answers.end(), uint8_t{1}));
    }
}

}  // namespace kdrt::cli
