// proto/openapi.yaml matches the server:
//   - the routes the server registers (kdrt::server::HttpServer::routes) are exactly the documented
//     operations, and every documented operation is answered by a real kdrt-server (no "no route"
//     or "method not allowed");
//   - the document's examples, and answers captured from a real server for every route (success
//     and error statuses), validate against its schemas (tests/client/openapi_check.py: python3
//     with python3-yaml and python3-jsonschema).

#include <gtest/gtest.h>

#include <sys/wait.h>

#include <cstdio>
#include <iostream>
#include <nlohmann/json.hpp>
#include <regex>
#include <set>
#include <sstream>
#include <thread>

#include "http/http_server.h"
#include "kdrt/proto/file_io.h"
#include "kdrt/proto/json_api.h"
#include "kdrt/proto/mesh_io.h"
#include "kdrt/proto/ray_batch.h"
#include "server_process.h"
#include "service.h"
#include "test_util.h"

namespace kdrt::test {
namespace {

using Operation = std::pair<std::string, std::string>;  // method (upper case), path template

std::string openapi_path() { return std::string(KDRT_SOURCE_DIR) + "/proto/openapi.yaml"; }

std::string read_text(const std::string& path) {
    auto bytes = proto::read_file_bytes(path);
    if (!bytes) throw std::runtime_error(bytes.error());
    return {reinterpret_cast<const char*>(bytes->data()), bytes->size()};
}

/// The operations under `paths:` of the document, read from its layout (two-space indents:
/// "  /path:" then "    get:"), which a YAML library is not needed for.
std::set<Operation> documented_operations(const std::string& yaml) {
    std::set<Operation> out;
    std::istringstream in(yaml);
    const std::regex path_line(R"(^  (/[^:\s]*):\s*$)");
    const std::regex method_line(R"(^    (get|put|post|delete|patch|head|options|trace):\s*$)");
    bool in_paths = false;
    std::string path;
    for (std::string line; std::getline(in, line);) {
        if (!line.empty() && line[0] != ' ' && line[0] != '#') {
            in_paths = line.rfind("paths:", 0) == 0;
            continue;
        }
        if (!in_paths) continue;
        std::smatch m;
        if (std::regex_match(line, m, path_line)) {
            path = m[1];
        } else if (!path.empty() && std::regex_match(line, m, method_line)) {
            std::string method = m[1];
            for (char& c : method)
                c = static_cast<char>(std::toupper(static_cast<unsigned char>(c)));
            out.emplace(method, path);
        }
    }
    return out;
}

TEST(OpenApiRoutes, DocumentedOperationsAreExactlyTheServersRoutes) {
    const std::set<Operation> documented = documented_operations(read_text(openapi_path()));
    TempDir dir;
    server::ServerConfig config;
    config.cache_dir = (dir.path() / "cache").string();
    config.threads = 1;
    server::Service service(config);
    server::HttpServer http(service);
    std::set<Operation> served;
    for (const server::RouteInfo& route : http.routes()) served.emplace(route.method, route.path);
    ASSERT_GE(served.size(), 12u);
    ASSERT_GE(documented.size(), 12u);
    for (const Operation& op : served)
        EXPECT_TRUE(documented.count(op))
            << op.first << " " << op.second << " is served but not in proto/openapi.yaml";
    for (const Operation& op : documented)
        EXPECT_TRUE(served.count(op))
            << op.first << " " << op.second << " is in proto/openapi.yaml but not served";
}

TEST(OpenApiRoutes, EveryDocumentedOperationIsAnsweredByTheServer) {
    TempDir dir;
    ServerProcess server({.cache_dir = dir.path() / "cache"});
    auto cli = server.client();
    for (const auto& [method, route] : documented_operations(read_text(openapi_path()))) {
        SCOPED_TRACE(method + " " + route);
        const std::string path = std::regex_replace(
            std::regex_replace(route, std::regex(R"(\{id\})"), std::string(32, '0')),
            std::regex(R"(\{file\})"), "viewer.js");
        httplib::Result res = method == "GET"      ? cli->Get(path)
                              : method == "DELETE" ? cli->Delete(path)
                                                   : cli->Post(path, "{}", "application/json");
        ASSERT_TRUE(res) << httplib::to_string(res.error());
        EXPECT_NE(res->status, 405) << res->body;
        EXPECT_EQ(res->body.find("urn:kdrt:problem:not-found"), std::string::npos) << res->body;
    }
}

/// Answers captured from a live server, as openapi_check.py reads them.
class Captures {
public:
    void add(const std::string& method, const std::string& route, const httplib::Result& res) {
        if (!res) {
            ADD_FAILURE() << method << " " << route << ": " << httplib::to_string(res.error());
            return;
        }
        nlohmann::json capture;
        capture["method"] = method;
        capture["route"] = route;
        capture["status"] = res->status;
        capture["content_type"] = res->get_header_value("Content-Type");
        const bool text =
            capture["content_type"].get<std::string>().find("json") != std::string::npos;
        capture["body"] = text ? res->body : std::string(res->body.empty() ? "" : "<binary>");
        statuses_.insert(method + " " + route + " " + std::to_string(res->status));
        list_.push_back(std::move(capture));
    }
    [[nodiscard]] bool has(const std::string& method_route_status) const {
        return statuses_.count(method_route_status);
    }
    [[nodiscard]] std::string json() const { return list_.dump(1); }

private:
    nlohmann::json list_ = nlohmann::json::array();
    std::set<std::string> statuses_;
};

std::string as_string(const std::vector<std::byte>& bytes) {
    return {reinterpret_cast<const char*>(bytes.data()), bytes.size()};
}

/// Runs the checker on `captures`; returns its exit status and output.
std::pair<int, std::string> run_checker(const std::string& captures_path) {
    const std::string command = std::string(KDRT_PYTHON) + " " + KDRT_SOURCE_DIR +
                                "/tests/client/openapi_check.py " + openapi_path() + " " +
                                captures_path + " 2>&1";
    std::string output;
    FILE* pipe = ::popen(command.c_str(), "r");
    if (!pipe) return {-1, "cannot run " + command};
    char buf[4096];
    while (size_t n = std::fread(buf, 1, sizeof buf, pipe)) output.append(buf, n);
    const int status = ::pclose(pipe);
    return {WIFEXITED(status) ? WEXITSTATUS(status) : -1, output};
}

TEST(OpenApiSchemas, ExamplesAndLiveAnswersValidate) {
    TempDir dir;
    ServerProcess server({.cache_dir = dir.path() / "cache", .args = {"--max-jobs", "4"}});
    ServerProcess limited({.cache_dir = dir.path() / "cache2",
                           .args = {"--token", "tok", "--max-upload-bytes", "1024", "--max-rays",
                                    "10", "--max-json-rays", "5"}});
    auto cli = server.client();
    Captures c;
    Rng rng(test_seed());
    const Mesh mesh = random_soup(rng, 300);
    const std::string raw = as_string(proto::write_mesh(mesh, proto::MeshFormat::kRaw));

    // Meshes.
    auto created = cli->Post("/v1/meshes", raw, "application/x-kdrt-mesh");
    c.add("POST", "/v1/meshes", created);
    ASSERT_TRUE(created && created->status == 201) << (created ? created->body : "");
    const std::string id = proto::decode_mesh_summary(created->body)->id;
    c.add("POST", "/v1/meshes", cli->Post("/v1/meshes", raw, "application/x-kdrt-mesh"));
    c.add("POST", "/v1/meshes", cli->Post("/v1/meshes", "v 0 0 0\nf 1 2 3\n", "model/obj"));
    c.add("POST", "/v1/meshes", cli->Post("/v1/meshes", "# nothing\n", "model/obj"));
    c.add("POST", "/v1/meshes", cli->Post("/v1/meshes", "hello", "text/plain"));
    c.add("POST", "/v1/meshes", cli->Post("/v1/meshes?format=fbx", "hello", "text/plain"));
    c.add("GET", "/v1/meshes", cli->Get("/v1/meshes"));
    c.add("GET", "/v1/meshes/{id}", cli->Get("/v1/meshes/" + id));
    c.add("GET", "/v1/meshes/{id}", cli->Get("/v1/meshes/" + std::string(64, 'a')));
    c.add("GET", "/v1/meshes/{id}", cli->Get("/v1/meshes/not-an-id"));

    // Rays.
    const std::string intersect = "/v1/meshes/" + id + "/intersect";
    const std::string json_rays =
        R"({"rays": [[0.5, 0.5, -3, 0, 0, 1], [9, 9, 9, 1, 0, 0, 0, 5]]})";
    c.add("POST", "/v1/meshes/{id}/intersect", cli->Post(intersect, json_rays, "application/json"));
    c.add("POST", "/v1/meshes/{id}/intersect",
          cli->Post(intersect, R"({"rays": [[0.5, 0.5, -3, 0, 0, 1]], "occlusion": true})",
                    "application/json"));
    const std::vector<Ray> rays(4, Ray{0.5f, 0.5f, -3, 0, 0, 0, 1, INFINITY});
    c.add("POST", "/v1/meshes/{id}/intersect",
          cli->Post(intersect, as_string(proto::encode_rays(rays, false)),
                    "application/x-kdrt-rays"));
    c.add(
        "POST", "/v1/meshes/{id}/intersect",
        cli->Post(intersect, as_string(proto::encode_rays(rays, true)), "application/x-kdrt-rays"));
    c.add("POST", "/v1/meshes/{id}/intersect",
          cli->Post(intersect, "ABCDxxxxxxxxxxxxxxxx", "application/x-kdrt-rays"));
    c.add("POST", "/v1/meshes/{id}/intersect",
          cli->Post(intersect, R"({"rays": [[1, 2]]})", "application/json"));
    c.add("POST", "/v1/meshes/{id}/intersect", cli->Post(intersect, "{", "application/json"));
    c.add("POST", "/v1/meshes/{id}/intersect", cli->Post(intersect, "x", "text/plain"));
    c.add("POST", "/v1/meshes/{id}/intersect",
          cli->Post("/v1/meshes/" + std::string(64, 'b') + "/intersect", json_rays,
                    "application/json"));

    // Every hit along a ray.
    const std::string all = "/v1/meshes/" + id + "/intersect_all";
    const std::string kdrr = as_string(proto::encode_rays(rays, false));
    for (const char* query : {"", "?count_only=true", "?fields=t_prim&normal=true&point=true",
                              "?max_hits=0", "?fields=uv"})
        c.add("POST", "/v1/meshes/{id}/intersect_all",
              cli->Post(all + query, kdrr, "application/x-kdrt-rays"));
    c.add("POST", "/v1/meshes/{id}/intersect_all",
          cli->Post(all, as_string(proto::encode_rays(rays, true)), "application/x-kdrt-rays"));
    c.add("POST", "/v1/meshes/{id}/intersect_all", cli->Post(all, "{}", "application/json"));
    c.add("POST", "/v1/meshes/{id}/intersect_all",
          cli->Post("/v1/meshes/" + std::string(64, 'b') + "/intersect_all", kdrr,
                    "application/x-kdrt-rays"));

    // Sensor scans.
    const std::string scan = "/v1/meshes/" + id + "/scan";
    const std::string pin =
        R"({"pinhole": {"intrinsics": {"fx": 20, "fy": 20, "cx": 8, "cy": 6, "width": 16, )"
        R"("height": 12}, "pose": [[1,0,0,0.5],[0,1,0,0.5],[0,0,1,-3],[0,0,0,1]], "normals": true})";
    const std::string lid =
        R"({"lidar": {"vertical_fov": [-20, 20], "channels": 8, "azimuth_steps": 32, )"
        R"("returns": 2, "pose": [[1,0,0,0.5],[0,1,0,0.5],[0,0,1,0.5],[0,0,0,1]]})";
    for (const std::string format : {"binary", "exr"})
        c.add("POST", "/v1/meshes/{id}/scan",
              cli->Post(scan, pin + R"(, "format": ")" + format + R"("})", "application/json"));
    for (const std::string format : {"binary", "ply"})
        c.add("POST", "/v1/meshes/{id}/scan",
              cli->Post(scan, lid + R"(, "format": ")" + format + R"("})", "application/json"));
    c.add("POST", "/v1/meshes/{id}/scan",
          cli->Post(scan, R"({"lidar": {"elevation_deg": [0], "azimuth_steps": 4, "pose": 1}})",
                    "application/json"));
    c.add("POST", "/v1/meshes/{id}/scan",
          cli->Post(scan,
                    R"({"lidar": {"elevation_deg": [0], "azimuth_steps": 4, "returns": 99999}})",
                    "application/json"));
    c.add("POST", "/v1/meshes/{id}/scan", cli->Post(scan, pin + "}", "text/plain"));
    c.add("POST", "/v1/meshes/{id}/scan",
          cli->Post("/v1/meshes/" + std::string(64, 'b') + "/scan", pin + "}", "application/json"));

    // Renders and jobs.
    const std::string small = R"({"mesh": ")" + id + R"(", "width": 32, "height": 24)";
    for (const char* format : {"png", "jpg", "exr"})
        c.add("POST", "/v1/render",
              cli->Post("/v1/render", small + R"(, "format": ")" + format + "\"}",
                        "application/json"));
    c.add("POST", "/v1/render",
          cli->Post("/v1/render", R"({"mesh": ")" + id + R"(", "spp": 0})", "application/json"));
    c.add("POST", "/v1/render",
          cli->Post("/v1/render", R"({"mesh": ")" + std::string(64, 'c') + "\"}",
                    "application/json"));
    c.add("POST", "/v1/render", cli->Post("/v1/render", "{}", "text/plain"));
    const httplib::Headers async = {{"Prefer", "respond-async"}};
    auto queued = cli->Post("/v1/render", async, small + "}", "application/json");
    c.add("POST", "/v1/render", queued);
    ASSERT_TRUE(queued && queued->status == 202) << (queued ? queued->body : "");
    const std::string job = proto::decode_job_status(queued->body)->id;
    for (int i = 0; i < 600; ++i) {  // bounded: 60 s
        auto status = cli->Get("/v1/jobs/" + job);
        ASSERT_TRUE(status);
        if (proto::decode_job_status(status->body)->state == proto::JobState::kDone) {
            c.add("GET", "/v1/jobs/{id}", status);
            break;
        }
        std::this_thread::sleep_for(std::chrono::milliseconds(100));
    }
    c.add("GET", "/v1/jobs/{id}/result", cli->Get("/v1/jobs/" + job + "/result"));
    c.add("DELETE", "/v1/jobs/{id}", cli->Delete("/v1/jobs/" + job));
    c.add("GET", "/v1/jobs/{id}", cli->Get("/v1/jobs/" + job));
    c.add("GET", "/v1/jobs/{id}/result", cli->Get("/v1/jobs/" + job + "/result"));
    c.add("DELETE", "/v1/jobs/{id}", cli->Delete("/v1/jobs/" + job));
    // A long job: its result is not there yet (409) and deleting it cancels it (202).
    auto slow = cli->Post(
        "/v1/render", async,
        R"({"mesh": ")" + id + R"(", "width": 2048, "height": 2048, "shading": "ao", "spp": 64})",
        "application/json");
    c.add("POST", "/v1/render", slow);
    ASSERT_TRUE(slow && slow->status == 202);
    const std::string slow_job = proto::decode_job_status(slow->body)->id;
    c.add("GET", "/v1/jobs/{id}/result", cli->Get("/v1/jobs/" + slow_job + "/result"));
    c.add("DELETE", "/v1/jobs/{id}", cli->Delete("/v1/jobs/" + slow_job));

