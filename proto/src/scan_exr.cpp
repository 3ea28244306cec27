// Depth images as OpenEXR (kdrt/proto/scan_image.h): float depth, uint prim and float normal
// channels in one scanline file, written and read through OpenImageIO's in-memory proxies.

#include <OpenImageIO/filesystem.h>
#include <OpenImageIO/imageio.h>

#include <cstring>
#include <mutex>

#include "kdrt/proto/errors.h"
#include "kdrt/proto/scan_image.h"

namespace kdrt::proto {
namespace {

/// As image_io.cpp: kdrt parallelises with oneTBB, so OIIO works on the calling thread.
void configure_oiio_once() {
    static std::once_flag once;
    std::call_once(once, [] {
        OIIO::attribute("threads", 1);
        OIIO::attribute("exr_threads", 1);
    });
}

template <class Object>
std::string object_error(Object& object, std::string_view fallback) {
    std::string message = object.geterror();
    if (message.empty()) message = OIIO::geterror();
    return message.empty() ? std::string(fallback) : message;
}

}  // namespace

Result<std::vector<std::byte>, std::string> encode_depth_exr(
    const DepthImage& image, std::span<const uint32_t> geometry_ids) {
    const size_t n = size_t{image.width} * image.height;
    const bool normals = !image.normals.empty();
    const bool geoms = !geometry_ids.empty();
    if (image.width == 0 || image.height == 0 || image.depth.size() != n ||
        image.prim.size() != n || (normals && image.normals.size() != n) ||
        (geoms && geometry_ids.size() != n))
        return Err{std::string("depth image planes do not match its width x height")};
    configure_oiio_once();
    const int channels = (normals ? 5 : 2) + (geoms ? 1 : 0);
    OIIO::ImageSpec spec(static_cast<int>(image.width), static_cast<int>(image.height), channels,
                         OIIO::TypeDesc::FLOAT);
    spec.channelnames = {image.kind == DepthKind::kRange ? "range" : "Z", "prim"};
    spec.channelformats = {OIIO::TypeDesc::FLOAT, OIIO::TypeDesc::UINT};
    if (normals) {
        for (const char* c : {"N.X", "N.Y", "N.Z"}) {
            spec.channelnames.emplace_back(c);
            spec.channelformats.push_back(OIIO::TypeDesc::FLOAT);
        }
    }
    if (geoms) {
        spec.channelnames.emplace_back("geometry_id");
        spec.channelformats.push_back(OIIO::TypeDesc::UINT);
    }
    spec.z_channel = image.kind == DepthKind::kRange ? -1 : 0;
    spec.attribute("compression", "zip");
    spec.attribute("kdrt:depth_kind", image.kind == DepthKind::kRange ? "range" : "depth");
    // Interleaved native data, 4 bytes per channel.
    std::vector<uint32_t> data(n * static_cast<size_t>(channels));
    for (size_t p = 0; p < n; ++p) {
        uint32_t* px = &data[p * static_cast<size_t>(channels)];
        std::memcpy(px, &image.depth[p], 4);
        px[1] = image.prim[p];
        if (normals) std::memcpy(px + 2, &image.normals[p], 12);
        if (geoms) px[channels - 1] = geometry_ids[p];
    }
    std::vector<unsigned char> encoded;
    OIIO::Filesystem::IOVecOutput proxy(encoded);
    auto out = OIIO::ImageOutput::create("depth.exr", &proxy);
    if (!out) return Err{"cannot create an OpenImageIO exr writer: " + OIIO::geterror()};
    if (!out->open("depth.exr", spec))
        return Err{"cannot start depth.exr: " + object_error(*out, "open failed")};
    if (!out->write_image(OIIO::TypeDesc::UNKNOWN, data.data())) {
        std::string message = "cannot encode depth.exr: " + object_error(*out, "write failed");
        out->close();
        return Err{std::move(message)};
    }
    if (!out->close()) return Err{"cannot finish depth.exr: " + object_error(*out, "close failed")};
    std::vector<std::byte> bytes(encoded.size());
    if (!encoded.empty()) std::memcpy(bytes.data(), encoded.data(), encoded.size());
    return bytes;
}

Result<DepthImage, std::string> decode_depth_exr(std::span<const std::byte> bytes,
                                                 uint64_t max_pixels,
                                                 std::vector<uint32_t>* geometry_ids) {
    configure_oiio_once();
    OIIO::Filesystem::IOMemReader proxy(bytes.data(), bytes.size());
    OIIO::ImageSpec config;
    OIIO::Filesystem::IOProxy* proxy_pointer = &proxy;
    config.attribute("oiio:ioproxy", OIIO::TypeDesc::PTR, &proxy_pointer);
    auto in = OIIO::ImageInput::create("depth.exr", false, &config, &proxy);
    if (!in) return Err{"cannot create an OpenImageIO exr reader: " + OIIO::geterror()};
    OIIO::ImageSpec spec;
    if (!in->open("depth.exr", spec, config))
        return Err{"cannot read exr depth image: " + object_error(*in, "open failed")};
    if (spec.width < 1 || spec.height < 1 || spec.depth > 1)
        return Err{"exr depth image has unsupported dimensions " + std::to_string(spec.width) +
                   " x " + std::to_string(spec.height)};
    const uint64_t n = uint64_t(spec.width) * uint64_t(spec.height);
    if (n > max_pixels)
        return Err{"exr depth image has " + std::to_string(n) + " pixels, which " +
                   std::string(errors::kLimitExceeded) + " of " + std::to_string(max_pixels)};
    auto find = [&](std::string_view name) {
        for (int c = 0; c < spec.nchannels; ++c)
            if (spec.channelnames[static_cast<size_t>(c)] == name) return c;
        return -1;
    };
    auto format_of = [&](int c) {
        return spec.channelformats.empty() ? spec.format
                                           : spec.channelformats[static_cast<size_t>(c)];
    };
    DepthImage image;
    image.width = static_cast<uint32_t>(spec.width);
    image.height = static_cast<uint32_t>(spec.height);
    int depth_c = find("Z");
    image.kind = DepthKind::kDepth;
    if (depth_c < 0) {
        depth_c = find("range");
        image.kind = DepthKind::kRange;
    }
    const int prim_c = find("prim");
    if (depth_c < 0) return Err{std::string("exr depth image has no \"Z\" or \"range\" channel")};
    if (prim_c < 0) return Err{std::string("exr depth image has no \"prim\" channel")};
    if (format_of(depth_c) != OIIO::TypeDesc::FLOAT || format_of(prim_c) != OIIO::TypeDesc::UINT)
        return Err{std::string("exr depth image channels must be float (depth) and uint (prim)")};
    const int nx = find("N.X"), ny = find("N.Y"), nz = find("N.Z");
    const bool normals = nx >= 0 && ny >= 0 && nz >= 0;
    image.depth.resize(n);
    image.prim.resize(n);
    auto read = [&](int c, OIIO::TypeDesc type, void* out, size_t stride) {
        return in->read_image(0, 0, c, c + 1, type, out, static_cast<OIIO::stride_t>(stride));
    };
    if (!read(depth_c, OIIO::TypeDesc::FLOAT, image.depth.data(), 4) ||
        !read(prim_c, OIIO::TypeDesc::UINT, image.prim.data(), 4))
        return Err{"cannot decode exr depth image: " + object_error(*in, "read failed")};
    if (normals) {
        image.normals.resize(n);
        for (const int c : {nx, ny, nz}) {
            if (format_of(c) != OIIO::TypeDesc::FLOAT)
                return Err{std::string("exr depth image normal channels must be float")};
            float* base = &image.normals[0].x + (c == nx ? 0 : c == ny ? 1 : 2);
            if (!read(c, OIIO::TypeDesc::FLOAT, base, sizeof(Vec3)))
                return Err{"cannot decode exr depth image: " + object_error(*in, "read failed")};
        }
    }
    if (geometry_ids != nullptr) {
        geometry_ids->clear();
        const int geom_c = find("geometry_id");
        if (geom_c >= 0) {
            if (format_of(geom_c) != OIIO::TypeDesc::UINT)
                return Err{std::string("exr depth image channel \"geometry_id\" must be uint")};
            geometry_ids->resize(n);
            if (!read(geom_c, OIIO::TypeDesc::UINT, geometry_ids->data(), 4))
                return Err{"cannot decode exr depth image: " + object_error(*in, "read failed")};
        }
    }
    return image;
}

}  // namespace kdrt::proto
