// kdrt: dispatch, help texts, and the mesh, render and operations subcommands.

#include "cli_commands.h"

#include <algorithm>
#include <cctype>
#include <chrono>
#include <cmath>
#include <vector>

#include "cli_args.h"
#include "cli_context.h"
#include "cli_output.h"
#include "cli_progress.h"
#include "kdrt/camera.h"
#include "kdrt/proto/file_io.h"
#include "kdrt/proto/mesh_id.h"

namespace kdrt::cli {
namespace {

constexpr std::string_view kMainHelp =
    R"(usage: kdrt [--server URL] [--token TOKEN] COMMAND [ARGS...]

Command-line client of kdrt-server: upload meshes, trace ray files, render images.

Commands:
  upload FILE...          upload mesh files (OBJ, PLY, OFF, STL, raw); print id, triangles, build ms
  meshes                  list the stored meshes
  info ID                 show one stored mesh
  rm ID...                delete stored meshes
  render ID -o FILE       render an image as an async job (PNG, JPEG or EXR, from the extension)
  trace ID RAYS -o FILE   trace a KDRR ray file; write the KDRH hits (KDRO for occlusion rays)
  rays MESH -o FILE       generate a KDRR ray file locally (the ray sets of kdrt-bench rays)
  health                  check that the server is alive and ready
  metrics                 print the server's Prometheus metrics
  bench-remote ID         measure remote tracing speed in Mrays/s
  help [COMMAND]          this text, or a command's (also: kdrt COMMAND --help)

Options of every command that talks to the server (before or after COMMAND):
  --server URL      server address; default $KDRT_SERVER, else http://127.0.0.1:8080
  --token TOKEN     bearer token; default $KDRT_TOKEN
  --timeout S       seconds one socket read or write may take (default 300)
  --retries N       retries on connection errors and 503 answers, with exponential backoff
                    (Retry-After honoured; never on other errors; default 4)
  -h, --help        help
  --version         print the version

A mesh ID may be shortened to a unique prefix of 4 or more hex digits.

Exit status: 0 success; 1 the server refused the request (its message is printed) or a render
failed; 2 usage error (bad arguments, or a file named on the command line cannot be read or
written); 3 cannot connect to the server; 130 interrupted while waiting for a render.
)";

constexpr std::string_view kUploadHelp =
    R"(usage: kdrt upload FILE... [--format obj|ply|off|stl|raw] [--json]

Uploads each mesh file; the server builds its kD-tree and stores it. Prints one line per file:
  ID  TRIANGLES triangles  BUILD_MS ms  FILE
Uploading the same triangles again (in any format) returns the stored mesh without a rebuild.

  --format F   the format of every FILE (default: from each extension: .obj .ply .off .stl,
               .raw/.kdrtmesh for the raw format)
  --json       print one JSON object per file, one per line: "file" and the server's fields
               (id, triangles, vertices, bounds, build_ms, tree, in_memory)

A file the server cannot parse is reported with its line or byte (exit 1); the other files are
still uploaded.
)";

constexpr std::string_view kMeshesHelp = R"(usage: kdrt meshes [--json]

Lists the stored meshes, sorted by id: ID, TRIANGLES, VERTICES, BUILD_MS, IN_MEMORY.

  --json   one JSON object per mesh, one per line (the server's fields)
)";

constexpr std::string_view kInfoHelp = R"(usage: kdrt info ID [--json]

Shows one stored mesh: triangles, vertices, bounds, build time and kD-tree statistics.

  --json   the server's JSON object on one line
)";

constexpr std::string_view kRmHelp = R"(usage: kdrt rm ID...

Deletes stored meshes (their files on the server too). Prints "removed ID" per mesh.
)";

