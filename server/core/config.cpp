#include "core/config.h"

#include <algorithm>
#include <cctype>
#include <charconv>
#include <cstdio>
#include <filesystem>
#include <limits>
#include <optional>

#include "kdrt/mesh.h"
#include "kdrt/proto/config_json.h"
#include "kdrt/proto/file_io.h"
#include "kdrt/proto/image_format.h"
#include "kdrt/proto/json_api.h"
#include "kdrt/proto/raw_image.h"
#include "kdrt/proto/ray_batch.h"
#include "kdrt/proto/text.h"
#include "kdrt/query.h"
#include "kdrt/render.h"
#include "kdrt/scene.h"

namespace kdrt::server {
namespace {

using proto::Err;
using proto::in_quotes;
using proto::Result;

// Ranges of the settings the server alone enforces. The others take the limit of the layer that
// enforces it (the engine's kMax* constants, proto's decode limits), so a configured value is
// never one that layer then refuses on every request.
constexpr uint64_t kMaxThreadCount = 4096;     ///< http_threads, threads
constexpr uint64_t kMaxTimeoutSeconds = 3600;  ///< keep-alive, socket and shutdown timeouts
constexpr uint64_t kMaxQueued = 100000;        ///< max_inflight, max_jobs
constexpr uint64_t kMaxRequestsPerConnection = 1000000;
constexpr uint64_t kMaxJobTtlSeconds = 7 * 86400;  ///< one week
constexpr uint64_t kMinJsonBodyBytes = 1024;       ///< room for the smallest useful request
constexpr uint64_t kMinRequestHeadBytes = 1024;    ///< a request line and a few headers
constexpr uint64_t kMaxRequestHeadBytes = 1ull << 20;
constexpr uint64_t kMaxRequestHeaders = 10000;
constexpr uint64_t kMaxPrebufferBytes = 64ull << 20;
constexpr uint64_t kMaxConnections = 1000000;
constexpr uint64_t kMaxTokensFileBytes = 1ull << 20;

/// One setting: its key, where it lives in ServerConfig, its range and its help line.
struct Setting {
    std::string_view key;
    std::string_view help;
    std::string ServerConfig::*text = nullptr;
    unsigned ServerConfig::*u32 = nullptr;
    uint64_t ServerConfig::*u64 = nullptr;
    std::vector<std::string> ServerConfig::*list = nullptr;
    bool bytes = false;  ///< u64 accepts K/M/G/T suffixes
    uint64_t min = 0;
    uint64_t max = std::numeric_limits<uint64_t>::max();
    std::vector<std::string_view> choices = {};
};

const std::vector<Setting>& settings() {
    static const std::vector<Setting> table = {
        {.key = "listen",
         .help = "HOST:PORT to listen on (port 0: any free port)",
         .text = &ServerConfig::listen},
        {.key = "port_file",
         .help = "write the bound port to this file once listening",
         .text = &ServerConfig::port_file},
        {.key = "http_threads",
         .help = "threads serving HTTP requests (idle and slow connections hold none)",
         .u32 = &ServerConfig::http_threads,
         .min = 1,
         .max = kMaxThreadCount},
        {.key = "keep_alive_timeout_s",
         .help = "seconds an idle keep-alive connection is kept",
         .u32 = &ServerConfig::keep_alive_timeout_s,
         .min = 1,
         .max = kMaxTimeoutSeconds},
        {.key = "keep_alive_max_requests",
         .help = "requests served on one connection before it is closed",
         .u32 = &ServerConfig::keep_alive_max_requests,
         .min = 1,
         .max = kMaxRequestsPerConnection},
        {.key = "read_timeout_s",
         .help = "socket read timeout in seconds",
         .u32 = &ServerConfig::read_timeout_s,
         .min = 1,
         .max = kMaxTimeoutSeconds},
        {.key = "write_timeout_s",
         .help = "socket write timeout in seconds",
         .u32 = &ServerConfig::write_timeout_s,
         .min = 1,
         .max = kMaxTimeoutSeconds},
        {.key = "request_head_timeout_s",
         .help = "seconds to receive a whole request head (line and headers), else 408",
         .u32 = &ServerConfig::request_head_timeout_s,
         .min = 1,
         .max = kMaxTimeoutSeconds},
        {.key = "request_timeout_s",
         .help = "seconds to receive a whole request, head and body, else 408",
         .u32 = &ServerConfig::request_timeout_s,
         .min = 1,
         .max = kMaxTimeoutSeconds},
        {.key = "max_request_head_bytes",
         .help = "largest request head (request line and headers), else 431",
         .u64 = &ServerConfig::max_request_head_bytes,
         .bytes = true,
         .min = kMinRequestHeadBytes,
         .max = kMaxRequestHeadBytes},
        {.key = "max_request_headers",
         .help = "most header lines in a request, else 431",
         .u32 = &ServerConfig::max_request_headers,
         .min = 1,
         .max = kMaxRequestHeaders},
        {.key = "request_prebuffer_bytes",
         .help = "body bytes received before a request is given a thread (0: none)",
         .u64 = &ServerConfig::request_prebuffer_bytes,
         .bytes = true,
         .max = kMaxPrebufferBytes},
        {.key = "max_connections",
         .help = "open client connections; further ones get 503 and are closed",
         .u32 = &ServerConfig::max_connections,
         .min = 1,
         .max = kMaxConnections},
        {.key = "token",
         .help = "bearer token required on /v1 requests (empty: no authentication); as a "
                 "flag it is visible to every user in /proc/PID/cmdline: prefer KDRT_TOKEN or "
                 "--token-file",
         .text = &ServerConfig::token},
        {.key = "token_file",
         .help = "file holding the bearer token (one line; instead of token)",
         .text = &ServerConfig::token_file},
        {.key = "tokens_file",
         .help = "file of further bearer tokens with their roles, one 'ROLES TOKEN' line each "
                 "(ROLES: read, write or read,write; write = upload and delete meshes)",
         .text = &ServerConfig::tokens_file},
        {.key = "threads",
         .help = "tracing and build threads (0: all cores)",
         .u32 = &ServerConfig::threads,
         .max = kMaxThreadCount},
        {.key = "cache_dir",
         .help = "directory of the stored meshes and trees",
         .text = &ServerConfig::cache_dir},
        {.key = "replica",
         .help = "name of this replica behind a proxy: prefixes job ids, X-Kdrt-Replica header",
         .text = &ServerConfig::replica},
        {.key = "memory_budget",
         .help = "bytes of kD-trees (and their distance surface indexes and scan clearances) "
                 "kept in memory; least recently used are evicted",
         .u64 = &ServerConfig::memory_budget,
         .bytes = true},
        {.key = "preload",
         .help = "mesh files to upload at start-up",
         .list = &ServerConfig::preload},
        {.key = "buffer_pool_bytes",
         .help = "idle ray-batch buffers kept for reuse (saves page faults)",
         .u64 = &ServerConfig::buffer_pool_bytes,
         .bytes = true},
        {.key = "max_upload_bytes",
         .help = "largest mesh upload body",
         .u64 = &ServerConfig::max_upload_bytes,
         .bytes = true,
         .min = 1},
        {.key = "upload_memory_bytes",
         .help = "uploads larger than this are spooled to a temp file",
         .u64 = &ServerConfig::upload_memory_bytes,
         .bytes = true},
        {.key = "max_triangles",
         .help = "most triangles in one mesh",
         .u64 = &ServerConfig::max_triangles,
         .min = 1,
         .max = kMaxTriangles},
        {.key = "max_rays",
         .help = "most rays in one KDRR batch",
         .u32 = &ServerConfig::max_rays,
         .min = 1,
         .max = proto::DecodeLimits{}.max_rays},
        {.key = "max_hits_per_ray",
         .help = "most hits kept per ray by intersect_all (its max_hits parameter)",
         .u32 = &ServerConfig::max_hits_per_ray,
         .min = 1,
         .max = kMaxHitsPerRay},
        {.key = "max_distance_points",
         .help = "most query points in one distance request (KDRP batch)",
         .u32 = &ServerConfig::max_distance_points,
         .min = 1,
         .max = proto::DecodeLimits{}.max_rays},
        {.key = "max_distance_work",
         .help = "most work of one distance request (cells visited + triangles tested), "
                 "stopped with 400 beyond it",
         .u64 = &ServerConfig::max_distance_work,
         .min = 1},
        {.key = "max_sensor_beams",
         .help = "most beams (channels x azimuth_steps) in one lidar scan",
         .u32 = &ServerConfig::max_sensor_beams,
         .min = 1,
         .max = 1u << 26},
        {.key = "max_scan_points",
         .help = "most pixels of a pinhole scan, or beams x returns of a lidar scan",
         .u32 = &ServerConfig::max_scan_points,
         .min = 1,
         .max = 1u << 28},
        {.key = "max_instances",
         .help = "most instances in one scene, and most poses in one pose update",
         .u32 = &ServerConfig::max_instances,
         .min = 1,
         .max = kMaxSceneInstances},
        {.key = "max_scenes",
         .help = "most scenes in the store (POST /v1/scenes beyond it: 413)",
         .u32 = &ServerConfig::max_scenes,
         .min = 1,
         .max = 1u << 24},
        {.key = "scene_revisions_kept",
         .help = "newest revisions of each scene kept on disk for queries that pin a revision",
         .u32 = &ServerConfig::scene_revisions_kept,
         .min = 1,
         .max = 1024},
        {.key = "scene_sync",
         .help = "commit: a scene revision is flushed to disk before it is acknowledged (it "
                 "survives a power loss); none: written but not flushed (it survives the server "
                 "being killed; a power loss may drop the newest revisions, the store stays valid)",
         .text = &ServerConfig::scene_sync,
         .choices = {"commit", "none"}},
        {.key = "scene_memory_budget",
         .help = "bytes of built scenes (top levels and instance data, not their meshes' trees) "
                 "kept in memory; least recently used are dropped and rebuilt when needed",
         .u64 = &ServerConfig::scene_memory_budget,
         .bytes = true},
        {.key = "max_json_rays",
         .help = "most rays in one JSON batch",
         .u32 = &ServerConfig::max_json_rays,
         .min = 1,
         .max = proto::kMaxJsonRays},
        {.key = "max_json_bytes",
         .help = "largest JSON request body",
         .u64 = &ServerConfig::max_json_bytes,
         .bytes = true,
         .min = kMinJsonBodyBytes},
        {.key = "max_inflight",
         .help = "uploads, traces and renders in flight before 503",
         .u32 = &ServerConfig::max_inflight,
         .min = 1,
         .max = kMaxQueued},
        {.key = "max_image_width",
         .help = "widest render",
         .u32 = &ServerConfig::max_image_width,
         .min = 1,
         .max = kMaxImageSize},
        {.key = "max_image_height",
         .help = "tallest render",
         .u32 = &ServerConfig::max_image_height,
         .min = 1,
         .max = kMaxImageSize},
        {.key = "max_spp",
         .help = "most samples per pixel",
         .u32 = &ServerConfig::max_spp,
         .min = 1,
         .max = kMaxSamplesPerPixel},
        {.key = "png_compression",
         .help =
             "zlib level 0-9 of rendered PNGs when the request has no \"compression\" (1: fast)",
         .u32 = &ServerConfig::png_compression,
         .min = 0,
         .max = proto::kMaxPngCompression},
        {.key = "max_jobs",
         .help = "async render jobs queued or running before 503",
         .u32 = &ServerConfig::max_jobs,
         .min = 1,
         .max = kMaxQueued},
        {.key = "job_ttl_s",
         .help = "seconds a finished job and its image are kept",
         .u32 = &ServerConfig::job_ttl_s,
         .min = 1,
         .max = kMaxJobTtlSeconds},
        {.key = "job_result_bytes",
         .help = "bytes of finished async jobs' images kept; the oldest are forgotten beyond",
         .u64 = &ServerConfig::job_result_bytes,
         .bytes = true,
         .min = 1},
        {.key = "batch_memory_budget",
         .help = "bytes of ray batches in flight (their rays and answers); 503 beyond",
         .u64 = &ServerConfig::batch_memory_budget,
         .bytes = true,
         .min = 1},
        {.key = "max_render_rays",
         .help = "largest render: pixels x samples x rays per sample, refused before it starts",
         .u64 = &ServerConfig::max_render_rays,
         .min = 1},
        {.key = "max_raw_render_bytes",
         .help = "largest answer of a \"format\": \"raw\" render (32 + 12 bytes a pixel), "
                 "refused before it starts",
         .u64 = &ServerConfig::max_raw_render_bytes,
         .bytes = true,
         .min = proto::kRawImageHeaderBytes + 12},
        {.key = "max_renders",
         .help = "synchronous renders running at once (more wait in the queue, then 503)",
         .u32 = &ServerConfig::max_renders,
         .min = 1,
         .max = kMaxQueued},
        {.key = "max_builds",
         .help = "mesh uploads parsed and built at once (more wait in the queue, then 503)",
         .u32 = &ServerConfig::max_builds,
         .min = 1,
         .max = kMaxQueued},
        {.key = "max_queued",
         .help = "requests that wait for a render or a build slot; more get 503 at once",
         .u32 = &ServerConfig::max_queued,
         .max = kMaxQueued},
        {.key = "shutdown_timeout_s",
         .help = "seconds in-flight requests get to finish on SIGTERM/SIGINT",
         .u32 = &ServerConfig::shutdown_timeout_s,
         .min = 1,
         .max = kMaxTimeoutSeconds},
        {.key = "log_level",
         .help = "trace, debug, info, warn, error, critical or off",
         .text = &ServerConfig::log_level,
         .choices = {"trace", "debug", "info", "warn", "error", "critical", "off"}},
        {.key = "log_format",
         .help = "text or json (one JSON object per line)",
         .text = &ServerConfig::log_format,
         .choices = {"text", "json"}},
        {.key = "web_viewer",
         .help = "on: serve the web viewer at / (server/web); off: / and /ui/ answer 404",
         .text = &ServerConfig::web_viewer,
         .choices = {"on", "off"}},
    };
    return table;
}

std::string flag_name(std::string_view key) {
    std::string flag = "--";
    for (const char c : key) flag.push_back(c == '_' ? '-' : c);
    return flag;
}

std::string env_name(std::string_view key) {
    std::string env = "KDRT_";
    for (const char c : key)
        env.push_back(static_cast<char>(std::toupper(static_cast<unsigned char>(c))));
    return env;
}

const Setting* find_setting(std::string_view key) {
    for (const Setting& s : settings())
        if (s.key == key) return &s;
    return nullptr;
}

Result<uint64_t, std::string> parse_unsigned(std::string_view text) {
    uint64_t value = 0;
    const auto [ptr, ec] = std::from_chars(text.data(), text.data() + text.size(), value);
    if (text.empty() || ec != std::errc() || ptr != text.data() + text.size())
        return Err{in_quotes(text) + " is not a non-negative integer"};
    return value;
}

/// Applies a textual value (flag, environment, or a config string/number) to `config`.
Result<void, std::string> apply(const Setting& s, std::string_view text, ServerConfig& config) {
    if (s.text) {
        if (!s.choices.empty() &&
            std::find(s.choices.begin(), s.choices.end(), text) == s.choices.end()) {
            std::string allowed;
            for (const auto c : s.choices)
                allowed += (allowed.empty() ? "" : ", ") + std::string(c);
            return Err{in_quotes(text) + " is not one of " + allowed};
        }
        if (s.key == "listen") {
            auto split = split_listen(text);
            if (!split) return Err{std::move(split).error()};
        }
        config.*s.text = std::string(text);
        return {};
    }
    if (s.list) {
        // Environment form: colon-separated, like PATH.
        std::vector<std::string> items;
        size_t start = 0;
        while (start <= text.size()) {
            const size_t colon = text.find(':', start);
            const std::string_view item =
                text.substr(start, colon == std::string_view::npos ? colon : colon - start);
            if (!item.empty()) items.emplace_back(item);
            if (colon == std::string_view::npos) break;
            start = colon + 1;
        }
        config.*s.list = std::move(items);
        return {};
    }
    auto value = s.bytes ? parse_bytes(text) : parse_unsigned(text);
    if (!value) return Err{std::move(value).error()};
    if (*value < s.min || *value > s.max)
        return Err{in_quotes(text) + " is outside " + std::to_string(s.min) + ".." +
                   std::to_string(s.max)};
    if (s.u32)
        config.*s.u32 = static_cast<unsigned>(*value);
    else
        config.*s.u64 = *value;
    return {};
}

Result<void, std::string> apply_config_file(const std::string& path, ServerConfig& config) {
    auto bytes = proto::read_file_bytes(path, 1u << 20);
    if (!bytes) return Err{std::move(bytes).error()};
    const std::string_view text(reinterpret_cast<const char*>(bytes->data()), bytes->size());
    return apply_config_text(text, path, config);
}

}  // namespace

Result<void, std::string> apply_config_text(std::string_view text, const std::string& path,
                                            ServerConfig& config) {
    auto entries = proto::parse_config_object(text);
    if (!entries) return Err{path + ": " + entries.error()};
    for (const proto::ConfigEntry& e : *entries) {
        const Setting* s = find_setting(e.key);
        if (!s)
            return Err{path + ": unknown setting " + in_quotes(e.key) +
                       " (kdrt-server --help lists them)"};
        Result<void, std::string> applied;
        if (const auto* list = std::get_if<std::vector<std::string>>(&e.value)) {
            if (!s->list)
                return Err{path + ": " + in_quotes(e.key) + " takes a single value, not a list"};
            config.*s->list = *list;
        } else if (const auto* str = std::get_if<std::string>(&e.value)) {
            if (s->list)
                config.*s->list = {*str};
            else
                applied = apply(*s, *str, config);
        } else if (const auto* integer = std::get_if<int64_t>(&e.value)) {
            if (s->text || s->list)
                return Err{path + ": " + in_quotes(e.key) + " must be a string"};
            if (*integer < 0) return Err{path + ": " + in_quotes(e.key) + " must not be negative"};
            applied = apply(*s, std::to_string(*integer), config);
        } else {
            return Err{path + ": " + in_quotes(e.key) + " must be " +
                       (s->text   ? "a string"
                        : s->list ? "a list of strings"
                                  : "a non-negative integer")};
        }
        if (!applied) return Err{path + ": " + in_quotes(e.key) + ": " + applied.error()};
    }
    config.config_file = path;
    return {};
}

std::string default_json(const Setting& s) {
    const ServerConfig defaults;
    if (s.text) return proto::json_string(defaults.*s.text);
    if (s.u32) return std::to_string(defaults.*s.u32);
    if (s.u64) return std::to_string(defaults.*s.u64);
    std::string out = "[";
    for (const std::string& item : defaults.*s.list)
        out += (out.size() > 1 ? ", " : "") + proto::json_string(item);
    return out + "]";
}

Result<std::pair<std::string, int>, std::string> split_listen(std::string_view listen) {
    const size_t colon = listen.rfind(':');
    if (colon == std::string_view::npos || colon == 0)
        return Err{in_quotes(listen) + " is not HOST:PORT (e.g. 127.0.0.1:8080)"};
    std::string_view host = listen.substr(0, colon);
    if (host.size() >= 2 && host.front() == '[' && host.back() == ']')
        host = host.substr(1, host.size() - 2);
    auto port = parse_unsigned(listen.substr(colon + 1));
    if (!port || *port > 65535)
        return Err{in_quotes(listen) + " has no port number 0..65535 after the last ':'"};
    return std::pair{std::string(host), static_cast<int>(*port)};
}

Result<uint64_t, std::string> parse_bytes(std::string_view text) {
    uint64_t scale = 1;
    std::string_view digits = text;
    if (!digits.empty()) {
        switch (std::toupper(static_cast<unsigned char>(digits.back()))) {
            case 'K':
                scale = 1ull << 10;
                break;
            case 'M':
                scale = 1ull << 20;
                break;
            case 'G':
                scale = 1ull << 30;
                break;
            case 'T':
                scale = 1ull << 40;
                break;
            default:
                break;
        }
        if (scale != 1) digits.remove_suffix(1);
    }
    auto value = parse_unsigned(digits);
    if (!value)
        return Err{in_quotes(text) +
                   " is not a byte count (digits with an optional K, M, G or T suffix)"};
    if (*value > std::numeric_limits<uint64_t>::max() / scale)
        return Err{in_quotes(text) + " is too large"};
    return *value * scale;
}

Result<Invocation, std::string> parse_invocation(const std::vector<std::string>& args,
                                                 const std::vector<std::string>& env) {
    Invocation inv;
    // --help and --version work whatever the config file, environment or other flags say.
    for (const std::string& arg : args) {
        if (arg == "--mesh-id") break;  // file names follow
        if (arg == "--help" || arg == "-h" || arg == "--version") {
            inv.mode = arg == "--version" ? Invocation::Mode::kVersion : Invocation::Mode::kHelp;
            return inv;
        }
    }
    // The config file comes first (flag, then environment), whatever its position on the line.
    std::string config_path;
    for (const std::string& e : env)
        if (e.rfind("KDRT_CONFIG=", 0) == 0) config_path = e.substr(12);
    for (size_t i = 0; i < args.size(); ++i) {
        if (args[i] == "--config") {
            if (i + 1 >= args.size()) return Err{std::string("--config needs a file name")};
            config_path = args[i + 1];
        } else if (args[i].rfind("--config=", 0) == 0) {
            config_path = args[i].substr(9);
        }
    }
    if (!config_path.empty()) {
        auto applied = apply_config_file(config_path, inv.config);
        if (!applied) return Err{std::move(applied).error()};
    }
    for (const Setting& s : settings()) {
        const std::string prefix = env_name(s.key) + "=";
        for (const std::string& e : env) {
            if (e.rfind(prefix, 0) != 0) continue;
            auto applied = apply(s, std::string_view(e).substr(prefix.size()), inv.config);
            if (!applied) return Err{env_name(s.key) + ": " + applied.error()};
        }
    }
    for (size_t i = 0; i < args.size(); ++i) {
        std::string arg = args[i];
        if (arg == "--help" || arg == "-h") {
            inv.mode = Invocation::Mode::kHelp;
            return inv;
        }
        if (arg == "--version") {
            inv.mode = Invocation::Mode::kVersion;
            return inv;
        }
        if (arg == "--mesh-id") {
            inv.mode = Invocation::Mode::kMeshId;
            inv.mesh_files.assign(args.begin() + static_cast<std::ptrdiff_t>(i) + 1, args.end());
            if (inv.mesh_files.empty())
                return Err{std::string("--mesh-id needs at least one mesh file")};
            return inv;
        }
        if (arg == "--check-store") {
            inv.mode = Invocation::Mode::kCheckStore;  // with the other flags (--cache-dir)
            continue;
        }
        std::optional<std::string> inline_value;
        if (const size_t eq = arg.find('='); arg.rfind("--", 0) == 0 && eq != std::string::npos) {
            inline_value = arg.substr(eq + 1);
            arg.resize(eq);
        }
        if (arg == "--config") {
            if (!inline_value) ++i;
            continue;
        }
        const Setting* found = nullptr;
        for (const Setting& s : settings())
            if (flag_name(s.key) == arg) found = &s;
        if (!found)
            return Err{"unknown argument " + in_quotes(arg) +
                       " (kdrt-server --help lists the flags)"};
        if (found->list) {
            // --preload A B C: every following argument up to the next flag.
            std::vector<std::string> items;
            if (inline_value) items.push_back(*inline_value);
            while (i + 1 < args.size() && args[i + 1].rfind("--", 0) != 0)
                items.push_back(args[++i]);
            if (items.empty()) return Err{arg + " needs at least one value"};
            inv.config.*found->list = std::move(items);
            continue;
        }
        if (!inline_value) {
            if (i + 1 >= args.size()) return Err{arg + " needs a value"};
            inline_value = args[++i];
        }
        auto applied = apply(*found, *inline_value, inv.config);
        if (!applied) return Err{arg + ": " + applied.error()};
    }
    if (inv.config.replica.size() > 64)
        return Err{"replica: " + in_quotes(inv.config.replica) + " is longer than 64 characters"};
    for (const char c : inv.config.replica)
        if (!std::isalnum(static_cast<unsigned char>(c)) && c != '-' && c != '_')
            return Err{"replica: " + in_quotes(inv.config.replica) +
                       " may hold only letters, digits, '-' and '_'"};
    if (!inv.config.token_file.empty()) {
        if (!inv.config.token.empty())
            return Err{std::string("token and token_file are both set; give the token one way")};
        auto bytes = proto::read_file_bytes(inv.config.token_file, 4096);
        if (!bytes) return Err{"token_file: " + bytes.error()};
        std::string token(reinterpret_cast<const char*>(bytes->data()), bytes->size());
        while (!token.empty() && (token.back() == '\n' || token.back() == '\r')) token.pop_back();
        if (token.empty())
            return Err{"token_file " + in_quotes(inv.config.token_file) + " is empty"};
        for (const char c : token)
            if (static_cast<unsigned char>(c) <= ' ' || c == 0x7f)
                return Err{"token_file " + in_quotes(inv.config.token_file) +
                           " holds more than one line, spaces or control characters"};
        inv.config.token = std::move(token);
        if (auto w = secret_file_warning("token_file", inv.config.token_file))
            inv.warnings.push_back(std::move(*w));
    }
    if (!inv.config.tokens_file.empty()) {
        auto bytes = proto::read_file_bytes(inv.config.tokens_file, kMaxTokensFileBytes);
        if (!bytes) return Err{"tokens_file: " + bytes.error()};
        auto tokens = parse_tokens_text(
            std::string_view(reinterpret_cast<const char*>(bytes->data()), bytes->size()),
            "tokens_file " + in_quotes(inv.config.tokens_file));
        if (!tokens) return Err{std::move(tokens).error()};
        for (const ApiToken& t : *tokens)
            if (t.token == inv.config.token)
                return Err{"tokens_file " + in_quotes(inv.config.tokens_file) +
                           " repeats the token of token/token_file"};
        inv.config.role_tokens = std::move(*tokens);
        if (auto w = secret_file_warning("tokens_file", inv.config.tokens_file))
            inv.warnings.push_back(std::move(*w));
    }
    return inv;
}

std::string role_names(unsigned roles) {
    std::string out;
    if (roles & kRoleRead) out = "read";
    if (roles & kRoleWrite) out += out.empty() ? "write" : ",write";
    return out;
}

Result<std::vector<ApiToken>, std::string> parse_tokens_text(std::string_view text,
                                                             const std::string& origin) {
    std::vector<ApiToken> tokens;
    size_t line_number = 0;
    while (!text.empty()) {
        ++line_number;
        const size_t end = std::min(text.find('\n'), text.size());
        std::string_view line = text.substr(0, end);
        text.remove_prefix(std::min(end + 1, text.size()));
        if (!line.empty() && line.back() == '\r') line.remove_suffix(1);
        const auto where = [&] { return origin + " line " + std::to_string(line_number) + ": "; };
        const auto blank = [](char c) { return c == ' ' || c == '\t'; };
        while (!line.empty() && blank(line.front())) line.remove_prefix(1);
        while (!line.empty() && blank(line.back())) line.remove_suffix(1);
        if (line.empty() || line.front() == '#') continue;
        const size_t gap = std::min(line.find_first_of(" \t"), line.size());
        std::string_view roles = line.substr(0, gap);
        std::string_view token = line.substr(gap);
        while (!token.empty() && blank(token.front())) token.remove_prefix(1);
        if (token.empty())
            return Err{where() + "expected 'ROLES TOKEN' (ROLES: read, write or read,write)"};
        ApiToken entry{.token = std::string(token), .roles = 0};
        while (!roles.empty()) {
            const size_t comma = std::min(roles.find(','), roles.size());
            const std::string_view role = roles.substr(0, comma);
            roles.remove_prefix(std::min(comma + 1, roles.size()));
            if (role == "read")
                entry.roles |= kRoleRead;
            else if (role == "write")
                entry.roles |= kRoleWrite;
            else
                return Err{where() + "unknown role " + in_quotes(role) + " (read, write)"};
        }
        for (const char c : entry.token)
            if (static_cast<unsigned char>(c) <= ' ' || c == 0x7f)
                return Err{where() + "the token holds a space or a control character"};
        if (entry.token.size() < kMinTokenChars)
            return Err{where() + "the token has " + std::to_string(entry.token.size()) +
                       " characters; a token needs at least " + std::to_string(kMinTokenChars) +
                       " (a random one: head -c 24 /dev/urandom | base64)"};
        for (const ApiToken& other : tokens)
            if (other.token == entry.token)
                return Err{where() + "the token of an earlier line again"};
        tokens.push_back(std::move(entry));
    }
    if (tokens.empty()) return Err{origin + " holds no token"};
    return tokens;
}

std::optional<std::string> secret_file_warning(std::string_view setting, const std::string& path) {
    namespace fs = std::filesystem;
    std::error_code ec;
    const fs::perms perms = fs::status(path, ec).permissions();
    if (ec) return std::nullopt;
    constexpr fs::perms kRead = fs::perms::group_read | fs::perms::others_read;
    constexpr fs::perms kWrite = fs::perms::group_write | fs::perms::others_write;
    const bool read = (perms & kRead) != fs::perms::none;
    const bool write = (perms & kWrite) != fs::perms::none;
    if (!read && !write) return std::nullopt;
    char mode[8];
    std::snprintf(mode, sizeof mode, "%04o", static_cast<unsigned>(perms & fs::perms::mask));
    return std::string(setting) + " " + in_quotes(path) + " can be " +
           (read && write ? "read and written"
            : read        ? "read"
                          : "written") +
           " by users other than its owner (mode " + mode +
           "): it holds bearer tokens; chmod 600 it";
}

std::vector<ApiToken> accepted_tokens(const ServerConfig& config) {
    std::vector<ApiToken> tokens;
    if (!config.token.empty()) tokens.push_back({config.token, kRoleRead | kRoleWrite});
    tokens.insert(tokens.end(), config.role_tokens.begin(), config.role_tokens.end());
    return tokens;
}

std::string help_text() {
    std::string out =
        "usage: kdrt-server [--config FILE] [--SETTING VALUE ...]\n"
        "       kdrt-server --mesh-id MESHFILE...   print the mesh id of each file and exit\n"
        "       kdrt-server --check-store [--cache-dir DIR]   verify every stored mesh, tree\n"
        "                and summary (read-only; exit 0 intact, 1 damage found, 2 unreadable)\n"
        "       kdrt-server --help | --version\n\n"
        "The kdrt ray-tracing HTTP service (API: proto/openapi.yaml). Settings come from their\n"
        "defaults, then the JSON config file (--config FILE or KDRT_CONFIG; // comments allowed),\n"
        "then KDRT_* environment variables, then flags. Byte counts take K, M, G, T suffixes.\n\n"
        "  flag / environment variable                    default      meaning\n";
    for (const Setting& s : settings()) {
        std::string line = "  " + flag_name(s.key);
        if (s.list) line += " FILE...";
        line += " / " + env_name(s.key);
        line.resize(std::max<size_t>(line.size() + 1, 49), ' ');
        std::string def = default_json(s);
        line += def;
        line.resize(std::max<size_t>(line.size() + 1, 62), ' ');
        out += line + std::string(s.help) + "\n";
    }
    return out;
}

std::vector<std::string> setting_keys() {
    std::vector<std::string> keys;
    for (const Setting& s : settings()) keys.emplace_back(s.key);
    return keys;
}

std::string setting_default_json(std::string_view key) {
    const Setting* s = find_setting(key);
    return s ? default_json(*s) : std::string();
}

}  // namespace kdrt::server
