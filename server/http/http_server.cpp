#include "http/http_server.h"

#include <httplib.h>

#include <algorithm>
#include <array>
#include <cctype>
#include <cstring>
#include <regex>
#include <utility>

#include "core/log.h"
#include "http/http_front.h"
#include "http/http_routes.h"
#include "http/http_util.h"
#include "http/problems.h"
#include "kdrt/proto/distance.h"
#include "kdrt/proto/text.h"

namespace kdrt::server {
namespace {

using proto::ProblemKind;

/// Connections waiting to be accepted (a small backlog makes a burst of new connections wait
/// for SYN retransmits, 1 s and more).
constexpr int kListenBacklog = 1024;

/// A path segment (mesh or job id) in a route pattern.
constexpr const char* kIdPattern = "([^/]+)";

/// What the wrapper checks before a handler runs.
struct RouteFlags {
    bool api = false;    ///< /v1: bearer token and readiness
    bool heavy = false;  ///< counts against max_inflight (503 beyond)
    bool write = false;  ///< changes the stored meshes: the token needs the write role
};

/// Compares a presented token with the configured one in time that depends only on the
/// configured token's length (no early exit on the first differing byte).
bool same_secret(std::string_view given, std::string_view expected) {
    unsigned char diff = given.size() == expected.size() ? 0 : 1;
    for (size_t i = 0; i < expected.size(); ++i)
        diff |= static_cast<unsigned char>((i < given.size() ? given[i] : 0) ^ expected[i]);
    return diff == 0;
}

/// True for the Content-Encoding "identity" (any case): no encoding.
bool is_identity(std::string_view encoding) {
    constexpr std::string_view kIdentity = "identity";
    return encoding.size() == kIdentity.size() &&
           std::equal(encoding.begin(), encoding.end(), kIdentity.begin(), [](char a, char b) {
               return std::tolower(static_cast<unsigned char>(a)) == b;
           });
}

/// The connection layer's gauges as metric families (kdrt_http_connections, ...).
void add_connection_families(std::vector<proto::MetricFamily>& families,
                             const ConnectionGauges& gauges, unsigned threads) {
    const auto gauge = [&](const char* name, const char* help, size_t value) {
        proto::MetricFamily f;
        f.name = name;
        f.help = help;
        f.type = proto::MetricType::kGauge;
        f.samples.push_back({{}, static_cast<double>(value)});
        families.push_back(std::move(f));
    };
    gauge("kdrt_http_connections",
          "Open client connections (idle keep-alive, arriving, or being answered).",
          gauges.open.load());
    gauge("kdrt_http_threads", "Threads answering HTTP requests (http_threads).", threads);
    gauge("kdrt_http_threads_busy", "HTTP threads answering a request now.", gauges.busy.load());
    gauge("kdrt_http_threads_idle", "HTTP threads started and free for the next request.",
          gauges.idle.load());
    gauge("kdrt_http_requests_waiting", "Requests fully received and waiting for an HTTP thread.",
          gauges.waiting.load());
}

/// The connection layer's limits from the configuration.
ConnectionLimits connection_limits(const ServerConfig& c) {
    return {.threads = c.http_threads,
            .keep_alive_timeout_s = c.keep_alive_timeout_s,
            .keep_alive_max_requests = c.keep_alive_max_requests,
            .read_timeout_s = c.read_timeout_s,
            .write_timeout_s = c.write_timeout_s,
            .head_timeout_s = c.request_head_timeout_s,
            .request_timeout_s = c.request_timeout_s,
            .max_head_bytes = static_cast<size_t>(c.max_request_head_bytes),
            .max_headers = c.max_request_headers,
            .prebuffer_bytes = static_cast<size_t>(c.request_prebuffer_bytes),
            .max_connections = c.max_connections};
}

/// True for the methods HTTP defines that a route could take (RFC 9110, RFC 5789).
bool is_known_method(std::string_view method) {
    static constexpr std::array<std::string_view, 7> kMethods = {"GET",    "HEAD",  "POST",   "PUT",
                                                                 "DELETE", "PATCH", "OPTIONS"};
    return std::find(kMethods.begin(), kMethods.end(), method) != kMethods.end();
}

/// True when the request asks for `100 Continue` before it sends its body.
bool expects_continue(const httplib::Request& req) {
    return req.has_header("Expect");  // the front accepts no other expectation
}

}  // namespace

struct HttpServer::Impl {
    explicit Impl(Service& service)
        : svc(service),
          routes(service),
          tokens(accepted_tokens(service.config)),
          http(
              connection_limits(service.config),
              [this](int status, std::string_view method, const std::string& detail) {
                  return early_reply(status, method, detail);
              },
              [this](httplib::Request& req, httplib::Response& res,
                     const httplib::ContentReader& reader) { answer(req, res, reader); },
              [this](const httplib::Request& req, const httplib::Response& res) {
                  on_logged(req, res);
              }) {}

