// kdrt scene create|get|list|rm|poses|trace|hits|distance|scan: scenes (many stored meshes placed
// by transforms, queried as one) through kdrt::Client's scene calls; the outputs are the mesh
// commands' with a geometry id per answer (proto/FORMATS.md, "Scenes").

#include <algorithm>
#include <cctype>
#include <optional>
#include <sstream>
#include <string>
#include <vector>

#include "cli_command.h"
#include "cli_context.h"
#include "cli_output.h"
#include "cli_ray_sets.h"
#include "cli_scan.h"
#include "kdrt/proto/distance.h"
#include "kdrt/proto/file_io.h"
#include "kdrt/proto/json_api.h"
#include "kdrt/proto/multi_hit.h"
#include "kdrt/proto/ray_batch.h"
#include "kdrt/proto/scan.h"
#include "kdrt/proto/scene.h"

namespace kdrt::cli {
namespace {

constexpr std::string_view kSceneHelp =
    R"(usage: kdrt scene SUBCOMMAND [ARGS...]

Scenes: stored meshes placed by affine transforms and queried as one; every answer names the
instance (its geometry id: its index in the scene). Every change makes a new revision.

  scene create FILE                 create a scene from FILE; print its id
  scene get ID [-o FILE]            the scene's instances (JSON with -o or --json)
  scene list                        every scene: id, revision, instances
  scene rm ID...                    delete scenes
  scene poses ID FILE               move instances (one new revision)
  scene trace ID RAYS -o FILE       closest hits of a KDRR file (KDRH + geometry ids, or KDRO)
  scene hits ID RAYS --all -o FILE  every hit along each ray (KDRM + geometry ids, or KDRC)
  scene distance ID POINTS -o OUT   closest points (CSV with a geometry_id column, or KDRD + ids)
  scene scan ID --pinhole|--lidar -o FILE   a sensor scan (EXR / PLY, or KDRZ / KDRL; with the
                                    geometry ids)

`kdrt scene SUBCOMMAND --help` describes each. The queries answer from the current revision, or
from --revision N (one of the newest revisions the server keeps); a query sent as several
requests answers from one revision throughout. --if-revision N makes a change (poses, rm)
conditional: refused (exit 1, 412) when the scene is no longer at revision N.
)";

/// --revision N / --if-revision N.
proto::Result<std::optional<uint64_t>, int> revision_option(const Context& ctx,
                                                            std::string_view name) {
    const auto text = ctx.args.value(name);
    if (!text) return std::optional<uint64_t>{};
    auto n = parse_uint(*text, 1, UINT64_MAX);
    if (!n) return proto::Err{ctx.usage_error("--" + std::string(name) + ": " + n.error())};
    return std::optional<uint64_t>{*n};
}

/// The family option --revision, refused by the subcommands that change or list scenes.
std::optional<int> no_revision(const Context& ctx) {
    if (!ctx.args.has("revision")) return std::nullopt;
    return ctx.usage_error(
        "--revision applies to get and the queries (changes take --if-revision)");
}

std::string_view as_text(const std::vector<std::byte>& bytes) {
    return {reinterpret_cast<const char*>(bytes.data()), bytes.size()};
}

/// A whole file, or the exit code after saying why it cannot be read.
proto::Result<std::vector<std::byte>, int> read_input(const Context& ctx, const std::string& path,
                                                      std::string_view what) {
    auto bytes = proto::read_file_bytes(path);
    if (!bytes)
        return proto::Err{ctx.fail(make_client_error(
            ErrorKind::kInput, "cannot read " + std::string(what), bytes.error()))};
    return std::move(*bytes);
}

/// Does the text start (after white space) with '{'?
bool looks_like_json(std::string_view text) {
    const size_t first = text.find_first_not_of(" \t\r\n");
    return first != std::string_view::npos && text[first] == '{';
}

std::string scene_json_line(const SceneDocument& doc) { return proto::encode_scene_json(doc); }

/// The one-line summary of a scene revision.
std::string revision_line(const SceneRevision& r) {
    return r.id + "  revision " + std::to_string(r.revision) + "  " + std::to_string(r.instances) +
           (r.instances == 1 ? " instance" : " instances");
}

SceneRevision revision_of(const SceneDocument& doc) {
    return {doc.id, doc.revision, doc.instances.size()};
}

std::string revision_json(const SceneRevision& r) { return proto::encode_scene_revision(r); }

// ---- create, get, list, rm, poses ------------------------------------------------------------

constexpr std::string_view kCreateHelp = R"(usage: kdrt scene create FILE [--json] [--quiet]

Creates a scene and prints its id, revision and instance count. FILE is either the JSON of
POST /v1/scenes ({"instances": [{"mesh": ID, "transform": [12 numbers], "name": N}, ...]}; what
kdrt scene get -o writes is accepted too) or text, one instance a line:

