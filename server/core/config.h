#pragma once
/// kdrt-server settings: defaults (the member initialisers below), overridden by a JSON config
/// file (--config FILE or KDRT_CONFIG), then by KDRT_* environment variables, then by
/// command-line flags. Every setting has one key, used as-is in the config file, upper-cased
/// with a KDRT_ prefix as its environment variable, and with '_' -> '-' as its flag:
///   memory_budget  <->  KDRT_MEMORY_BUDGET  <->  --memory-budget
/// config/kdrt.json lists them all with their defaults; `kdrt-server --help` prints the table.

#include <cstddef>
#include <cstdint>
#include <optional>
#include <string>
#include <string_view>
#include <vector>

#include "kdrt/proto/result.h"

namespace kdrt::server {

/// What a bearer token may do on /v1 (a bit set). kRoleRead: every route that leaves the stored
/// meshes as they are (listings, summaries, ray batches, renders, jobs); kRoleWrite: the routes
/// that change them (uploads, deletions). `token` / `token_file` have both; a line of
/// `tokens_file` names its own.
enum TokenRole : unsigned { kRoleRead = 1, kRoleWrite = 2 };

/// "read", "write" or "read,write".
[[nodiscard]] std::string role_names(unsigned roles);

/// One accepted bearer token and its roles.
struct ApiToken {
    std::string token;
    unsigned roles = 0;  ///< TokenRole bits
};

struct ServerConfig {
    // Network
    std::string listen = "127.0.0.1:8080";  ///< HOST:PORT; port 0 picks a free port
    std::string port_file;                  ///< when set, the bound port is written there
    unsigned http_threads = 32;         ///< threads serving requests (idle connections hold none)
    unsigned keep_alive_timeout_s = 2;  ///< idle keep-alive connections close after this
    unsigned keep_alive_max_requests = 1000;  ///< requests per connection before it is closed
    unsigned read_timeout_s = 30;             ///< per socket read
    unsigned write_timeout_s = 30;            ///< per socket write
    unsigned request_head_timeout_s = 10;     ///< whole request head (line + headers), else 408
    unsigned request_timeout_s = 60;          ///< whole request head and body, else 408
    uint64_t max_request_head_bytes = 32ull << 10;    ///< request line + headers, else 431
    unsigned max_request_headers = 100;               ///< header lines, else 431
    uint64_t request_prebuffer_bytes = 256ull << 10;  ///< body bytes read before a thread
    unsigned max_connections = 4096;                  ///< open connections; more are refused
    std::string token;                                ///< bearer token for /v1 (empty = no auth)
    std::string token_file;   ///< file holding the token (read once at start; excludes `token`)
    std::string tokens_file;  ///< file of "ROLES TOKEN" lines (read once at start)
    std::vector<ApiToken> role_tokens;  ///< the tokens of tokens_file (not a setting)

    // Engine and cache
    unsigned threads = 0;                       ///< tracing/build threads (0 = all cores)
    std::string cache_dir = "kdrt-cache";       ///< where meshes and trees are stored
    uint64_t memory_budget = 2ull << 30;        ///< bytes of trees kept in memory (LRU beyond)
    std::vector<std::string> preload;           ///< mesh files uploaded at start-up
    uint64_t buffer_pool_bytes = 256ull << 20;  ///< idle ray-batch buffers kept for reuse
    /// This replica's name ([A-Za-z0-9_-]{0,64}): prefixes job ids, sent as X-Kdrt-Replica.
    std::string replica;