    /// A route's handler (GET and DELETE handlers ignore the reader).
    using Handler = std::function<void(const httplib::Request&, httplib::Response&,
                                       const httplib::ContentReader&)>;

    Service& svc;
    Routes routes;
    struct Known {
        std::regex pattern;
        std::string method;
        std::string name;  ///< the path template, e.g. "/v1/meshes/{id}"
        RouteFlags flags;
        Handler handler;
        bool listed = true;  ///< false for add_route_for_tests
    };
    std::vector<Known> known;  ///< the router: first match by method and path
    std::atomic<uint64_t> next_request_id{1};
    const std::vector<ApiToken> tokens;  ///< empty: no authentication
    HttpFront http;                      ///< last: its callbacks use the members above

    /// Checks the bearer token when tokens are configured, and that it has the role the route
    /// needs (write for `write` routes, else read). On refusal replies 401 (no or an unknown
    /// token) or 403 (a token without the role) and returns false.
    bool authorized(const httplib::Request& req, httplib::Response& res, bool write) {
        if (tokens.empty()) return true;
        const std::string auth = req.get_header_value("Authorization");
        // RFC 9110 11.1: the scheme is case-insensitive, and one or more spaces end it.
        const bool bearer =
            auth.size() > 7 && auth[6] == ' ' &&
            std::equal(auth.begin(), auth.begin() + 6, "bearer", [](char a, char b) {
                return std::tolower(static_cast<unsigned char>(a)) == b;
            });
        if (!bearer) {
            reply_problem(
                req, res,
                make_problem(ProblemKind::kUnauthorized,
                             req.path + " " + std::string(proto::api_errors::kMissingToken)));
            return false;
        }
        // Every configured token is compared, in full: the time taken does not say which
        // (or how much of one) matched.
        const std::string_view given = std::string_view(auth).substr(
            auth.find_first_not_of(' ', 6) == std::string::npos ? auth.size()
                                                                : auth.find_first_not_of(' ', 6));
        unsigned roles = 0;
        bool found = false;
        for (const ApiToken& t : tokens) {
            const bool same = same_secret(given, t.token);
            found |= same;
            roles |= same ? t.roles : 0;
        }
        if (!found) {
            reply_problem(req, res,
                          make_problem(ProblemKind::kUnauthorized,
                                       "the " + std::string(proto::api_errors::kWrongToken)));
            return false;
        }
        const unsigned needed = write ? kRoleWrite : kRoleRead;
        if ((roles & needed) == 0) {
            const std::string role = role_names(needed);
            const std::string& route =
                request_context().route.empty() ? req.path : request_context().route;
            auto p = make_problem(ProblemKind::kForbidden,
                                  req.method + " " + route + " " +
                                      std::string(proto::api_errors::kMissingRole) + " " + role +
                                      "; this token has the role " + role_names(roles));
            p.code = role;
            reply_problem(req, res, std::move(p));
            // RFC 6750 section 3.1: the scope the request lacks.
            res.set_header(
                "WWW-Authenticate",
                "Bearer realm=\"kdrt\", error=\"insufficient_scope\", scope=\"" + role + "\"");
            return false;
        }
        return true;
    }