  MESH [T] [NAME]

MESH a mesh id (64 hex digits), T the transform as 12 numbers (row-major 3 x 4: L in columns
0-2, the translation in column 3) or 3 numbers (a translation), none for the identity, NAME an
optional instance name; fields separated by spaces, tabs or commas; '#' lines skipped. The
order of the instances is their geometry ids'. Errors name the line, or (from the server) the
instance and field ("instances[3].transform": a singular transform; "instances[0].mesh": a mesh
that is not stored).

  --json       the scene's JSON document on one line (stdout)
  -q, --quiet  print only the id
)";

int run_create(Context& ctx) {
    int code = kExitOk;
    if (!positional_count_ok(ctx, 1, 1, "FILE (the scene: JSON or one instance a line)", code))
        return code;
    if (auto failed = no_revision(ctx)) return *failed;
    const std::string& path = ctx.args.positional[0];
    auto bytes = read_input(ctx, path, "the scene");
    if (!bytes) return bytes.error();
    const std::string_view text = as_text(*bytes);
    const proto::SceneLimits any{.max_instances = UINT32_MAX};
    std::vector<proto::SceneInstanceSpec> instances;
    if (looks_like_json(text)) {
        auto doc = proto::decode_scene_json(text, any, /*stored=*/true);
        if (!doc)
            return ctx.fail(make_client_error(ErrorKind::kInput, "cannot read the scene",
                                              path + ": " + doc.error().detail));
        instances = std::move(doc->instances);
    } else {
        auto parsed = proto::parse_scene_text(text, any);
        if (!parsed)
            return ctx.fail(make_client_error(ErrorKind::kInput, "cannot read the scene",
                                              path + ": " + parsed.error()));
        instances = std::move(*parsed);
    }
    auto doc = ctx.connect(ctx.client_options()).create_scene(instances);
    if (!doc) return ctx.fail(doc.error());
    ctx.console.out << (ctx.json()    ? scene_json_line(*doc)
                        : ctx.quiet() ? doc->id
                                      : revision_line(revision_of(*doc)))
                    << "\n";
    return kExitOk;
}

constexpr std::string_view kGetHelp =
    R"(usage: kdrt scene get ID [--revision N] [-o FILE] [--json] [--quiet]

Shows a scene: its revision and one line per instance (geometry id, mesh id, name, transform).

  --revision N        that revision instead of the current one
  -o, --output FILE   write the scene's JSON document to FILE (- for standard output); kdrt
                      scene create FILE makes a copy of it
  --json              the JSON document on one line (stdout)
  -q, --quiet         print only the revision
)";

constexpr OptionSpec kGetOptions[] = {{"output", true, 'o'}};

int run_get(Context& ctx) {
    int code = kExitOk;
    if (!positional_count_ok(ctx, 1, 1, "ID (a scene id)", code)) return code;
    auto revision = revision_option(ctx, "revision");
    if (!revision) return revision.error();
    auto doc = ctx.connect(ctx.client_options()).scene(ctx.args.positional[0], *revision);
    if (!doc) return ctx.fail(doc.error());
    const std::string json = scene_json_line(*doc);
    if (auto output = ctx.args.value("output")) {
        const auto* p = reinterpret_cast<const std::byte*>(json.data());
        if (auto failed =
                ctx.write_output(*output, std::vector<std::byte>(p, p + json.size()), "the scene"))
            return *failed;
        ctx.report(*output, "wrote " + revision_line(revision_of(*doc)) + " -> " + *output,
                   revision_json(revision_of(*doc)));
        return kExitOk;
    }
    if (ctx.json()) {
        ctx.console.out << json << "\n";
    } else if (ctx.quiet()) {
        ctx.console.out << doc->revision << "\n";
    } else {
        std::ostringstream out;
        out << revision_line(revision_of(*doc)) << "\n";
        for (size_t g = 0; g < doc->instances.size(); ++g) {
            const proto::SceneInstanceSpec& inst = doc->instances[g];
            out << "  " << g << "  " << inst.mesh << "  " << (inst.name.empty() ? "-" : inst.name)
                << "  [";
            for (size_t k = 0; k < 12; ++k)
                out << (k == 0 ? "" : k % 4 == 0 ? " | " : " ") << inst.transform.m[k];
            out << "]\n";
        }
        ctx.console.out << out.str();
    }
    return kExitOk;
}

