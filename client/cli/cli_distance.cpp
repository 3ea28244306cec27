// kdrt distance: query points (KDRP, or XYZ / CSV text) against a stored mesh; closest points,
// distances and sides as CSV or KDRD.

#include <cctype>
#include <cmath>
#include <limits>
#include <sstream>
#include <string>
#include <vector>

#include "cli_command.h"
#include "cli_context.h"
#include "cli_output.h"
#include "cli_ray_sets.h"
#include "kdrt/proto/distance.h"
#include "kdrt/proto/file_io.h"
#include "kdrt/proto/json_api.h"

namespace kdrt::cli {
namespace {

constexpr std::string_view kDistanceHelp =
    R"(usage: kdrt distance ID POINTS -o OUT [--max-distance D] [--signed] [--chunk-points N]
                     [--json]

The closest point on a stored mesh to each query point (POST /v1/meshes/{id}/distance): its
distance, triangle, barycentrics (u, v), the point and the feature it lies on (face, edge,
vertex), and with --signed which side of the surface the query point is on.

POINTS is a KDRP file (proto/FORMATS.md; recognised by its magic) or text: one point a line,
three numbers separated by spaces, tabs or commas (XYZ, CSV; further columns are ignored, '#'
lines and a non-numeric first line such as a CSV header are skipped). Every coordinate must be
finite. OUT is written by its extension:
  .csv    x,y,z,distance,signed_distance,side,prim,u,v,px,py,pz,feature with a header line
          (signed_distance and prim empty where undefined)
  .kdrd   the server's KDRD records (proto/FORMATS.md)

  -o, --output OUT     the .csv or .kdrd file (required; - for standard output)
  --format NAME        csv or kdrd: the format when OUT's extension does not say
  --max-distance D     only triangles at most D away count (D >= 0; default: no limit); a
                       point with none gets distance inf, no prim and feature "none"
  --signed             decide inside / outside: exact on a closed, consistently oriented mesh;
                       on any other mesh every side is "unknown" (the summary says why)
  --chunk-points N     points per request (default 65536; smaller when the server's
                       max_distance_points is)
  --json               the summary as one JSON object (on stdout; stderr with -o -)
  -q, --quiet          no summary line

Prints the point count, time, points/s, the points found and, with --signed, how many are
inside and outside.
)";

constexpr OptionSpec kDistanceOptions[] = {
    {"output", true, 'o'},  {"max-distance", true}, {"signed", false},
    {"chunk-points", true}, {"format", true},
};

/// Most points per request --chunk-points accepts (the server's default max_distance_points).
constexpr uint64_t kMaxChunkPoints = uint64_t{1} << 22;

int run_distance(Context& ctx) {
    if (ctx.args.positional.size() < 2)
        return ctx.usage_error("missing ID and POINTS (a mesh id and a points file)");
    if (ctx.args.positional.size() > 2)
        return ctx.usage_error("unexpected argument \"" + ctx.args.positional[2] + "\"");
    auto out = distance_output_option(ctx);
    if (!out) return out.error();
    const std::string& output = out->path;
    const DistanceOutput kind = out->kind;
    auto query = distance_query_options(ctx);
    if (!query) return query.error();
    auto options = distance_client_options(ctx);
    if (!options) return options.error();
    const std::string& points_path = ctx.args.positional[1];
    auto points = points_from_file(ctx, points_path);
    if (!points) return points.error();
    Client& client = ctx.connect(*options);
    auto id = ctx.resolve_mesh_id(ctx.args.positional[0]);
    if (!id) return id.error();

    const auto start = Clock::now();
    auto answer = client.distance(*id, *points, *query);
    if (!answer) return ctx.fail(answer.error());
    const double seconds = seconds_since(start);
    const std::vector<std::byte> bytes =
        kind == DistanceOutput::kCsv ? [&] {
            const std::string csv = proto::distances_csv(*points, answer->points);
            const auto* p = reinterpret_cast<const std::byte*>(csv.data());
            return std::vector<std::byte>(p, p + csv.size());
        }()
                                  : proto::encode_distances(answer->points, query->signed_query);
    if (auto failed = ctx.write_output(output, bytes, "the answers")) return *failed;
    const auto [found, inside, outside] = count_sides(answer->points);
    const double rate = seconds > 0 ? static_cast<double>(points->size()) / seconds : 0.0;
    const proto::JsonField fields[] = {{"command", std::string_view("distance")},
                                       {"mesh", std::string_view(*id)},
                                       {"points_file", std::string_view(points_path)},
                                       {"points", uint64_t{points->size()}},
                                       {"signed", query->signed_query},
                                       {"surface", std::string_view(answer->surface)},
                                       {"closed", answer->closed()},
                                       {"seconds", seconds},
                                       {"points_per_s", rate},
                                       {"found", found},
                                       {"inside", inside},
                                       {"outside", outside},
                                       {"out", std::string_view(output)}};
    std::ostringstream human;
    human << "queried " << points->size() << " points in " << fixed(seconds, 3) << " s, "
          << fixed(rate, 0) << " points/s: " << found << " found";
    if (query->signed_query) {
        human << ", " << inside << " inside, " << outside << " outside";
        if (!answer->closed()) human << " (sides unknown: the mesh is " << answer->surface << ")";
    }
    human << " -> " << output;
    ctx.report(output, human.str(), proto::encode_flat_object(fields));
    return kExitOk;
}

}  // namespace

