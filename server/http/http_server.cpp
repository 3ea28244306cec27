#include "http/http_server.h"

#include <httplib.h>

#include <algorithm>
#include <array>
#include <cstring>
#include <regex>
#include <utility>

#include "core/log.h"
#include "http/http_routes.h"
#include "http/http_util.h"
#include "http/httplib_internals.h"
#include "http/problems.h"
#include "kdrt/proto/distance.h"
#include "kdrt/proto/text.h"

namespace kdrt::server {
namespace {

using proto::ProblemKind;

/// Connections waiting to be accepted (httplib 0.11.4 listens with 5: a burst of new
/// connections beyond that waits for SYN retransmits, 1 s and more).
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
    gauge("kdrt_http_requests_waiting", "Requests fully received and waiting for an HTTP thread.",
          gauges.waiting.load());
}

}  // namespace

struct HttpServer::Impl {
    explicit Impl(Service& service)
        : svc(service), routes(service), tokens(accepted_tokens(service.config)) {}

    Service& svc;
    Routes routes;
    ConnectionServer http;
    struct Known {
        std::regex pattern;
        std::string method;
        std::string name;  ///< the path template, e.g. "/v1/meshes/{id}"
        RouteFlags flags;
    };
    std::vector<Known> known;  ///< for 405 vs 404
    std::atomic<uint64_t> next_request_id{1};
    const std::vector<ApiToken> tokens;  ///< empty: no authentication