constexpr std::string_view kRenderHelp =
    R"(usage: kdrt render ID -o FILE [--size WxH] [--eye X,Y,Z] [--look-at X,Y,Z] [--up X,Y,Z]
                   [--fov DEG] [--ortho HEIGHT] [--shading MODE] [--spp N] [--seed N]
                   [--tile X,Y,W,H] [--quiet]

Renders an image of a stored mesh as an async job and writes the encoded image to FILE. The
format follows the extension: .png, .jpg/.jpeg or .exr. Progress goes to stderr: a bar on a
terminal, a line per 10 % otherwise. Ctrl-C cancels the job (exit 130).

  -o, --output FILE   the image file (required)
  --size WxH          image size in pixels (default 512x512)
  --eye X,Y,Z         camera position
  --look-at X,Y,Z     point the camera looks at
  --up X,Y,Z          up direction (default 0,1,0)
  --fov DEG           vertical field of view in degrees (default 40)
  --ortho HEIGHT      orthographic projection showing HEIGHT world units vertically
                      Camera options left out come from the default view of the mesh's bounds;
                      with none, the server frames the mesh itself.
  --shading MODE      normals, eyelight (default), ao, diffuse, depth or primid
  --spp N             samples per pixel (default 1)
  --seed N            seed of every random number (default 1)
  --tile X,Y,W,H      render only this part of the frame
  --quiet             no progress output
)";

constexpr std::string_view kHealthHelp = R"(usage: kdrt health

Asks the server whether it is alive (/healthz) and ready (/readyz). Prints "ok: URL is alive and
ready"; exit 1 with the server's reason when it is alive but not ready (starting, shutting down).
)";

constexpr std::string_view kMetricsHelp = R"(usage: kdrt metrics

Prints the server's metrics in the Prometheus text format (GET /metrics).
)";

constexpr std::string_view kTraceHelp =
    R"(usage: kdrt trace ID RAYS.kdrr -o FILE [--connections N] [--chunk-rays N] [--json]

Traces every ray of a KDRR file (kdrt rays, kdrt-bench rays, proto/FORMATS.md) against a stored
mesh and writes the answers to FILE: KDRH closest hits, or KDRO occlusion bytes when the file's
occlusion flag is set. Large files go in chunks over several keep-alive connections in parallel.
Prints the ray count, time, Mrays/s and hits.

  -o, --output FILE    the KDRH / KDRO file (required)
  --connections N      chunks in flight at once (default 4)
  --chunk-rays N       rays per request (default 65536)
  --json               print the summary as one JSON object
)";

constexpr std::string_view kRaysHelp =
    R"(usage: kdrt rays MESH -o FILE [--kind primary|shadow|diffuse|random] [--res N] [--seed N] [--json]

Generates a deterministic KDRR ray set for a mesh file, locally (no server): the same bytes as
`kdrt-bench rays` on every machine. The mesh's kD-tree is built in this process.

  -o, --output FILE   the KDRR file (required)
  --kind K            primary: R x R camera rays of the default view (default)
                      shadow: from each primary hit towards a point light (occlusion query)
                      diffuse: from each primary hit, cosine-weighted
                      random: R x R rays with random origins in the bounds, random directions
  --res R             resolution (default 1024, at most 8192)
  --seed N            seed (default 1)
  --json              print the summary as one JSON object
)";

constexpr std::string_view kBenchHelp =
    R"(usage: kdrt bench-remote ID [--kind primary|shadow|diffuse|random] [--res N] [--seed N]
                         [--mesh FILE | --rays FILE] [--connections N] [--chunk-rays N]
                         [--reps K] [--json]

Measures how fast the server traces a batch over the network: one untimed pass, then K timed
passes (default 3) of the whole batch through kdrt::Client (chunked, in parallel over
--connections keep-alive connections). Prints the median time and Mrays/s.