    /// The route `req` goes to (by method and path; HEAD is answered as GET), or null. Sets
    /// req.matches (the path's captures: a mesh or job id).
    const Known* find_route(httplib::Request& req) const {
        const std::string& method = req.method == "HEAD" ? std::string("GET") : req.method;
        for (const Known& k : known)
            if (k.method == method && std::regex_match(req.path, req.matches, k.pattern)) return &k;
        return nullptr;
    }

    /// The body limit of the route `req` is for (uploads, KDRR batches, JSON).
    [[nodiscard]] uint64_t body_limit(const httplib::Request& req) const {
        const ServerConfig& c = svc.config;
        if (req.path == "/v1/meshes") return c.max_upload_bytes;
        auto ends_with = [&](std::string_view tail) {
            return req.path.size() > tail.size() &&
                   req.path.compare(req.path.size() - tail.size(), tail.size(), tail) == 0;
        };
        if ((ends_with("/intersect") || ends_with("/intersect_all")) &&
            proto::media_type_essence(req.get_header_value("Content-Type")) ==
                proto::kRaysMediaType)
            return proto::kdrr_body_size(c.max_rays);
        if (ends_with("/distance") && proto::media_type_essence(req.get_header_value(
                                          "Content-Type")) == proto::kPointMediaType)
            return proto::kdrp_body_size(c.max_distance_points);
        return c.max_json_bytes;
    }

    /// Starts the per-request context (id, clock). Called again by the pre-routing handler
    /// after an accepted `Expect: 100-continue`, which then starts the clock anew.
    void begin_request(httplib::Response& res) {
        RequestContext& context = request_context();
        context = RequestContext{};
        context.active = true;
        context.start = std::chrono::steady_clock::now();
        context.request_id = proto::hex(next_request_id.fetch_add(1), 16);
        res.headers.erase("X-Request-Id");
        res.set_header("X-Request-Id", context.request_id);
        if (!svc.config.replica.empty()) {
            res.headers.erase("X-Kdrt-Replica");
            res.set_header("X-Kdrt-Replica", svc.config.replica);
        }
    }

    /// Checks token, readiness and capacity. On refusal replies and returns false.
    bool admit(const RouteFlags& flags, const httplib::Request& req, httplib::Response& res,
               std::optional<AdmissionGate::Slot>& slot) {
        if (flags.api && !authorized(req, res, flags.write)) return false;
        if (flags.api && (svc.shutting_down || !svc.ready)) {
            reply_problem(req, res, not_ready_problem(svc.shutting_down));
            return false;
        }
        return !flags.heavy || take_slot(req, res, slot);
    }

    /// Takes a max_inflight slot for a heavy route. On refusal replies and returns false.
    bool take_slot(const httplib::Request& req, httplib::Response& res,
                   std::optional<AdmissionGate::Slot>& slot) {
        slot = svc.gate.try_enter();
        if (slot && svc.shutting_down) {
            // Shutdown began between the readiness check and taking the slot: the shutdown
            // sequence may already have seen zero requests in flight.
            slot.reset();
            reply_problem(req, res, not_ready_problem(true));
            return false;
        }
        if (!slot) {
            auto p = make_problem(ProblemKind::kOverCapacity,
                                  std::to_string(svc.gate.limit()) + " " +
                                      std::string(proto::api_errors::kOverCapacity) +
                                      " (max_inflight); retry later");
            p.retry_after = 1;
            p.limit = svc.gate.limit();
            reply_problem(req, res, std::move(p));
            return false;
        }
        return true;
    }

