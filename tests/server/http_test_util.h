#pragma once
// Helpers shared by the HTTP integration tests: test meshes, rays, requests.

#include <httplib.h>
#include <sys/socket.h>
#include <sys/wait.h>

#include <cstdio>
#include <string>
#include <utility>
#include <vector>

#include "kdrt/kdtree.h"
#include "kdrt/mesh.h"
#include "kdrt/proto/json_api.h"
#include "kdrt/proto/mesh_io.h"
#include "kdrt/proto/problem.h"
#include "kdrt/proto/ray_batch.h"
#include "kdrt/trace.h"
#include "server_process.h"
#include "test_util.h"

namespace kdrt::test {

inline std::string bytes_to_string(const std::vector<std::byte>& bytes) {
    return {reinterpret_cast<const char*>(bytes.data()), bytes.size()};
}

inline std::vector<std::byte> string_to_bytes(const std::string& text) {
    const auto* p = reinterpret_cast<const std::byte*>(text.data());
    return {p, p + text.size()};
}

inline Mesh load_bunny() {
    auto mesh = proto::load_mesh_file(std::string(KDRT_TEST_DATA_DIR) + "/bunny00.off");
    if (!mesh) throw std::runtime_error(mesh.error().to_string());
    return std::move(*mesh);
}

/// A small random soup that builds in milliseconds (distinct seeds give distinct ids).
inline Mesh small_mesh(uint64_t seed, size_t triangles = 500) {
    Rng rng(seed);
    return random_soup(rng, triangles);
}

/// The mesh as a request body in `format`.
inline std::string mesh_body(const Mesh& mesh, proto::MeshFormat format, bool binary = true) {
    proto::MeshWriteOptions options;
    options.binary = binary;
    return bytes_to_string(proto::write_mesh(mesh, format, options));
}

/// Uploads in raw form; returns the response (status 201/200 expected).
inline httplib::Result upload(httplib::Client& cli, const Mesh& mesh) {
    return cli.Post("/v1/meshes", mesh_body(mesh, proto::MeshFormat::kRaw),
                    "application/x-kdrt-mesh");
}

/// Uploads and returns the id, failing the test on any other status.
inline std::string upload_id(httplib::Client& cli, const Mesh& mesh) {
    auto res = upload(cli, mesh);
    if (!res || (res->status != 201 && res->status != 200)) {
        ADD_FAILURE() << "upload failed: " << (res ? res->status : -1) << " "
                      << (res ? res->body : "");
        return {};
    }
    auto summary = proto::decode_mesh_summary(res->body);
    if (!summary) {
        ADD_FAILURE() << summary.error();
        return {};
    }
    return summary->id;
}

/// Random rays through the box around the mesh: about half hit, some miss.
inline std::vector<Ray> random_rays(const Aabb& bounds, size_t count, uint64_t seed) {
    Rng rng(seed);
    std::vector<Ray> rays(count);
    const Vec3 centre = (bounds.lo + bounds.hi) * 0.5f;
    const Vec3 extent = bounds.extent();
    const Aabb big{centre - extent * 1.5f, centre + extent * 1.5f};
    for (Ray& r : rays) {
        const Vec3 o = rng.in_box(big);
        const Vec3 target = rng.in_box(bounds);
        const Vec3 d = target - o;
        r = Ray{o.x, o.y, o.z, 0.0f, d.x, d.y, d.z, std::numeric_limits<float>::infinity()};
    }
    return rays;
}

/// The body of a problem reply, decoded; fails the test if it is not problem+json with the
/// given status.
/// The KDRH answer the engine gives in-process for `rays` on `mesh`.
inline std::string engine_hits(const Mesh& mesh, const std::vector<Ray>& rays) {
    const KdTree tree = build_kdtree(mesh);
    std::vector<Hit> hits(rays.size());
    intersect(tree, rays, hits);
    return bytes_to_string(proto::encode_hits(hits));
}

/// POST /v1/meshes/{id}/intersect with `rays` as a KDRR body.
inline httplib::Result trace(httplib::Client& cli, const std::string& id,
                             const std::vector<Ray>& rays) {
    return cli.Post("/v1/meshes/" + id + "/intersect",
                    bytes_to_string(proto::encode_rays(rays, false)), "application/x-kdrt-rays");
}

/// Sends all of `data` on a raw socket; false if the connection refused it.
inline bool send_all(int fd, const std::string& data) {
    size_t sent = 0;
    while (sent < data.size()) {
        const ssize_t n = ::send(fd, data.data() + sent, data.size() - sent, MSG_NOSIGNAL);
        if (n <= 0) return false;
        sent += static_cast<size_t>(n);
    }
    return true;
}

/// The whole output (stdout and stderr) of a shell command line, and its exit code.
inline std::pair<int, std::string> run_shell(const std::string& command) {
    FILE* pipe = ::popen((command + " 2>&1").c_str(), "r");
    std::string out;
    char buf[4096];
    size_t n = 0;
    while ((n = std::fread(buf, 1, sizeof buf, pipe)) > 0) out.append(buf, n);
    const int status = ::pclose(pipe);
    return {WIFEXITED(status) ? WEXITSTATUS(status) : -1, out};
}

inline proto::Problem expect_problem(const httplib::Result& res, int status) {
    if (!res) {
        ADD_FAILURE() << "no response (" << httplib::to_string(res.error()) << ")";
        return {};
    }
    EXPECT_EQ(res->status, status) << res->body;
    EXPECT_EQ(res->get_header_value("Content-Type"), "application/problem+json") << res->body;
    auto problem = proto::decode_problem(res->body);
    if (!problem) {
        ADD_FAILURE() << problem.error() << ": " << res->body;
        return {};
    }
    EXPECT_EQ(problem->status(), status);
    EXPECT_FALSE(problem->request_id.empty());
    return std::move(*problem);
}

}  // namespace kdrt::test
