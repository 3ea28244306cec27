// Scale-out: nginx (Debian's, with the routing of docker/nginx/) in front of kdrt-server
// replicas sharing one store directory, all on loopback (docs/scale-out.md).

#include <netinet/in.h>
#include <signal.h>
#include <spawn.h>
#include <sys/socket.h>
#include <sys/wait.h>
#include <unistd.h>

#include <atomic>
#include <cstring>
#include <fstream>
#include <functional>
#include <map>
#include <set>
#include <thread>

#include <gtest/gtest.h>

#include "http_test_util.h"
#include "kdrt/client/client.h"
#include "kdrt/proto/mesh_id.h"
#include "kdrt/proto/raw_image.h"
#include "kdrt/proto/ray_batch_codec.h"
#include "kdrt/proto/scene.h"
#include "kdrt/scene.h"

extern char** environ;

namespace kdrt::test {
namespace {

namespace fs = std::filesystem;
using kdrt::Client;
using kdrt::ClientOptions;
constexpr const char* kNginx = "/usr/sbin/nginx";

/// A free loopback port (bound and released: nginx cannot report a port 0 bind).
int free_port() {
    const int fd = ::socket(AF_INET, SOCK_STREAM, 0);
    sockaddr_in addr{};
    addr.sin_family = AF_INET;
    addr.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
    addr.sin_port = 0;
    ::bind(fd, reinterpret_cast<sockaddr*>(&addr), sizeof addr);
    socklen_t len = sizeof addr;
    ::getsockname(fd, reinterpret_cast<sockaddr*>(&addr), &len);
    ::close(fd);
    return ntohs(addr.sin_port);
}

/// nginx in the foreground with the shipped routing files and upstreams for `replicas`.
class Nginx {
public:
    Nginx(const fs::path& dir, const std::vector<std::pair<std::string, int>>& replicas)
        : dir_(dir) {
        fs::create_directories(dir_ / "temp");
        port_ = free_port();
        const std::string source = KDRT_SOURCE_DIR;
        std::string servers, replica_upstreams, job_map;
        for (const auto& [name, port] : replicas) {
            const std::string address = "127.0.0.1:" + std::to_string(port);
            servers += "        server " + address + " max_fails=1 fail_timeout=5s;\n";
            replica_upstreams += "    upstream kdrt_replica_" + name + " { server " + address +
                                 "; keepalive 4; keepalive_timeout 1s; }\n";
            job_map += "        " + name + " kdrt_replica_" + name + ";\n";
        }
        const std::string temp = (dir_ / "temp").string();
        std::ofstream conf(dir_ / "nginx.conf");
        conf << (::geteuid() == 0 ? "user root;\n" : "") << "daemon off;\nmaster_process on;\n"
             << "worker_processes 2;\npid " << (dir_ / "nginx.pid").string() << ";\n"
             << "error_log " << (dir_ / "error.log").string() << " warn;\n"
             << "events { worker_connections 1024; }\nhttp {\n    access_log off;\n"
             << "    client_body_temp_path " << temp << "/body;\n"
             << "    proxy_temp_path " << temp << "/proxy;\n"
             << "    fastcgi_temp_path " << temp << "/fastcgi;\n"
             << "    uwsgi_temp_path " << temp << "/uwsgi;\n"
             << "    scgi_temp_path " << temp << "/scgi;\n"
             << "    include " << source << "/docker/nginx/kdrt-http.conf;\n"
             << "    upstream kdrt_mesh {\n        hash $kdrt_route_key consistent;\n"
             << servers << "        keepalive 16;\n        keepalive_timeout 1s;\n    }\n"
             << "    upstream kdrt_any {\n        least_conn;\n"
             << servers << "        keepalive 16;\n        keepalive_timeout 1s;\n    }\n"
             << replica_upstreams << "    map $kdrt_job_replica $kdrt_job_upstream {\n"
             << "        default kdrt_any;\n"
             << job_map << "    }\n"
             << "    server {\n        listen 127.0.0.1:" << port_ << ";\n"
             << "        include " << source << "/docker/nginx/kdrt-locations.conf;\n    }\n}\n";
        conf.close();
        const std::string conf_path = (dir_ / "nginx.conf").string();
        const std::string error_log = (dir_ / "error.log").string();
        const std::string prefix = dir_.string() + "/";
        std::vector<std::string> args = {kNginx, "-p", prefix, "-e", error_log, "-c", conf_path};
        std::vector<char*> argv;
        for (auto& a : args) argv.push_back(a.data());
        argv.push_back(nullptr);
        if (::posix_spawn(&pid_, kNginx, nullptr, nullptr, argv.data(), environ) != 0) {
            ADD_FAILURE() << "cannot start " << kNginx << " (scripts/deps.sh installs nginx)";
            pid_ = -1;
            return;
        }
        for (int i = 0; i < 200; ++i) {
            httplib::Client cli("127.0.0.1", port_);
            cli.set_connection_timeout(std::chrono::milliseconds(200));
            if (auto res = cli.Get("/healthz"); res && res->status == 200) return;
            int status = 0;
            if (::waitpid(pid_, &status, WNOHANG) == pid_) break;
            std::this_thread::sleep_for(std::chrono::milliseconds(50));
        }
        std::ifstream log(dir_ / "error.log");
        ADD_FAILURE() << "nginx did not come up: "
                      << std::string(std::istreambuf_iterator<char>(log), {});
    }
    ~Nginx() {
        if (pid_ <= 0) return;
        ::kill(pid_, SIGQUIT);
        int status = 0;
        ::waitpid(pid_, &status, 0);
    }
    Nginx(const Nginx&) = delete;
    Nginx& operator=(const Nginx&) = delete;
    [[nodiscard]] int port() const noexcept { return port_; }
    [[nodiscard]] std::unique_ptr<httplib::Client> client() const {
        auto cli = std::make_unique<httplib::Client>("127.0.0.1", port_);
        cli->set_read_timeout(std::chrono::seconds(60));
        cli->set_keep_alive(true);
        return cli;
    }

private:
    fs::path dir_;
    int port_ = 0;
    pid_t pid_ = -1;
};

/// `request` until it gets an answer that is not a gateway or availability error (a client
/// behind a proxy retries those: the kdrt client does).
template <typename F>
httplib::Result retrying(F&& request, int* retries = nullptr) {
    for (int attempt = 0;; ++attempt) {
        httplib::Result res = request();
        const bool retry = !res || res->status == 502 || res->status == 503 || res->status == 504;
        if (!retry || attempt == 50) return res;
        if (retries) ++*retries;
        std::this_thread::sleep_for(std::chrono::milliseconds(100));
    }
}

class ScaleOut : public ::testing::Test {
protected:
    void SetUp() override {
        store_ = dir_.path() / "store";
        for (int i = 0; i < 3; ++i) add_replica();
    }
    void add_replica() {
        std::string name = std::to_string(replicas_.size());
        name.insert(0, 1, 'r');
        replicas_.push_back(std::make_unique<ServerProcess>(ServerProcess::Options{
            .cache_dir = store_,
            .args = {"--replica", name, "--keep-alive-timeout-s", "3", "--memory-budget", "64M"}}));
        names_.push_back(name);
    }
    std::vector<std::pair<std::string, int>> upstreams() const {
        std::vector<std::pair<std::string, int>> out;
        for (size_t i = 0; i < replicas_.size(); ++i)
            if (replicas_[i]->running()) out.emplace_back(names_[i], replicas_[i]->port());
        return out;
    }
    std::unique_ptr<Nginx> start_nginx() {
        return std::make_unique<Nginx>(dir_.path() / ("nginx" + std::to_string(++nginx_count_)),
                                       upstreams());
    }
    /// Traces (through `cli`) of mesh `id` counted by each replica's metrics.
    double traces_on(size_t replica) const {
        return replicas_[replica]
            ->metric(
                "kdrt_http_requests_total{route=\"/v1/meshes/{id}/intersect\",method=\"POST\","
                "status=\"200\"}")
            .value_or(0);
    }
    /// `value()` once it equals `expected`, else its value after 5 s. The per-request counters
    /// are updated just after the answer is sent, so a client may see the answer first.
    template <typename F>
    static double counted(F&& value, double expected) {
        double now = value();
        for (int i = 0; i < 100 && now != expected; ++i) {
            std::this_thread::sleep_for(std::chrono::milliseconds(50));
            now = value();
        }
        return now;
    }
    /// A mesh uploaded through `cli` whose split keys "<id>.0" .. "<id>.<parts - 1>" do not all
    /// hash to one replica, and the replica of each key (asked of nginx: the X-Kdrt-Replica of a
    /// GET of the mesh with ?route=KEY). The ring depends on the replicas' ephemeral ports: six
    /// keys all land on one of three replicas for one mesh in 243, so such a mesh is replaced by
    /// another (the spread is what the split tests check, not the ring's luck).
    static std::pair<Mesh, std::string> spread_mesh(httplib::Client& cli, uint64_t seed,
                                                    size_t triangles, unsigned parts,
                                                    std::vector<std::string>& key_replicas) {
        key_replicas.assign(parts, "");
        for (uint64_t attempt = 0; attempt < 8; ++attempt) {
            Mesh mesh = small_mesh(seed + attempt, triangles);
            std::string id = upload_id(cli, mesh);
            for (unsigned k = 0; k < parts; ++k) {
                auto res = retrying([&] {
                    return cli.Get("/v1/meshes/" + id + "?route=" + id + "." + std::to_string(k));
                });
                EXPECT_TRUE(res && res->status == 200) << (res ? res->body : "no answer");
                key_replicas[k] = res ? res->get_header_value("X-Kdrt-Replica") : "";
            }
            if (std::set<std::string>(key_replicas.begin(), key_replicas.end()).size() > 1)
                return {std::move(mesh), std::move(id)};
        }
        ADD_FAILURE() << "8 meshes' split keys all hashed to one replica";
        return {};
    }
    /// Which replica answers GET /v1/meshes/{id} through nginx.
    static std::string owner(httplib::Client& cli, const std::string& id) {
        auto res = retrying([&] { return cli.Get("/v1/meshes/" + id); });
        EXPECT_TRUE(res && res->status == 200) << (res ? res->body : "no answer");
        return res ? res->get_header_value("X-Kdrt-Replica") : "";
    }

