#pragma once
/// The address of a kdrt-server: "http://HOST[:PORT][/PREFIX]", "https://...", or a bare
/// "HOST[:PORT]" (http). IPv6 hosts go in brackets: "http://[::1]:8080".

#include <string>
#include <string_view>

#include "kdrt/proto/result.h"

namespace kdrt {

/// Default address of the `kdrt` CLI and of KDRT_SERVER-less callers.
inline constexpr std::string_view kDefaultServerUrl = "http://127.0.0.1:8080";

struct ServerUrl {
    std::string scheme = "http";  ///< "http" or "https"
    std::string host;             ///< without brackets for IPv6
    int port = 80;                ///< 1 .. 65535; default 80 (http) or 443 (https)
    std::string base_path;  ///< "" or "/prefix" (no trailing '/'): prepended to every API path

    /// "scheme://host:port/prefix", IPv6 hosts in brackets.
    [[nodiscard]] std::string to_string() const;
};

/// Parses a server address. Errors name the value and the problem: an unknown scheme, an empty
/// host, a port that is not 1 .. 65535, a query or fragment, characters not allowed in a host.
[[nodiscard]] proto::Result<ServerUrl, std::string> parse_server_url(std::string_view text);

}  // namespace kdrt
