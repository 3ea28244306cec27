// kdrt render: an image of a stored mesh, as an async job.

#include <atomic>
#include <chrono>
#include <cmath>
#include <limits>
#include <optional>
#include <set>
#include <string>

#include "cli_command.h"
#include "cli_context.h"
#include "cli_output.h"
#include "cli_progress.h"
#include "kdrt/camera.h"
#include "kdrt/proto/file_io.h"
#include "kdrt/proto/image_module.h"
#include "kdrt/proto/json_api.h"

namespace kdrt::cli {
namespace {

constexpr std::string_view kRenderHelp =
    R"(usage: kdrt render ID -o FILE [--size WxH] [--eye X,Y,Z] [--look-at X,Y,Z] [--up X,Y,Z]
                   [--fov DEG] [--ortho HEIGHT] [--shading MODE] [--spp N] [--seed N]
                   [--ao-samples N] [--ao-distance D] [--light X,Y,Z] [--light-intensity I]
                   [--bounces N] [--sky S] [--background R,G,B] [--tile X,Y,W,H]
                   [--split N] [--connections N] [--format png|jpg|exr] [--json] [--quiet]

Renders an image of a stored mesh as an async job and writes the encoded image to FILE (-o -:
standard output). The format follows the extension: .png, .jpg/.jpeg or .exr (or --format,
needed with -o -). Progress and the summary go to stderr: a bar on a terminal, a line per 10 %
otherwise. Ctrl-C cancels the job (exit 130).

With --split N the frame (or the --tile) is rendered as N bands of rows instead, each a
synchronous request for its float pixels with its own routing key (?route=ID.K), so a proxy in
front of replicas (docs/scale-out.md) spreads them; the bands are stitched and encoded here,
byte for byte the image one server encodes (an EXR's header differs only in its capDate, the
time of encoding). A band's pixels travel as floats, 12 bytes a pixel, and must fit the
server's max_raw_render_bytes (512 MiB by default): split a huge frame into more bands. Ctrl-C
stops asking for bands (exit 130).

