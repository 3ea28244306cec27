#pragma once
/// The HTTP/1.1 request head reader of the connection layer (http_front.*): finds where a head
/// ends in the bytes received so far, and parses a complete head strictly (RFC 9112). It knows
/// no sockets and no cpp-httplib, so unit tests and the libFuzzer target
/// (tests/fuzz/request_head_fuzz.cpp) drive it directly.

#include <cstddef>
#include <cstdint>
#include <optional>
#include <string>
#include <string_view>
#include <utility>
#include <vector>

#include "kdrt/proto/result.h"

namespace kdrt::server {

/// Limits a head is read against (ConnectionLimits / config: max_request_head_bytes,
/// max_request_headers).
struct HeadLimits {
    size_t max_head_bytes = size_t{32} << 10;
    size_t max_headers = 100;
};

/// A parsed request head. Header names keep their case (compare them case-insensitively).
struct RequestHead {
    std::string method;   ///< a token, e.g. "GET"
    std::string target;   ///< as sent (origin-form; an absolute-form target is reduced to it)
    std::string path;     ///< the target's path, percent-decoded
    std::string version;  ///< "HTTP/1.1" or "HTTP/1.0"
    std::vector<std::pair<std::string, std::string>> query;    ///< decoded, '+' is a space
    std::vector<std::pair<std::string, std::string>> headers;  ///< values without OWS
    std::optional<uint64_t> content_length;                    ///< the one Content-Length, if given
    bool chunked = false;                                      ///< Transfer-Encoding: chunked
    bool expect_continue = false;                              ///< Expect: 100-continue
    bool keep_alive = true;  ///< HTTP/1.1 without "Connection: close", or 1.0 with keep-alive
};

/// Why a head was refused: the status to answer with (400, or 431 over a limit) and a detail
/// naming what and where (the header's name, the line number).
struct HeadError {
    int status = 400;
    std::string detail;
};

/// What find_head_end has seen of a head still arriving.
struct HeadScan {
    size_t scanned = 0;  ///< bytes already searched for the blank line (resume point)
    size_t lines = 0;    ///< line ends seen so far
};

/// The length of the head at the start of `data` (through its blank line: CRLF CRLF, or bare
/// LFs as RFC 9112 2.2 allows), or nullopt while it is incomplete. `scan` carries the search
/// across calls on a growing buffer (start with a fresh HeadScan for each head); its `lines`
/// counts the head's line ends, for the header-count limit while the head still arrives.
/// Empty lines before the request line must have been skipped by the caller.
[[nodiscard]] std::optional<size_t> find_head_end(std::string_view data, HeadScan& scan) noexcept;

/// Parses a complete head (as delimited by find_head_end, blank line included). Strict: a
/// method token, an origin-form (or absolute-form) target of visible ASCII, HTTP/1.0 or 1.1;
/// header names are tokens with no space before the colon, values have no control characters,
/// no obsolete line folding; Content-Length is one decimal number, not combined with
/// Transfer-Encoding; Transfer-Encoding is "chunked" alone; Expect is 100-continue alone; at
/// most one Host; a target that percent-decodes (no bad escape, no encoded NUL). Any of these
/// broken: 400 naming it; over `limits`: 431. Never throws on any input.
[[nodiscard]] proto::Result<RequestHead, HeadError> parse_request_head(std::string_view head,
                                                                       const HeadLimits& limits);

/// True when `a` and `b` are equal ignoring ASCII case.
[[nodiscard]] bool iequals(std::string_view a, std::string_view b) noexcept;

}  // namespace kdrt::server
