// KDRZ (depth image), KDRL (lidar point cloud) and KDRB (lidar ranges) codecs, and point
// clouds as PLY.

#include <bit>
#include <cmath>
#include <cstring>
#include <limits>
#include <optional>
#include <stdexcept>
#include <string>

#include "byte_io.h"
#include "kdrt/proto/scan.h"
#include "kdrt/proto/text.h"

namespace kdrt::proto {
namespace {

Err<DecodeError> fail(DecodeErrorCode code, std::string detail) {
    return Err{DecodeError{code, std::move(detail)}};
}

/// The checks both headers share: size, magic, version.
std::optional<DecodeError> check_magic(std::span<const std::byte> body, std::string_view magic,
                                       size_t header_bytes) {
    if (body.size() < header_bytes)
        return DecodeError{DecodeErrorCode::kTooShort, "body has " + std::to_string(body.size()) +
                                                           " bytes, fewer than the " +
                                                           std::to_string(header_bytes) + "-byte " +
                                                           std::string(magic) + " header"};
    if (std::memcmp(body.data(), magic.data(), 4) != 0) {
        std::string got;
        for (int i = 0; i < 4; ++i) {
            const auto c = static_cast<unsigned char>(body[static_cast<size_t>(i)]);
            got += c >= 0x20 && c < 0x7f ? static_cast<char>(c) : '?';
        }
        return DecodeError{DecodeErrorCode::kBadMagic,
                           "bad magic " + quote_value(got) + ", expected " + quote_value(magic)};
    }
    const uint16_t version = detail::load_le16(body.data() + 4);
    if (version != kBatchVersion)
        return DecodeError{DecodeErrorCode::kBadVersion,
                           "version " + std::to_string(version) + ", expected 1"};
    return std::nullopt;
}

/// KDRB's beam index is a u32: channels x azimuth_steps at most 2^32.
constexpr uint64_t kMaxBeams = uint64_t{1} << 32;

/// KDRL's and KDRB's 32-byte header (with `magic`) for `cloud`'s points, at `out`'s start, after
/// checking the u32 count and the room for `size` bytes. `what` names the writer in errors.
std::byte* store_cloud_header(std::span<std::byte> out, size_t size, std::string_view magic,
                              const PointCloud& cloud, const char* what) {
    if (cloud.points.size() > std::numeric_limits<uint32_t>::max())
        throw std::length_error(std::string(magic) + " point cloud exceeds the u32 count field");
    if (out.size() < size) throw std::length_error(std::string(what) + ": the buffer is too small");
    std::byte* p = out.data();
    std::memcpy(p, magic.data(), 4);
    detail::store_le16(p + 4, kBatchVersion);
    detail::store_le16(p + 6, 0);
    detail::store_le32(p + 8, static_cast<uint32_t>(cloud.points.size()));
    detail::store_le32(p + 12, cloud.channels);
    detail::store_le32(p + 16, cloud.azimuth_steps);
    detail::store_le32(p + 20, cloud.returns);
    detail::store_le32(p + 24, 0);
    detail::store_le32(p + 28, 0);
    return p + kPointCloudHeaderBytes;
}

/// The header checks KDRL and KDRB share, in order: size, magic, version, flags 0, reserved 0,
/// channels, azimuth_steps and returns >= 1 (with `beam_index`, KDRB's: channels x
/// azimuth_steps <= 2^32, its u32 beam index), the count against max_points, the exact size for
/// `record_bytes` a point. Sets `sensor`'s counts and returns the point count.
Result<uint32_t, DecodeError> load_cloud_header(std::span<const std::byte> body,
                                                std::string_view magic, uint32_t max_points,
                                                size_t record_bytes, bool beam_index,
                                                PointCloud& sensor) {
    if (auto e = check_magic(body, magic, kPointCloudHeaderBytes)) return Err{*e};
    const uint16_t flags = detail::load_le16(body.data() + 6);
    if (flags != 0)
        return fail(
            DecodeErrorCode::kBadFlags,
            "flags 0x" + hex(flags, 4) + " (no flag is defined for " + std::string(magic) + ")");
    const uint32_t count = detail::load_le32(body.data() + 8);
    sensor.channels = detail::load_le32(body.data() + 12);
    sensor.azimuth_steps = detail::load_le32(body.data() + 16);
    sensor.returns = detail::load_le32(body.data() + 20);
    if (detail::load_le32(body.data() + 24) != 0 || detail::load_le32(body.data() + 28) != 0)
        return fail(DecodeErrorCode::kBadReserved, "reserved bytes 24..31 must be 0");
    if (sensor.channels == 0 || sensor.azimuth_steps == 0 || sensor.returns == 0 ||
        (beam_index && uint64_t{sensor.channels} * sensor.azimuth_steps > kMaxBeams))
        return fail(DecodeErrorCode::kBadRecord,
                    "channels " + std::to_string(sensor.channels) + ", azimuth_steps " +
                        std::to_string(sensor.azimuth_steps) + ", returns " +
                        std::to_string(sensor.returns) +
                        (beam_index ? " (each must be at least 1, and channels x azimuth_steps "
                                      "at most 2^32)"
                                    : " (each must be at least 1)"));
    if (count > max_points)
        return fail(DecodeErrorCode::kTooManyRays, "header says " + std::to_string(count) +
                                                       " points, more than the limit of " +
                                                       std::to_string(max_points));
    const uint64_t want = kPointCloudHeaderBytes + uint64_t{record_bytes} * count;
    if (body.size() != want)
        return fail(DecodeErrorCode::kLengthMismatch,
                    "header says " + std::to_string(count) + " points (" + std::to_string(want) +
                        " bytes) but body has " + std::to_string(body.size()) + " bytes");
    return count;
}

bool is_zero(Vec3 v) { return v.x == 0.0f && v.y == 0.0f && v.z == 0.0f; }
bool is_finite(Vec3 v) { return std::isfinite(v.x) && std::isfinite(v.y) && std::isfinite(v.z); }

}  // namespace

std::vector<std::byte> encode_depth_image(const DepthImage& image) {
    const uint64_t n = uint64_t{image.width} * image.height;
    const bool normals = !image.normals.empty();
    if (image.depth.size() != n || image.prim.size() != n || (normals && image.normals.size() != n))
        throw std::invalid_argument("encode_depth_image: planes do not match width x height");
    std::vector<std::byte> out(kdrz_body_size(n, normals));
    std::byte* p = out.data();
    std::memcpy(p, kDepthImageMagic.data(), 4);
    detail::store_le16(p + 4, kBatchVersion);
    uint16_t flags = 0;
    if (image.kind == DepthKind::kRange) flags |= kDepthFlagRange;
    if (normals) flags |= kDepthFlagNormals;
    detail::store_le16(p + 6, flags);
    detail::store_le32(p + 8, image.width);
    detail::store_le32(p + 12, image.height);
    p += kDepthImageHeaderBytes;
    // The host is little-endian (byte_io.h): the planes are the vectors' bytes.
    std::memcpy(p, image.depth.data(), n * 4);
    std::memcpy(p + n * 4, image.prim.data(), n * 4);
    if (normals) std::memcpy(p + n * 8, image.normals.data(), n * 12);
    return out;
}

Result<DepthImage, DecodeError> decode_depth_image(std::span<const std::byte> body,
                                                   uint64_t max_pixels) {
    if (auto e = check_magic(body, kDepthImageMagic, kDepthImageHeaderBytes)) return Err{*e};
    const uint16_t flags = detail::load_le16(body.data() + 6);
    if ((flags & ~(kDepthFlagRange | kDepthFlagNormals)) != 0)
        return fail(DecodeErrorCode::kBadFlags,
                    "unknown flag bits 0x" +
                        hex(flags & ~(kDepthFlagRange | kDepthFlagNormals), 4) + " in flags 0x" +
                        hex(flags, 4) + " (bit 0 range and bit 1 normals are defined for KDRZ)");
    DepthImage image;
    image.width = detail::load_le32(body.data() + 8);
    image.height = detail::load_le32(body.data() + 12);
    image.kind = (flags & kDepthFlagRange) ? DepthKind::kRange : DepthKind::kDepth;
    const bool normals = (flags & kDepthFlagNormals) != 0;
    if (image.width == 0 || image.height == 0)
        return fail(DecodeErrorCode::kBadRecord, "image is " + std::to_string(image.width) + " x " +
                                                     std::to_string(image.height) +
                                                     " pixels (each must be at least 1)");
    const uint64_t n = uint64_t{image.width} * image.height;
    if (n > max_pixels)
        return fail(DecodeErrorCode::kTooManyRays, "image has " + std::to_string(n) +
                                                       " pixels, more than the limit of " +
                                                       std::to_string(max_pixels));
    const uint64_t want = kdrz_body_size(n, normals);
    if (body.size() != want)
        return fail(DecodeErrorCode::kLengthMismatch,
                    "header says " + std::to_string(image.width) + " x " +
                        std::to_string(image.height) + " pixels" +
                        (normals ? " with normals" : "") + " (" + std::to_string(want) +
                        " bytes) but body has " + std::to_string(body.size()) + " bytes");
    const std::byte* p = body.data() + kDepthImageHeaderBytes;
    image.depth.resize(n);
    image.prim.resize(n);
    std::memcpy(image.depth.data(), p, n * 4);
    std::memcpy(image.prim.data(), p + n * 4, n * 4);
    if (normals) {
        image.normals.resize(n);
        std::memcpy(image.normals.data(), p + n * 8, n * 12);
    }
    for (uint64_t i = 0; i < n; ++i) {
        const float d = image.depth[i];
        const bool miss = image.prim[i] == kNoHit;
        const Vec3 nrm = normals ? image.normals[i] : Vec3{};
        const bool ok = miss ? (d == std::numeric_limits<float>::infinity() && is_zero(nrm))
                             : (std::isfinite(d) && d >= 0.0f && is_finite(nrm));
        if (!ok)
            return fail(DecodeErrorCode::kBadRecord,
                        "pixel (" + std::to_string(i % image.width) + ", " +
                            std::to_string(i / image.width) + "): " +
                            (miss ? "a miss (prim 0xffffffff) must have depth +inf and normal 0 0 0"
                                  : "a hit must have a finite depth >= 0 and a finite normal"));
    }
    return image;
}

std::vector<std::byte> encode_point_cloud(const PointCloud& cloud) {
    std::vector<std::byte> out(kdrl_body_size(cloud.points.size()));
    write_point_cloud(out, cloud);
    return out;
}

size_t write_point_cloud(std::span<std::byte> out, const PointCloud& cloud) {
    const size_t size = kdrl_body_size(cloud.points.size());
    std::byte* p = store_cloud_header(out, size, kPointCloudMagic, cloud, "write_point_cloud");
    static_assert(sizeof(LidarPoint) == kLidarPointBytes);
    if (!cloud.points.empty())
        std::memcpy(p, cloud.points.data(), cloud.points.size() * kLidarPointBytes);
    return size;
}

Result<PointCloud, DecodeError> decode_point_cloud(std::span<const std::byte> body,
                                                   uint32_t max_points) {
    PointCloud cloud;
    auto header = load_cloud_header(body, kPointCloudMagic, max_points, kLidarPointBytes,
                                    /*beam_index=*/false, cloud);
    if (!header) return Err{std::move(header).error()};
    const uint32_t count = *header;
    cloud.points.resize(count);
    if (count > 0)
        std::memcpy(cloud.points.data(), body.data() + kPointCloudHeaderBytes,
                    size_t{count} * kLidarPointBytes);
    uint64_t last_beam = 0;
    uint32_t last_return = 0;
    for (uint32_t i = 0; i < count; ++i) {
        const LidarPoint& q = cloud.points[i];
        std::string why;
        if (!std::isfinite(q.x) || !std::isfinite(q.y) || !std::isfinite(q.z))
            why = "x, y and z must be finite";
        else if (!std::isfinite(q.range) || !(q.range >= 0.0f))
            why = "range must be finite and >= 0";
        else if (q.channel >= cloud.channels)
            why = "channel " + std::to_string(q.channel) + " >= channels " +
                  std::to_string(cloud.channels);
        else if (q.azimuth_index >= cloud.azimuth_steps)
            why = "azimuth_index " + std::to_string(q.azimuth_index) + " >= azimuth_steps " +
                  std::to_string(cloud.azimuth_steps);
        else if (q.return_index >= cloud.returns)
            why = "return_index " + std::to_string(q.return_index) + " >= returns " +
                  std::to_string(cloud.returns);
        else if (q.prim == kNoHit)
            why = "prim 0xffffffff (a miss) is not a return";
        if (why.empty()) {
            const uint64_t beam = uint64_t{q.azimuth_index} * cloud.channels + q.channel;
            const bool first_of_beam = i == 0 || beam != last_beam;
            if (i > 0 && beam < last_beam)
                why = "beam (channel " + std::to_string(q.channel) + ", azimuth_index " +
                      std::to_string(q.azimuth_index) + ") comes after a later beam";
            else if (first_of_beam ? q.return_index != 0 : q.return_index != last_return + 1)
                why = "return_index " + std::to_string(q.return_index) + " out of sequence";
            last_beam = beam;
            last_return = q.return_index;
        }
        if (!why.empty())
            return fail(DecodeErrorCode::kBadRecord, "point " + std::to_string(i) + ": " + why);
    }
    return cloud;
}

std::vector<std::byte> encode_lidar_ranges(const PointCloud& cloud) {
    std::vector<std::byte> out(kdrb_body_size(cloud.points.size()));
    write_lidar_ranges(out, cloud);
    return out;
}

size_t write_lidar_ranges(std::span<std::byte> out, const PointCloud& cloud) {
    if (uint64_t{cloud.channels} * cloud.azimuth_steps > kMaxBeams)
        throw std::length_error("KDRB: channels x azimuth_steps exceed the u32 beam index");
    const size_t size = kdrb_body_size(cloud.points.size());
    std::byte* p = store_cloud_header(out, size, kLidarRangesMagic, cloud, "write_lidar_ranges");
    for (const LidarPoint& q : cloud.points) {
        const auto beam =
            static_cast<uint32_t>(uint64_t{q.azimuth_index} * cloud.channels + q.channel);
        detail::store_le32(p, std::bit_cast<uint32_t>(q.range));
        detail::store_le32(p + 4, beam);
        detail::store_le32(p + 8, q.prim);
        p += kLidarRangeBytes;
    }
    return size;
}

Result<LidarRanges, DecodeError> decode_lidar_ranges(std::span<const std::byte> body,
                                                     uint32_t max_points) {
    PointCloud sensor;
    auto header = load_cloud_header(body, kLidarRangesMagic, max_points, kLidarRangeBytes,
                                    /*beam_index=*/true, sensor);
    if (!header) return Err{std::move(header).error()};
    const uint32_t count = *header;
    const uint64_t beams = uint64_t{sensor.channels} * sensor.azimuth_steps;
    LidarRanges out;
    out.channels = sensor.channels;
    out.azimuth_steps = sensor.azimuth_steps;
    out.returns = sensor.returns;
    out.points.resize(count);
    const std::byte* p = body.data() + kPointCloudHeaderBytes;
    uint32_t run = 0;  // records of the current beam so far
    for (uint32_t i = 0; i < count; ++i, p += kLidarRangeBytes) {
        LidarRange& q = out.points[i];
        q.range = std::bit_cast<float>(detail::load_le32(p));
        q.beam = detail::load_le32(p + 4);
        q.prim = detail::load_le32(p + 8);
        std::string why;
        if (!std::isfinite(q.range) || !(q.range >= 0.0f))
            why = "range must be finite and >= 0";
        else if (q.beam >= beams)
            why = "beam " + std::to_string(q.beam) + " >= channels x azimuth_steps " +
                  std::to_string(beams);
        else if (q.prim == kNoHit)
            why = "prim 0xffffffff (a miss) is not a return";
        else if (i > 0 && q.beam < out.points[i - 1].beam)
            why = "beam " + std::to_string(q.beam) + " comes after a later beam";
        else {
            run = i > 0 && q.beam == out.points[i - 1].beam ? run + 1 : 1;
            if (run > out.returns)
                why = "beam " + std::to_string(q.beam) + " has more than returns " +
                      std::to_string(out.returns) + " records";
        }
        if (!why.empty())
            return fail(DecodeErrorCode::kBadRecord, "point " + std::to_string(i) + ": " + why);
    }
    return out;
}

std::vector<std::byte> encode_point_cloud_ply(const PointCloud& cloud,
                                              std::span<const uint32_t> geometry_ids) {
    const bool geoms = !geometry_ids.empty();
    const std::string header =
        "ply\nformat binary_little_endian 1.0\ncomment kdrt lidar scan\ncomment channels " +
        std::to_string(cloud.channels) + "\ncomment azimuth_steps " +
        std::to_string(cloud.azimuth_steps) + "\ncomment returns " + std::to_string(cloud.returns) +
        "\nelement vertex " + std::to_string(cloud.points.size()) +
        "\nproperty float x\nproperty float y\nproperty float z\nproperty float range\n"
        "property uint channel\nproperty uint azimuth_index\nproperty uint return_index\n"
        "property uint prim\n" +
        (geoms ? "property uint geometry_id\n" : "") + "end_header\n";
    const size_t stride = kLidarPointBytes + (geoms ? 4 : 0);
    std::vector<std::byte> out(header.size() + cloud.points.size() * stride);
    std::memcpy(out.data(), header.data(), header.size());
    if (!geoms) {
        if (!cloud.points.empty())
            std::memcpy(out.data() + header.size(), cloud.points.data(),
                        cloud.points.size() * kLidarPointBytes);
        return out;
    }
    std::byte* p = out.data() + header.size();
    for (size_t i = 0; i < cloud.points.size(); ++i, p += stride) {
        std::memcpy(p, &cloud.points[i], kLidarPointBytes);
        std::memcpy(p + kLidarPointBytes, &geometry_ids[i], 4);
    }
    return out;
}

std::string_view scan_format_name(ScanFormat format) noexcept {
    switch (format) {
        case ScanFormat::kBinary:
            return "binary";
        case ScanFormat::kExr:
            return "exr";
        case ScanFormat::kPly:
            return "ply";
        case ScanFormat::kRanges:
            return "ranges";
    }
    return "binary";
}

}  // namespace kdrt::proto