    /// Registers a GET or DELETE route.
    void add(const char* method, const std::string& pattern, const std::string& name,
             RouteFlags flags,
             void (Routes::*handler)(const httplib::Request&, httplib::Response&)) {
        known.push_back(
            {std::regex(pattern), method, name, flags,
             [this, name, flags, handler](const httplib::Request& req, httplib::Response& res,
                                          const httplib::ContentReader&) {
                 request_context().route = name;
                 std::optional<AdmissionGate::Slot> slot;
                 if (admit(flags, req, res, slot)) (routes.*handler)(req, res);
             }});
    }

    void get(const std::string& pattern, const std::string& name, RouteFlags flags,
             void (Routes::*handler)(const httplib::Request&, httplib::Response&)) {
        add("GET", pattern, name, flags, handler);
    }

    void del(const std::string& pattern, const std::string& name, RouteFlags flags,
             void (Routes::*handler)(const httplib::Request&, httplib::Response&)) {
        add("DELETE", pattern, name, flags, handler);
    }

    /// A POST route. A refused request's body is left unread (the front drains or closes), and
    /// with `Expect: 100-continue` a body declared over the route's limit is refused before the
    /// client sends it. The admission slot is kept until the response has been written, so the
    /// shutdown sequence (which waits for zero slots) never cuts a reply short.
    void post(const std::string& pattern, const std::string& name, RouteFlags flags,
              void (Routes::*handler)(const httplib::Request&, httplib::Response&,
                                      const httplib::ContentReader&),
              const char* method = "POST") {
        known.push_back(
            {std::regex(pattern), method, name, flags,
             [this, name, flags, handler](const httplib::Request& req, httplib::Response& res,
                                          const httplib::ContentReader& reader) {
                 request_context().route = name;
                 std::optional<AdmissionGate::Slot> slot;
                 if (!admit(flags, req, res, slot)) return;
                 if (expects_continue(req)) {
                     const uint64_t limit = body_limit(req);
                     if (declared_body_bytes(req).value_or(0) > limit)
                         return reply_problem(req, res,
                                              body_too_large_problem(limit, "this route"));
                 }
                 (routes.*handler)(req, res, reader);
                 if (slot) keep_until_sent(std::make_shared<AdmissionGate::Slot>(std::move(*slot)));
             }});
    }

    /// A PATCH route: as post().
    void patch(const std::string& pattern, const std::string& name, RouteFlags flags,
               void (Routes::*handler)(const httplib::Request&, httplib::Response&,
                                       const httplib::ContentReader&)) {
        post(pattern, name, flags, handler, "PATCH");
    }