    // Operations, and deleting the mesh.
    c.add("GET", "/healthz", cli->Get("/healthz"));
    c.add("GET", "/readyz", cli->Get("/readyz"));
    c.add("GET", "/metrics", cli->Get("/metrics"));
    c.add("DELETE", "/v1/meshes/{id}", cli->Delete("/v1/meshes/" + id));
    c.add("DELETE", "/v1/meshes/{id}", cli->Delete("/v1/meshes/" + id));

    // Authentication and limits (the second server).
    auto guarded = limited.client();
    c.add("GET", "/v1/meshes", guarded->Get("/v1/meshes"));
    c.add("POST", "/v1/meshes", guarded->Post("/v1/meshes", raw, "application/x-kdrt-mesh"));
    guarded->set_bearer_token_auth("tok");
    c.add("POST", "/v1/meshes", guarded->Post("/v1/meshes", raw, "application/x-kdrt-mesh"));
    const std::string tiny =
        as_string(proto::write_mesh(random_soup(rng, 4), proto::MeshFormat::kRaw));
    auto tiny_created = guarded->Post("/v1/meshes", tiny, "application/x-kdrt-mesh");
    c.add("POST", "/v1/meshes", tiny_created);
    ASSERT_TRUE(tiny_created && tiny_created->status == 201)
        << (tiny_created ? tiny_created->body : "");
    const std::string tiny_intersect =
        "/v1/meshes/" + proto::decode_mesh_summary(tiny_created->body)->id + "/intersect";
    std::string too_many = as_string(proto::encode_rays(std::vector<Ray>(4), false));
    too_many[8] = 11;  // the header claims 11 rays: over max_rays before the length is checked
    c.add("POST", "/v1/meshes/{id}/intersect",
          guarded->Post(tiny_intersect, too_many, "application/x-kdrt-rays"));
    c.add(
        "POST", "/v1/meshes/{id}/intersect",
        guarded->Post(
            tiny_intersect,
            R"({"rays": [[0,0,0,1,0,0],[0,0,0,1,0,0],[0,0,0,1,0,0],[0,0,0,1,0,0],[0,0,0,1,0,0],[0,0,0,1,0,0]]})",
            "application/json"));

