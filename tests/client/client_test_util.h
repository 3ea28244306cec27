#pragma once
// Helpers shared by the client tests: test meshes and files, a kdrt-server per suite.

#include <gtest/gtest.h>

#include <cstring>
#include <filesystem>
#include <fstream>
#include <string>
#include <vector>

#include "kdrt/client/client.h"
#include "kdrt/kdtree.h"
#include "kdrt/proto/file_io.h"
#include "kdrt/proto/image_io.h"
#include "kdrt/proto/mesh_io.h"
#include "server_process.h"
#include "test_util.h"

namespace kdrt::test {

inline std::string data_path(const std::string& name) {
    return std::string(KDRT_TEST_DATA_DIR) + "/" + name;
}

inline Mesh load_mesh(const std::string& path) {
    auto mesh = proto::load_mesh_file(path);
    if (!mesh) throw std::runtime_error(mesh.error().to_string());
    return std::move(*mesh);
}

inline std::string server_url(const ServerProcess& server) {
    return "http://127.0.0.1:" + std::to_string(server.port());
}

/// Writes `text` to `path`.
inline void write_text(const std::filesystem::path& path, const std::string& text) {
    std::ofstream out(path, std::ios::binary | std::ios::trunc);
    out << text;
}

inline std::vector<std::byte> read_bytes(const std::filesystem::path& path) {
    auto bytes = proto::read_file_bytes(path);
    if (!bytes) throw std::runtime_error(bytes.error());
    return std::move(*bytes);
}

/// The bytes as a std::string (to compare with a CLI's captured stdout).
inline std::string as_string(const std::vector<std::byte>& bytes) {
    return {reinterpret_cast<const char*>(bytes.data()), bytes.size()};
}

/// Options that make failures fast in tests: short backoff.
inline ClientOptions fast_options() {
    ClientOptions options;
    options.backoff_initial = std::chrono::milliseconds(1);
    options.backoff_max = std::chrono::milliseconds(20);
    options.connect_timeout = std::chrono::milliseconds(2000);
    return options;
}

/// Bitwise equality of two arrays of trivially copyable values (hits compare NaN-safe).
template <class T, class A>
bool same_bits(const std::vector<T, A>& a, const std::vector<T, A>& b) {
    return a.size() == b.size() &&
           (a.empty() || std::memcmp(a.data(), b.data(), a.size() * sizeof(T)) == 0);
}

/// The same rendered image: identical bytes for PNG and JPEG; for EXR (whose header carries the
/// time it was written) identical size and pixels.
inline void expect_same_image(const std::vector<std::byte>& got, const std::vector<std::byte>& want,
                              const std::string& format) {
    if (format != "exr") {
        EXPECT_EQ(got, want);
        return;
    }
    auto a = proto::decode_image(got);
    auto b = proto::decode_image(want);
    ASSERT_TRUE(a) << a.error();
    ASSERT_TRUE(b) << b.error();
    EXPECT_EQ(a->width, b->width);
    EXPECT_EQ(a->height, b->height);
    EXPECT_EQ(a->channels, b->channels);
    EXPECT_TRUE(same_bits(a->pixels, b->pixels));
}

/// Images render deterministically: the request every render test uses (small, fast).
inline RenderRequest small_render(const std::string& id, Shading shading = Shading::kEyelight,
                                  std::string format = "png") {
    RenderRequest request;
    request.mesh = id;
    request.settings.width = 96;
    request.settings.height = 64;
    request.settings.shading = shading;
    request.format = std::move(format);
    return request;
}

}  // namespace kdrt::test
