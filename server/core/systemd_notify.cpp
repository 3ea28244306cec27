// sd_notify's datagram protocol (systemd_notify.h).

#include "core/systemd_notify.h"

#include <sys/socket.h>
#include <sys/un.h>
#include <unistd.h>

#include <cerrno>
#include <cstdlib>
#include <cstring>

namespace kdrt::server {

proto::Result<void, std::string> notify_systemd(std::string_view state) {
    const char* name = std::getenv("NOTIFY_SOCKET");
    if (!name || !*name) return {};
    const std::string path(name);
    sockaddr_un address{};
    address.sun_family = AF_UNIX;
    // A path, or '@' for the abstract namespace (a leading NUL byte, no terminator).
    if ((path[0] != '/' && path[0] != '@') || path.size() > sizeof(address.sun_path) ||
        (path[0] == '/' && path.size() == sizeof(address.sun_path)))
        return proto::Err{"NOTIFY_SOCKET \"" + path +
                          "\" is not an absolute path or @abstract name that fits sun_path"};
    std::memcpy(address.sun_path, path.data(), path.size());
    if (path[0] == '@') address.sun_path[0] = '\0';
    const auto length = static_cast<socklen_t>(offsetof(sockaddr_un, sun_path) + path.size() +
                                               (path[0] == '/' ? 1 : 0));
    const int fd = ::socket(AF_UNIX, SOCK_DGRAM | SOCK_CLOEXEC, 0);
    if (fd < 0) return proto::Err{"NOTIFY_SOCKET: socket(): " + std::string(std::strerror(errno))};
    const ssize_t sent = ::sendto(fd, state.data(), state.size(), MSG_NOSIGNAL,
                                  reinterpret_cast<const sockaddr*>(&address), length);
    const int error = errno;
    ::close(fd);
    if (sent < 0 || static_cast<size_t>(sent) != state.size())
        return proto::Err{"NOTIFY_SOCKET " + path + ": sendto(): " +
                          std::string(sent < 0 ? std::strerror(error) : "short write")};
    return {};
}

}  // namespace kdrt::server