    void register_routes() {
        const std::string meshes = "/v1/meshes";
        const std::string mesh = meshes + "/" + kIdPattern;
        post(meshes, "/v1/meshes", {.api = true, .heavy = true, .write = true},
             &Routes::upload_mesh);
        get(meshes, "/v1/meshes", {.api = true}, &Routes::list_meshes);
        get(mesh, "/v1/meshes/{id}", {.api = true}, &Routes::get_mesh);
        del(mesh, "/v1/meshes/{id}", {.api = true, .write = true}, &Routes::delete_mesh);
        post(mesh + "/intersect", "/v1/meshes/{id}/intersect", {.api = true, .heavy = true},
             &Routes::intersect);
        post(mesh + "/intersect_all", "/v1/meshes/{id}/intersect_all", {.api = true, .heavy = true},
             &Routes::intersect_all);
        post(mesh + "/distance", "/v1/meshes/{id}/distance", {.api = true, .heavy = true},
             &Routes::distance);
        post(mesh + "/scan", "/v1/meshes/{id}/scan", {.api = true, .heavy = true}, &Routes::scan);
        post("/v1/render", "/v1/render", {.api = true, .heavy = true}, &Routes::render);
        const std::string scenes = "/v1/scenes";
        const std::string scene = scenes + "/" + kIdPattern;
        post(scenes, "/v1/scenes", {.api = true, .heavy = true, .write = true},
             &Routes::create_scene);
        get(scenes, "/v1/scenes", {.api = true}, &Routes::list_scenes);
        get(scene, "/v1/scenes/{id}", {.api = true}, &Routes::get_scene);
        del(scene, "/v1/scenes/{id}", {.api = true, .write = true}, &Routes::delete_scene);
        // PATCH is the method; POST is accepted too for clients that cannot send PATCH.
        patch(scene + "/poses", "/v1/scenes/{id}/poses", {.api = true, .write = true},
              &Routes::set_poses);
        post(scene + "/poses", "/v1/scenes/{id}/poses", {.api = true, .write = true},
             &Routes::set_poses);
        post(scene + "/instances", "/v1/scenes/{id}/instances",
             {.api = true, .heavy = true, .write = true}, &Routes::edit_instances);
        post(scene + "/intersect", "/v1/scenes/{id}/intersect", {.api = true, .heavy = true},
             &Routes::scene_intersect);
        post(scene + "/intersect_all", "/v1/scenes/{id}/intersect_all",
             {.api = true, .heavy = true}, &Routes::scene_intersect_all);
        post(scene + "/distance", "/v1/scenes/{id}/distance", {.api = true, .heavy = true},
             &Routes::scene_distance);
        post(scene + "/scan", "/v1/scenes/{id}/scan", {.api = true, .heavy = true},
             &Routes::scene_scan);
        post(scene + "/render", "/v1/scenes/{id}/render", {.api = true, .heavy = true},
             &Routes::scene_render);
        const std::string job = std::string("/v1/jobs/") + kIdPattern;
        get(job, "/v1/jobs/{id}", {.api = true}, &Routes::get_job);
        del(job, "/v1/jobs/{id}", {.api = true}, &Routes::delete_job);
        get(job + "/result", "/v1/jobs/{id}/result", {.api = true}, &Routes::job_result);
        get("/healthz", "/healthz", {}, &Routes::healthz);
        get("/readyz", "/readyz", {}, &Routes::readyz);
        get("/metrics", "/metrics", {}, &Routes::metrics);
        if (svc.config.web_viewer == "on") {
            // The page is public (it holds no data); its API calls carry the token.
            get("/", "/", {}, &Routes::web_file);
            get("/ui/([A-Za-z0-9_-]+\\.[a-z]+)", "/ui/{file}", {}, &Routes::web_file);
        }
    }

    /// The methods registered for `path` ("GET, DELETE"), and whether `method` is one of them
    /// (HEAD counts as GET).
    [[nodiscard]] std::pair<std::string, bool> allowed_methods(const std::string& path,
                                                               const std::string& method) const {
        std::string allowed;
        bool method_allowed = false;
        for (const Known& k : known) {
            if (!std::regex_match(path, k.pattern)) continue;
            if (k.method == method || (k.method == "GET" && method == "HEAD"))
                method_allowed = true;
            if (allowed.find(k.method) == std::string::npos)
                allowed += (allowed.empty() ? "" : ", ") + k.method;
        }
        return {allowed, method_allowed};
    }

    /// 404 for a path no route serves, 405 (with Allow) for a wrong method on one. The path is
    /// the problem's instance; the detail does not repeat it.
    void route_not_found(const httplib::Request& req, httplib::Response& res) {
        request_context().route = "unmatched";
        const auto [allowed, method_allowed] = allowed_methods(req.path, req.method);
        if (allowed.empty() || method_allowed)
            return reply_problem(
                req, res,
                make_problem(ProblemKind::kNotFound, std::string(proto::api_errors::kNoRoute) +
                                                         " " + req.method + " at this path"));
        res.set_header("Allow", allowed);
        reply_problem(
            req, res,
            make_problem(ProblemKind::kMethodNotAllowed,
                         "this path " + std::string(proto::api_errors::kMethodNotAllowed) + " " +
                             req.method + " (allowed: " + allowed + ")"));
    }