    /// Checks the bearer token when tokens are configured, and that it has the role the route
    /// needs (write for `write` routes, else read). On refusal replies 401 (no or an unknown
    /// token) or 403 (a token without the role) and returns false.
    bool authorized(const httplib::Request& req, httplib::Response& res, bool write) {
        if (tokens.empty()) return true;
        const std::string auth = req.get_header_value("Authorization");
        if (auth.rfind("Bearer ", 0) != 0) {
            reply_problem(
                req, res,
                make_problem(ProblemKind::kUnauthorized,
                             req.path + " " + std::string(proto::api_errors::kMissingToken)));
            return false;
        }
        // Every configured token is compared, in full: the time taken does not say which
        // (or how much of one) matched.
        const std::string_view given = std::string_view(auth).substr(7);
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

    /// The route `req` goes to (by method and path), or null.
    [[nodiscard]] const Known* find_route(const httplib::Request& req) const {
        for (const Known& k : known)
            if (k.method == req.method && std::regex_match(req.path, k.pattern)) return &k;
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

    /// `Expect: 100-continue`: refuse before the client sends the body when the token is wrong
    /// or the declared length is over the route's limit (curl asks for bodies over 1 MiB).
    int on_expect_continue(const httplib::Request& req, httplib::Response& res) {
        begin_request(res);
        const bool api = req.path.rfind("/v1/", 0) == 0 || req.path == "/v1";
        if (api && !tokens.empty()) {
            const Known* route = find_route(req);
            if (route) request_context().route = route->name;
            if (!authorized(req, res, route && route->flags.write)) {
                res.set_header("Connection", "close");
                return res.status;
            }
        }
        const uint64_t limit = body_limit(req);
        if (req.get_header_value<uint64_t>("Content-Length") > limit) {
            reply_problem(req, res, body_too_large_problem(limit, "this route"));
            res.set_header("Connection", "close");
            return res.status;
        }
        return 100;
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

    /// A streamed response is written after the handler returns, and httplib stops streaming
    /// once the server is stopped: keep the admission slot until the response is gone, so the
    /// shutdown sequence (which waits for zero slots) never cuts a reply short.
    static void hold_until_sent(httplib::Response& res, AdmissionGate::Slot slot) {
        keep_until_sent(res, std::make_shared<AdmissionGate::Slot>(std::move(slot)));
    }

    void get(const std::string& pattern, const std::string& name, RouteFlags flags,
             void (Routes::*handler)(const httplib::Request&, httplib::Response&)) {
        known.push_back({std::regex(pattern), "GET", name, flags});
        http.Get(pattern,
                 [this, name, flags, handler](const httplib::Request& req, httplib::Response& res) {
                     request_context().route = name;
                     std::optional<AdmissionGate::Slot> slot;
                     if (admit(flags, req, res, slot)) (routes.*handler)(req, res);
                 });
    }

    void del(const std::string& pattern, const std::string& name, RouteFlags flags,
             void (Routes::*handler)(const httplib::Request&, httplib::Response&)) {
        known.push_back({std::regex(pattern), "DELETE", name, flags});
        http.Delete(pattern, [this, name, flags, handler](const httplib::Request& req,
                                                          httplib::Response& res) {
            request_context().route = name;
            std::optional<AdmissionGate::Slot> slot;
            if (admit(flags, req, res, slot)) (routes.*handler)(req, res);
        });
    }

    void post(const std::string& pattern, const std::string& name, RouteFlags flags,
              void (Routes::*handler)(const httplib::Request&, httplib::Response&,
                                      const httplib::ContentReader&)) {
        known.push_back({std::regex(pattern), "POST", name, flags});
        http.Post(pattern,
                  [this, name, flags, handler](const httplib::Request& req, httplib::Response& res,
                                               const httplib::ContentReader& reader) {
                      request_context().route = name;
                      std::optional<AdmissionGate::Slot> slot;
                      if (!admit(flags, req, res, slot)) return discard_body(req, res, reader);
                      (routes.*handler)(req, res, reader);
                      if (slot) hold_until_sent(res, std::move(*slot));
                  });
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

    /// The problem for an error status httplib set itself (other than a wrong method).
    [[nodiscard]] proto::Problem http_layer_problem(const httplib::Request& req, int status) const {
        if (status == 404)
            return make_problem(ProblemKind::kNotFound, std::string(proto::api_errors::kNoRoute) +
                                                            " " + req.method + " " + req.path);
        if (status == 413) return body_too_large_problem(largest_body(), "any request");
        if (status >= 500)
            return make_problem(ProblemKind::kInternal, "the server failed to answer the request");
        return make_problem(
            ProblemKind::kBadRequest,
            "malformed HTTP request (status " + std::to_string(status) + " from the HTTP layer)");
    }

    /// Fills the body of errors httplib produced itself (unknown route, malformed request,
    /// Content-Length over the payload limit).
    httplib::Server::HandlerResponse on_error(const httplib::Request& req, httplib::Response& res) {
        fresh_context_if_rejected(res);
        if (response_has_content(res)) return httplib::Server::HandlerResponse::Unhandled;
        const auto [allowed, method_allowed] = allowed_methods(req.path, req.method);
        if ((res.status == 404 || res.status == 400) && !allowed.empty() && !method_allowed) {
            // httplib answers 404 (or 400 for methods it has no handlers for) when only the
            // method is wrong.
            res.status = 405;
            res.set_header("Allow", allowed);
            reply_problem(
                req, res,
                make_problem(ProblemKind::kMethodNotAllowed,
                             req.path + " " + std::string(proto::api_errors::kMethodNotAllowed) +
                                 " " + req.method + " (allowed: " + allowed + ")"));
        } else {
            reply_problem(req, res, http_layer_problem(req, res.status));
        }
        return httplib::Server::HandlerResponse::Handled;
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

    /// Starts the per-request context; answers requests httplib would mishandle.
    httplib::Server::HandlerResponse on_pre_routing(const httplib::Request& req,
                                                    httplib::Response& res) {
        begin_request(res);
        svc.requests.begin(request_context().request_id, method_label(req.method), req.path);
        // httplib reads Content-Length with strtoull: "abc" is 0, "0x10" is 0, "1, 2" is 1.
        // RFC 9110: one value of decimal digits (a list of equal values is not worth the risk).
        if (req.has_header("Content-Length")) {
            const std::string value = req.get_header_value("Content-Length");
            const bool digits = !value.empty() && value.size() <= 19 &&
                                value.find_first_not_of("0123456789") == std::string::npos;
            if (!digits || req.get_header_value_count("Content-Length") != 1) {
                request_context().route = "unmatched";
                reply_problem(req, res,
                              make_problem(ProblemKind::kBadRequest,
                                           "invalid Content-Length " + proto::in_quotes(value) +
                                               " (one decimal number of bytes)"));
                res.set_header("Connection", "close");
                return httplib::Server::HandlerResponse::Handled;
            }
        }
        // httplib 0.11.4 reads a POST without Content-Length or chunked framing until the peer
        // closes; HTTP/1.1 says such a body is empty. Answer now instead of hanging.
        if (req.method == "POST" && !req.has_header("Content-Length") &&
            !req.has_header("Transfer-Encoding")) {
            request_context().route = "unmatched";
            reply_problem(req, res,
                          make_problem(ProblemKind::kBadRequest,
                                       "a POST needs a Content-Length (or chunked) body"));
            return httplib::Server::HandlerResponse::Handled;
        }
        // Compressed request bodies are refused (RFC 7694): httplib would inflate them with no
        // bound on the decoded size (a 2 MB gzip body becomes a 1 GiB spooled upload).
        const std::string encoding = req.get_header_value("Content-Encoding");
        if (!encoding.empty() && !is_identity(encoding)) {
            request_context().route = "unmatched";
            reply_problem(req, res,
                          make_problem(ProblemKind::kUnsupportedMediaType,
                                       "Content-Encoding " + proto::in_quotes(encoding) +
                                           " is not accepted; send request bodies "
                                           "uncompressed (identity)"));
            res.set_header("Accept-Encoding", "identity");
            res.set_header("Connection", "close");  // the body is not read
            return httplib::Server::HandlerResponse::Handled;
        }
        return httplib::Server::HandlerResponse::Unhandled;
    }

    /// A request httplib refused before routing (malformed request line, unknown method) never
    /// reached the pre-routing handler: give it its own context instead of the previous
    /// request's on this thread (id, route "rejected").
    void fresh_context_if_rejected(httplib::Response& res) {
        if (request_context().active) return;
        begin_request(res);
        request_context().route = "rejected";
        // What follows an unparsed request line on the connection cannot be framed: answer and
        // close (the connection layer closes a connection whose response says so).
        res.set_header("Connection", "close");
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
        note_response_sent(res);
    }

    /// The problem+json body of a refusal the connection layer sends before httplib parses the
    /// request (408, 431, 503); logged and counted like a request on no route.
    std::string early_reply(int status, std::string_view method, const std::string& detail) {
        const ProblemKind kind = status == 408   ? ProblemKind::kRequestTimeout
                                 : status == 431 ? ProblemKind::kHeadersTooLarge
                                 : status == 503 ? ProblemKind::kOverCapacity
                                                 : ProblemKind::kBadRequest;
        proto::Problem problem = make_problem(kind, detail);
        problem.request_id = proto::hex(next_request_id.fetch_add(1), 16);
        if (status == 503) problem.retry_after = 1;
        std::string body = proto::encode_problem(problem);
        static constexpr std::array<std::string_view, 7> kMethods = {
            "GET", "HEAD", "POST", "PUT", "DELETE", "PATCH", "OPTIONS"};
        const bool known_method =
            std::find(kMethods.begin(), kMethods.end(), method) != kMethods.end();
        const std::string method_label = known_method ? std::string(method) : "other";
        svc.metrics.record_request("unmatched", method_label, status, 0, 0, body.size());
        log_event(LogLevel::kWarn, "request refused",
                  {{"method", method_label},
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
        const ServerConfig& c = svc.config;
        http.set_connection_limits(
            {.threads = c.http_threads,
             .keep_alive_timeout_s = c.keep_alive_timeout_s,
             .keep_alive_max_requests = c.keep_alive_max_requests,
             .read_timeout_s = c.read_timeout_s,
             .write_timeout_s = c.write_timeout_s,
             .head_timeout_s = c.request_head_timeout_s,
             .request_timeout_s = c.request_timeout_s,
             .max_head_bytes = static_cast<size_t>(c.max_request_head_bytes),
             .max_headers = c.max_request_headers,
             .prebuffer_bytes = static_cast<size_t>(c.request_prebuffer_bytes),
             .max_connections = c.max_connections},
            [this](int status, std::string_view method, const std::string& detail) {
                return early_reply(status, method, detail);
            });
        http.set_tcp_nodelay(true);
        // httplib's default also sets SO_REUSEPORT, which lets a second server bind the same
        // port and take half the connections. SO_REUSEADDR alone still allows a restart while
        // old connections are in TIME_WAIT.
        http.set_socket_options([](socket_t sock) {
            int yes = 1;
            ::setsockopt(sock, SOL_SOCKET, SO_REUSEADDR, &yes, sizeof yes);
        });
        http.set_keep_alive_max_count(c.keep_alive_max_requests);
        http.set_keep_alive_timeout(c.keep_alive_timeout_s);
        http.set_read_timeout(c.read_timeout_s, 0);
        http.set_write_timeout(c.write_timeout_s, 0);
        http.set_payload_max_length(largest_body());
        http.set_pre_routing_handler(
            [this](const auto& req, auto& res) { return on_pre_routing(req, res); });
        http.set_error_handler(httplib::Server::HandlerWithResponse(
            [this](const auto& req, auto& res) { return on_error(req, res); }));
        http.set_exception_handler([this](const auto& req, auto& res, std::exception_ptr ep) {
            on_exception(req, res, std::move(ep));
        });
        http.set_expect_100_continue_handler(
            [this](const auto& req, auto& res) { return on_expect_continue(req, res); });
        http.set_logger([this](const auto& req, const auto& res) { on_logged(req, res); });
        svc.metrics.add_collector(
            [gauges = http.gauges(), threads = c.http_threads](auto& families) {
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
    if (port == 0) {
        const int bound = impl_->http.bind_to_any_port(host);
        if (bound <= 0)
            return proto::Err{"cannot listen on " + host + ":0: " + std::strerror(errno)};
        if (!impl_->http.set_listen_backlog(kListenBacklog))
            return proto::Err{"cannot set the listen backlog of " + host + ": " +
                              std::strerror(errno)};
        return bound;
    }
    errno = 0;
    if (!impl_->http.bind_to_port(host, port)) {
        const int err = errno;
        std::string why = err ? std::strerror(err) : "bind failed";
        if (err == EADDRINUSE)
            why += " (another process, perhaps another kdrt-server, listens there)";
        return proto::Err{"cannot listen on " + host + ":" + std::to_string(port) + ": " + why};
    }
    if (!impl_->http.set_listen_backlog(kListenBacklog))
        return proto::Err{"cannot set the listen backlog of " + host + ":" + std::to_string(port) +
                          ": " + std::strerror(errno)};
    return port;
}

bool HttpServer::serve() { return impl_->http.listen_after_bind(); }

void HttpServer::stop() { impl_->http.stop(); }

std::vector<RouteInfo> HttpServer::routes() const {
    std::vector<RouteInfo> out;
    for (const Impl::Known& k : impl_->known) out.push_back({k.method, k.name});
    return out;
}

void HttpServer::add_route_for_tests(const std::string& path, std::function<void()> action) {
    impl_->http.Get(
        path, [path, action = std::move(action)](const httplib::Request&, httplib::Response& res) {
            request_context().route = path;
            action();
            res.status = 204;
        });
}

std::string httplib_version() { return CPPHTTPLIB_VERSION; }

}  // namespace kdrt::server
