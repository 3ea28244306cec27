// Large KDRR batches against the real binary: bodies streamed into the ray buffer (read from the
// socket directly past the first piece) and traced while they arrive. Answers equal the engine's
// bit for bit; refusals name the first bad ray by index; the keep-alive connection stays usable
// after a large body, a refused one and pipelined requests; a body cut short or framed as chunks
// never hangs or kills the server.

#include <gtest/gtest.h>
#include <netinet/in.h>
#include <netinet/tcp.h>
#include <poll.h>
#include <sys/socket.h>
#include <unistd.h>

#include <chrono>
#include <cmath>
#include <cstring>
#include <limits>
#include <thread>
#include <vector>

#include "http_test_util.h"
#include "kdrt/proto/ray_batch.h"

namespace kdrt::test {
namespace {

/// More than twice StreamTrace::kBlockRays (65536), so the server traces while receiving.
constexpr size_t kLargeBatch = 200'000;

class HttpBatch : public ::testing::Test {
protected:
    static void SetUpTestSuite() {
        dir_ = new TempDir();
        server_ = new ServerProcess({.cache_dir = dir_->path() / "cache"});
        mesh_ = new Mesh(load_bunny());
        tree_ = new KdTree(build_kdtree(*mesh_));
        id_ = upload_id(*server_->client(), *mesh_);
        rays_ = new std::vector<Ray>(random_rays(mesh_bounds(*mesh_), kLargeBatch, test_seed()));
    }
    static void TearDownTestSuite() {
        delete server_;
        delete dir_;
        delete mesh_;
        delete tree_;
        delete rays_;
    }
    static std::string path() { return "/v1/meshes/" + id_ + "/intersect"; }
    static std::string expected_hits(const std::vector<Ray>& rays) {
        std::vector<Hit> hits(rays.size());
        intersect(*tree_, rays, hits);
        return bytes_to_string(proto::encode_hits(hits));
    }
    static TempDir* dir_;
    static ServerProcess* server_;
    static Mesh* mesh_;
    static KdTree* tree_;
    static std::string id_;
    static std::vector<Ray>* rays_;
};
TempDir* HttpBatch::dir_ = nullptr;
ServerProcess* HttpBatch::server_ = nullptr;
Mesh* HttpBatch::mesh_ = nullptr;
KdTree* HttpBatch::tree_ = nullptr;
std::string HttpBatch::id_;
std::vector<Ray>* HttpBatch::rays_ = nullptr;

/// A plain TCP connection to the server, for what httplib's client cannot do (pipelining,
/// cutting a body short).
class Socket {
public:
    explicit Socket(int port) {
        fd_ = ::socket(AF_INET, SOCK_STREAM | SOCK_CLOEXEC, 0);
        sockaddr_in addr{};
        addr.sin_family = AF_INET;
        addr.sin_port = htons(static_cast<uint16_t>(port));
        addr.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
        EXPECT_EQ(::connect(fd_, reinterpret_cast<sockaddr*>(&addr), sizeof addr), 0);
    }
    ~Socket() { ::close(fd_); }
    Socket(const Socket&) = delete;
    Socket& operator=(const Socket&) = delete;

    void send_all(const std::string& data) {
        size_t done = 0;
        while (done < data.size()) {
            const ssize_t n = ::send(fd_, data.data() + done, data.size() - done, MSG_NOSIGNAL);
            ASSERT_GT(n, 0) << std::strerror(errno);
            done += static_cast<size_t>(n);
        }
    }
    void shutdown_write() { ::shutdown(fd_, SHUT_WR); }