constexpr std::string_view kListHelp = R"(usage: kdrt scene list [--json] [--quiet]

Lists the scenes, sorted by id: ID, current revision, instance count.

  --json       one JSON object per scene, one per line
  -q, --quiet  print only the ids
)";

int run_list(Context& ctx) {
    int code = kExitOk;
    if (!positional_count_ok(ctx, 0, 0, "", code)) return code;
    if (auto failed = no_revision(ctx)) return *failed;
    auto list = ctx.connect(ctx.client_options()).scenes();
    if (!list) return ctx.fail(list.error());
    if (list->empty() && !ctx.json() && !ctx.quiet()) ctx.console.out << "no scenes stored\n";
    for (const SceneRevision& r : *list)
        ctx.console.out << (ctx.json()    ? revision_json(r)
                            : ctx.quiet() ? r.id
                                          : revision_line(r))
                        << "\n";
    return kExitOk;
}

constexpr std::string_view kRmHelp =
    R"(usage: kdrt scene rm ID... [--if-revision N] [--json] [--quiet]

Deletes scenes (every revision). Prints "removed ID" per scene.

  --if-revision N  only if the scene is at revision N (exit 1, 412, when it is not)
  --json           {"removed": ID} per scene instead
  -q, --quiet      print nothing but errors
)";

constexpr OptionSpec kRmOptions[] = {{"if-revision", true}};

int run_rm(Context& ctx) {
    int code = kExitOk;
    if (!positional_count_ok(ctx, 1, SIZE_MAX, "ID (the scenes to delete)", code)) return code;
    if (auto failed = no_revision(ctx)) return *failed;
    auto condition = revision_option(ctx, "if-revision");
    if (!condition) return condition.error();
    Client& client = ctx.connect(ctx.client_options());
    for (const std::string& id : ctx.args.positional) {
        auto removed = client.remove_scene(id, *condition);
        if (!removed) {
            const int failed = ctx.fail(removed.error());
            if (failed == kExitUnreachable) return failed;
            code = std::max(code, failed);
            continue;
        }
        if (ctx.json()) {
            const proto::JsonField fields[] = {{"removed", std::string_view(id)}};
            ctx.console.out << proto::encode_flat_object(fields) << "\n" << std::flush;
        } else if (!ctx.quiet()) {
            ctx.console.out << "removed " << id << "\n" << std::flush;
        }
    }
    return code;
}

constexpr std::string_view kPosesHelp =
    R"(usage: kdrt scene poses ID FILE [--if-revision N] [--json] [--quiet]

Moves instances of a scene in one request: one new revision, whose number is printed. FILE is
the JSON of PATCH /v1/scenes/{id}/poses ({"poses": [{"geometry_id": 3, "transform": [...]},
{"name": "car", "transform": [...]}]}), a KDRX pose batch (proto/FORMATS.md), or text, one pose
a line:

  INSTANCE T

INSTANCE a geometry id (digits) or an instance name, T 12 numbers (row-major 3 x 4) or 3 (a
translation). A later line for the same instance wins. Poses by geometry id go as KDRX.

  --if-revision N  only if the scene is still at revision N (exit 1, 412, when it moved on)
  --json           {"id", "revision", "instances"} on one line
  -q, --quiet      print only the new revision
)";

constexpr OptionSpec kPosesOptions[] = {{"if-revision", true}};