    TempDir dir_;
    fs::path store_;
    std::vector<std::unique_ptr<ServerProcess>> replicas_;
    std::vector<std::string> names_;
    int nginx_count_ = 0;
};

TEST_F(ScaleOut, EveryRequestForAMeshLandsOnOneReplica) {
    auto nginx = start_nginx();
    auto cli = nginx->client();
    std::vector<Mesh> meshes;
    std::vector<std::string> ids;
    for (int m = 0; m < 12; ++m) {
        meshes.push_back(small_mesh(9000 + m, 200));
        ids.push_back(upload_id(*cli, meshes.back()));
    }
    std::map<std::string, double> expected_traces;  // per replica name
    std::set<std::string> used;
    for (size_t m = 0; m < ids.size(); ++m) {
        const auto rays = random_rays(mesh_bounds(meshes[m]), 64, 5 + m);
        std::string replica;
        for (int k = 0; k < 4; ++k) {
            auto res = trace(*cli, ids[m], rays);
            ASSERT_TRUE(res);
            ASSERT_EQ(res->status, 200) << res->body;
            EXPECT_EQ(res->body, engine_hits(meshes[m], rays));
            const std::string served_by = res->get_header_value("X-Kdrt-Replica");
            if (k == 0) replica = served_by;
            EXPECT_EQ(served_by, replica) << "mesh " << ids[m] << " moved between replicas";
        }
        expected_traces[replica] += 4;
        used.insert(replica);
    }
    // The replicas' own counts agree: each traced exactly the meshes that hash to it.
    for (size_t r = 0; r < replicas_.size(); ++r)
        EXPECT_EQ(counted([&] { return traces_on(r); }, expected_traces[names_[r]]),
                  expected_traces[names_[r]])
            << names_[r];
    EXPECT_GT(used.size(), 1u) << "12 meshes all hashed to one replica";
    // Every replica lists every mesh (the store is the index), whichever replica stored it.
    for (const auto& replica : replicas_) {
        auto res = replica->client()->Get("/v1/meshes");
        ASSERT_TRUE(res);
        auto listed = proto::decode_mesh_list(res->body);
        ASSERT_TRUE(listed) << res->body;
        std::set<std::string> listed_ids;
        for (const auto& s : *listed) listed_ids.insert(s.id);
        for (const std::string& id : ids) EXPECT_TRUE(listed_ids.count(id)) << id;
    }
}

TEST_F(ScaleOut, ASplitBatchSpreadsOverReplicasAndEqualsTheOneReplicaAnswer) {
    auto nginx = start_nginx();
    std::vector<std::string> key_replicas;
    const auto [mesh, id] = spread_mesh(*nginx->client(), 9050, 2000, 6, key_replicas);
    ASSERT_FALSE(id.empty());
    const auto rays = random_rays(mesh_bounds(mesh), 60000, 17);
    // The answer of one replica, asked directly, unsplit.
    auto direct = trace(*replicas_[0]->client(), id, rays);
    ASSERT_TRUE(direct);
    ASSERT_EQ(direct->status, 200) << direct->body;

    // The direct trace is counted on replica 0 (the replicas are new: nothing else was traced).
    EXPECT_EQ(counted([&] { return traces_on(0); }, 1.0), 1.0);
    std::vector<double> before;
    for (size_t r = 0; r < replicas_.size(); ++r) before.push_back(traces_on(r));
    ClientOptions options;
    options.split = 6;
    Client client("http://127.0.0.1:" + std::to_string(nginx->port()), options);
    auto hits = client.intersect(id, rays);
    ASSERT_TRUE(hits) << hits.error().to_string();
    EXPECT_EQ(bytes_to_string(proto::encode_hits(*hits)), direct->body);
    const auto parts_served = [&] {
        double parts = 0;
        for (size_t r = 0; r < replicas_.size(); ++r) parts += traces_on(r) - before[r];
        return parts;
    };
    EXPECT_EQ(counted(parts_served, 6.0), 6.0);
    int serving = 0;
    for (size_t r = 0; r < replicas_.size(); ++r) serving += traces_on(r) - before[r] > 0;
    EXPECT_GT(serving, 1) << "all six parts hashed to one replica";
}

/// Images a replica rendered (kdrt_renders_total: counted before the answer is sent, so a
/// client that has its answer sees it counted; the per-request counters follow the answer).
double renders_on(const ServerProcess& replica) {
    return replica.metric("kdrt_renders_total").value_or(0);
}

TEST_F(ScaleOut, ASplitRenderSpreadsOverReplicasAndEqualsTheOneReplicaFrame) {
    constexpr unsigned kParts = 6;
    auto nginx = start_nginx();
    auto cli = nginx->client();
    // The replica each band's routing key "<id>.<k>" hashes to.
    std::vector<std::string> band_replica;
    const auto [mesh, id] = spread_mesh(*cli, 9600, 1500, kParts, band_replica);
    ASSERT_FALSE(id.empty());
    const std::set<std::string> expected_replicas(band_replica.begin(), band_replica.end());

    // The frame of one replica, asked directly and unsplit.
    const std::string request = "{\"mesh\":\"" + id + "\",\"width\":96,\"height\":64}";
    auto direct = replicas_[0]->client()->Post("/v1/render", request, "application/json");
    ASSERT_TRUE(direct);
    ASSERT_EQ(direct->status, 200) << direct->body;
    ASSERT_EQ(direct->get_header_value("Content-Type"), "image/png");
    auto direct_raw = replicas_[0]->client()->Post(
        "/v1/render", "{\"mesh\":\"" + id + "\",\"width\":96,\"height\":64,\"format\":\"raw\"}",
        "application/json");
    ASSERT_TRUE(direct_raw);
    ASSERT_EQ(direct_raw->status, 200) << direct_raw->body;
    auto whole = proto::decode_raw_image(string_to_bytes(direct_raw->body));
    ASSERT_TRUE(whole) << whole.error();

    const auto served_since = [&](const std::vector<double>& before) {
        std::map<std::string, double> served;
        for (size_t r = 0; r < replicas_.size(); ++r) {
            const double n = renders_on(*replicas_[r]) - before[r];
            if (n != 0) served[names_[r]] = n;
        }
        return served;
    };
    std::map<std::string, double> expected_served;
    for (const std::string& replica : band_replica) ++expected_served[replica];
    std::vector<double> before;
    for (const auto& replica : replicas_) before.push_back(renders_on(*replica));

    // The kdrt CLI through nginx: the PNG is the one replica's file, byte for byte.
    const fs::path out = dir_.path() / "split.png";
    const std::string url = "http://127.0.0.1:" + std::to_string(nginx->port());
    const auto [code, output] =
        run_shell(std::string("env -u KDRT_TOKEN -u KDRT_SERVER ") + KDRT_CLI_BINARY +
                  " --server " + url + " render " + id + " -o " + out.string() +
                  " --size 96x64 --split " + std::to_string(kParts) + " --quiet --json");
    ASSERT_EQ(code, 0) << output;
    // --quiet: no progress; --json: the summary alone, with the parts and replicas that served.
    EXPECT_NE(
        output.find("\"parts\":6,\"replicas\":" + std::to_string(expected_replicas.size()) + ","),
        std::string::npos)
        << output;
    std::ifstream file(out, std::ios::binary);
    const std::string png(std::istreambuf_iterator<char>(file), {});
    EXPECT_EQ(png.size(), direct->body.size());
    EXPECT_TRUE(png == direct->body) << "the split render's PNG differs from the one replica's";
    // Each band was rendered by the replica its key hashes to: more than one served the frame.
    EXPECT_EQ(served_since(before), expected_served);

    // The client library: the stitched float pixels are the one replica's, bit for bit, and
    // each band's answer names the replica its key hashes to.
    before.clear();
    for (const auto& replica : replicas_) before.push_back(renders_on(*replica));
    Client client(url);
    RenderRequest split_request;
    split_request.mesh = id;
    split_request.settings.width = 96;
    split_request.settings.height = 64;
    auto frame = client.render_split(split_request, kParts);
    ASSERT_TRUE(frame) << frame.error().to_string();
    EXPECT_EQ(frame->replicas, band_replica);
    EXPECT_EQ(frame->image.width, whole->image.width);
    EXPECT_EQ(frame->image.height, whole->image.height);
    EXPECT_EQ(frame->image.channels, whole->image.channels);
    ASSERT_EQ(frame->image.pixels.size(), whole->image.pixels.size());
    EXPECT_EQ(std::memcmp(frame->image.pixels.data(), whole->image.pixels.data(),
                          whole->image.pixels.size() * sizeof(float)),
              0);
    EXPECT_EQ(served_since(before), expected_served);
}

TEST_F(ScaleOut, AsyncJobsAreRoutedToTheReplicaThatRunsThem) {
    auto nginx = start_nginx();
    auto cli = nginx->client();
    const std::string id = upload_id(*cli, small_mesh(9100, 300));
    std::set<std::string> replicas_seen;
    for (int j = 0; j < 6; ++j) {
        httplib::Headers headers = {{"Prefer", "respond-async"}};
        auto res =
            cli->Post("/v1/render", headers, "{\"mesh\":\"" + id + "\",\"width\":16,\"height\":16}",
                      "application/json");
        ASSERT_TRUE(res);
        ASSERT_EQ(res->status, 202) << res->body;
        const std::string job = proto::decode_job_status(res->body)->id;
        const std::string replica = res->get_header_value("X-Kdrt-Replica");
        replicas_seen.insert(replica);
        EXPECT_EQ(job.substr(0, job.find('.')), replica);
        for (int poll = 0; poll < 200; ++poll) {
            auto status = cli->Get("/v1/jobs/" + job);
            ASSERT_TRUE(status);
            ASSERT_EQ(status->status, 200) << status->body;
            EXPECT_EQ(status->get_header_value("X-Kdrt-Replica"), replica);
            if (proto::decode_job_status(status->body)->state == proto::JobState::kDone) break;
            std::this_thread::sleep_for(std::chrono::milliseconds(20));
        }
        auto image = cli->Get("/v1/jobs/" + job + "/result");
        ASSERT_TRUE(image);
        EXPECT_EQ(image->status, 200) << image->body;
        EXPECT_EQ(image->get_header_value("X-Kdrt-Replica"), replica);
    }
    // Renders without ?route= go to any replica: the jobs did not all run on one.
    EXPECT_GT(replicas_seen.size(), 1u);
    // An id naming no replica is answered by one (404 unknown job), not by nginx.
    auto unknown = cli->Get("/v1/jobs/nosuchreplica.0123456789abcdef0123456789abcdef");
    ASSERT_TRUE(unknown);
    EXPECT_EQ(unknown->status, 404);
    EXPECT_EQ(unknown->get_header_value("Content-Type"), "application/problem+json");
}

TEST_F(ScaleOut, AReplicaKilledMidRunLosesNothing) {
    auto nginx = start_nginx();
    std::vector<Mesh> meshes;
    std::vector<std::string> ids;
    {
        auto cli = nginx->client();
        for (int m = 0; m < 9; ++m) {
            meshes.push_back(small_mesh(9200 + m, 300));
            ids.push_back(upload_id(*cli, meshes.back()));
        }
    }
    // The victim: the replica the first mesh hashes to.
    std::string victim_name;
    {
        auto cli = nginx->client();
        victim_name = owner(*cli, ids[0]);
    }
    const size_t victim = std::find(names_.begin(), names_.end(), victim_name) - names_.begin();
    ASSERT_LT(victim, replicas_.size());

    std::atomic<int> done{0}, wrong{0}, failed{0}, retries{0};
    std::atomic<bool> killed{false};
    auto worker = [&](int seed) {
        auto cli = nginx->client();
        for (int i = 0; i < 40; ++i) {
            const size_t m = static_cast<size_t>(seed * 7 + i) % ids.size();
            int tries = 0;
            if (i % 5 == 4) {
                auto res = retrying(
                    [&] {
                        return cli->Post("/v1/render?route=" + ids[m],
                                         "{\"mesh\":\"" + ids[m] + "\",\"width\":24,\"height\":24}",
                                         "application/json");
                    },
                    &tries);
                if (!res || res->status != 200) ++failed;
            } else {
                const auto rays = random_rays(mesh_bounds(meshes[m]), 2000, seed * 100 + i);
                auto res = retrying([&] { return trace(*cli, ids[m], rays); }, &tries);
                if (!res || res->status != 200)
                    ++failed;
                else if (res->body != engine_hits(meshes[m], rays))
                    ++wrong;
            }
            retries += tries;
            ++done;
        }
    };
    std::vector<std::thread> clients;
    for (int c = 0; c < 3; ++c) clients.emplace_back(worker, c);
    while (done < 20) std::this_thread::sleep_for(std::chrono::milliseconds(5));
    EXPECT_EQ(replicas_[victim]->stop(SIGKILL, std::chrono::seconds(10)), -1);
    killed = true;
    for (auto& t : clients) t.join();
    EXPECT_EQ(done, 120);
    EXPECT_EQ(failed, 0);
    EXPECT_EQ(wrong, 0);

    // Every acknowledged mesh is still served, the victim's by the survivors from the store.
    auto cli = nginx->client();
    for (size_t m = 0; m < ids.size(); ++m) {
        const auto rays = random_rays(mesh_bounds(meshes[m]), 100, 77 + m);
        auto res = retrying([&] { return trace(*cli, ids[m], rays); });
        ASSERT_TRUE(res);
        ASSERT_EQ(res->status, 200) << res->body;
        EXPECT_EQ(res->body, engine_hits(meshes[m], rays));
        EXPECT_NE(res->get_header_value("X-Kdrt-Replica"), victim_name);
    }
    auto res = retrying([&] { return cli->Get("/v1/meshes"); });
    ASSERT_TRUE(res);
    auto listed = proto::decode_mesh_list(res->body);
    ASSERT_TRUE(listed) << res->body;
    std::set<std::string> listed_ids;
    for (const auto& s : *listed) listed_ids.insert(s.id);
    for (const std::string& id : ids) EXPECT_TRUE(listed_ids.count(id)) << id;
    // A survivor loaded the victim's first mesh from the store (a cache miss, no upload).
    double misses = 0;
    for (size_t r = 0; r < replicas_.size(); ++r)
        if (r != victim) misses += replicas_[r]->metric("kdrt_cache_misses_total").value_or(0);
    EXPECT_GE(misses, 1.0);
    std::printf("kill -9 of %s: %d client retries\n", victim_name.c_str(), retries.load());
}

TEST_F(ScaleOut, AFourthReplicaTakesAboutAQuarterOfTheMeshes) {
    constexpr int kMeshes = 80;
    std::vector<std::string> ids;
    std::map<std::string, std::string> before;
    {
        auto nginx = start_nginx();
        auto cli = nginx->client();
        for (int m = 0; m < kMeshes; ++m) ids.push_back(upload_id(*cli, small_mesh(9300 + m, 40)));
        for (const std::string& id : ids) before[id] = owner(*cli, id);
    }
    add_replica();
    auto nginx = start_nginx();
    auto cli = nginx->client();
    int moved = 0;
    for (const std::string& id : ids) {
        const std::string now = owner(*cli, id);
        if (now == before[id]) continue;
        ++moved;
        // Consistent hashing: a mesh moves only to the new replica, never between old ones.
        EXPECT_EQ(now, names_.back()) << id << " moved from " << before[id];
    }
    std::printf("adding a 4th replica moved %d of %d meshes\n", moved, kMeshes);
    // About a quarter (20 of 80); the ring's points make it uneven, never most of them.
    EXPECT_GE(moved, kMeshes / 10);
    EXPECT_LE(moved, kMeshes * 45 / 100);
}

TEST_F(ScaleOut, TheSameUploadToTwoReplicasAtOnceIsStoredOnce) {
    for (int round = 0; round < 3; ++round) {
        const Mesh mesh = small_mesh(9400 + round, 5000);
        const std::string body = mesh_body(mesh, proto::MeshFormat::kPly);
        std::vector<int> statuses(2);
        std::vector<std::string> answered(2);
        std::atomic<int> ready{0};
        std::vector<std::thread> uploads;
        for (int r = 0; r < 2; ++r)
            uploads.emplace_back([&, r] {
                auto cli = replicas_[r]->client();
                ++ready;
                while (ready < 2) {
                }
                auto res = cli->Post("/v1/meshes", body, "application/ply");
                statuses[r] = res ? res->status : -1;
                if (res && res->status / 100 == 2)
                    answered[r] = proto::decode_mesh_summary(res->body)->id;
            });
        for (auto& t : uploads) t.join();
        const std::string id = proto::mesh_id(mesh);
        EXPECT_EQ(answered[0], id);
        EXPECT_EQ(answered[1], id);
        // Exactly one replica created it (201); the other found it stored (200).
        std::multiset<int> got(statuses.begin(), statuses.end());
        EXPECT_EQ(got, (std::multiset<int>{200, 201})) << statuses[0] << " " << statuses[1];
        // One copy of each file, nothing left in flight.
        int files = 0;
        for (const auto& f : fs::directory_iterator(store_ / "meshes"))
            files += f.path().stem() == id;
        EXPECT_EQ(files, 3);
    }
    for (const auto& f : fs::recursive_directory_iterator(store_ / "tmp"))
        EXPECT_TRUE(f.is_directory() || f.path().extension() == ".lock") << f.path();
}

TEST_F(ScaleOut, AMeshDeletedThroughOneReplicaIsGoneFromEveryReplica) {
    // Every replica holds the tree in memory (each traced it); the delete reaches one of them.
    const Mesh mesh = small_mesh(9700, 800);
    const std::string id = upload_id(*replicas_[0]->client(), mesh);
    const auto rays = random_rays(mesh_bounds(mesh), 32, 97);
    for (auto& replica : replicas_) {
        auto res = trace(*replica->client(), id, rays);
        ASSERT_TRUE(res);
        ASSERT_EQ(res->status, 200) << res->body;
        EXPECT_EQ(res->body, engine_hits(mesh, rays));
    }
    auto deleted = replicas_[1]->client()->Delete("/v1/meshes/" + id);
    ASSERT_TRUE(deleted);
    ASSERT_EQ(deleted->status, 204) << deleted->body;
    // The others answer as if they never had it, without a listing or a restart in between.
    for (size_t r : {size_t{0}, size_t{2}}) {
        SCOPED_TRACE(names_[r]);
        auto cli = replicas_[r]->client();
        expect_problem(trace(*cli, id, rays), 404);
        auto info = cli->Get("/v1/meshes/" + id);
        ASSERT_TRUE(info);
        EXPECT_EQ(info->status, 404) << info->body;
    }
    // Uploading it again works everywhere.
    EXPECT_EQ(upload_id(*replicas_[2]->client(), mesh), id);
    for (auto& replica : replicas_) {
        auto res = trace(*replica->client(), id, rays);
        ASSERT_TRUE(res);
        EXPECT_EQ(res->status, 200) << res->body;
    }
}

TEST_F(ScaleOut, AReplicaStartingBesideALiveOneLeavesItsUncommittedFilesAlone) {
    // Files of a mesh without a summary: a live replica's upload in progress, for all a newly
    // started replica knows. It must not quarantine them (a lone server does, see
    // http_store_test).
    const Mesh mesh = small_mesh(9500, 100);
    const std::string id = proto::mesh_id(mesh);
    {
        std::ofstream out(store_ / "meshes" / (id + ".mesh"), std::ios::binary);
        out << bytes_to_string(proto::write_mesh(mesh, proto::MeshFormat::kRaw));
    }
    add_replica();
    ASSERT_TRUE(replicas_.back()->running());
    EXPECT_TRUE(fs::exists(store_ / "meshes" / (id + ".mesh")));
    EXPECT_FALSE(fs::exists(store_ / "quarantine"));
}

// ---- Scenes across replicas ------------------------------------------------------------------

/// A pose: uniform scale `s`, moved by (x, x / 10, -x / 20).
proto::Transform pose(float x, float s = 1.0f) {
    proto::Transform t;
    t.m = {s, 0, 0, x, 0, s, 0, 0.1f * x, 0, 0, s, -0.05f * x};
    return t;
}

/// Two meshes in the shared store and their trees built here, for the engine's answer to any
/// scene of them (the oracle of every scene query below).
class ScaleOutScenes : public ScaleOut {
protected:
    void SetUp() override {
        ScaleOut::SetUp();
        meshes_ = {small_mesh(9800, 300), small_mesh(9801, 200)};
        for (const Mesh& m : meshes_) {
            mesh_ids_.push_back(upload_id(*replicas_[0]->client(), m));
            trees_[mesh_ids_.back()] = std::make_shared<const KdTree>(build_kdtree(m));
        }
        rays_ = random_rays(Aabb{{-0.5f, -0.5f, -0.5f}, {2.5f, 1.5f, 1.5f}}, 400, 9802);
    }
    /// Instances of both meshes, the k-th placed at pose(k * spacing + shift).
    std::vector<proto::SceneInstanceSpec> instances(size_t n, float shift) const {
        std::vector<proto::SceneInstanceSpec> out(n);
        for (size_t k = 0; k < n; ++k) {
            out[k].mesh = mesh_ids_[k % 2];
            out[k].transform = pose(0.6f * static_cast<float>(k) + shift, 0.8f);
        }
        return out;
    }
    static std::string create_scene(httplib::Client& cli,
                                    const std::vector<proto::SceneInstanceSpec>& inst) {
        auto res = retrying([&] {
            return cli.Post("/v1/scenes", proto::encode_scene_request(inst), "application/json");
        });
        if (!res || res->status != 201) {
            ADD_FAILURE() << (res ? res->body : "no answer");
            return {};
        }
        auto doc = proto::decode_scene_json(res->body, {}, true);
        EXPECT_TRUE(doc.ok()) << res->body;
        return doc ? doc->id : std::string();
    }
    /// Every instance's pose as a KDRX batch (by geometry id).
    static std::string pose_batch(const std::vector<proto::SceneInstanceSpec>& inst) {
        std::vector<proto::PoseEntry> poses(inst.size());
        for (size_t k = 0; k < inst.size(); ++k) {
            poses[k].geometry_id = static_cast<uint32_t>(k);
            poses[k].transform = inst[k].transform;
        }
        return bytes_to_string(proto::encode_pose_batch(poses));
    }
    static httplib::Result set_poses(httplib::Client& cli, const std::string& id,
                                     const std::vector<proto::SceneInstanceSpec>& inst,
                                     std::optional<uint64_t> if_match = std::nullopt) {
        httplib::Headers headers;
        if (if_match) headers.emplace("If-Match", "\"" + std::to_string(*if_match) + "\"");
        return cli.Patch("/v1/scenes/" + id + "/poses", headers, pose_batch(inst),
                         std::string(proto::kPoseBatchMediaType));
    }
    httplib::Result intersect(httplib::Client& cli, const std::string& id,
                              std::optional<uint64_t> revision = std::nullopt) const {
        return cli.Post("/v1/scenes/" + id + "/intersect" +
                            (revision ? "?revision=" + std::to_string(*revision) : ""),
                        bytes_to_string(proto::encode_rays(rays_, false)),
                        "application/x-kdrt-rays");
    }
    /// Checks a scene's closest-hit answer: status 200, from `revision`, equal bit for bit to
    /// the engine's scene of `inst` (hits and geometry ids).
    void expect_answer(const httplib::Result& res, uint64_t revision,
                       const std::vector<proto::SceneInstanceSpec>& inst) const {
        ASSERT_TRUE(res) << "no answer";
        ASSERT_EQ(res->status, 200) << res->body;
        EXPECT_EQ(res->get_header_value("X-Kdrt-Scene-Revision"), std::to_string(revision));
        std::vector<SceneInstance> engine(inst.size());
        for (size_t k = 0; k < inst.size(); ++k) {
            engine[k].tree = trees_.at(inst[k].mesh);
            std::memcpy(engine[k].transform.m, inst[k].transform.m.data(),
                        sizeof engine[k].transform.m);
        }
        const Scene scene = build_scene(std::move(engine));
        std::vector<SceneHit> expected(rays_.size());
        kdrt::intersect(scene, rays_, expected);
        auto split = proto::split_geometry_ids(string_to_bytes(res->body));
        ASSERT_TRUE(split.ok()) << split.error().to_string();
        auto hits = proto::decode_hits(split->mesh_body);
        ASSERT_TRUE(hits.ok()) << hits.error().to_string();
        ASSERT_EQ(hits->size(), rays_.size());
        ASSERT_EQ(split->geometry_ids.size(), rays_.size());
        size_t hit_count = 0;
        for (size_t i = 0; i < rays_.size(); ++i) {
            const SceneHit got{(*hits)[i].t, (*hits)[i].prim, (*hits)[i].u, (*hits)[i].v,
                               split->geometry_ids[i]};
            ASSERT_EQ(got, expected[i]) << "ray " << i << " of revision " << revision;
            hit_count += expected[i].is_hit();
        }
        EXPECT_GT(hit_count, rays_.size() / 20) << "the rays miss the scene: a weak check";
    }
    /// Scene intersects answered 200 by replica r (its own count).
    double scene_traces_on(size_t r) const {
        return replicas_[r]
            ->metric(
                "kdrt_http_requests_total{route=\"/v1/scenes/{id}/intersect\",method=\"POST\","
                "status=\"200\"}")
            .value_or(0);
    }

