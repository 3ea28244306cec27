#pragma once
/// Readiness and stop notices to systemd (a unit with Type=notify, deploy/systemd/kdrt.service),
/// by the public sd_notify protocol: one datagram of "KEY=VALUE\n" lines to the AF_UNIX socket
/// named by $NOTIFY_SOCKET (a path, or "@name" for the abstract namespace). No libsystemd. Without
/// $NOTIFY_SOCKET (not started by systemd) it does nothing.

#include <string>
#include <string_view>

#include "kdrt/proto/result.h"

namespace kdrt::server {

/// Sends `state` (e.g. "READY=1\nSTATUS=serving") to $NOTIFY_SOCKET. Ok when the variable is
/// unset or empty (nothing to notify); an error names the socket and the reason (a bad name,
/// or a failed sendto) so the caller can log it. Thread-safe.
[[nodiscard]] proto::Result<void, std::string> notify_systemd(std::string_view state);

}  // namespace kdrt::server
