#include "http/request_head.h"

#include <algorithm>
#include <cctype>
#include <charconv>

namespace kdrt::server {
namespace {

using proto::Err;

/// RFC 9110 5.6.2: tchar.
bool is_tchar(char c) noexcept {
    const auto u = static_cast<unsigned char>(c);
    if (u >= '0' && u <= '9') return true;
    if ((u | 0x20) >= 'a' && (u | 0x20) <= 'z') return true;
    return std::string_view("!#$%&'*+-.^_`|~").find(c) != std::string_view::npos;
}

bool is_token(std::string_view s) noexcept {
    return !s.empty() && std::all_of(s.begin(), s.end(), is_tchar);
}

/// A header value's characters: visible ASCII, obs-text, space and tab (no CTLs, no DEL).
bool is_field_value(std::string_view s) noexcept {
    return std::all_of(s.begin(), s.end(), [](char c) {
        const auto u = static_cast<unsigned char>(c);
        return u == '\t' || (u >= 0x20 && u != 0x7f);
    });
}

std::string_view trim_ows(std::string_view s) noexcept {
    while (!s.empty() && (s.front() == ' ' || s.front() == '\t')) s.remove_prefix(1);
    while (!s.empty() && (s.back() == ' ' || s.back() == '\t')) s.remove_suffix(1);
    return s;
}

int hex_digit(char c) noexcept {
    if (c >= '0' && c <= '9') return c - '0';
    if (c >= 'a' && c <= 'f') return c - 'a' + 10;
    if (c >= 'A' && c <= 'F') return c - 'A' + 10;
    return -1;
}

/// Percent-decodes `in` (and '+' as a space for query parts). False on a bad escape or an
/// encoded NUL.
bool percent_decode(std::string_view in, bool plus_is_space, std::string& out) {
    out.clear();
    out.reserve(in.size());
    for (size_t i = 0; i < in.size(); ++i) {
        const char c = in[i];
        if (c == '%') {
            if (i + 2 >= in.size()) return false;
            const int hi = hex_digit(in[i + 1]), lo = hex_digit(in[i + 2]);
            if (hi < 0 || lo < 0 || (hi == 0 && lo == 0)) return false;
            out.push_back(static_cast<char>(hi * 16 + lo));
            i += 2;
        } else {
            out.push_back(plus_is_space && c == '+' ? ' ' : c);
        }
    }
    return true;
}

/// The request line and the target's parts; the rest of the head is parsed by the caller.
std::optional<HeadError> parse_request_line(std::string_view line, RequestHead& head) {
    const size_t sp1 = line.find(' ');
    const size_t sp2 = sp1 == std::string_view::npos ? sp1 : line.find(' ', sp1 + 1);
    if (sp2 == std::string_view::npos || line.find(' ', sp2 + 1) != std::string_view::npos)
        return HeadError{400, "the request line is not METHOD SP TARGET SP HTTP-VERSION"};
    const std::string_view method = line.substr(0, sp1);
    std::string_view target = line.substr(sp1 + 1, sp2 - sp1 - 1);
    const std::string_view version = line.substr(sp2 + 1);
    if (!is_token(method) || method.size() > 32)
        return HeadError{400, "the request method is not a token of at most 32 characters"};
    if (version != "HTTP/1.1" && version != "HTTP/1.0") {
        const bool http = version.size() == 8 && version.substr(0, 5) == "HTTP/" &&
                          std::isdigit(static_cast<unsigned char>(version[5])) &&
                          version[6] == '.' && std::isdigit(static_cast<unsigned char>(version[7]));
        if (http)
            return HeadError{400, "HTTP version " + std::string(version) + " (only 1.0, 1.1)"};
        return HeadError{400, "the request line does not end in an HTTP version"};
    }
    const bool visible = !target.empty() && std::all_of(target.begin(), target.end(), [](char c) {
        const auto u = static_cast<unsigned char>(c);
        return u > 0x20 && u < 0x7f;
    });
    if (!visible)
        return HeadError{400,
                         "the request target is empty or has characters outside visible "
                         "ASCII"};
    head.method = std::string(method);
    head.version = std::string(version);
    head.keep_alive = version == "HTTP/1.1";  // 1.0: only with Connection: keep-alive
    // RFC 9112 3.2.2: a server accepts the absolute form; only its path and query matter here.
    for (std::string_view scheme : {"http://", "https://"}) {
        if (target.size() > scheme.size() && iequals(target.substr(0, scheme.size()), scheme)) {
            const size_t slash = target.find('/', scheme.size());
            const size_t query = target.find('?', scheme.size());
            const size_t start = std::min(slash, query);
            target = start == std::string_view::npos ? std::string_view("/") : target.substr(start);
            break;
        }
    }
    if (target.front() != '/' && !(target == "*" && method == "OPTIONS"))
        return HeadError{400, "the request target is not a path (origin form, starting with /)"};
    head.target = target.front() == '?' ? "/" + std::string(target) : std::string(target);
    const std::string_view full = head.target;
    const size_t question = full.find('?');
    std::string_view path = full.substr(0, question);
    const size_t fragment = path.find('#');
    path = path.substr(0, fragment);
    if (!percent_decode(path, false, head.path))
        return HeadError{400, "the request path has an invalid percent escape (or %00)"};
    if (question == std::string_view::npos) return std::nullopt;
    std::string_view query = full.substr(question + 1);
    query = query.substr(0, query.find('#'));
    while (!query.empty()) {
        const size_t amp = query.find('&');
        const std::string_view part = query.substr(0, amp);
        query = amp == std::string_view::npos ? std::string_view() : query.substr(amp + 1);
        if (part.empty()) continue;
        const size_t eq = part.find('=');
        std::string key, value;
        if (!percent_decode(part.substr(0, eq), true, key) ||
            !percent_decode(eq == std::string_view::npos ? std::string_view() : part.substr(eq + 1),
                            true, value))
            return HeadError{400, "the query string has an invalid percent escape (or %00)"};
        head.query.emplace_back(std::move(key), std::move(value));
    }
    return std::nullopt;
}

/// Applies one header field to what the connection layer must know (framing, continuation).
std::optional<HeadError> note_field(std::string_view name, std::string_view value,
                                    RequestHead& head, bool& seen_length, bool& seen_host) {
    if (iequals(name, "Content-Length")) {
        uint64_t n = 0;
        const auto [end, ec] = std::from_chars(value.data(), value.data() + value.size(), n);
        const bool digits =
            !value.empty() && value.size() <= 19 &&
            std::all_of(value.begin(), value.end(), [](char c) { return c >= '0' && c <= '9'; });
        if (seen_length || !digits || ec != std::errc() || end != value.data() + value.size())
            return HeadError{400, "invalid Content-Length \"" + std::string(value.substr(0, 64)) +
                                      "\" (one decimal number of bytes, given once)"};
        seen_length = true;
        head.content_length = n;
    } else if (iequals(name, "Transfer-Encoding")) {
        if (head.chunked || !iequals(value, "chunked"))
            return HeadError{400, "Transfer-Encoding \"" + std::string(value.substr(0, 64)) +
                                      "\" is not supported (only chunked, alone)"};
        head.chunked = true;
    } else if (iequals(name, "Expect")) {
        if (!iequals(value, "100-continue"))
            return HeadError{400, "Expect \"" + std::string(value.substr(0, 64)) +
                                      "\" is not supported (only 100-continue)"};
        head.expect_continue = true;
    } else if (iequals(name, "Host")) {
        if (seen_host) return HeadError{400, "the request has more than one Host header"};
        seen_host = true;
    } else if (iequals(name, "Connection")) {
        // A list of tokens: close, keep-alive, or header names.
        std::string_view rest = value;
        while (!rest.empty()) {
            const size_t comma = rest.find(',');
            const std::string_view option = trim_ows(rest.substr(0, comma));
            rest = comma == std::string_view::npos ? std::string_view() : rest.substr(comma + 1);
            if (iequals(option, "close")) head.keep_alive = false;
            if (iequals(option, "keep-alive") && head.version == "HTTP/1.0") head.keep_alive = true;
        }
    }
    return std::nullopt;
}

}  // namespace

bool iequals(std::string_view a, std::string_view b) noexcept {
    return a.size() == b.size() && std::equal(a.begin(), a.end(), b.begin(), [](char x, char y) {
               return std::tolower(static_cast<unsigned char>(x)) ==
                      std::tolower(static_cast<unsigned char>(y));
           });
}

std::optional<size_t> find_head_end(std::string_view data, HeadScan& scan) noexcept {
    for (size_t i = scan.scanned; i < data.size(); ++i) {
        if (data[i] != '\n') continue;
        if (i + 1 < data.size() && data[i + 1] == '\n') return i + 2;
        if (i + 2 < data.size() && data[i + 1] == '\r' && data[i + 2] == '\n') return i + 3;
        if (i + 2 >= data.size()) {  // the blank line may still be arriving: look here again
            scan.scanned = i;
            return std::nullopt;
        }
        ++scan.lines;
    }
    scan.scanned = data.size();
    return std::nullopt;
}

proto::Result<RequestHead, HeadError> parse_request_head(std::string_view head,
                                                         const HeadLimits& limits) {
    if (head.size() > limits.max_head_bytes)
        return Err{HeadError{431, "the request head exceeds " +
                                      std::to_string(limits.max_head_bytes) +
                                      " bytes (max_request_head_bytes)"}};
    RequestHead out;
    bool seen_length = false, seen_host = false;
    size_t line_number = 0;
    size_t pos = 0;
    while (pos < head.size()) {
        size_t end = head.find('\n', pos);
        if (end == std::string_view::npos) end = head.size();
        std::string_view line = head.substr(pos, end - pos);
        pos = end + 1;
        if (!line.empty() && line.back() == '\r') line.remove_suffix(1);
        ++line_number;
        if (line.find('\r') != std::string_view::npos)
            return Err{HeadError{
                400, "line " + std::to_string(line_number) + " of the request head has a bare CR"}};
        if (line_number == 1) {
            if (auto error = parse_request_line(line, out)) return Err{std::move(*error)};
            continue;
        }
        if (line.empty()) break;  // the blank line that ends the head
        if (out.headers.size() >= limits.max_headers)
            return Err{HeadError{431, "the request has more than " +
                                          std::to_string(limits.max_headers) +
                                          " header lines (max_request_headers)"}};
        if (line.front() == ' ' || line.front() == '\t')
            return Err{HeadError{400, "line " + std::to_string(line_number) +
                                          " of the request head is folded (obsolete line "
                                          "folding is not accepted)"}};
        const size_t colon = line.find(':');
        const std::string_view name =
            line.substr(0, colon == std::string_view::npos ? line.size() : colon);
        if (colon == std::string_view::npos || !is_token(name))
            return Err{HeadError{400, "line " + std::to_string(line_number) +
                                          " of the request head is not NAME: VALUE (a token "
                                          "name, no space before the colon)"}};
        const std::string_view value = trim_ows(line.substr(colon + 1));
        if (!is_field_value(value))
            return Err{HeadError{400, "header " + std::string(name.substr(0, 64)) +
                                          " has a control character in its value"}};
        if (auto error = note_field(name, value, out, seen_length, seen_host))
            return Err{std::move(*error)};
        out.headers.emplace_back(std::string(name), std::string(value));
    }
    if (line_number == 0) return Err{HeadError{400, "the request head is empty"}};
    if (out.version == "HTTP/1.0" && out.chunked)
        return Err{HeadError{400, "Transfer-Encoding in an HTTP/1.0 request"}};
    // RFC 9112 6.3: both framings is a smuggling attempt, or a broken client.
    if (out.chunked && out.content_length)
        return Err{HeadError{400, "the request has both Content-Length and Transfer-Encoding"}};
    return out;
}

}  // namespace kdrt::server