Rays:
  --rays FILE     a KDRR file (its flag picks closest hits or occlusion)
  --mesh FILE     the mesh file that was uploaded as ID (its id is checked): the --kind ray set
                  is generated from it exactly as `kdrt rays` does
  (neither)       --kind primary only: R x R camera rays of the default view of the bounds the
                  server reports (the server does not send triangles back, so the other kinds
                  need --mesh)
  --kind K        primary (default), shadow, diffuse or random
  --res R         resolution (default 1024, at most 8192)
  --seed N        seed (default 1)
  --connections N chunks in flight at once (default 4)
  --chunk-rays N  rays per request (default 65536)
  --reps K        timed passes, 1 .. 100 (default 3)
  --json          print one JSON object: mesh, kind, source, rays, occlusion, connections,
                  chunk_rays, reps, seconds (median), seconds_min, mrays_per_s, hits
)";

int run_upload(Context& ctx);
int run_meshes(Context& ctx);
int run_info(Context& ctx);
int run_rm(Context& ctx);
int run_render(Context& ctx);
int run_health(Context& ctx);
int run_metrics(Context& ctx);

struct CommandSpec {
    std::string_view name;
    std::string_view help;
    std::vector<OptionSpec> options;  ///< besides kGlobalOptions
    bool needs_server = true;
    int (*run)(Context&) = nullptr;
};

const std::vector<CommandSpec>& commands() {
    static const std::vector<CommandSpec> kCommands = {
        {"upload", kUploadHelp, {{"format", true}, {"json", false}}, true, run_upload},
        {"meshes", kMeshesHelp, {{"json", false}}, true, run_meshes},
        {"info", kInfoHelp, {{"json", false}}, true, run_info},
        {"rm", kRmHelp, {}, true, run_rm},
        {"render",
         kRenderHelp,
         {{"output", true, 'o'},
          {"size", true},
          {"eye", true},
          {"look-at", true},
          {"up", true},
          {"fov", true},
          {"ortho", true},
          {"shading", true},
          {"spp", true},
          {"seed", true},
          {"tile", true},
          {"quiet", false}},
         true,
         run_render},
        {"trace",
         kTraceHelp,
         {{"output", true, 'o'}, {"connections", true}, {"chunk-rays", true}, {"json", false}},
         true,
         run_trace},
        {"rays",
         kRaysHelp,
         {{"output", true, 'o'}, {"kind", true}, {"res", true}, {"seed", true}, {"json", false}},
         false,
         run_rays},
        {"health", kHealthHelp, {}, true, run_health},
        {"metrics", kMetricsHelp, {}, true, run_metrics},
        {"bench-remote",
         kBenchHelp,
         {{"kind", true},
          {"res", true},
          {"seed", true},
          {"mesh", true},
          {"rays", true},
          {"connections", true},
          {"chunk-rays", true},
          {"reps", true},
          {"json", false}},
         true,
         run_bench_remote},
    };
    return kCommands;
}

const CommandSpec* find_command(std::string_view name) {
    for (const CommandSpec& c : commands())
        if (c.name == name) return &c;
    return nullptr;
}

bool is_global_value_option(std::string_view arg) {
    for (const OptionSpec& s : kGlobalOptions) {
        if (!s.takes_value) continue;
        const std::string flag = "--" + std::string(s.name);
        if (arg == flag || arg.rfind(flag + "=", 0) == 0) return true;
    }
    return false;
}

/// Checks the positional count: at least `min`, at most `max`.
bool positional_count_ok(Context& ctx, size_t min, size_t max, std::string_view what, int& code) {
    const size_t n = ctx.args.positional.size();
    if (n < min) {
        code = ctx.usage_error("missing " + std::string(what));
        return false;
    }
    if (n > max) {
        code = ctx.usage_error("unexpected argument \"" + ctx.args.positional[max] + "\"");
        return false;
    }
    return true;
}

// ---- upload, meshes, info, rm ----------------------------------------------------------------