    void on_exception(const httplib::Request& req, httplib::Response& res, std::exception_ptr ep) {
        std::string what = "unknown exception";
        try {
            std::rethrow_exception(std::move(ep));
        } catch (const std::exception& e) {
            what = e.what();
        } catch (...) {
        }
        log_event(LogLevel::kError, "unhandled exception",
                  {{"request_id", request_context().request_id},
                   {"route", request_context().route},
                   {"error", what}});
        // Whatever the handler had set goes (a half-built reply), except the request id.
        res.headers.clear();
        res.set_header("X-Request-Id", request_context().request_id);
        reply_problem(
            req, res,
            make_problem(ProblemKind::kInternal, "internal error; see the server log for request " +
                                                     request_context().request_id));
        res.set_header("Connection", "close");
    }

    /// One request, from the front (on a worker thread): the per-request context, the checks
    /// every request passes, the router, and the handler inside the exception handling.
    void answer(httplib::Request& req, httplib::Response& res,
                const httplib::ContentReader& reader) {
        begin_request(res);
        svc.requests.begin(request_context().request_id, method_label(req.method), req.path);
        if (!is_known_method(req.method)) {
            // Not a method of RFC 9110 or 5789: no route could take it.
            request_context().route = "rejected";
            reply_problem(req, res,
                          make_problem(ProblemKind::kBadRequest,
                                       "unknown request method (GET, HEAD, POST, PUT, DELETE, "
                                       "PATCH, OPTIONS are the ones HTTP defines here)"));
            res.set_header("Connection", "close");
            return;
        }
        if (refused_before_routing(req, res)) return;
        const Known* route = find_route(req);
        if (route == nullptr) return route_not_found(req, res);
        try {
            route->handler(req, res, reader);
        } catch (...) {
            on_exception(req, res, std::current_exception());
        }
        if (res.status == -1) res.status = res.body.empty() ? 204 : 200;
    }

    /// Answers what no route should see: a POST without a framed body, a compressed body, a
    /// body over the largest any route takes. True when it answered.
    bool refused_before_routing(const httplib::Request& req, httplib::Response& res) {
        // HTTP/1.1 says a POST without Content-Length or chunked framing has an empty body;
        // every kdrt POST needs one, and saying so is clearer than a decoder's complaint.
        if (req.method == "POST" && !req.has_header("Content-Length") &&
            !req.has_header("Transfer-Encoding")) {
            request_context().route = "unmatched";
            reply_problem(req, res,
                          make_problem(ProblemKind::kBadRequest,
                                       "a POST needs a Content-Length (or chunked) body"));
            return true;
        }
        if (declared_body_bytes(req).value_or(0) > largest_body()) {
            request_context().route = "unmatched";
            reply_problem(req, res, body_too_large_problem(largest_body(), "any request"));
            res.set_header("Connection", "close");  // the body is not read
            return true;
        }
        // Compressed request bodies are refused (RFC 7694): httplib would inflate them with no
        // bound on the decoded size (a 2 MB gzip body becomes a 1 GiB spooled upload).
        const std::string encoding = req.get_header_value("Content-Encoding");
        if (!encoding.empty() && !is_identity(encoding)) {
            request_context().route = "unmatched";
            reply_problem(req, res,
                          make_problem(ProblemKind::kUnsupportedMediaType,
                                       "Content-Encoding " + proto::quote_value(encoding) +
                                           " is not accepted; send request bodies "
                                           "uncompressed (identity)"));
            res.set_header("Accept-Encoding", "identity");
            res.set_header("Connection", "close");  // the body is not read
            return true;
        }
        return false;
    }