int run_poses(Context& ctx) {
    int code = kExitOk;
    if (!positional_count_ok(ctx, 2, 2, "ID and FILE (a scene id and the poses)", code))
        return code;
    if (auto failed = no_revision(ctx)) return *failed;
    auto condition = revision_option(ctx, "if-revision");
    if (!condition) return condition.error();
    const std::string& path = ctx.args.positional[1];
    auto bytes = read_input(ctx, path, "the poses");
    if (!bytes) return bytes.error();
    const std::string_view text = as_text(*bytes);
    const proto::SceneLimits any{.max_instances = UINT32_MAX};
    std::vector<proto::PoseEntry> poses;
    std::string error;
    if (text.substr(0, proto::kPoseBatchMagic.size()) == proto::kPoseBatchMagic) {
        auto decoded = proto::decode_pose_batch(*bytes, any);
        if (decoded)
            poses = std::move(*decoded);
        else
            error = decoded.error().to_string();
    } else if (looks_like_json(text)) {
        auto decoded = proto::decode_pose_json(text, any);
        if (decoded)
            poses = std::move(*decoded);
        else
            error = decoded.error().detail;
    } else {
        auto decoded = proto::parse_pose_text(text, any);
        if (decoded)
            poses = std::move(*decoded);
        else
            error = decoded.error();
    }
    if (!error.empty())
        return ctx.fail(
            make_client_error(ErrorKind::kInput, "cannot read the poses", path + ": " + error));
    auto revision =
        ctx.connect(ctx.client_options()).set_poses(ctx.args.positional[0], poses, *condition);
    if (!revision) return ctx.fail(revision.error());
    ctx.console.out << (ctx.json()    ? revision_json(*revision)
                        : ctx.quiet() ? std::to_string(revision->revision)
                                      : revision_line(*revision))
                    << "\n";
    return kExitOk;
}

// ---- queries -----------------------------------------------------------------------------------

/// The report fields every query shares, then its own.
void report_query(Context& ctx, std::string_view command, const std::string& id, uint64_t revision,
                  const std::string& output, std::string_view human,
                  std::initializer_list<proto::JsonField> more) {
    std::vector<proto::JsonField> fields = {
        {"command", command}, {"scene", std::string_view(id)}, {"revision", revision}};
    fields.insert(fields.end(), more.begin(), more.end());
    fields.push_back({"out", std::string_view(output)});
    ctx.report(output, human, proto::encode_flat_object(fields));
}

/// The rays of a query command: -o given, positionals ID RAYS.
struct RayQuery {
    std::string output;
    std::optional<uint64_t> revision;
    ClientOptions options;
    RaySet set;
};

proto::Result<RayQuery, int> ray_query(Context& ctx, std::string_view output_what) {
    int code = kExitOk;
    if (!positional_count_ok(ctx, 2, 2, "ID and RAYS (a scene id and a KDRR file)", code))
        return proto::Err{code};
    RayQuery q;
    const auto output = ctx.args.value("output");
    if (!output)
        return proto::Err{ctx.usage_error("missing -o FILE (the " + std::string(output_what) +
                                          " file to write)")};
    q.output = *output;
    auto revision = revision_option(ctx, "revision");
    if (!revision) return proto::Err{revision.error()};
    q.revision = *revision;
    auto options = trace_client_options(ctx);
    if (!options) return proto::Err{options.error()};
    q.options = *options;
    auto set = rays_from_file(ctx, ctx.args.positional[1]);
    if (!set) return proto::Err{set.error()};
    q.set = std::move(*set);
    return q;
}

constexpr std::string_view kTraceHelp =
    R"(usage: kdrt scene trace ID RAYS.kdrr -o FILE [--revision N] [--chunk-rays N] [--split N]
                        [--connections N] [--json] [--quiet]

Traces every ray of a KDRR file against a scene and writes the answers to FILE: KDRH closest
hits with a geometry-id plane (proto/FORMATS.md "Scenes": the instance each ray hit), or KDRO
occlusion bytes when the file's occlusion flag is set. Prints the ray count, time, Mrays/s,
hits and the revision that answered.

  -o, --output FILE   the answers (required; - for standard output)
  --revision N        that revision instead of the current one
  --chunk-rays N      rays per request (default 65536)
  --split N           at least N requests, each with its own routing key (?route=ID.K), so a
                      proxy in front of replicas spreads them (docs/scale-out.md); the first
                      fixes the revision, the others pin it and go over --connections at once
  --connections N     with --split: requests in flight at once (default 4)
  --json              the summary as one JSON object (on stdout; stderr with -o -)
  -q, --quiet         no summary line
)";

constexpr OptionSpec kTraceOptions[] = {
    {"output", true, 'o'}, {"chunk-rays", true}, {"split", true}, {"connections", true}};

