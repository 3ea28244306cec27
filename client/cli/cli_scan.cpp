// kdrt scan: a depth camera or lidar scan of a stored mesh, its rays made on the server, written
// as a file a user can open (EXR depth image, PLY point cloud) or in kdrt's binary formats.

#include <chrono>
#include <cmath>
#include <limits>
#include <optional>
#include <string>
#include <vector>

#include "cli_command.h"
#include "cli_context.h"
#include "cli_output.h"
#include "cli_scan.h"
#include "kdrt/proto/file_io.h"
#include "kdrt/proto/image_module.h"
#include "kdrt/proto/json_api.h"
#include "kdrt/proto/scan.h"

namespace kdrt::cli {
namespace {

constexpr std::string_view kScanHelp =
    R"(usage: kdrt scan ID --pinhole -o FILE (--intrinsics FX,FY,CX,CY --size WxH --pose M
                                          | --eye X,Y,Z --look-at X,Y,Z [--up X,Y,Z] [--fov DEG]
                                            [--size WxH])
                 [--range] [--normals] [--min-range R] [--max-range R]
       kdrt scan ID --lidar -o FILE (--channels N --vertical-fov LO,HI | --elevations E,E,...)
                 --azimuth-steps N [--returns N] [--pose M] [--min-range R] [--max-range R]

Scans a stored mesh with a sensor whose rays the server makes (proto/FORMATS.md, "Sensor
scans") and writes FILE, whose extension picks the format:
  pinhole: .exr  OpenEXR with float Z (depth) or range, uint prim and, with --normals,
                 N.X N.Y N.Z channels; .kdrz  the KDRZ depth image
  lidar:   .ply  binary PLY point cloud (x y z range channel azimuth_index return_index prim);
                 .kdrl  the KDRL point cloud; .kdrb  the compact KDRB record (range, beam, prim)
Misses: depth +inf, prim 4294967295; a lidar beam without a hit has no point.

  --pinhole             a pinhole depth camera (OpenCV frame: +x right, +y down, +z forward;
                        pixel (i, j)'s ray through (i + 0.5, j + 0.5))
  --lidar               a spinning lidar (frame: +x forward = azimuth 0, +y left, +z up;
                        azimuth counter-clockwise seen from above)
  -o, --output FILE     the file to write (required; - for standard output)
  --format NAME         exr, kdrz (pinhole), ply, kdrl or kdrb (lidar): the format when FILE's
                        extension does not say
  --intrinsics FX,FY,CX,CY  focal lengths and principal point in pixels (with --size, --pose)
  --size WxH            image size in pixels (default 640x480 with --eye)
  --pose M              sensor-to-world rigid transform: 16 numbers, row-major, comma-separated
                        (lidar default: the identity)
  --eye X,Y,Z           look-at camera position, instead of --intrinsics and --pose
  --look-at X,Y,Z       the point it looks at
  --up X,Y,Z            up direction (default 0,1,0)
  --fov DEG             vertical field of view in degrees (default 40)
  --range               answer the distance along each ray instead of the depth (z)
  --normals             also answer each hit's geometric normal
  --channels N          lidar channels, evenly spaced over --vertical-fov (channel 0 the top)
  --vertical-fov LO,HI  lowest and highest elevation in degrees
  --elevations E,...    one elevation per channel in degrees, instead of the two above
  --azimuth-steps N     firings per turn, evenly spaced over 360 degrees
  --returns N           hits kept per beam, nearest first (default 1)
  --min-range R         only hits at least R away (default 0)
  --max-range R         only hits at most R away (default: no limit)
  --json                the summary as one JSON object (on stdout; stderr with -o -)
  -q, --quiet           no summary line (it goes to stderr)
)";

/// Comma-separated finite numbers.
std::optional<std::vector<double>> parse_numbers(const std::string& text) {
    std::vector<double> out;
    size_t start = 0;
    while (true) {
        const size_t comma = text.find(',', start);
        auto v =
            parse_number(text.substr(start, comma == std::string::npos ? comma : comma - start));
        if (!v) return std::nullopt;
        out.push_back(*v);
        if (comma == std::string::npos) return out;
        start = comma + 1;
    }
}

bool ends_with(const std::string& text, std::string_view tail) {
    if (text.size() < tail.size()) return false;
    for (size_t i = 0; i < tail.size(); ++i)
        if (std::tolower(static_cast<unsigned char>(text[text.size() - tail.size() + i])) !=
            tail[i])
            return false;
    return true;
}

/// The options shared by both sensors: --pose, --min-range, --max-range.
std::optional<int> common_options(Context& ctx, Pose* pose, float& min_range, float& max_range) {
    const ParsedArgs& a = ctx.args;
    if (auto text = a.value("pose")) {
        auto m = parse_numbers(*text);
        if (!m || m->size() != 16)
            return ctx.usage_error("--pose: \"" + *text +
                                   "\" is not 16 comma-separated numbers (a row-major 4x4)");
        for (size_t i = 0; i < 16; ++i) pose->m[i] = (*m)[i];
    }
    for (auto [name, target] :
         {std::pair{"min-range", &min_range}, std::pair{"max-range", &max_range}}) {
        if (auto text = a.value(name)) {
            auto v = parse_number(*text);
            if (!v || *v < 0 || !(std::abs(*v) <= 3.4e38))
                return ctx.usage_error("--" + std::string(name) + ": \"" + *text +
                                       "\" is not a number >= 0");
            *target = static_cast<float>(*v);
        }
    }
    return std::nullopt;
}

/// Fills a pinhole request from the command line, or returns the usage error's exit code.
std::optional<int> pinhole_request(Context& ctx, proto::ScanRequest& request) {
    const ParsedArgs& a = ctx.args;
    for (const char* lidar_only :
         {"channels", "vertical-fov", "elevations", "azimuth-steps", "returns"})
        if (a.has(lidar_only))
            return ctx.usage_error("--" + std::string(lidar_only) + " applies to --lidar only");
    PinholeSpec& spec = request.pinhole;
    std::pair<uint32_t, uint32_t> size{640, 480};
    const bool sized = a.has("size");
    if (auto text = a.value("size")) {
        auto wh = parse_size(*text);
        if (!wh) return ctx.usage_error("--size: " + wh.error());
        size = *wh;
    }
    const bool look_at = a.has("eye") || a.has("look-at") || a.has("up") || a.has("fov");
    if (look_at) {
        if (a.has("intrinsics") || a.has("pose"))
            return ctx.usage_error(
                "give either --eye/--look-at (a look-at camera) or --intrinsics and --pose");
        if (!a.has("eye") || !a.has("look-at"))
            return ctx.usage_error("a look-at camera needs both --eye and --look-at");
        request.look_at = true;
        for (auto [name, target] :
             {std::pair{"eye", &request.camera.eye}, std::pair{"look-at", &request.camera.look_at},
              std::pair{"up", &request.camera.up}}) {
            if (auto text = a.value(name)) {
                auto v = parse_vec3(*text);
                if (!v) return ctx.usage_error("--" + std::string(name) + ": " + v.error());
                *target = *v;
            }
        }
        if (auto text = a.value("fov")) {
            auto deg = parse_number(*text);
            if (!deg || *deg <= 0 || *deg >= 180)
                return ctx.usage_error("--fov: \"" + *text +
                                       "\" is not a number of degrees in (0, 180)");
            request.camera.fov_deg = static_cast<float>(*deg);
        }
        request.camera_width = size.first;
        request.camera_height = size.second;
    } else {
        const auto text = a.value("intrinsics");
        if (!text)
            return ctx.usage_error(
                "a pinhole needs --intrinsics FX,FY,CX,CY with --size and --pose, or --eye and "
                "--look-at");
        auto k = parse_numbers(*text);
        if (!k || k->size() != 4)
            return ctx.usage_error("--intrinsics: \"" + *text +
                                   "\" is not four numbers fx,fy,cx,cy");
        if (!sized) return ctx.usage_error("--intrinsics needs --size WxH");
        if (!a.has("pose")) return ctx.usage_error("--intrinsics needs --pose");
        spec.intrinsics = {(*k)[0], (*k)[1], (*k)[2], (*k)[3], size.first, size.second};
    }
    spec.kind = a.has("range") ? DepthKind::kRange : DepthKind::kDepth;
    spec.normals = a.has("normals");
    return common_options(ctx, &spec.pose, spec.min_range, spec.max_range);
}

/// Fills a lidar request from the command line, or returns the usage error's exit code.
std::optional<int> lidar_request(Context& ctx, proto::ScanRequest& request) {
    const ParsedArgs& a = ctx.args;
    for (const char* pinhole_only :
         {"intrinsics", "size", "eye", "look-at", "up", "fov", "range", "normals"})
        if (a.has(pinhole_only))
            return ctx.usage_error("--" + std::string(pinhole_only) + " applies to --pinhole only");
    request.lidar = true;
    LidarSpec& spec = request.lidar_spec;
    if (auto text = a.value("elevations")) {
        if (a.has("channels") || a.has("vertical-fov"))
            return ctx.usage_error("give either --elevations or --channels with --vertical-fov");
        auto e = parse_numbers(*text);
        if (!e) return ctx.usage_error("--elevations: \"" + *text + "\" is not numbers e1,e2,...");
        spec.elevation_deg = *e;
    } else {
        const auto channels = a.value("channels");
        const auto fov = a.value("vertical-fov");
        if (!channels || !fov)
            return ctx.usage_error(
                "a lidar needs --channels N with --vertical-fov LO,HI, or --elevations");
        auto n = parse_uint(*channels, 1, UINT32_MAX);
        if (!n) return ctx.usage_error("--channels: " + n.error());
        auto lohi = parse_numbers(*fov);
        if (!lohi || lohi->size() != 2)
            return ctx.usage_error("--vertical-fov: \"" + *fov + "\" is not two numbers lo,hi");
        request.vertical_fov = true;
        request.channels = static_cast<uint32_t>(*n);
        request.fov_lower = (*lohi)[0];
        request.fov_upper = (*lohi)[1];
    }
    const auto steps = a.value("azimuth-steps");
    if (!steps) return ctx.usage_error("a lidar needs --azimuth-steps N");
    auto n = parse_uint(*steps, 1, UINT32_MAX);
    if (!n) return ctx.usage_error("--azimuth-steps: " + n.error());
    spec.azimuth_steps = static_cast<uint32_t>(*n);
    if (auto text = a.value("returns")) {
        auto r = parse_uint(*text, 1, UINT32_MAX);
        if (!r) return ctx.usage_error("--returns: " + r.error());
        spec.returns = static_cast<uint32_t>(*r);
    }
    return common_options(ctx, &spec.pose, spec.min_range, spec.max_range);
}

}  // namespace

std::optional<int> scan_request_from_args(Context& ctx, proto::ScanRequest& request) {
    const bool pinhole = ctx.args.has("pinhole"), lidar = ctx.args.has("lidar");
    if (pinhole == lidar) return ctx.usage_error("give exactly one of --pinhole and --lidar");
    return pinhole ? pinhole_request(ctx, request) : lidar_request(ctx, request);
}

proto::Result<ScanFile, int> scan_file_format(Context& ctx, const std::string& output,
                                              bool pinhole) {
    const std::string format_path = ctx.format_path(output);
    if (!pinhole && ends_with(format_path, ".kdrb")) return ScanFile::kRanges;
    const bool binary = ends_with(format_path, pinhole ? ".kdrz" : ".kdrl");
    if (!binary && !ends_with(format_path, pinhole ? ".exr" : ".ply"))
        return proto::Err{ctx.usage_error(
            (ctx.args.has("format")
                 ? "--format: \"" + *ctx.args.value("format") + "\" is not "
                 : "cannot tell the format of \"" + output + "\" from its extension (") +
            (pinhole ? "a pinhole scan is .exr or .kdrz" : "a lidar scan is .ply, .kdrl or .kdrb") +
            ")")};
    // An EXR is encoded here: its encoder must load before the scan starts.
    if (pinhole && !binary)
        if (auto failed = ctx.need_image_module()) return proto::Err{*failed};
    return binary ? ScanFile::kBinary : ScanFile::kUser;
}

proto::Result<std::vector<std::byte>, int> encode_scan_file(
    Context& ctx, const DepthImage* depth, const PointCloud* cloud,
    std::span<const uint32_t> geometry_ids) {
    if (cloud != nullptr) return proto::encode_point_cloud_ply(*cloud, geometry_ids);
    auto exr = (*proto::image_module())->encode_depth_exr(*depth, geometry_ids);
    if (!exr)
        return proto::Err{
            ctx.fail(make_client_error(ErrorKind::kInput, "cannot encode the EXR", exr.error()))};
    return std::move(*exr);
}

namespace {

int run_scan(Context& ctx) {
    int code = kExitOk;
    if (!positional_count_ok(ctx, 1, 1, "ID (the mesh to scan)", code)) return code;
    const bool pinhole = ctx.args.has("pinhole"), lidar = ctx.args.has("lidar");
    if (pinhole == lidar) return ctx.usage_error("give exactly one of --pinhole and --lidar");
    const auto output = ctx.args.value("output");
    if (!output) return ctx.usage_error("missing -o FILE (the scan to write)");
    const auto file = scan_file_format(ctx, *output, pinhole);
    if (!file) return file.error();
    const bool binary = *file == ScanFile::kBinary;
    proto::ScanRequest request;
    if (auto failed = scan_request_from_args(ctx, request)) return *failed;
    ctx.connect(ctx.client_options());
    auto id = ctx.resolve_mesh_id(ctx.args.positional[0]);
    if (!id) return id.error();

    const auto start = std::chrono::steady_clock::now();
    std::vector<std::byte> bytes;
    std::string summary;
    uint64_t hits = 0, points = 0;
    // The answer is KDRZ / KDRL, decoded (checked) by the client library; EXR and PLY are
    // encoded here with proto, as the server would.
    if (pinhole) {
        auto image = ctx.client->scan_pinhole(*id, request);
        if (!image) return ctx.fail(image.error());
        for (const uint32_t p : image->prim) hits += p != kNoHit;
        summary = std::to_string(image->width) + "x" + std::to_string(image->height) + " " +
                  (image->kind == DepthKind::kRange ? "range" : "depth") + ", " +
                  std::to_string(hits) + " pixels hit";
        if (binary) {
            bytes = proto::encode_depth_image(*image);
        } else {
            auto exr = encode_scan_file(ctx, &*image, nullptr);
            if (!exr) return exr.error();
            bytes = std::move(*exr);
        }
    } else if (*file == ScanFile::kRanges) {
        // The compact answer as it came, checked by its decoder.
        request.format = proto::ScanFormat::kRanges;
        auto answer = ctx.client->scan(*id, request);
        if (!answer) return ctx.fail(answer.error());
        auto ranges = proto::decode_lidar_ranges(*answer, std::numeric_limits<uint32_t>::max());
        if (!ranges)
            return ctx.fail(
                make_client_error(ErrorKind::kProtocol, "bad response",
                                  "the KDRB scan answer: " + ranges.error().to_string()));
        points = ranges->points.size();
        summary = std::to_string(points) + " points from " + std::to_string(ranges->channels) +
                  " x " + std::to_string(ranges->azimuth_steps) + " beams";
        bytes = std::move(*answer);
    } else {
        auto cloud = ctx.client->scan_lidar(*id, request);
        if (!cloud) return ctx.fail(cloud.error());
        points = cloud->points.size();
        summary = std::to_string(cloud->points.size()) + " points from " +
                  std::to_string(cloud->channels) + " x " + std::to_string(cloud->azimuth_steps) +
                  " beams";
        if (binary) {
            bytes = proto::encode_point_cloud(*cloud);
        } else {
            auto ply = encode_scan_file(ctx, nullptr, &*cloud);
            if (!ply) return ply.error();
            bytes = std::move(*ply);
        }
    }
    const double seconds =
        std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
    if (auto failed = ctx.write_output(*output, bytes, "the scan")) return *failed;
    const proto::JsonField fields[] = {{"command", std::string_view("scan")},
                                       {"mesh", std::string_view(*id)},
                                       {"sensor", std::string_view(pinhole ? "pinhole" : "lidar")},
                                       {"out", std::string_view(*output)},
                                       {"bytes", uint64_t{bytes.size()}},
                                       {"hits", hits},
                                       {"points", points},
                                       {"seconds", seconds}};
    ctx.report(*output,
               "wrote " + *output + " (" + std::to_string(bytes.size()) + " bytes, " + summary +
                   ", " + fixed(seconds, 3) + " s)",
               proto::encode_flat_object(fields));
    return kExitOk;
}

}  // namespace

const Command kScanCommand{
    .name = "scan",
    .synopsis = "scan ID --pinhole|--lidar",
    .summary = "scan a mesh with a depth camera or lidar; write EXR / PLY",
    .help = kScanHelp,
    .options = kScanOptions,
    .run = run_scan,
};

}  // namespace kdrt::cli