    std::vector<Mesh> meshes_;
    std::vector<std::string> mesh_ids_;
    std::map<std::string, std::shared_ptr<const KdTree>> trees_;
    std::vector<Ray> rays_;
};

TEST_F(ScaleOutScenes, ARevisionWrittenThroughOneReplicaIsWhatEveryOtherAnswers) {
    // No nginx: each step goes to a chosen replica, each of which keeps what it saw in memory.
    std::vector<std::unique_ptr<httplib::Client>> cli;
    for (auto& r : replicas_) cli.push_back(r->client());
    auto rev1 = instances(3, 0.0f);
    const std::string id = create_scene(*cli[0], rev1);
    ASSERT_FALSE(id.empty());
    // Every replica builds and keeps revision 1 (r1 and r2 load it and its meshes from the store:
    // they never saw either).
    for (size_t r = 0; r < cli.size(); ++r) {
        SCOPED_TRACE(names_[r]);
        expect_answer(intersect(*cli[r], id), 1, rev1);
    }
    // Revision 2 through r1.
    const auto rev2 = instances(3, 0.3f);
    auto res = set_poses(*cli[1], id, rev2);
    ASSERT_TRUE(res);
    ASSERT_EQ(res->status, 200) << res->body;
    EXPECT_EQ(res->get_header_value("ETag"), "\"2\"");
    // r2 still holds revision 1 as the newest it saw: a conditional update on it is stale.
    expect_problem(set_poses(*cli[2], id, rev1, 1), 412);
    // On revision 2 it succeeds (revision 3), though r2 never saw revision 2.
    const auto rev3 = instances(3, -0.4f);
    res = set_poses(*cli[2], id, rev3, 2);
    ASSERT_TRUE(res);
    ASSERT_EQ(res->status, 200) << res->body;
    EXPECT_EQ(res->get_header_value("ETag"), "\"3\"");
    // r0 (holding revision 1) answers from revision 3, and a pinned revision 2 it never saw.
    expect_answer(intersect(*cli[0], id), 3, rev3);
    expect_answer(intersect(*cli[0], id, 2), 2, rev2);
    expect_answer(intersect(*cli[1], id, 1), 1, rev1);
    for (size_t r = 0; r < cli.size(); ++r) {
        auto doc = cli[r]->Get("/v1/scenes/" + id);
        ASSERT_TRUE(doc);
        EXPECT_EQ(doc->get_header_value("ETag"), "\"3\"") << names_[r];
    }
    // An instance edit through r0 (revision 4: one instance added); r1 answers from it.
    proto::InstanceEdit edit;
    edit.add = instances(4, -0.4f);
    edit.add.erase(edit.add.begin(), edit.add.begin() + 3);
    auto rev4 = rev3;
    rev4.push_back(edit.add[0]);
    res = cli[0]->Post("/v1/scenes/" + id + "/instances", {{"If-Match", "\"3\""}},
                       proto::encode_instance_edit_json(edit), "application/json");
    ASSERT_TRUE(res);
    ASSERT_EQ(res->status, 200) << res->body;
    expect_answer(intersect(*cli[1], id), 4, rev4);
    // A conditional delete on r2 (which saw revision 3 last) of revision 3 is stale; of 4 it
    // deletes the scene for every replica.
    expect_problem(cli[2]->Delete("/v1/scenes/" + id, {{"If-Match", "\"3\""}}), 412);
    res = cli[2]->Delete("/v1/scenes/" + id, {{"If-Match", "\"4\""}});
    ASSERT_TRUE(res);
    EXPECT_EQ(res->status, 204) << res->body;
    for (size_t r = 0; r < cli.size(); ++r) {
        SCOPED_TRACE(names_[r]);
        expect_problem(intersect(*cli[r], id), 404);
        expect_problem(intersect(*cli[r], id, 4), 404);
        expect_problem(cli[r]->Get("/v1/scenes/" + id), 404);
    }
}

TEST_F(ScaleOutScenes, ConcurrentConditionalWritesOnTwoReplicasHaveOneWinner) {
    // r0 and r1 both change revision N at once ("If-Match: N"): one answers 2xx, the other
    // 412 (or 404 when the winner deleted the scene), and the store holds the winner's change.
    auto c0 = replicas_[0]->client();
    auto c1 = replicas_[1]->client();
    auto c2 = replicas_[2]->client();
    const auto base = instances(2, 0.0f);
    const std::string id = create_scene(*c0, base);
    ASSERT_FALSE(id.empty());
    const auto at_once = [](const std::function<int()>& a, const std::function<int()>& b) {
        std::atomic<int> ready{0};
        int status_b = 0;
        std::thread other([&] {
            ++ready;
            while (ready < 2) {
            }
            status_b = b();
        });
        ++ready;
        while (ready < 2) {
        }
        const int status_a = a();
        other.join();
        return std::pair{status_a, status_b};
    };
    const auto status = [](const httplib::Result& res) { return res ? res->status : -1; };
    uint64_t revision = 1;
    int wins[2] = {0, 0};
    for (int round = 0; round < 12; ++round) {
        SCOPED_TRACE("round " + std::to_string(round));
        const auto p0 = instances(2, 0.05f * static_cast<float>(round));
        const auto p1 = instances(2, -0.05f * static_cast<float>(round) - 0.01f);
        const auto [s0, s1] = at_once([&] { return status(set_poses(*c0, id, p0, revision)); },
                                      [&] { return status(set_poses(*c1, id, p1, revision)); });
        ASSERT_EQ(std::multiset<int>({s0, s1}), std::multiset<int>({200, 412})) << s0 << " " << s1;
        ++revision;
        ++wins[s0 == 200 ? 0 : 1];
        // The third replica answers from the winner's poses.
        expect_answer(intersect(*c2, id), revision, s0 == 200 ? p0 : p1);
    }
    std::printf("pose updates won: r0 %d, r1 %d\n", wins[0], wins[1]);
    // A conditional delete on r1 against a conditional pose update on r0 of the same revision.
    int deletes_won = 0;
    for (int round = 0; round < 12; ++round) {
        SCOPED_TRACE("delete round " + std::to_string(round));
        const std::string doomed = create_scene(*c2, base);
        ASSERT_FALSE(doomed.empty());
        const auto moved = instances(2, 0.2f);
        const auto [s_pose, s_delete] =
            at_once([&] { return status(set_poses(*c0, doomed, moved, 1)); },
                    [&] {
                        // 0 .. 88 ms late: both orders happen, and the near ties between them
                        // (a PATCH with a body took about 44 ms to commit here, a DELETE less).
                        std::this_thread::sleep_for(std::chrono::milliseconds(8 * round));
                        return status(c1->Delete("/v1/scenes/" + doomed, {{"If-Match", "\"1\""}}));
                    });
        if (s_pose == 200) {
            EXPECT_EQ(s_delete, 412)
                << "the delete of revision 1 won after revision 2 was acknowledged";
            expect_answer(intersect(*c2, doomed), 2, moved);
            ASSERT_EQ(status(c2->Delete("/v1/scenes/" + doomed)), 204);
        } else {
            ++deletes_won;
            EXPECT_EQ(s_delete, 204);
            EXPECT_TRUE(s_pose == 412 || s_pose == 404) << s_pose;
            expect_problem(intersect(*c2, doomed), 404);
        }
    }
    std::printf("deletes won %d of 12 races with a pose update\n", deletes_won);
}

TEST_F(ScaleOutScenes, EveryRequestForASceneLandsOnOneReplicaAndSurvivesItsLoss) {
    auto nginx = start_nginx();
    auto cli = nginx->client();
    // Created through nginx (any replica), queried through nginx: each scene on one replica.
    constexpr int kScenes = 8;
    std::vector<std::string> ids;
    std::vector<std::vector<proto::SceneInstanceSpec>> current;
    for (int k = 0; k < kScenes; ++k) {
        current.push_back(instances(2 + k % 3, 0.1f * static_cast<float>(k)));
        ids.push_back(create_scene(*cli, current.back()));
        ASSERT_FALSE(ids.back().empty());
    }
    std::map<std::string, double> expected;  // scene intersects per replica name
    std::vector<std::string> owner(kScenes);
    for (int k = 0; k < kScenes; ++k) {
        for (int q = 0; q < 3; ++q) {
            auto res = intersect(*cli, ids[k]);
            expect_answer(res, 1, current[k]);
            const std::string by = res ? res->get_header_value("X-Kdrt-Replica") : "";
            if (q == 0) owner[k] = by;
            EXPECT_EQ(by, owner[k]) << "scene " << ids[k] << " moved between replicas";
        }
        auto doc = cli->Get("/v1/scenes/" + ids[k]);
        ASSERT_TRUE(doc);
        EXPECT_EQ(doc->get_header_value("X-Kdrt-Replica"), owner[k]);
        expected[owner[k]] += 3;
    }
    for (size_t r = 0; r < replicas_.size(); ++r)
        EXPECT_EQ(counted([&] { return scene_traces_on(r); }, expected[names_[r]]),
                  expected[names_[r]])
            << names_[r];
    EXPECT_GT(expected.size(), 1u) << "8 scenes all hashed to one replica";

    // A pose update through nginx: every replica, asked directly, answers from it.
    current[0] = instances(current[0].size(), 0.7f);
    auto res = set_poses(*cli, ids[0], current[0], 1);
    ASSERT_TRUE(res);
    ASSERT_EQ(res->status, 200) << res->body;
    EXPECT_EQ(res->get_header_value("X-Kdrt-Replica"), owner[0]);
    for (size_t r = 0; r < replicas_.size(); ++r) {
        SCOPED_TRACE(names_[r]);
        expect_answer(intersect(*replicas_[r]->client(), ids[0]), 2, current[0]);
    }
    // A revision written on another replica behind nginx's back (as while the owner was out of
    // the ring): the owner, which holds revision 2, answers from revision 3 through nginx.
    const size_t owner0 = std::find(names_.begin(), names_.end(), owner[0]) - names_.begin();
    ASSERT_LT(owner0, replicas_.size());
    const size_t other = (owner0 + 1) % replicas_.size();
    current[0] = instances(current[0].size(), -0.3f);
    res = set_poses(*replicas_[other]->client(), ids[0], current[0], 2);
    ASSERT_TRUE(res);
    ASSERT_EQ(res->status, 200) << res->body;
    res = intersect(*cli, ids[0]);
    expect_answer(res, 3, current[0]);
    EXPECT_EQ(res->get_header_value("X-Kdrt-Replica"), owner[0]);

    // The owner stops: its scenes answer from another replica with the latest acknowledged
    // revision, and take new revisions there.
    EXPECT_EQ(replicas_[owner0]->stop(SIGKILL, std::chrono::seconds(10)), -1);
    for (int k = 0; k < kScenes; ++k) {
        if (owner[k] != owner[0]) continue;
        SCOPED_TRACE(ids[k]);
        res = retrying([&] { return intersect(*cli, ids[k]); });
        expect_answer(res, k == 0 ? 3 : 1, current[k]);
        EXPECT_NE(res->get_header_value("X-Kdrt-Replica"), owner[0]);
    }
    current[0] = instances(current[0].size(), 0.45f);
    res = retrying([&] { return set_poses(*cli, ids[0], current[0], 3); });
    ASSERT_TRUE(res);
    ASSERT_EQ(res->status, 200) << res->body;
    expect_answer(retrying([&] { return intersect(*cli, ids[0]); }), 4, current[0]);
    // Every scene is listed by nginx's any replica.
    res = retrying([&] { return cli->Get("/v1/scenes"); });
    ASSERT_TRUE(res);
    ASSERT_EQ(res->status, 200) << res->body;
    auto listed = proto::decode_scene_list(res->body);
    ASSERT_TRUE(listed) << res->body;
    std::set<std::string> listed_ids;
    for (const auto& s : *listed) listed_ids.insert(s.id);
    for (const std::string& id : ids) EXPECT_TRUE(listed_ids.count(id)) << id;
}

TEST_F(ScaleOutScenes, ASplitSceneQuerySpreadsOverReplicasAndAnswersFromOneRevision) {
    auto nginx = start_nginx();
    auto cli = nginx->client();
    // A scene whose six keys "<id>.<k>" do not all hash to one replica (one in 243 would: see
    // spread_mesh), asked of nginx with GETs carrying each key.
    std::string id;
    for (int attempt = 0; attempt < 8 && id.empty(); ++attempt) {
        const std::string candidate = create_scene(*cli, instances(3, 0.0f));
        ASSERT_FALSE(candidate.empty());
        std::set<std::string> replicas;
        for (int k = 0; k < 6; ++k) {
            auto got = retrying([&] {
                return cli->Get("/v1/scenes/" + candidate + "?route=" + candidate + "." +
                                std::to_string(k));
            });
            ASSERT_TRUE(got && got->status == 200) << (got ? got->body : "no answer");
            replicas.insert(got->get_header_value("X-Kdrt-Replica"));
        }
        if (replicas.size() > 1) id = candidate;
    }
    ASSERT_FALSE(id.empty()) << "8 scenes' split keys all hashed to one replica";
    // Revision 2 through nginx (the scene's replica): the other replicas never saw it.
    const auto rev2 = instances(3, 0.25f);
    auto res = set_poses(*cli, id, rev2, 1);
    ASSERT_TRUE(res);
    ASSERT_EQ(res->status, 200) << res->body;
    std::vector<double> before;
    for (size_t r = 0; r < replicas_.size(); ++r) before.push_back(scene_traces_on(r));
    const auto parts_on = [&](size_t r) { return scene_traces_on(r) - before[r]; };
    const auto parts = [&] {
        double n = 0;
        for (size_t r = 0; r < replicas_.size(); ++r) n += parts_on(r);
        return n;
    };

    // The C++ client: 6 parts, each with its routing key "<id>.<k>", all from revision 2.
    ClientOptions options;
    options.split = 6;
    Client client("http://127.0.0.1:" + std::to_string(nginx->port()), options);
    auto hits = client.intersect_scene(id, rays_);
    ASSERT_TRUE(hits) << hits.error().to_string();
    EXPECT_EQ(hits->revision, 2u);
    // Byte for byte one replica's unsplit answer of revision 2 (itself the engine's).
    std::vector<std::byte> split_answer = proto::encode_hits(hits->hits);
    proto::append_geometry_ids(split_answer, hits->geometry_ids);
    auto direct = intersect(*replicas_[0]->client(), id, 2);
    expect_answer(direct, 2, rev2);
    ASSERT_TRUE(direct);
    EXPECT_EQ(bytes_to_string(split_answer), direct->body);
    EXPECT_EQ(counted(parts, 6.0 + 1.0), 7.0) << "6 parts and the direct query";
    int serving = 0;
    for (size_t r = 0; r < replicas_.size(); ++r) serving += parts_on(r) > 0;
    EXPECT_GT(serving, 1) << "all six parts hashed to one replica";

    // kdrt scene trace --split 6 through nginx writes the same bytes.
    TempDir dir;
    const fs::path rays_file = dir.path() / "rays.kdrr", out = dir.path() / "hits.kdrh";
    {
        std::ofstream f(rays_file, std::ios::binary);
        f << bytes_to_string(proto::encode_rays(rays_, false));
    }
    const std::string url = "http://127.0.0.1:" + std::to_string(nginx->port());
    const auto [code, output] =
        run_shell(std::string("env -u KDRT_TOKEN -u KDRT_SERVER ") + KDRT_CLI_BINARY +
                  " --server " + url + " scene trace " + id + " " + rays_file.string() + " -o " +
                  out.string() + " --split 6 --connections 3 --quiet");
    ASSERT_EQ(code, 0) << output;
    std::ifstream written(out, std::ios::binary);
    const std::string cli_body(std::istreambuf_iterator<char>(written), {});
    EXPECT_EQ(cli_body, bytes_to_string(split_answer));
    EXPECT_EQ(counted(parts, 13.0), 13.0) << "6 more parts";
}

TEST(ScaleOutConfig, TheComposeNginxConfigurationIsValid) {
    // docker/nginx.conf as nginx -t sees it, with the Compose host names and include paths of
    // this checkout (nginx -t resolves upstream hosts; it binds no port).
    TempDir dir;
    std::ifstream in(std::string(KDRT_SOURCE_DIR) + "/docker/nginx.conf");
    std::string conf(std::istreambuf_iterator<char>(in), {});
    ASSERT_FALSE(conf.empty());
    const auto replace_all = [&](const std::string& from, const std::string& to) {
        size_t count = 0;
        for (size_t at = conf.find(from); at != std::string::npos; at = conf.find(from, at)) {
            conf.replace(at, from.size(), to);
            at += to.size();
            ++count;
        }
        return count;
    };
    EXPECT_EQ(replace_all("/etc/nginx/kdrt/", std::string(KDRT_SOURCE_DIR) + "/docker/nginx/"), 2u);
    for (const char* host : {"kdrt-1:8080", "kdrt-2:8080", "kdrt-3:8080"})
        EXPECT_EQ(replace_all(host, "127.0.0.1:8080"), 3u) << host;
    replace_all("pid /tmp/nginx.pid;", "pid " + (dir.path() / "nginx.pid").string() + ";");
    replace_all("http {", "http {\n    client_body_temp_path " + dir.path().string() +
                              "/body;\n    proxy_temp_path " + dir.path().string() + "/proxy;");
    {
        std::ofstream out(dir.path() / "nginx.conf");
        out << conf;
    }
    const auto [code, output] = run_shell(std::string(kNginx) + " -t -p " + dir.path().string() +
                                          "/ -e " + (dir.path() / "error.log").string() + " -c " +
                                          (dir.path() / "nginx.conf").string());
    EXPECT_EQ(code, 0) << output;
    EXPECT_NE(output.find("syntax is ok"), std::string::npos) << output;
}

}  // namespace
}  // namespace kdrt::test