int run_trace(Context& ctx) {
    auto q = ray_query(ctx, "KDRH/KDRO");
    if (!q) return q.error();
    const std::string& id = ctx.args.positional[0];
    Client& client = ctx.connect(q->options);
    const auto start = Clock::now();
    std::vector<std::byte> answer;
    uint64_t hits = 0, revision = 0;
    if (q->set.occlusion) {
        auto occluded = client.occluded_scene(id, q->set.rays, q->revision);
        if (!occluded) return ctx.fail(occluded.error());
        hits = count_answers(occluded->occluded);
        answer = proto::encode_occlusion(occluded->occluded);
        revision = occluded->revision;
    } else {
        auto found = client.intersect_scene(id, q->set.rays, q->revision);
        if (!found) return ctx.fail(found.error());
        hits = count_answers(found->hits);
        answer = proto::encode_hits(found->hits);
        proto::append_geometry_ids(answer, found->geometry_ids);
        revision = found->revision;
    }
    const double seconds = seconds_since(start);
    if (auto failed = ctx.write_output(q->output, answer, "the answers")) return *failed;
    const size_t rays = q->set.rays.size();
    const double mrays = seconds > 0 ? static_cast<double>(rays) / seconds / 1e6 : 0.0;
    std::ostringstream human;
    human << "traced " << rays << " rays (" << (q->set.occlusion ? "occlusion" : "closest hits")
          << ") in " << fixed(seconds, 3) << " s, " << fixed(mrays, 2) << " Mrays/s: " << hits
          << (q->set.occlusion ? " occluded" : " hits");
    human << " (revision " << revision << ") -> " << q->output;
    report_query(ctx, "scene trace", id, revision, q->output, human.str(),
                 {{"rays_file", std::string_view(ctx.args.positional[1])},
                  {"rays", uint64_t{rays}},
                  {"occlusion", q->set.occlusion},
                  {"seconds", seconds},
                  {"mrays_per_s", mrays},
                  {"hits", hits}});
    return kExitOk;
}

constexpr std::string_view kHitsHelp =
    R"(usage: kdrt scene hits ID RAYS.kdrr --all -o FILE [--max-hits N] [--merge] [--count-only]
                       [--fields full|t|t_prim] [--normal] [--point] [--revision N]
                       [--chunk-rays N] [--json] [--quiet]

Every hit along each ray of a KDRR file over a scene's instances, as kdrt hits does for a mesh:
FILE gets the KDRM answer with a geometry-id plane (one id per hit record), or KDRC counts with
--count-only. Coincident hits are merged within an instance (--merge), never across instances.

  --all               every hit (required)
  -o, --output FILE   the KDRM / KDRC file (required; - for standard output)
  --max-hits N        hits kept per ray (default 16; the server caps it)
  --merge             report coincident hits at a shared edge or vertex once
  --count-only        only the number of hits of each ray (KDRC)
  --fields F          record fields: full (t prim u v, default), t, t_prim
  --normal            add the world-space unit normal of each hit
  --point             add the world-space hit point
  --revision N        that revision instead of the current one
  --chunk-rays N      rays per request (default 65536)
  --json              the summary as one JSON object (on stdout; stderr with -o -)
  -q, --quiet         no summary line
)";

constexpr OptionSpec kHitsOptions[] = {
    {"all", false},    {"output", true, 'o'}, {"max-hits", true},
    {"merge", false},  {"count-only", false}, {"fields", true},
    {"normal", false}, {"point", false},      {"chunk-rays", true},
};