int run_upload(Context& ctx) {
    int code = kExitOk;
    if (!positional_count_ok(ctx, 1, SIZE_MAX, "FILE (the mesh files to upload)", code))
        return code;
    std::optional<proto::MeshFormat> format;
    if (auto name = ctx.args.value("format")) {
        format = proto::mesh_format_from_name(*name);
        if (!format)
            return ctx.usage_error("--format: \"" + *name + "\" is not obj, ply, off, stl or raw");
    }
    const bool json = ctx.args.has("json");
    Client& client = ctx.connect(ctx.client_options());
    for (const std::string& file : ctx.args.positional) {
        auto mesh = client.upload(file, format);
        if (!mesh) {
            const int failed = ctx.fail(mesh.error(), file);
            if (failed == kExitUnreachable)
                return failed;  // the other files would fail the same way
            code = std::max(code, failed);
            continue;
        }
        ctx.console.out << (json ? mesh_json_line(*mesh, file) : upload_line(*mesh, file)) << "\n"
                        << std::flush;
    }
    return code;
}

int run_meshes(Context& ctx) {
    int code = kExitOk;
    if (!positional_count_ok(ctx, 0, 0, "", code)) return code;
    auto list = ctx.connect(ctx.client_options()).meshes();
    if (!list) return ctx.fail(list.error());
    if (ctx.args.has("json")) {
        for (const MeshInfo& m : *list) ctx.console.out << mesh_json_line(m) << "\n";
    } else if (list->empty()) {
        ctx.console.out << "no meshes stored\n";
    } else {
        ctx.console.out << mesh_table(*list);
    }
    return kExitOk;
}

int run_info(Context& ctx) {
    int code = kExitOk;
    if (!positional_count_ok(ctx, 1, 1, "ID (a mesh id)", code)) return code;
    ctx.connect(ctx.client_options());
    auto id = ctx.resolve_mesh_id(ctx.args.positional[0]);
    if (!id) return id.error();
    auto mesh = ctx.client->mesh(*id);
    if (!mesh) return ctx.fail(mesh.error());
    ctx.console.out << (ctx.args.has("json") ? mesh_json_line(*mesh) + "\n" : mesh_details(*mesh));
    return kExitOk;
}

int run_rm(Context& ctx) {
    int code = kExitOk;
    if (!positional_count_ok(ctx, 1, SIZE_MAX, "ID (the meshes to delete)", code)) return code;
    ctx.connect(ctx.client_options());
    for (const std::string& arg : ctx.args.positional) {
        auto id = ctx.resolve_mesh_id(arg);
        if (!id) {
            if (id.error() == kExitUnreachable) return id.error();
            code = std::max(code, id.error());
            continue;
        }
        auto removed = ctx.client->remove(*id);
        if (!removed) {
            const int failed = ctx.fail(removed.error());
            if (failed == kExitUnreachable) return failed;
            code = std::max(code, failed);
            continue;
        }
        ctx.console.out << "removed " << *id << "\n" << std::flush;
    }
    return code;
}

// ---- render ---------------------------------------------------------------------------------