    // The captures cover every documented success and the main errors of each route.
    for (const char* expected : {"POST /v1/meshes 201",
                                 "POST /v1/meshes 200",
                                 "POST /v1/meshes 401",
                                 "POST /v1/meshes 413",
                                 "POST /v1/meshes 415",
                                 "POST /v1/meshes 422",
                                 "GET /v1/meshes 200",
                                 "GET /v1/meshes 401",
                                 "GET /v1/meshes/{id} 200",
                                 "GET /v1/meshes/{id} 404",
                                 "DELETE /v1/meshes/{id} 204",
                                 "DELETE /v1/meshes/{id} 404",
                                 "POST /v1/meshes/{id}/intersect 200",
                                 "POST /v1/meshes/{id}/intersect 400",
                                 "POST /v1/meshes/{id}/intersect 404",
                                 "POST /v1/meshes/{id}/intersect 413",
                                 "POST /v1/meshes/{id}/intersect 415",
                                 "POST /v1/render 200",
                                 "POST /v1/render 202",
                                 "POST /v1/render 400",
                                 "POST /v1/render 404",
                                 "POST /v1/render 415",
                                 "GET /v1/jobs/{id} 200",
                                 "GET /v1/jobs/{id} 404",
                                 "DELETE /v1/jobs/{id} 202",
                                 "DELETE /v1/jobs/{id} 204",
                                 "DELETE /v1/jobs/{id} 404",
                                 "GET /v1/jobs/{id}/result 200",
                                 "GET /v1/jobs/{id}/result 404",
                                 "GET /v1/jobs/{id}/result 409",
                                 "GET /healthz 200",
                                 "GET /readyz 200",
                                 "GET /metrics 200"})
        EXPECT_TRUE(c.has(expected)) << expected;

    const std::string captures_path = (dir.path() / "captures.json").string();
    const std::string text = c.json();
    ASSERT_TRUE(
        proto::write_file_bytes(captures_path, std::as_bytes(std::span(text.data(), text.size()))));
    const auto [status, output] = run_checker(captures_path);
    EXPECT_EQ(status, 0)
        << output << "(" << KDRT_PYTHON
        << " needs the yaml and jsonschema modules: Debian python3-yaml python3-jsonschema)";
    EXPECT_NE(output.find("answers checked, 0 problems"), std::string::npos) << output;
    std::cout << output;  // the checker's summary line
}

}  // namespace
}  // namespace kdrt::test