int run_hits(Context& ctx) {
    if (!ctx.args.has("all"))
        return ctx.usage_error("kdrt scene hits needs --all (closest hits: kdrt scene trace)");
    auto parsed = multi_hit_options(ctx);
    if (!parsed) return parsed.error();
    const proto::MultiHitQuery query = *parsed;
    auto q = ray_query(ctx, "KDRM/KDRC");
    if (!q) return q.error();
    if (q->set.occlusion)
        return ctx.usage_error(ctx.args.positional[1] +
                               " is an occlusion ray set (flag bit 0); kdrt scene hits takes "
                               "closest-hit rays");
    const std::string& id = ctx.args.positional[0];
    Client& client = ctx.connect(q->options);
    const auto start = Clock::now();
    std::vector<std::byte> answer;
    uint64_t total = 0, kept = 0, revision = 0;
    if (query.count_only) {
        auto counts =
            client.count_scene_intersections(id, q->set.rays, query.merge_coincident, q->revision);
        if (!counts) return ctx.fail(counts.error());
        for (const uint32_t c : counts->counts) total += c;
        answer = proto::encode_hit_counts(counts->counts);
        revision = counts->revision;
    } else {
        auto all = client.intersect_all_scene(id, q->set.rays, query, q->revision);
        if (!all) return ctx.fail(all.error());
        for (const uint32_t c : all->all.counts) total += c;
        kept = all->all.hits.size();
        answer = multi_hits_bytes(all->all);
        proto::append_geometry_ids(answer, all->geometry_ids);
        revision = all->revision;
    }
    const double seconds = seconds_since(start);
    if (auto failed = ctx.write_output(q->output, answer, "the answers")) return *failed;
    const size_t rays = q->set.rays.size();
    const double mrays = seconds > 0 ? static_cast<double>(rays) / seconds / 1e6 : 0.0;
    std::ostringstream human;
    human << "traced " << rays << " rays (every hit) in " << fixed(seconds, 3) << " s, "
          << fixed(mrays, 2) << " Mrays/s: " << total << " hits";
    if (!query.count_only) human << ", " << kept << " kept";
    human << " (revision " << revision << ") -> " << q->output;
    report_query(ctx, "scene hits", id, revision, q->output, human.str(),
                 {{"rays_file", std::string_view(ctx.args.positional[1])},
                  {"rays", uint64_t{rays}},
                  {"max_hits", uint64_t{query.max_hits}},
                  {"merge_coincident", query.merge_coincident},
                  {"count_only", query.count_only},
                  {"seconds", seconds},
                  {"hits", total},
                  {"kept", kept}});
    return kExitOk;
}

constexpr std::string_view kDistanceHelp =
    R"(usage: kdrt scene distance ID POINTS -o OUT [--max-distance D] [--signed] [--revision N]
                           [--chunk-points N] [--json] [--quiet]

The closest point of a scene to each query point, as kdrt distance does for a mesh, and the
instance it lies on. Every instance needs a similarity transform (a rotation or mirror times a
uniform scale; the server names the instance otherwise). POINTS is a KDRP file or text (one
point a line: x y z). OUT by its extension:
  .csv    kdrt distance's columns, then geometry_id (empty where nothing was found)
  .kdrd   the KDRD records with a geometry-id plane (proto/FORMATS.md "Scenes")

  -o, --output OUT     the .csv or .kdrd file (required; - for standard output)
  --format NAME        csv or kdrd: the format when OUT's extension does not say
  --max-distance D     only surfaces at most D away count (default: no limit)
  --signed             inside / outside of the nearest instance's closed mesh
  --revision N         that revision instead of the current one
  --chunk-points N     points per request (default 65536)
  --json               the summary as one JSON object (on stdout; stderr with -o -)
  -q, --quiet          no summary line
)";

constexpr OptionSpec kDistanceOptions[] = {
    {"output", true, 'o'},  {"max-distance", true}, {"signed", false},
    {"chunk-points", true}, {"format", true},
};