    /// One access-log line and the request metrics, after the response is written.
    void on_logged(const httplib::Request& req, const httplib::Response& res) {
        if (!request_context().active) {
            RequestContext& context = request_context();
            context = RequestContext{};
            context.active = true;
            context.start = std::chrono::steady_clock::now();
            context.request_id = proto::hex(next_request_id.fetch_add(1), 16);
            context.route = "rejected";
        }
        RequestContext& context = request_context();
        const double seconds =
            context.active
                ? std::chrono::duration<double>(std::chrono::steady_clock::now() - context.start)
                      .count()
                : 0;
        const std::string route = context.route.empty() ? "unmatched" : context.route;
        const uint64_t bytes_in = context.bytes_in ? context.bytes_in : req.body.size();
        const uint64_t bytes_out = response_body_bytes(res);
        svc.metrics.record_request(route, req.method, res.status, seconds, bytes_in, bytes_out);
        log_event(LogLevel::kInfo, "request",
                  {{"method", method_label(req.method)},
                   {"route", route},
                   {"status", static_cast<int64_t>(res.status)},
                   {"in", bytes_in},
                   {"out", bytes_out},
                   {"rays", context.rays},
                   {"ms", seconds * 1e3},
                   {"id", context.request_id}});
        context.active = false;
        svc.requests.end();
    }

    /// The problem+json body of a refusal the front sends itself (400, 408, 431, 503: see
    /// HttpFront); logged and counted like a request on no route.
    std::string early_reply(int status, std::string_view method, const std::string& detail) {
        const ProblemKind kind = status == 408   ? ProblemKind::kRequestTimeout
                                 : status == 431 ? ProblemKind::kHeadersTooLarge
                                 : status == 503 ? ProblemKind::kOverCapacity
                                                 : ProblemKind::kBadRequest;
        proto::Problem problem = make_problem(kind, detail);
        problem.request_id = proto::hex(next_request_id.fetch_add(1), 16);
        if (status == 503) problem.retry_after = 1;
        std::string body = proto::encode_problem(problem);
        const std::string method_label = is_known_method(method) ? std::string(method) : "other";
        // A head the front could not parse is "rejected"; one refused for a limit "unmatched".
        const std::string route = status == 400 ? "rejected" : "unmatched";
        svc.metrics.record_request(route, method_label, status, 0, 0, body.size());
        log_event(LogLevel::kWarn, "request refused",
                  {{"method", method_label},
                   {"route", route},
                   {"status", static_cast<int64_t>(status)},
                   {"error", detail},
                   {"id", problem.request_id}});
        return body;
    }

    [[nodiscard]] uint64_t largest_body() const {
        const ServerConfig& c = svc.config;
        return std::max({c.max_upload_bytes, c.max_json_bytes, proto::kdrr_body_size(c.max_rays)});
    }

    void configure() {
        svc.metrics.add_collector(
            [gauges = http.gauges(), threads = svc.config.http_threads](auto& families) {
                add_connection_families(families, *gauges, threads);
            });
        register_routes();
    }
};

HttpServer::HttpServer(Service& service) : impl_(std::make_unique<Impl>(service)) {
    impl_->configure();
}

HttpServer::~HttpServer() = default;

proto::Result<int, std::string> HttpServer::bind(const std::string& host, int port) {
    auto bound = impl_->http.bind(host, port, kListenBacklog);
    if (bound) return *bound;
    std::string why = bound.error();
    if (why == std::strerror(EADDRINUSE))
        why += " (another process, perhaps another kdrt-server, listens there)";
    return proto::Err{"cannot listen on " + host + ":" + std::to_string(port) + ": " + why};
}

bool HttpServer::serve() { return impl_->http.serve(); }

void HttpServer::stop() { impl_->http.stop(); }

std::vector<RouteInfo> HttpServer::routes() const {
    std::vector<RouteInfo> out;
    for (const Impl::Known& k : impl_->known)
        if (k.listed) out.push_back({k.method, k.name});
    return out;
}

void HttpServer::add_route_for_tests(const std::string& path, std::function<void()> action) {
    impl_->known.push_back(
        {std::regex(path), "GET", path, RouteFlags{},
         [path, action = std::move(action)](const httplib::Request&, httplib::Response& res,
                                            const httplib::ContentReader&) {
             request_context().route = path;
             action();
             res.status = 204;
         },
         false});
}

std::string httplib_version() { return CPPHTTPLIB_VERSION; }

}  // namespace kdrt::server
