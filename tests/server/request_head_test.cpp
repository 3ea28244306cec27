// The request head reader of the HTTP front (server/http/request_head.*): finding a head's end
// in arriving bytes, and strict parsing, on good and hostile heads.

#include "http/request_head.h"

#include <gtest/gtest.h>

#include <string>

namespace kdrt::server {
namespace {

const HeadLimits kLimits{.max_head_bytes = 32 << 10, .max_headers = 100};

RequestHead parse_ok(const std::string& head) {
    auto parsed = parse_request_head(head, kLimits);
    EXPECT_TRUE(parsed) << head << " -> " << (parsed ? "" : parsed.error().detail);
    return parsed ? std::move(parsed).value() : RequestHead{};
}

HeadError parse_error(const std::string& head, const HeadLimits& limits = kLimits) {
    auto parsed = parse_request_head(head, limits);
    EXPECT_FALSE(parsed) << head;
    return parsed ? HeadError{0, ""} : parsed.error();
}

TEST(RequestHead, FindsTheEndAcrossPiecesAndCountsLines) {
    const std::string head = "GET / HTTP/1.1\r\nHost: x\r\nA: b\r\n\r\nNEXT";
    // Fed a byte more at a time, the end is found exactly once all of it has arrived.
    HeadScan scan;
    std::optional<size_t> end;
    size_t arrived = 0;
    while (!end && arrived < head.size()) end = find_head_end(head.substr(0, ++arrived), scan);
    ASSERT_TRUE(end);
    EXPECT_EQ(*end, head.size() - 4);
    EXPECT_EQ(arrived, head.size() - 4);
    // Bare LFs end a head too (RFC 9112 2.2).
    HeadScan lf;
    EXPECT_EQ(find_head_end("GET / HTTP/1.1\nHost: x\n\nrest", lf), 24u);
    // Lines are counted while the head is incomplete (the header-count limit).
    HeadScan many;
    EXPECT_FALSE(find_head_end("GET / HTTP/1.1\r\nA: 1\r\nB: 2\r\nC: 3\r\n", many));
    EXPECT_GE(many.lines, 3u);
}

TEST(RequestHead, ParsesMethodTargetQueryAndHeaders) {
    const RequestHead h = parse_ok(
        "POST /v1/meshes/ab%20c/intersect?max_hits=4&x=a+b&flag&e=%26 HTTP/1.1\r\n"
        "Host: x\r\nContent-Type:  application/x-kdrt-rays \r\nContent-Length: 48\r\n\r\n");
    EXPECT_EQ(h.method, "POST");
    EXPECT_EQ(h.path, "/v1/meshes/ab c/intersect");
    EXPECT_EQ(h.version, "HTTP/1.1");
    ASSERT_EQ(h.query.size(), 4u);
    EXPECT_EQ(h.query[0], (std::pair<std::string, std::string>{"max_hits", "4"}));
    EXPECT_EQ(h.query[1], (std::pair<std::string, std::string>{"x", "a b"}));
    EXPECT_EQ(h.query[2], (std::pair<std::string, std::string>{"flag", ""}));
    EXPECT_EQ(h.query[3], (std::pair<std::string, std::string>{"e", "&"}));
    ASSERT_EQ(h.headers.size(), 3u);
    EXPECT_EQ(h.headers[1].second, "application/x-kdrt-rays");
    EXPECT_EQ(h.content_length, 48u);
    EXPECT_FALSE(h.chunked);
    EXPECT_TRUE(h.keep_alive);
}

TEST(RequestHead, FramingAndConnectionOptions) {
    EXPECT_TRUE(parse_ok("POST / HTTP/1.1\r\nTransfer-Encoding: Chunked\r\n\r\n").chunked);
    EXPECT_TRUE(parse_ok("POST / HTTP/1.1\r\nExpect: 100-Continue\r\n\r\n").expect_continue);
    EXPECT_FALSE(parse_ok("GET / HTTP/1.1\r\nConnection: keep-alive, close\r\n\r\n").keep_alive);
    EXPECT_FALSE(parse_ok("GET / HTTP/1.0\r\n\r\n").keep_alive);
    EXPECT_TRUE(parse_ok("GET / HTTP/1.0\r\nConnection: Keep-Alive\r\n\r\n").keep_alive);
    // The absolute form is reduced to its path and query.
    const RequestHead absolute =
        parse_ok("GET http://example.org:8080/healthz?a=1 HTTP/1.1\r\n\r\n");
    EXPECT_EQ(absolute.path, "/healthz");
    EXPECT_EQ(absolute.target, "/healthz?a=1");
    EXPECT_EQ(parse_ok("OPTIONS * HTTP/1.1\r\n\r\n").path, "*");
}

TEST(RequestHead, RefusesHostileHeadsNamingWhatIsWrong) {
    const struct {
        const char* head;
        const char* detail;
    } cases[] = {
        {"GET / HTTP/1.1\r\nContent-Length: 1\r\nContent-Length: 1\r\n\r\n", "given once"},
        {"GET / HTTP/1.1\r\nContent-Length: -1\r\n\r\n", "Content-Length"},
        {"GET / HTTP/1.1\r\nContent-Length: 0x10\r\n\r\n", "Content-Length"},
        {"GET / HTTP/1.1\r\nContent-Length: 1, 2\r\n\r\n", "Content-Length"},
        {"GET / HTTP/1.1\r\nContent-Length: 99999999999999999999\r\n\r\n", "Content-Length"},
        {"POST / HTTP/1.1\r\nContent-Length: 3\r\nTransfer-Encoding: chunked\r\n\r\n", "both"},
        {"POST / HTTP/1.1\r\nTransfer-Encoding: gzip, chunked\r\n\r\n", "only chunked"},
        {"POST / HTTP/1.1\r\nTransfer-Encoding: chunked\r\nTransfer-Encoding: chunked\r\n\r\n",
         "only chunked"},
        {"POST / HTTP/1.0\r\nTransfer-Encoding: chunked\r\n\r\n", "HTTP/1.0"},
        {"GET / HTTP/1.1\r\nExpect: 200-ok\r\n\r\n", "only 100-continue"},
        {"GET / HTTP/1.1\r\nHost: a\r\nHost: b\r\n\r\n", "more than one Host"},
        {"GET / HTTP/1.1\r\nBad Name: x\r\n\r\n", "line 2"},
        {"GET / HTTP/1.1\r\nName : x\r\n\r\n", "no space before the colon"},
        {"GET / HTTP/1.1\r\nNoColon\r\n\r\n", "NAME: VALUE"},
        {"GET / HTTP/1.1\r\nA: b\r\n  folded\r\n\r\n", "folded"},
        {"GET / HTTP/1.1\r\nA: b\x01\r\n\r\n", "control character"},
        {"GET / HTTP/1.1\r\nA: b\rc\r\n\r\n", "bare CR"},
        {"GET /%00 HTTP/1.1\r\n\r\n", "percent escape"},
        {"GET /%4 HTTP/1.1\r\n\r\n", "percent escape"},
        {"GET /?a=%g1 HTTP/1.1\r\n\r\n", "query string"},
        {"GET / HTTP/1.2\r\n\r\n", "HTTP version"},
        {"GET / HTTP/1.1 x\r\n\r\n", "METHOD SP TARGET"},
        {"GET  / HTTP/1.1\r\n\r\n", "METHOD SP TARGET"},
        {"GET /\r\n\r\n", "METHOD SP TARGET"},
        {"G(T / HTTP/1.1\r\n\r\n", "method"},
        {"GET relative HTTP/1.1\r\n\r\n", "origin form"},
        {"GET /\x7f HTTP/1.1\r\n\r\n", "visible ASCII"},
        {"\r\n\r\n", "METHOD SP TARGET"},
    };
    for (const auto& c : cases) {
        const HeadError e = parse_error(c.head);
        EXPECT_EQ(e.status, 400) << c.head;
        EXPECT_NE(e.detail.find(c.detail), std::string::npos) << c.head << " -> " << e.detail;
    }
}

TEST(RequestHead, LimitsAre431) {
    std::string many = "GET / HTTP/1.1\r\n";
    for (int i = 0; i < 5; ++i) many += "X-" + std::to_string(i) + ": y\r\n";
    many += "\r\n";
    HeadError e = parse_error(many, {.max_head_bytes = 1 << 10, .max_headers = 4});
    EXPECT_EQ(e.status, 431);
    EXPECT_NE(e.detail.find("max_request_headers"), std::string::npos) << e.detail;
    e = parse_error(many, {.max_head_bytes = 40, .max_headers = 100});
    EXPECT_EQ(e.status, 431);
    EXPECT_NE(e.detail.find("max_request_head_bytes"), std::string::npos) << e.detail;
    // A long target within the limit is fine (issue 25 item 8: no lower limit of its own).
    const std::string target(30000, 'a');
    EXPECT_EQ(parse_ok("GET /?q=" + target + " HTTP/1.1\r\n\r\n").query[0].second, target);
}

TEST(RequestHead, EveryByteStringIsAnsweredWithoutCrashing) {
    // Truncations and single-byte changes of a valid head: each parses or is refused with 400/431.
    const std::string valid =
        "POST /v1/meshes/a/intersect?x=1 HTTP/1.1\r\nHost: h\r\nContent-Length: 5\r\n\r\n";
    for (size_t cut = 0; cut <= valid.size(); ++cut) {
        auto parsed = parse_request_head(valid.substr(0, cut), kLimits);
        if (!parsed) {
            EXPECT_TRUE(parsed.error().status == 400 || parsed.error().status == 431);
        }
    }
    for (size_t at = 0; at < valid.size(); ++at) {
        for (int byte : {0, int{'\r'}, int{'\n'}, int{' '}, int{':'}, int{'%'}, 0x80, 0xff}) {
            std::string changed = valid;
            changed[at] = static_cast<char>(byte);
            auto parsed = parse_request_head(changed, kLimits);
            if (!parsed) {
                EXPECT_FALSE(parsed.error().detail.empty()) << at << " " << byte;
            }
        }
    }
}

}  // namespace
}  // namespace kdrt::server