int run_distance(Context& ctx) {
    int code = kExitOk;
    if (!positional_count_ok(ctx, 2, 2, "ID and POINTS (a scene id and a points file)", code))
        return code;
    auto out = distance_output_option(ctx);
    if (!out) return out.error();
    const std::string& output = out->path;
    const DistanceOutput kind = out->kind;
    auto revision = revision_option(ctx, "revision");
    if (!revision) return revision.error();
    auto query = distance_query_options(ctx);
    if (!query) return query.error();
    auto options = distance_client_options(ctx);
    if (!options) return options.error();
    const std::string& points_path = ctx.args.positional[1];
    auto points = points_from_file(ctx, points_path);
    if (!points) return points.error();
    const std::string& id = ctx.args.positional[0];
    const auto start = Clock::now();
    auto answer = ctx.connect(*options).scene_distance(id, *points, *query, *revision);
    if (!answer) return ctx.fail(answer.error());
    const double seconds = seconds_since(start);
    std::vector<std::byte> bytes;
    if (kind == DistanceOutput::kCsv) {
        const std::string csv = proto::distances_csv(*points, answer->points, answer->geometry_ids);
        const auto* p = reinterpret_cast<const std::byte*>(csv.data());
        bytes.assign(p, p + csv.size());
    } else {
        bytes = proto::encode_distances(answer->points, query->signed_query);
        proto::append_geometry_ids(bytes, answer->geometry_ids);
    }
    if (auto failed = ctx.write_output(output, bytes, "the answers")) return *failed;
    const auto [found, inside, outside] = count_sides(answer->points);
    const double rate = seconds > 0 ? static_cast<double>(points->size()) / seconds : 0.0;
    std::ostringstream human;
    human << "queried " << points->size() << " points in " << fixed(seconds, 3) << " s, "
          << fixed(rate, 0) << " points/s: " << found << " found";
    if (query->signed_query) human << ", " << inside << " inside, " << outside << " outside";
    human << " (revision " << answer->revision << ") -> " << output;
    report_query(ctx, "scene distance", id, answer->revision, output, human.str(),
                 {{"points_file", std::string_view(points_path)},
                  {"points", uint64_t{points->size()}},
                  {"signed", query->signed_query},
                  {"seconds", seconds},
                  {"points_per_s", rate},
                  {"found", found},
                  {"inside", inside},
                  {"outside", outside}});
    return kExitOk;
}

constexpr std::string_view kScanHelp =
    R"(usage: kdrt scene scan ID --pinhole|--lidar -o FILE [SENSOR OPTIONS] [--revision N]
                       [--json] [--quiet]

Scans a scene with a depth camera or a lidar whose rays the server makes; the sensor options are
kdrt scan's (kdrt scan --help). FILE's extension picks the format, as for kdrt scan, and every
format carries the geometry id of each pixel or point (the instance it hit):
  pinhole: .exr  OpenEXR as kdrt scan writes it (float Z or range, uint prim, N.X N.Y N.Z with
                 --normals) plus a uint "geometry_id" channel (4294967295 for a miss);
                 .kdrz  the server's answer: KDRZ with a geometry-id plane
  lidar:   .ply  binary PLY point cloud (x y z range channel azimuth_index return_index prim)
                 plus a "uint geometry_id" vertex property;
                 .kdrl  the server's answer: KDRL with a geometry-id plane;
                 .kdrb  the server's compact answer: KDRB (range, beam, prim) with the plane
(proto/FORMATS.md, "Sensor scans" and "Scenes").

  -o, --output FILE   the file to write (required; - for standard output)
  --format NAME       exr, kdrz (pinhole), ply, kdrl or kdrb (lidar): the format when FILE's
                      extension does not say (-o -)
  --revision N        that revision instead of the current one

SENSOR OPTIONS (kdrt scan --help describes them): --pinhole with --intrinsics, --size and --pose,
or --eye, --look-at, --up, --fov; --range, --normals; --lidar with --channels and --vertical-fov,
or --elevations; --azimuth-steps, --returns, --pose; --min-range, --max-range.
  --json              the summary as one JSON object (on stdout; stderr with -o -)
  -q, --quiet         no summary line
)";