proto::Result<DistanceOutputFile, int> distance_output_option(const Context& ctx) {
    const auto output = ctx.args.value("output");
    if (!output)
        return proto::Err{ctx.usage_error("missing -o OUT (the .csv or .kdrd file to write)")};
    const auto kind = distance_output(ctx.format_path(*output));
    if (!kind)
        return proto::Err{ctx.usage_error("cannot tell the output format of \"" + *output +
                                          "\" from its extension (.csv or .kdrd)")};
    return DistanceOutputFile{*output, *kind};
}

std::optional<DistanceOutput> distance_output(std::string_view path) {
    const size_t dot = path.rfind('.');
    if (dot == std::string_view::npos) return std::nullopt;
    std::string ext(path.substr(dot + 1));
    for (char& c : ext) c = static_cast<char>(std::tolower(static_cast<unsigned char>(c)));
    if (ext == "csv") return DistanceOutput::kCsv;
    if (ext == "kdrd") return DistanceOutput::kKdrd;
    return std::nullopt;
}

proto::Result<std::vector<Vec3>, int> points_from_file(const Context& ctx,
                                                       const std::string& path) {
    auto bytes = proto::read_file_bytes(path);
    if (!bytes)
        return proto::Err{ctx.fail(
            make_client_error(ErrorKind::kInput, "cannot read the points", bytes.error()))};
    const std::string_view magic = proto::kPointMagic;
    const bool binary =
        bytes->size() >= magic.size() &&
        std::string_view(reinterpret_cast<const char*>(bytes->data()), magic.size()) == magic;
    if (binary) {
        auto points = proto::decode_points(
            *bytes, {.max_rays = std::numeric_limits<uint32_t>::max(), .reject_non_finite = true});
        if (!points)
            return proto::Err{ctx.fail(make_client_error(
                ErrorKind::kInput, "cannot read the points",
                path + " is not a usable KDRP point batch: " + points.error().to_string()))};
        return std::move(*points);
    }
    auto points = proto::parse_points_text(
        std::string_view(reinterpret_cast<const char*>(bytes->data()), bytes->size()));
    if (!points)
        return proto::Err{ctx.fail(make_client_error(ErrorKind::kInput, "cannot read the points",
                                                     path + ": " + points.error()))};
    return std::move(*points);
}

SideCounts count_sides(std::span<const ClosestPoint> points) {
    SideCounts counts;
    for (const ClosestPoint& c : points) {
        counts.found += c.found() ? 1 : 0;
        counts.inside += c.side == Side::kInside ? 1 : 0;
        counts.outside += c.side == Side::kOutside ? 1 : 0;
    }
    return counts;
}

proto::Result<DistanceQuery, int> distance_query_options(const Context& ctx) {
    DistanceQuery query;
    if (auto text = ctx.args.value("max-distance")) {
        // proto's reading of the query parameter: a number >= 0, or inf.
        auto parsed =
            proto::parse_distance_query([&](std::string_view name) -> std::optional<std::string> {
                if (name == proto::kQueryMaxDistance) return *text;
                return std::nullopt;
            });
        if (!parsed) return proto::Err{ctx.usage_error("--max-distance: " + parsed.error())};
        query.max_distance = parsed->max_distance;
    }
    query.signed_query = ctx.args.has("signed");
    return query;
}

proto::Result<ClientOptions, int> distance_client_options(const Context& ctx) {
    ClientOptions options = ctx.client_options();
    if (auto text = ctx.args.value("chunk-points")) {
        auto n = parse_uint(*text, 1, kMaxChunkPoints);
        if (!n) return proto::Err{ctx.usage_error("--chunk-points: " + n.error())};
        options.chunk_rays = static_cast<size_t>(*n);
    }
    return options;
}

constinit const Command kDistanceCommand{
    .name = "distance",
    .synopsis = "distance ID POINTS -o OUT",
    .summary = "closest points, distances and sides of query points (CSV or KDRD)",
    .help = kDistanceHelp,
    .options = kDistanceOptions,
    .needs_server = true,
    .run = run_distance,
};

}  // namespace kdrt::cli
