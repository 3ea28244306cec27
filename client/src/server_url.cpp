#include "kdrt/client/server_url.h"

#include <cctype>
#include <charconv>

#include "kdrt/proto/text.h"

namespace kdrt {
namespace {

using proto::in_quotes;

bool is_host_char(char c) noexcept {
    return (c >= 'a' && c <= 'z') || (c >= 'A' && c <= 'Z') || (c >= '0' && c <= '9') || c == '-' ||
           c == '.' || c == '_';
}

}  // namespace

std::string ServerUrl::to_string() const {
    const bool ipv6 = host.find(':') != std::string::npos;
    return scheme + "://" + (ipv6 ? "[" + host + "]" : host) + ":" + std::to_string(port) +
           base_path;
}

proto::Result<ServerUrl, std::string> parse_server_url(std::string_view text) {
    const std::string what = "server URL " + in_quotes(text);
    ServerUrl url;
    std::string_view rest = text;
    if (const size_t sep = rest.find("://"); sep != std::string_view::npos) {
        const std::string_view scheme = rest.substr(0, sep);
        if (scheme == "http" || scheme == "HTTP") {
            url.scheme = "http";
        } else if (scheme == "https" || scheme == "HTTPS") {
            url.scheme = "https";
            url.port = 443;
        } else {
            return proto::Err{what + ": unknown scheme " + in_quotes(scheme) +
                              " (expected http or https)"};
        }
        rest.remove_prefix(sep + 3);
    }
    if (rest.find_first_of("?#") != std::string_view::npos)
        return proto::Err{what + ": a server URL has no query or fragment"};
    if (rest.find('@') != std::string_view::npos)
        return proto::Err{what +
                          ": user information in the URL is not supported (use the token option)"};
    const size_t slash = rest.find('/');
    std::string_view authority = rest.substr(0, slash);
    std::string_view path =
        slash == std::string_view::npos ? std::string_view() : rest.substr(slash);
    while (!path.empty() && path.back() == '/') path.remove_suffix(1);
    url.base_path = std::string(path);

    std::string_view port_text;
    if (!authority.empty() && authority.front() == '[') {
        const size_t close = authority.find(']');
        if (close == std::string_view::npos)
            return proto::Err{what + ": unterminated [ in the IPv6 host"};
        url.host = std::string(authority.substr(1, close - 1));
        for (char c : url.host)
            if (!(std::isxdigit(static_cast<unsigned char>(c)) || c == ':' || c == '.'))
                return proto::Err{what + ": " + in_quotes(url.host) + " is not an IPv6 address"};
        std::string_view after = authority.substr(close + 1);
        if (!after.empty()) {
            if (after.front() != ':')
                return proto::Err{what + ": expected :PORT after the IPv6 host"};
            port_text = after.substr(1);
            if (port_text.empty()) return proto::Err{what + ": empty port"};
        }
    } else {
        const size_t colon = authority.rfind(':');
        url.host = std::string(authority.substr(0, colon));
        if (colon != std::string_view::npos) {
            port_text = authority.substr(colon + 1);
            if (port_text.empty()) return proto::Err{what + ": empty port"};
        }
        for (char c : url.host)
            if (!is_host_char(c))
                return proto::Err{what + ": " + in_quotes(url.host) + " is not a host name"};
    }
    if (url.host.empty()) return proto::Err{what + ": no host"};
    if (!port_text.empty()) {
        int port = 0;
        const auto [end, ec] =
            std::from_chars(port_text.data(), port_text.data() + port_text.size(), port);
        if (ec != std::errc() || end != port_text.data() + port_text.size() || port < 1 ||
            port > 65535)
            return proto::Err{what + ": port " + in_quotes(port_text) +
                              " is not a number in 1 .. 65535"};
        url.port = port;
    }
    return url;
}

}  // namespace kdrt