int run_scan(Context& ctx) {
    int code = kExitOk;
    if (!positional_count_ok(ctx, 1, 1, "ID (the scene to scan)", code)) return code;
    const auto output = ctx.args.value("output");
    if (!output) return ctx.usage_error("missing -o FILE (the scan to write)");
    const bool pinhole = ctx.args.has("pinhole");
    if (pinhole == ctx.args.has("lidar"))
        return ctx.usage_error("give exactly one of --pinhole and --lidar");
    // The server answers in the binary form (KDRZ / KDRL with the plane), written as it came;
    // EXR and PLY are encoded here by kdrt scan's writer, with the geometry ids.
    const auto file = scan_file_format(ctx, *output, pinhole);
    if (!file) return file.error();
    auto revision = revision_option(ctx, "revision");
    if (!revision) return revision.error();
    proto::ScanRequest request;
    if (auto failed = scan_request_from_args(ctx, request)) return *failed;
    if (*file == ScanFile::kRanges) request.format = proto::ScanFormat::kRanges;
    const std::string& id = ctx.args.positional[0];
    const auto start = Clock::now();
    auto scan = ctx.connect(ctx.client_options()).scan_scene(id, request, *revision);
    if (!scan) return ctx.fail(scan.error());
    std::vector<std::byte> user_file;
    if (*file == ScanFile::kUser) {
        auto encoded = encode_scan_file(ctx, scan->depth ? &*scan->depth : nullptr,
                                        scan->cloud ? &*scan->cloud : nullptr, scan->geometry_ids);
        if (!encoded) return encoded.error();
        user_file = std::move(*encoded);
    }
    const std::vector<std::byte>& bytes = *file == ScanFile::kUser ? user_file : scan->body;
    const double seconds = seconds_since(start);
    if (auto failed = ctx.write_output(*output, bytes, "the scan")) return *failed;
    uint64_t hits = 0, points = 0;
    std::string summary;
    if (scan->depth) {
        for (const uint32_t p : scan->depth->prim) hits += p != kNoHit;
        summary = std::to_string(scan->depth->width) + "x" + std::to_string(scan->depth->height) +
                  ", " + std::to_string(hits) + " pixels hit";
    } else {
        points = scan->ranges ? scan->ranges->points.size() : scan->cloud->points.size();
        summary = std::to_string(points) + " points";
    }
    report_query(ctx, "scene scan", id, scan->revision, *output,
                 "wrote " + *output + " (" + std::to_string(bytes.size()) + " bytes, " + summary +
                     ", revision " + std::to_string(scan->revision) + ", " + fixed(seconds, 3) +
                     " s)",
                 {{"sensor", std::string_view(pinhole ? "pinhole" : "lidar")},
                  {"bytes", uint64_t{bytes.size()}},
                  {"hits", hits},
                  {"points", points},
                  {"seconds", seconds}});
    return kExitOk;
}

constexpr OptionSpec kSceneOptions[] = {{"revision", true}};

constinit const Command kCreate{.name = "scene create",
                                .synopsis = "scene create FILE",
                                .summary = "create a scene",
                                .help = kCreateHelp,
                                .run = run_create};
constinit const Command kGet{.name = "scene get",
                             .synopsis = "scene get ID",
                             .summary = "show a scene",
                             .help = kGetHelp,
                             .options = kGetOptions,
                             .run = run_get};
constinit const Command kList{.name = "scene list",
                              .synopsis = "scene list",
                              .summary = "list the scenes",
                              .help = kListHelp,
                              .run = run_list};
constinit const Command kRm{.name = "scene rm",
                            .synopsis = "scene rm ID...",
                            .summary = "delete scenes",
                            .help = kRmHelp,
                            .options = kRmOptions,
                            .run = run_rm};
constinit const Command kPoses{.name = "scene poses",
                               .synopsis = "scene poses ID FILE",
                               .summary = "move instances",
                               .help = kPosesHelp,
                               .options = kPosesOptions,
                               .run = run_poses};
constinit const Command kTrace{.name = "scene trace",
                               .synopsis = "scene trace ID RAYS -o FILE",
                               .summary = "closest hits over a scene",
                               .help = kTraceHelp,
                               .options = kTraceOptions,
                               .run = run_trace};
constinit const Command kHits{.name = "scene hits",
                              .synopsis = "scene hits ID RAYS --all -o FILE",
                              .summary = "every hit over a scene",
                              .help = kHitsHelp,
                              .options = kHitsOptions,
                              .run = run_hits};
constinit const Command kDistance{.name = "scene distance",
                                  .synopsis = "scene distance ID POINTS -o OUT",
                                  .summary = "closest points of a scene",
                                  .help = kDistanceHelp,
                                  .options = kDistanceOptions,
                                  .run = run_distance};
constinit const Command kScan{.name = "scene scan",
                              .synopsis = "scene scan ID --pinhole|--lidar -o FILE",
                              .summary = "scan a scene",
                              .help = kScanHelp,
                              .options = kScanOptions,
                              .run = run_scan};

constexpr const Command* kSubcommands[] = {&kCreate, &kGet,  &kList,     &kRm,  &kPoses,
                                           &kTrace,  &kHits, &kDistance, &kScan};

}  // namespace

constinit const Command kSceneCommand{
    .name = "scene",
    .synopsis = "scene SUBCOMMAND",
    .summary = "scenes: create, get, list, rm, poses; trace, hits, distance, scan",
    .help = kSceneHelp,
    .options = kSceneOptions,
    .needs_server = true,
    .run = nullptr,
    .subcommands = kSubcommands,
};

}  // namespace kdrt::cli
