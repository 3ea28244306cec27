// notify_systemd (server/core/systemd_notify.h) against AF_UNIX datagram sockets this test creates
// (a path and an abstract name), as systemd would: the datagram holds exactly the state sent.

#include "core/systemd_notify.h"

#include <gtest/gtest.h>
#include <sys/socket.h>
#include <sys/un.h>
#include <unistd.h>

#include <cstdlib>
#include <cstring>
#include <filesystem>
#include <string>

namespace kdrt::server {
namespace {

/// A bound datagram socket; `name` is what NOTIFY_SOCKET holds for it.
class NotifySocket {
public:
    explicit NotifySocket(const std::string& name) : name_(name) {
        fd_ = ::socket(AF_UNIX, SOCK_DGRAM | SOCK_CLOEXEC, 0);
        sockaddr_un address{};
        address.sun_family = AF_UNIX;
        std::memcpy(address.sun_path, name.data(), name.size());
        if (name[0] == '@') address.sun_path[0] = '\0';
        const auto length = static_cast<socklen_t>(offsetof(sockaddr_un, sun_path) + name.size() +
                                                   (name[0] == '/' ? 1 : 0));
        bound_ = fd_ >= 0 && ::bind(fd_, reinterpret_cast<const sockaddr*>(&address), length) == 0;
        timeval timeout{2, 0};
        ::setsockopt(fd_, SOL_SOCKET, SO_RCVTIMEO, &timeout, sizeof timeout);
    }
    ~NotifySocket() {
        if (fd_ >= 0) ::close(fd_);
        if (name_[0] == '/') std::filesystem::remove(name_);
    }
    [[nodiscard]] bool bound() const { return bound_; }
    /// The next datagram, or "<none>" after 2 s.
    std::string receive() {
        char buf[4096];
        const ssize_t n = ::recv(fd_, buf, sizeof buf, 0);
        return n < 0 ? "<none>" : std::string(buf, static_cast<size_t>(n));
    }

private:
    std::string name_;
    int fd_ = -1;
    bool bound_ = false;
};

/// Sets NOTIFY_SOCKET for one test.
class NotifyEnv {
public:
    explicit NotifyEnv(const std::string& value) { ::setenv("NOTIFY_SOCKET", value.c_str(), 1); }
    ~NotifyEnv() { ::unsetenv("NOTIFY_SOCKET"); }
};

TEST(SystemdNotify, WithoutNotifySocketItDoesNothing) {
    ::unsetenv("NOTIFY_SOCKET");
    EXPECT_TRUE(notify_systemd("READY=1"));
    NotifyEnv empty("");
    EXPECT_TRUE(notify_systemd("READY=1"));
}

TEST(SystemdNotify, SendsTheStateToAPathSocket) {
    const std::string path =
        (std::filesystem::temp_directory_path() / ("kdrt-notify-" + std::to_string(::getpid())))
            .string();
    std::filesystem::remove(path);
    NotifySocket socket(path);
    ASSERT_TRUE(socket.bound()) << path;
    NotifyEnv env(path);
    ASSERT_TRUE(notify_systemd("READY=1\nSTATUS=ready, 3 meshes"));
    EXPECT_EQ(socket.receive(), "READY=1\nSTATUS=ready, 3 meshes");
    ASSERT_TRUE(notify_systemd("STOPPING=1"));
    EXPECT_EQ(socket.receive(), "STOPPING=1");
}

TEST(SystemdNotify, SendsTheStateToAnAbstractSocket) {
    const std::string name = "@kdrt-notify-test-" + std::to_string(::getpid());
    NotifySocket socket(name);
    ASSERT_TRUE(socket.bound()) << name;
    NotifyEnv env(name);
    ASSERT_TRUE(notify_systemd("READY=1"));
    EXPECT_EQ(socket.receive(), "READY=1");
}

TEST(SystemdNotify, ErrorsNameTheSocket) {
    {
        NotifyEnv env("relative/socket");
        auto sent = notify_systemd("READY=1");
        ASSERT_FALSE(sent);
        EXPECT_NE(sent.error().find("\"relative/socket\""), std::string::npos) << sent.error();
    }
    {
        NotifyEnv env("/nonexistent-dir/kdrt/notify");
        auto sent = notify_systemd("READY=1");
        ASSERT_FALSE(sent);
        EXPECT_NE(sent.error().find("/nonexistent-dir/kdrt/notify: sendto(): "), std::string::npos)
            << sent.error();
    }
    {
        NotifyEnv env("/" + std::string(200, 'x'));
        EXPECT_FALSE(notify_systemd("READY=1"));
    }
}

}  // namespace
}  // namespace kdrt::server