/// Fills `request.settings` from the command line. Returns an exit code on a usage error.
std::optional<int> render_settings(Context& ctx, const std::string& id, RenderRequest& request) {
    RenderSettings& s = request.settings;
    const ParsedArgs& a = ctx.args;
    if (auto size = a.value("size")) {
        auto wh = parse_size(*size);
        if (!wh) return ctx.usage_error("--size: " + wh.error());
        s.width = wh->first;
        s.height = wh->second;
    }
    if (auto shading = a.value("shading")) {
        auto mode = parse_shading(*shading);
        if (!mode)
            return ctx.usage_error("--shading: \"" + *shading +
                                   "\" is not normals, eyelight, ao, diffuse, depth or primid");
        s.shading = *mode;
    }
    if (auto spp = a.value("spp")) {
        auto n = parse_uint(*spp, 1, kMaxSamplesPerPixel);
        if (!n) return ctx.usage_error("--spp: " + n.error());
        s.spp = static_cast<uint32_t>(*n);
    }
    if (auto seed = a.value("seed")) {
        auto n = parse_uint(*seed, 0, UINT64_MAX);
        if (!n) return ctx.usage_error("--seed: " + n.error());
        s.seed = *n;
    }
    if (auto tile = a.value("tile")) {
        auto region = parse_region(*tile);
        if (!region) return ctx.usage_error("--tile: " + region.error());
        s.region = *region;
    }
    const bool camera =
        a.has("eye") || a.has("look-at") || a.has("up") || a.has("fov") || a.has("ortho");
    if (!camera) return std::nullopt;
    // Parse everything before asking the server for the bounds.
    std::optional<Vec3> eye, look_at, up;
    for (auto [name, target] :
         {std::pair{"eye", &eye}, std::pair{"look-at", &look_at}, std::pair{"up", &up}}) {
        if (auto text = a.value(name)) {
            auto v = parse_vec3(*text);
            if (!v) return ctx.usage_error("--" + std::string(name) + ": " + v.error());
            *target = *v;
        }
    }
    std::optional<float> fov, ortho;
    if (auto text = a.value("fov")) {
        auto deg = parse_number(*text);
        if (!deg || *deg <= 0 || *deg >= 180)
            return ctx.usage_error("--fov: \"" + *text +
                                   "\" is not a number of degrees in (0, 180)");
        fov = static_cast<float>(*deg);
    }
    if (auto text = a.value("ortho")) {
        auto height = parse_number(*text);
        if (!height || *height <= 0)
            return ctx.usage_error("--ortho: \"" + *text + "\" is not a positive number");
        ortho = static_cast<float>(*height);
    }
    auto mesh = ctx.client->mesh(id);
    if (!mesh) return ctx.fail(mesh.error());
    CameraSpec spec =
        default_camera(mesh->bounds, static_cast<float>(s.width) / static_cast<float>(s.height));
    if (eye) spec.eye = *eye;
    if (look_at) spec.look_at = *look_at;
    if (up) spec.up = *up;
    if (fov) spec.fov_deg = *fov;
    if (ortho) {
        spec.projection = Projection::kOrthographic;
        spec.ortho_height = *ortho;
    }
    s.camera = spec;
    return std::nullopt;
}

int run_render(Context& ctx) {
    int code = kExitOk;
    if (!positional_count_ok(ctx, 1, 1, "ID (the mesh to render)", code)) return code;
    const auto output = ctx.args.value("output");
    if (!output) return ctx.usage_error("missing -o FILE (the image to write)");
    const auto format = image_format_for_path(*output);
    if (!format)
        return ctx.usage_error("cannot tell the image format of \"" + *output +
                               "\" from its extension (use .png, .jpg, .jpeg or .exr)");
    ctx.connect(ctx.client_options());
    auto id = ctx.resolve_mesh_id(ctx.args.positional[0]);
    if (!id) return id.error();
    RenderRequest request;
    request.mesh = *id;
    request.format = *format;
    if (auto failed = render_settings(ctx, *id, request)) return *failed;

    const auto start = std::chrono::steady_clock::now();
    auto job = ctx.client->submit(request);
    if (!job) return ctx.fail(job.error());
    ProgressReporter progress(ctx.console.err, ctx.console.err_is_tty, ctx.args.has("quiet"),
                              "render");
    const std::atomic<bool>* interrupted = ctx.console.interrupted;
    if (ctx.console.waiting) ctx.console.waiting->store(true);
    auto image = ctx.client->wait(*job, [&](const Job& status) {
        progress.update(proto::job_state_name(status.state), status.progress);
        return !(interrupted && interrupted->load());
    });
    if (ctx.console.waiting) ctx.console.waiting->store(false);
    if (!image) {
        if (image.error().kind == ErrorKind::kCancelled && interrupted && interrupted->load()) {
            progress.finish("interrupted; job " + job->id + " cancelled");
            return kExitInterrupted;
        }
        progress.finish("failed");
        return ctx.fail(image.error());
    }
    (void)ctx.client->cancel(
        *job);  // forget the finished job: the server keeps its image otherwise
    const double seconds =
        std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
    if (auto written = proto::write_file_bytes(*output, *image); !written) {
        progress.finish("failed");
        return ctx.fail(
            make_client_error(ErrorKind::kInput, "cannot write the image", written.error()));
    }
    progress.finish("done in " + fixed(seconds, 2) + " s");
    ctx.console.out << "wrote " << *output << " (" << image->size() << " bytes, "
                    << request.settings.width << "x" << request.settings.height << " "
                    << shading_name(request.settings.shading) << ", " << request.settings.spp
                    << " spp)\n";
    return kExitOk;
}

