// The HTTP front's request head reader (server/http/request_head.cpp), fed as the front feeds
// it: the input arrives in pieces (the first byte picks the piece size), find_head_end looks for
// the head's end after each piece, and a complete head goes to parse_request_head; the bytes
// after it are the next pipelined request, read the same way.
// Oracles: a found end lies within what has arrived, and is the same whatever the piece size;
// a parsed head has a token method, a version of 1.0 or 1.1, a path that starts with / (or is
// *), no two framings and header counts within the limits; a refusal is 400 or 431 with a
// detail.

#include <algorithm>
#include <string>
#include <string_view>

#include "fuzz_check.h"
#include "http/request_head.h"

namespace {

using kdrt::fuzz::require;
using namespace kdrt::server;

const HeadLimits kLimits{.max_head_bytes = 4096, .max_headers = 16};

/// The end of the head at the start of `data` when it arrives `piece` bytes at a time.
std::optional<size_t> end_in_pieces(std::string_view data, size_t piece) {
    HeadScan scan;
    for (size_t arrived = std::min(piece, data.size());;
         arrived = std::min(arrived + piece, data.size())) {
        const std::optional<size_t> end = find_head_end(data.substr(0, arrived), scan);
        if (end) {
            require(*end <= arrived);
            return end;
        }
        require(scan.scanned <= arrived);
        if (arrived == data.size()) return std::nullopt;
    }
}

void check_head(std::string_view head) {
    auto parsed = parse_request_head(head, kLimits);
    if (!parsed) {
        require(parsed.error().status == 400 || parsed.error().status == 431);
        require(!parsed.error().detail.empty());
        return;
    }
    const RequestHead& h = *parsed;
    require(!h.method.empty() && h.method.size() <= 32);
    require(h.version == "HTTP/1.1" || h.version == "HTTP/1.0");
    require(h.path == "*" || (!h.path.empty() && h.path.front() == '/'));
    require(h.path.find('\0') == std::string::npos);
    require(!(h.chunked && h.content_length));
    require(h.headers.size() <= kLimits.max_headers);
    require(head.size() <= kLimits.max_head_bytes);
    for (const auto& [name, value] : h.headers) {
        require(!name.empty());
        require(value.find_first_of("\r\n") == std::string::npos);
    }
}

}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
    if (size == 0) return 0;
    const size_t piece = 1 + data[0] % 64;
    std::string_view rest(reinterpret_cast<const char*>(data) + 1, size - 1);
    for (int requests = 0; requests < 8 && !rest.empty(); ++requests) {
        // Empty lines before a request line are skipped (RFC 9112 2.2), as the front does.
        while (!rest.empty() && (rest.front() == '\r' || rest.front() == '\n'))
            rest.remove_prefix(1);
        const std::optional<size_t> end = end_in_pieces(rest, piece);
        HeadScan whole;
        require(find_head_end(rest, whole) == end);
        if (!end) break;
        check_head(rest.substr(0, *end));
        rest.remove_prefix(*end);
    }
    return 0;
}