  -o, --output FILE   the image file (required; - for standard output)
  --format NAME       png, jpg or exr: the format when FILE's extension does not say
  --size WxH          image size in pixels (default 512x512)
  --eye X,Y,Z         camera position
  --look-at X,Y,Z     point the camera looks at
  --up X,Y,Z          up direction (default 0,1,0)
  --fov DEG           vertical field of view in degrees (default 40)
  --ortho HEIGHT      orthographic projection showing HEIGHT world units vertically
                      Camera options left out come from the default view of the mesh's bounds;
                      with none, the server frames the mesh itself.
  --shading MODE      normals, eyelight (default), ao, diffuse, depth, primid or geomid
  --spp N             samples per pixel (default 1)
  --seed N            seed of every random number (default 1)
  --ao-samples N      ao: occlusion rays per sample (default 16)
  --ao-distance D     ao: occlusion ray length, a share of the mesh's bounding-box diagonal
                      (default 0.25)
  --light X,Y,Z       diffuse: direction from the scene towards the light (default 0.4,1,0.7)
  --light-intensity I diffuse: the light's radiance (default 1)
  --bounces N         diffuse: indirect bounces (default 0)
  --sky S             diffuse: radiance of the sky that escaping bounce rays see (default 0)
  --background R,G,B  linear colour of pixels whose camera rays miss (default 0,0,0)
  --tile X,Y,W,H      render only this part of the frame
  --split N           render as N bands of rows, 1 .. the rows of the frame or tile
  --connections N     with --split: bands in flight at once (default 4)
  --json              the summary as one JSON object (on stdout; stderr with -o -)
  -q, --quiet         no progress or summary
)";

constexpr OptionSpec kRenderOptions[] = {
    {"output", true, 'o'}, {"size", true},
    {"eye", true},         {"look-at", true},
    {"up", true},          {"fov", true},
    {"ortho", true},       {"shading", true},
    {"spp", true},         {"seed", true},
    {"ao-samples", true},  {"ao-distance", true},
    {"light", true},       {"light-intensity", true},
    {"bounces", true},     {"sky", true},
    {"background", true},  {"tile", true},
    {"split", true},       {"connections", true},
    {"format", true},
};

/// The server's default png_compression (config/kdrt.json), for a split render whose server does
/// not send X-Kdrt-Png-Compression.
constexpr int kDefaultServerPngCompression = 1;

/// A finite number >= `min` (> `min` when `strict`) from --NAME, into `out`.
std::optional<std::string> parse_setting(const std::string& name, const std::string& text,
                                         double min, bool strict, float& out) {
    auto v = parse_number(text);
    if (!v || !std::isfinite(*v) || (strict ? !(*v > min) : !(*v >= min)) ||
        !(std::abs(*v) <= std::numeric_limits<float>::max()))
        return "--" + name + ": \"" + text + "\" is not a number " + (strict ? "> " : ">= ") +
               (min == 0 ? "0" : std::to_string(min));
    out = static_cast<float>(*v);
    return std::nullopt;
}

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
            return ctx.usage_error(
                "--shading: \"" + *shading +
                "\" is not normals, eyelight, ao, diffuse, depth, primid or geomid");
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
    if (auto text = a.value("ao-samples")) {
        auto n = parse_uint(*text, 1, kMaxAoSamples);
        if (!n) return ctx.usage_error("--ao-samples: " + n.error());
        s.ao_samples = static_cast<uint32_t>(*n);
    }
    if (auto text = a.value("ao-distance")) {
        if (auto e = parse_setting("ao-distance", *text, 0, true, s.ao_distance))
            return ctx.usage_error(*e);
    }
    if (auto text = a.value("light")) {
        auto v = parse_vec3(*text);
        if (!v) return ctx.usage_error("--light: " + v.error());
        if (!(v->x * v->x + v->y * v->y + v->z * v->z > 0.0f))
            return ctx.usage_error("--light: the direction must not be the zero vector");
        s.light.direction = *v;
    }
    if (auto text = a.value("light-intensity")) {
        if (auto e = parse_setting("light-intensity", *text, 0, false, s.light.intensity))
            return ctx.usage_error(*e);
    }
    if (auto text = a.value("bounces")) {
        auto n = parse_uint(*text, 0, kMaxBounces);
        if (!n) return ctx.usage_error("--bounces: " + n.error());
        s.bounces = static_cast<uint32_t>(*n);
    }
    if (auto text = a.value("sky")) {
        if (auto e = parse_setting("sky", *text, 0, false, s.sky)) return ctx.usage_error(*e);
    }
    if (auto text = a.value("background")) {
        auto v = parse_vec3(*text);
        if (!v) return ctx.usage_error("--background: " + v.error());
        s.background = *v;
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

/// Largest --connections of a split render (as kdrt trace's).
constexpr uint64_t kMaxRenderConnections = 64;

/// The summary of a written image (human line or --json).
void report_image(const Context& ctx, const std::string& output, const RenderRequest& request,
                  size_t bytes, uint32_t width, uint32_t height, double seconds, unsigned parts,
                  size_t replicas) {
    const RenderSettings& s = request.settings;
    std::string human = "wrote " + output + " (" + std::to_string(bytes) + " bytes, " +
                        std::to_string(width) + "x" + std::to_string(height) + " " +
                        std::string(shading_name(s.shading)) + ", " + std::to_string(s.spp) +
                        " spp";
    if (parts > 0) human += ", " + std::to_string(parts) + (parts == 1 ? " part" : " parts");
    if (replicas > 0)
        human += " on " + std::to_string(replicas) + (replicas == 1 ? " replica" : " replicas");
    human += ")";  // the time is on the progress line
    const proto::JsonField fields[] = {{"command", std::string_view("render")},
                                       {"mesh", std::string_view(request.mesh)},
                                       {"out", std::string_view(output)},
                                       {"format", std::string_view(request.format)},
                                       {"bytes", uint64_t{bytes}},
                                       {"width", uint64_t{width}},
                                       {"height", uint64_t{height}},
                                       {"shading", shading_name(s.shading)},
                                       {"spp", uint64_t{s.spp}},
                                       {"parts", uint64_t{parts}},
                                       {"replicas", uint64_t{replicas}},
                                       {"seconds", seconds}};
    ctx.report(output, human, proto::encode_flat_object(fields));
}

/// --split N: the frame (or tile) as N bands of rows over up to --connections requests at once,
/// stitched and encoded here (Client::render_split).
int run_split_render(Context& ctx, const RenderRequest& request, unsigned parts,
                     const std::string& output) {
    const auto start = std::chrono::steady_clock::now();
    ProgressReporter progress(ctx.console.err, ctx.console.err_is_tty, ctx.quiet(), "render");
    const std::atomic<bool>* interrupted = ctx.console.interrupted;
    if (ctx.console.waiting) ctx.console.waiting->store(true);
    auto frame = ctx.client->render_split(request, parts, [&](unsigned done, unsigned all) {
        progress.update("running", static_cast<double>(done) / all);
        return !(interrupted && interrupted->load());
    });
    if (ctx.console.waiting) ctx.console.waiting->store(false);
    if (!frame) {
        if (frame.error().kind == ErrorKind::kCancelled && interrupted && interrupted->load()) {
            progress.finish("interrupted");
            return kExitInterrupted;
        }
        progress.finish("failed");
        return ctx.fail(frame.error());
    }
    // The server's level (X-Kdrt-Png-Compression); a server that does not say gets the default.
    auto bytes = (*proto::image_module())
                     ->encode_render(frame->image, request.format, request.settings.shading,
                                     frame->png_compression.value_or(kDefaultServerPngCompression));
    if (!bytes) {
        progress.finish("failed");
        return ctx.fail(
            make_client_error(ErrorKind::kInput, "cannot encode the image", bytes.error()));
    }
    const double seconds =
        std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
    progress.finish("done in " + fixed(seconds, 2) + " s");
    if (auto failed = ctx.write_output(output, *bytes, "the image")) return *failed;
    std::set<std::string> replicas(frame->replicas.begin(), frame->replicas.end());
    replicas.erase("");
    report_image(ctx, output, request, bytes->size(), frame->image.width, frame->image.height,
                 seconds, parts, replicas.size());
    return kExitOk;
}

int run_render(Context& ctx) {
    int code = kExitOk;
    if (!positional_count_ok(ctx, 1, 1, "ID (the mesh to render)", code)) return code;
    const auto output = ctx.args.value("output");
    if (!output) return ctx.usage_error("missing -o FILE (the image to write)");
    const auto format = image_format_for_path(ctx.format_path(*output));
    if (!format)
        return ctx.usage_error(
            ctx.args.has("format")
                ? "--format: \"" + *ctx.args.value("format") + "\" is not png, jpg or exr"
                : "cannot tell the image format of \"" + *output +
                      "\" from its extension (use .png, .jpg, .jpeg or .exr, or --format)");
    std::optional<unsigned> split;
    if (auto text = ctx.args.value("split")) {
        auto n = parse_uint(*text, 1, kMaxImageSize);
        if (!n)
            return ctx.usage_error("--split: " + n.error() +
                                   " (bands of rows, at most one per row of the frame or tile)");
        split = static_cast<unsigned>(*n);
        // The stitched frame is encoded here: the encoder must load before the job starts.
        if (auto failed = ctx.need_image_module()) return *failed;
    }
    ClientOptions options = ctx.client_options();
    if (auto text = ctx.args.value("connections")) {
        if (!split) return ctx.usage_error("--connections applies to --split renders only");
        auto n = parse_uint(*text, 1, kMaxRenderConnections);
        if (!n) return ctx.usage_error("--connections: " + n.error());
        options.connections = static_cast<unsigned>(*n);
    }
    ctx.connect(options);
    auto id = ctx.resolve_mesh_id(ctx.args.positional[0]);
    if (!id) return id.error();
    RenderRequest request;
    request.mesh = *id;
    request.format = *format;
    if (auto failed = render_settings(ctx, *id, request)) return *failed;
    if (split) {
        const RenderSettings& s = request.settings;
        const uint32_t rows = s.region ? s.region->height : s.height;
        if (*split > rows)
            return ctx.usage_error("--split: " + std::to_string(*split) + " bands, but the " +
                                   (s.region ? "tile" : "frame") + " has only " +
                                   std::to_string(rows) + " rows (at most one band per row)");
        return run_split_render(ctx, request, *split, *output);
    }

    const auto start = std::chrono::steady_clock::now();
    auto job = ctx.client->submit(request);
    if (!job) return ctx.fail(job.error());
    ProgressReporter progress(ctx.console.err, ctx.console.err_is_tty, ctx.quiet(), "render");
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
    progress.finish("done in " + fixed(seconds, 2) + " s");
    if (auto failed = ctx.write_output(*output, *image, "the image")) return *failed;
    const RenderSettings& s = request.settings;
    report_image(ctx, *output, request, image->size(), s.region ? s.region->width : s.width,
                 s.region ? s.region->height : s.height, seconds, 0, 0);
    return kExitOk;
}

}  // namespace

constinit const Command kRenderCommand{
    .name = "render",
    .synopsis = "render ID -o FILE",
    .summary = "render an image as an async job (PNG, JPEG or EXR, from the extension)",
    .help = kRenderHelp,
    .options = kRenderOptions,
    .needs_server = true,
    .run = run_render,
};

}  // namespace kdrt::cli