// ---- health, metrics --------------------------------------------------------------------------

int run_health(Context& ctx) {
    int code = kExitOk;
    if (!positional_count_ok(ctx, 0, 0, "", code)) return code;
    Client& client = ctx.connect(ctx.client_options());
    if (auto alive = client.health(); !alive) return ctx.fail(alive.error());
    if (auto ready = client.ready(); !ready) {
        ctx.console.out << client.url().to_string() << " is alive but not ready\n";
        return ctx.fail(ready.error());
    }
    ctx.console.out << "ok: " << client.url().to_string() << " is alive and ready\n";
    return kExitOk;
}

int run_metrics(Context& ctx) {
    int code = kExitOk;
    if (!positional_count_ok(ctx, 0, 0, "", code)) return code;
    auto text = ctx.connect(ctx.client_options()).metrics();
    if (!text) return ctx.fail(text.error());
    ctx.console.out << *text;
    return kExitOk;
}

}  // namespace

// ---- Context ----------------------------------------------------------------------------------

int exit_code_for(const Error& error) noexcept {
    switch (error.kind) {
        case ErrorKind::kConnection:
            return kExitUnreachable;
        case ErrorKind::kInput:
            return kExitUsage;
        case ErrorKind::kServer:
        case ErrorKind::kProtocol:
        case ErrorKind::kJobFailed:
        case ErrorKind::kCancelled:
            break;
    }
    return kExitRefused;
}

ClientOptions Context::client_options() const {
    ClientOptions options;
    options.token = settings.token;
    if (settings.timeout_s)
        options.io_timeout =
            std::chrono::milliseconds(static_cast<int64_t>(std::ceil(*settings.timeout_s * 1000)));
    if (settings.retries) options.max_retries = *settings.retries;
    return options;
}

Client& Context::connect(const ClientOptions& options) {
    client.emplace(settings.server, options);
    return *client;
}

int Context::usage_error(std::string_view message) const {
    console.err << "kdrt " << command << ": " << message << "\n"
                << "run 'kdrt " << command << " --help' for usage\n";
    return kExitUsage;
}

int Context::fail(const Error& error, std::string_view subject) const {
    console.err << "kdrt " << command << ": "
                << (subject.empty() ? "" : std::string(subject) + ": ") << error.to_string()
                << "\n";
    if (error.kind == ErrorKind::kConnection)
        console.err
            << "is kdrt-server running there? Set the address with --server URL or KDRT_SERVER.\n";
    if (error.kind == ErrorKind::kServer && error.status == 401)
        console.err << "set the server's bearer token with --token TOKEN or KDRT_TOKEN.\n";
    return exit_code_for(error);
}