    /// Reads one response with a Content-Length body; status -1 when the connection closed
    /// first or nothing came within 60 s.
    struct Response {
        int status = -1;
        std::string head, body;
    };
    Response read_response() {
        Response r;
        size_t end;
        while ((end = buffered_.find("\r\n\r\n")) == std::string::npos)
            if (!fill()) return r;
        r.head = buffered_.substr(0, end);
        buffered_.erase(0, end + 4);
        r.status = std::atoi(r.head.c_str() + r.head.find(' ') + 1);
        std::string lower = r.head;
        for (char& c : lower) c = static_cast<char>(std::tolower(static_cast<unsigned char>(c)));
        const size_t at = lower.find("content-length:");
        const size_t length = at == std::string::npos ? 0 : std::stoull(lower.substr(at + 15));
        while (buffered_.size() < length)
            if (!fill()) return Response{};
        r.body = buffered_.substr(0, length);
        buffered_.erase(0, length);
        return r;
    }

private:
    bool fill() {
        pollfd p{fd_, POLLIN, 0};
        if (::poll(&p, 1, 60'000) <= 0) return false;
        char chunk[65536];
        const ssize_t n = ::recv(fd_, chunk, sizeof chunk, 0);
        if (n <= 0) return false;
        buffered_.append(chunk, static_cast<size_t>(n));
        return true;
    }
    int fd_ = -1;
    std::string buffered_;
};

std::string post_head(const std::string& path, size_t length) {
    return "POST " + path +
           " HTTP/1.1\r\nHost: 127.0.0.1\r\nContent-Type: "
           "application/x-kdrt-rays\r\nContent-Length: " +
           std::to_string(length) + "\r\n\r\n";
}

TEST_F(HttpBatch, LargeBatchesMatchTheEngineAndKeepTheConnection) {
    auto cli = server_->client();
    for (int round = 0; round < 2;
         ++round) {  // the second round reuses the server's pooled buffers
        auto res = cli->Post(path(), bytes_to_string(proto::encode_rays(*rays_, false)),
                             "application/x-kdrt-rays");
        ASSERT_TRUE(res);
        ASSERT_EQ(res->status, 200) << res->body;
        EXPECT_EQ(res->get_header_value("Content-Type"), "application/x-kdrt-hits");
        EXPECT_TRUE(res->body == expected_hits(*rays_)) << "hits differ from the engine's";
    }
    std::vector<uint8_t> occluded_want(rays_->size());
    occluded(*tree_, *rays_, occluded_want);
    auto occ = cli->Post(path(), bytes_to_string(proto::encode_rays(*rays_, true)),
                         "application/x-kdrt-rays");
    ASSERT_TRUE(occ);
    ASSERT_EQ(occ->status, 200) << occ->body;
    EXPECT_EQ(occ->get_header_value("Content-Type"), "application/x-kdrt-occlusion");
    EXPECT_TRUE(occ->body == bytes_to_string(proto::encode_occlusion(occluded_want)));
    // Sizes around the thresholds (direct reads from 256 KiB, streamed tracing from 131072 rays).
    for (const size_t count :
         {size_t{8191}, size_t{8192}, size_t{131071}, size_t{131072}, size_t{131073}}) {
        SCOPED_TRACE(count);
        const std::vector<Ray> some(rays_->begin(), rays_->begin() + static_cast<ptrdiff_t>(count));
        auto r = cli->Post(path(), bytes_to_string(proto::encode_rays(some, false)),
                           "application/x-kdrt-rays");
        ASSERT_TRUE(r);
        ASSERT_EQ(r->status, 200) << r->body;
        EXPECT_TRUE(r->body == expected_hits(some));
    }
}

TEST_F(HttpBatch, InvalidRaysAreMissesWhenTheRequestSaysSo) {
    auto cli = server_->client();
    std::vector<Ray> rays(rays_->begin(), rays_->begin() + 1000);
    size_t hits_before = 0;
    for (size_t i = 0; i < 1000; i += 7) {
        hits_before += expected_hits({rays[i]}) != expected_hits({Ray{}});
        rays[i].dx = std::numeric_limits<float>::quiet_NaN();
        rays[i + 1].oz = -std::numeric_limits<float>::infinity();
    }
    ASSERT_GT(hits_before, 0u);  // some of the spoiled rays hit before
    const std::string body = bytes_to_string(proto::encode_rays(rays, false));
    // The default is to refuse the batch, naming the first bad ray.
    auto p = expect_problem(cli->Post(path(), body, "application/x-kdrt-rays"), 400);
    EXPECT_NE(p.detail.find("ray 0: field dx is NaN"), std::string::npos) << p.detail;
    p = expect_problem(cli->Post(path() + "?invalid_rays=refuse", body, "application/x-kdrt-rays"),
                       400);
    // ?invalid_rays=miss: the batch is answered; every invalid ray is a miss, the rest as usual.
    auto res = cli->Post(path() + "?invalid_rays=miss", body, "application/x-kdrt-rays");
    ASSERT_TRUE(res);
    ASSERT_EQ(res->status, 200) << res->body;
    EXPECT_TRUE(res->body == expected_hits(rays));
    auto hits = proto::decode_hits(string_to_bytes(res->body));
    ASSERT_TRUE(hits);
    for (size_t i = 0; i < 1000; i += 7) {
        EXPECT_FALSE((*hits)[i].is_hit()) << i;
        EXPECT_FALSE((*hits)[i + 1].is_hit()) << i + 1;
    }
    p = expect_problem(cli->Post(path() + "?invalid_rays=skip", body, "application/x-kdrt-rays"),
                       400);
    EXPECT_NE(p.detail.find("invalid_rays is \"skip\" (expected refuse or miss)"),
              std::string::npos)
        << p.detail;
}

TEST_F(HttpBatch, ARefusedRayIsNamedByIndexAndTheConnectionGoesOn) {
    auto cli = server_->client();
    for (const size_t bad : {size_t{0}, size_t{150'001}, kLargeBatch - 1}) {
        SCOPED_TRACE(bad);
        std::vector<Ray> rays = *rays_;
        rays[bad].dy = std::numeric_limits<float>::quiet_NaN();
        rays[kLargeBatch - 1].ox =
            std::numeric_limits<float>::infinity();  // later ones are not named
        auto p = expect_problem(cli->Post(path(), bytes_to_string(proto::encode_rays(rays, false)),
                                          "application/x-kdrt-rays"),
                                400);
        EXPECT_EQ(p.code, "non_finite_ray");
        const std::string field = bad == kLargeBatch - 1 ? "ox is +inf" : "dy is NaN";
        EXPECT_NE(p.detail.find("ray " + std::to_string(bad) + ": field " + field),
                  std::string::npos)
            << p.detail;
        // The same connection answers the next request.
        const std::vector<Ray> one(rays_->begin(), rays_->begin() + 1);
        auto ok = cli->Post(path(), bytes_to_string(proto::encode_rays(one, false)),
                            "application/x-kdrt-rays");
        ASSERT_TRUE(ok);
        EXPECT_EQ(ok->status, 200);
    }
    // A header that cannot match its Content-Length is refused before the body is read.
    std::string body = bytes_to_string(proto::encode_rays(*rays_, false));
    body.resize(body.size() - 32);
    auto p = expect_problem(cli->Post(path(), body, "application/x-kdrt-rays"), 400);
    EXPECT_EQ(p.code, "length_mismatch");
    EXPECT_NE(p.detail.find("header says 200000 rays (6400016 bytes) but body has 6399984 bytes"),
              std::string::npos)
        << p.detail;
}

// A request sent right behind a large body, before its answer: the server must have consumed
// exactly the body (the part read past httplib), or the next request would be garbled. (More
// than one request queued behind the body is not supported: httplib 0.11.4 drops bytes it has
// buffered when a request ends, so it does not serve general pipelining.)
TEST_F(HttpBatch, ARequestRightBehindALargeBodyIsAnswered) {
    Socket s(server_->port());
    const std::vector<Ray> few(rays_->begin(), rays_->begin() + 10);
    const std::string large = bytes_to_string(proto::encode_rays(*rays_, false));
    const std::string small = bytes_to_string(proto::encode_rays(few, false));
    s.send_all(post_head(path(), large.size()) + large + post_head(path(), small.size()) + small);
    const auto first = s.read_response();
    ASSERT_EQ(first.status, 200) << first.head;
    EXPECT_TRUE(first.body == expected_hits(*rays_));
    const auto second = s.read_response();
    ASSERT_EQ(second.status, 200) << second.head;
    EXPECT_TRUE(second.body == expected_hits(few));
}

// Several connections stream large bodies at once, interleaved, over keep-alive: each body is
// received from its own connection's socket (the part read past httplib), so each connection
// gets the answer to its own rays. A socket lookup that ever picked another connection's socket
// would garble both bodies, and the answers or the framing would be wrong.
TEST_F(HttpBatch, ConcurrentLargeBodiesEachGetTheirOwnAnswer) {
    constexpr int kConnections = 4;
    constexpr size_t kRays = 20'000;  // 640 KiB: read from the socket past the first piece
    std::vector<std::string> bodies, answers;
    for (int c = 0; c < kConnections; ++c) {
        const std::vector<Ray> own(rays_->begin() + static_cast<ptrdiff_t>(c * kRays),
                                   rays_->begin() + static_cast<ptrdiff_t>((c + 1) * kRays));
        bodies.push_back(bytes_to_string(proto::encode_rays(own, false)));
        answers.push_back(expected_hits(own));
    }
    std::vector<int> good(kConnections, 0);
    std::vector<std::thread> clients;
    clients.reserve(kConnections);
    for (int c = 0; c < kConnections; ++c) {
        clients.emplace_back([&, c] {
            Socket s(server_->port());
            for (int round = 0; round < 3; ++round) {
                const std::string& body = bodies[static_cast<size_t>(c)];
                s.send_all(post_head(path(), body.size()));
                for (size_t at = 0; at < body.size(); at += 50'000) {
                    s.send_all(body.substr(at, 50'000));
                    std::this_thread::sleep_for(std::chrono::milliseconds(1));  // interleave
                }
                const auto r = s.read_response();
                if (r.status == 200 && r.body == answers[static_cast<size_t>(c)])
                    ++good[static_cast<size_t>(c)];
            }
        });
    }
    for (std::thread& t : clients) t.join();
    for (int c = 0; c < kConnections; ++c)
        EXPECT_EQ(good[static_cast<size_t>(c)], 3) << "connection " << c;
}

TEST_F(HttpBatch, ABodyCutShortIsA400AndTheServerGoesOn) {
    const std::string large = bytes_to_string(proto::encode_rays(*rays_, false));
    {
        Socket s(server_->port());
        s.send_all(post_head(path(), large.size()) + large.substr(0, large.size() / 2));
        s.shutdown_write();
        const auto r = s.read_response();
        if (r.status != -1) {  // the server may also just close the connection
            EXPECT_EQ(r.status, 400) << r.head;
            EXPECT_NE(r.body.find("the request body could not be read"), std::string::npos)
                << r.body;
        }
    }
    {
        // Cut inside the first piece too (before the 16-byte header is complete).
        Socket s(server_->port());
        s.send_all(post_head(path(), large.size()) + large.substr(0, 10));
        s.shutdown_write();
        (void)s.read_response();
    }
    auto cli = server_->client();
    auto health = cli->Get("/healthz");
    ASSERT_TRUE(health);
    EXPECT_EQ(health->status, 200);
    auto m = server_->metric("kdrt_inflight_requests");
    ASSERT_TRUE(m);
    EXPECT_EQ(*m, 0.0);
}

TEST_F(HttpBatch, ChunkedBodiesAreDecodedAsTheyArrive) {
    auto cli = server_->client();
    const std::string body = bytes_to_string(proto::encode_rays(*rays_, false));
    const auto chunked_post = [&](const std::string& data) {
        return cli->Post(
            path(),
            [&data](size_t offset, httplib::DataSink& sink) {
                const size_t n = std::min<size_t>(data.size() - offset, 100'003);
                if (n > 0) sink.write(data.data() + offset, n);
                if (offset + n >= data.size()) sink.done();
                return true;
            },
            "application/x-kdrt-rays");
    };
    auto res = chunked_post(body);
    ASSERT_TRUE(res);
    ASSERT_EQ(res->status, 200) << res->body;
    EXPECT_TRUE(res->body == expected_hits(*rays_));
    // Without a declared size the length is checked first, then the first bad ray is named.
    std::vector<Ray> rays = *rays_;
    rays[7].tmin = std::numeric_limits<float>::quiet_NaN();
    std::string bad = bytes_to_string(proto::encode_rays(rays, false));
    auto p = expect_problem(chunked_post(bad), 400);
    EXPECT_NE(p.detail.find("ray 7: field tmin is NaN"), std::string::npos) << p.detail;
    bad.resize(bad.size() - 1);
    p = expect_problem(chunked_post(bad), 400);
    EXPECT_EQ(p.code, "length_mismatch") << p.detail;
}

}  // namespace
}  // namespace kdrt::test