    // Limits
    uint64_t max_upload_bytes = 1ull << 30;     ///< mesh upload body
    uint64_t upload_memory_bytes = 8ull << 20;  ///< uploads larger than this are spooled to disk
    uint64_t max_triangles = 1ull << 27;        ///< triangles per mesh
    uint32_t max_rays = 1u << 24;               ///< rays per KDRR batch (body = 16 + 32 x rays)
    uint32_t max_json_rays = 100'000;           ///< rays per JSON batch
    uint32_t max_hits_per_ray = 1024;           ///< intersect_all's largest max_hits
    uint32_t max_distance_points = 1u << 22;    ///< query points per distance request
    uint64_t max_distance_work = 1ull << 32;    ///< distance request work (cells + triangles)
    uint32_t max_sensor_beams = 1u << 21;       ///< channels x azimuth_steps of a lidar scan
    uint32_t max_scan_points = 1u << 24;        ///< a scan's pixels, or beams x returns
    uint32_t max_instances = 65536;     ///< instances of one scene (and poses of one update)
    uint32_t max_scenes = 10000;        ///< scenes in the store
    uint32_t scene_revisions_kept = 8;  ///< newest revisions of a scene kept (pinned queries)
    /// "commit": a scene revision is flushed to disk (fdatasync) before it is acknowledged;
    /// "none": written, not flushed (survives a killed server, not a power loss).
    std::string scene_sync = "commit";
    uint64_t scene_memory_budget = 256ull << 20;  ///< built scenes kept in memory (LRU beyond)
    uint64_t max_json_bytes = 32ull << 20;        ///< JSON request body
    unsigned max_inflight = 64;                   ///< uploads/traces/renders in flight before 503
    uint32_t max_image_width = 8192;
    uint32_t max_image_height = 8192;
    uint32_t max_spp = 1024;
    uint32_t png_compression = 1;  ///< zlib level of rendered PNGs when a request names none
    unsigned max_jobs = 16;        ///< async render jobs queued or running before 503
    unsigned job_ttl_s = 600;      ///< finished jobs are forgotten after this
    uint64_t job_result_bytes = 512ull << 20;  ///< finished jobs' images (oldest forgotten beyond)
    uint64_t batch_memory_budget = 2ull
                                   << 30;   ///< ray batches in flight (rays + answers), 503 beyond
    uint64_t max_render_rays = 1ull << 36;  ///< pixels x spp x rays per sample of one render
    uint64_t max_raw_render_bytes = 512ull << 20;  ///< KDRI answer of one "format": "raw" render
    unsigned max_renders = 2;                      ///< synchronous renders running at once
    unsigned max_builds = 2;                       ///< uploads parsed and built at once
    unsigned max_queued = 8;                       ///< requests waiting for a render or build slot
    unsigned shutdown_timeout_s = 10;              ///< in-flight requests get this long on SIGTERM

    // Logging
    std::string log_level = "info";   ///< trace, debug, info, warn, error, critical, off
    std::string log_format = "text";  ///< text or json

    // Web viewer
    std::string web_viewer = "on";  ///< "on": the viewer at / and /ui/; "off": those are 404

    std::string config_file;  ///< the file the settings came from (empty = none)
};

/// What the command line asks for.
struct Invocation {
    enum class Mode { kServe, kHelp, kVersion, kMeshId, kCheckStore };
    Mode mode = Mode::kServe;
    ServerConfig config;
    std::vector<std::string> mesh_files;  ///< kMeshId: files to print the ids of
    /// What the configuration allows but should not be so (a token file other users can read),
    /// one sentence each, for the log once it is set up.
    std::vector<std::string> warnings;
};

/// Builds the configuration from defaults, the config file, `env` (NAME=VALUE strings, e.g.
/// environ) and `args` (argv without argv[0]). Errors name the setting, its source and the
/// problem: `--threads: "x" is not a non-negative integer`, `config/kdrt.json: unknown setting
/// "thread"`.
[[nodiscard]] proto::Result<Invocation, std::string> parse_invocation(
    const std::vector<std::string>& args, const std::vector<std::string>& env);

/// Applies the settings of a config file's text (`origin` names it in errors) over `config`.
[[nodiscard]] proto::Result<void, std::string> apply_config_text(std::string_view text,
                                                                 const std::string& origin,
                                                                 ServerConfig& config);

/// The --help text: usage, commands, and every setting with its flag, variable and default.
[[nodiscard]] std::string help_text();

/// Every setting key, in help order (for tests that compare config/kdrt.json with the defaults).
[[nodiscard]] std::vector<std::string> setting_keys();

/// The default value of a setting as config/kdrt.json spells it (JSON text), or empty if unknown.
[[nodiscard]] std::string setting_default_json(std::string_view key);

/// The fewest characters a token of tokens_file may have (a shorter one can be guessed).
inline constexpr size_t kMinTokenChars = 16;

/// The tokens of a tokens_file's text: one `ROLES TOKEN` line per token, ROLES `read`, `write` or
/// `read,write`, TOKEN at least kMinTokenChars characters; blank lines and lines starting with
/// '#' are skipped. Errors name `origin`, the line and what is wrong (never the token).
[[nodiscard]] proto::Result<std::vector<ApiToken>, std::string> parse_tokens_text(
    std::string_view text, const std::string& origin);

/// A warning when the file at `path` (the secret file of `setting`: token_file, tokens_file) may
/// be read or written by users other than its owner (group or other permission bits), else
/// nullopt (also when it cannot be inspected: reading it reports that).
[[nodiscard]] std::optional<std::string> secret_file_warning(std::string_view setting,
                                                             const std::string& path);

/// Every token /v1 accepts: `token` (read and write) and `role_tokens`. Empty: no authentication.
[[nodiscard]] std::vector<ApiToken> accepted_tokens(const ServerConfig& config);

/// Splits "HOST:PORT" ("[::1]:80" for IPv6). Errors name the value.
[[nodiscard]] proto::Result<std::pair<std::string, int>, std::string> split_listen(
    std::string_view listen);

/// Parses a byte count: digits with an optional K, M, G or T suffix (powers of 1024), e.g. "512M".
[[nodiscard]] proto::Result<uint64_t, std::string> parse_bytes(std::string_view text);

}  // namespace kdrt::server