proto::Result<std::string, int> Context::resolve_mesh_id(std::string_view arg) {
    if (proto::is_mesh_id(arg)) return std::string(arg);
    std::string prefix(arg);
    std::transform(prefix.begin(), prefix.end(), prefix.begin(),
                   [](unsigned char c) { return static_cast<char>(std::tolower(c)); });
    const bool hex = prefix.size() >= 4 && prefix.size() < proto::kMeshIdLength &&
                     prefix.find_first_not_of("0123456789abcdef") == std::string::npos;
    if (!hex) return std::string(arg);  // the server explains what is wrong with it
    auto list = client->meshes();
    if (!list) return proto::Err{fail(list.error())};
    std::vector<std::string> matches;
    for (const MeshInfo& m : *list)
        if (m.id.rfind(prefix, 0) == 0) matches.push_back(m.id);
    if (matches.empty()) {
        console.err << "kdrt " << command << ": no stored mesh has an id starting with " << prefix
                    << "\n";
        return proto::Err{static_cast<int>(kExitRefused)};
    }
    if (matches.size() > 1)
        return proto::Err{usage_error("mesh id prefix " + prefix +
                                      " is ambiguous: " + std::to_string(matches.size()) +
                                      " stored meshes start with it; give more digits")};
    return matches.front();
}

// ---- run ----------------------------------------------------------------------------------------

int run(std::span<const std::string> args, const std::map<std::string, std::string>& env,
        const Console& console) {
    // The command is the first argument that is neither a global option nor its value.
    size_t command_index = args.size();
    for (size_t i = 0; i < args.size(); ++i) {
        const std::string& arg = args[i];
        if (arg == "--help" || arg == "-h") {
            console.out << kMainHelp;
            return kExitOk;
        }
        if (arg == "--version") {
            console.out << "kdrt " << KDRT_VERSION << "\n";
            return kExitOk;
        }
        if (is_global_value_option(arg)) {
            if (arg.find('=') == std::string::npos) ++i;
            continue;
        }
        if (arg.size() > 1 && arg[0] == '-') {
            console.err << "kdrt: unknown option \"" << arg << "\" before the command\n"
                        << "run 'kdrt --help' for usage\n";
            return kExitUsage;
        }
        command_index = i;
        break;
    }
    if (command_index == args.size()) {
        console.err << "kdrt: missing command\n\n" << kMainHelp;
        return kExitUsage;
    }
    const std::string& name = args[command_index];
    if (name == "help") {
        if (command_index + 1 >= args.size()) {
            console.out << kMainHelp;
            return kExitOk;
        }
        const CommandSpec* spec = find_command(args[command_index + 1]);
        if (!spec) {
            console.err << "kdrt help: unknown command \"" << args[command_index + 1] << "\"\n"
                        << "run 'kdrt --help' for the list of commands\n";
            return kExitUsage;
        }
        console.out << spec->help;
        return kExitOk;
    }
    const CommandSpec* spec = find_command(name);
    if (!spec) {
        console.err << "kdrt: unknown command \"" << name << "\"\n"
                    << "run 'kdrt --help' for the list of commands\n";
        return kExitUsage;
    }
    std::vector<std::string> rest(args.begin(),
                                  args.begin() + static_cast<std::ptrdiff_t>(command_index));
    rest.insert(rest.end(), args.begin() + static_cast<std::ptrdiff_t>(command_index) + 1,
                args.end());
    std::vector<OptionSpec> options = spec->options;
    options.insert(options.end(), std::begin(kGlobalOptions), std::end(kGlobalOptions));

    Context ctx{console, spec->name, {}, {}, std::nullopt};
    auto parsed = parse_args(rest, options, "kdrt " + std::string(spec->name));
    if (!parsed) {
        console.err << "kdrt " << spec->name << ": " << parsed.error() << "\n";
        return kExitUsage;
    }
    ctx.args = std::move(*parsed);
    if (ctx.args.has("help")) {
        console.out << spec->help;
        return kExitOk;
    }
    if (spec->needs_server) {
        auto settings = global_settings(ctx.args, env);
        if (!settings) return ctx.usage_error(settings.error());
        ctx.settings = std::move(*settings);
    }
    return spec->run(ctx);
}

}  // namespace kdrt::cli
