// KDRP (query points) and KDRD (closest points) codecs, the distance query parameters, and query
// points as text.

#include <charconv>
#include <cmath>
#include <cstring>
#include <limits>
#include <stdexcept>
#include <string>

#include "byte_io.h"
#include "kdrt/proto/distance.h"
#include "kdrt/proto/text.h"
#include "ray_batch_checks.h"

namespace kdrt::proto {
namespace {

constexpr detail::BatchKind kPoints{kPointMagic, kPointRecordBytes, 0, "point", "points"};
// The flag bit is checked after the shared header checks (their message names KDRR's bit).
constexpr detail::BatchKind kDistances{kDistanceMagic, kDistanceRecordBytes, 0xFFFF, "point",
                                       "points"};

constexpr std::string_view kAxisNames[3] = {"x", "y", "z"};

void write_header(std::byte* p, std::string_view magic, uint16_t flags, size_t count) {
    if (count > std::numeric_limits<uint32_t>::max())
        throw std::length_error(std::string(magic) + " batch exceeds the u32 count field");
    std::memcpy(p, magic.data(), 4);
    detail::store_le16(p + 4, kBatchVersion);
    detail::store_le16(p + 6, flags);
    detail::store_le32(p + 8, static_cast<uint32_t>(count));
    detail::store_le32(p + 12, 0);
}

/// The shortest decimal that reads back to the same float.
std::string float_text(float v) {
    char buf[32];
    const auto [end, ec] = std::to_chars(buf, buf + sizeof buf, v);
    return ec == std::errc{} ? std::string(buf, end) : std::string("nan");
}

}  // namespace

std::vector<std::byte> encode_points(std::span<const Vec3> points) {
    std::vector<std::byte> out(kdrp_body_size(points.size()));
    write_header(out.data(), kPointMagic, 0, points.size());
    std::byte* p = out.data() + kBatchHeaderBytes;
    for (const Vec3& v : points) {
        detail::store_le_f32(p, v.x);
        detail::store_le_f32(p + 4, v.y);
        detail::store_le_f32(p + 8, v.z);
        p += kPointRecordBytes;
    }
    return out;
}

std::optional<std::string> non_finite_point(std::span<const Vec3> points) {
    for (size_t i = 0; i < points.size(); ++i) {
        for (int a = 0; a < 3; ++a) {
            if (std::isfinite(points[i][a])) continue;
            std::string detail = "point " + std::to_string(i) + ": field ";
            detail += kAxisNames[a];
            detail += " is ";
            detail += non_finite_name(points[i][a]);
            return detail;
        }
    }
    return std::nullopt;
}

Result<std::vector<Vec3>, DecodeError> decode_points(std::span<const std::byte> body,
                                                     const DecodeLimits& limits) {
    auto header = detail::check_header(body, kPoints, limits);
    if (!header) return Err{std::move(header).error()};
    std::vector<Vec3> points(header->count);
    const std::byte* p = body.data() + kBatchHeaderBytes;
    for (size_t i = 0; i < points.size(); ++i, p += kPointRecordBytes)
        points[i] = {detail::load_le_f32(p), detail::load_le_f32(p + 4),
                     detail::load_le_f32(p + 8)};
    if (limits.reject_non_finite)
        if (auto bad = non_finite_point(points))
            return Err{DecodeError{DecodeErrorCode::kNonFinitePoint, std::move(*bad)}};
    return points;
}

std::vector<std::byte> encode_distances(std::span<const ClosestPoint> answers, bool signed_query) {
    std::vector<std::byte> out(kdrd_body_size(answers.size()));
    write_header(out.data(), kDistanceMagic, signed_query ? kDistanceFlagSigned : 0,
                 answers.size());
    std::byte* p = out.data() + kBatchHeaderBytes;
    for (const ClosestPoint& c : answers) {
        detail::store_le_f32(p, c.distance);
        detail::store_le32(p + 4, c.prim);
        detail::store_le_f32(p + 8, c.u);
        detail::store_le_f32(p + 12, c.v);
        detail::store_le_f32(p + 16, c.point.x);
        detail::store_le_f32(p + 20, c.point.y);
        detail::store_le_f32(p + 24, c.point.z);
        p[28] = static_cast<std::byte>(c.feature);
        p[29] = static_cast<std::byte>(c.side);
        detail::store_le16(p + 30, 0);
        p += kDistanceRecordBytes;
    }
    return out;
}

Result<Distances, DecodeError> decode_distances(std::span<const std::byte> body,
                                                const DecodeLimits& limits) {
    auto header = detail::check_header(body, kDistances, limits);
    if (!header) return Err{std::move(header).error()};
    if ((header->flags & ~kDistanceFlagSigned) != 0) {
        return Err{DecodeError{
            DecodeErrorCode::kBadFlags,
            "unknown flag bits 0x" + hex(header->flags & ~kDistanceFlagSigned, 4) + " in flags 0x" +
                hex(header->flags, 4) + " (only bit 0, signed, is defined for KDRD)"}};
    }
    Distances out;
    out.signed_query = (header->flags & kDistanceFlagSigned) != 0;
    out.points.resize(header->count);
    const std::byte* p = body.data() + kBatchHeaderBytes;
    for (size_t i = 0; i < out.points.size(); ++i, p += kDistanceRecordBytes) {
        const auto feature = static_cast<uint8_t>(p[28]);
        const auto side = static_cast<uint8_t>(p[29]);
        const uint16_t reserved = detail::load_le16(p + 30);
        if (feature > static_cast<uint8_t>(Feature::kNone) ||
            side > static_cast<uint8_t>(Side::kUnknown) || reserved != 0) {
            return Err{DecodeError{DecodeErrorCode::kBadRecord,
                                   "point " + std::to_string(i) + ": feature " +
                                       std::to_string(feature) + " (expected 0..7), side " +
                                       std::to_string(side) + " (expected 0..2), reserved " +
                                       std::to_string(reserved) + " (expected 0)"}};
        }
        ClosestPoint& c = out.points[i];
        c.distance = detail::load_le_f32(p);
        c.prim = detail::load_le32(p + 4);
        c.u = detail::load_le_f32(p + 8);
        c.v = detail::load_le_f32(p + 12);
        c.point = {detail::load_le_f32(p + 16), detail::load_le_f32(p + 20),
                   detail::load_le_f32(p + 24)};
        c.feature = static_cast<Feature>(feature);
        c.side = static_cast<Side>(side);
    }
    return out;
}

std::string_view feature_name(Feature feature) noexcept {
    switch (feature) {
        case Feature::kFace:
            return "face";
        case Feature::kEdge01:
            return "edge01";
        case Feature::kEdge12:
            return "edge12";
        case Feature::kEdge20:
            return "edge20";
        case Feature::kVertex0:
            return "vertex0";
        case Feature::kVertex1:
            return "vertex1";
        case Feature::kVertex2:
            return "vertex2";
        case Feature::kNone:
            break;
    }
    return "none";
}

std::string_view side_name(Side side) noexcept {
    switch (side) {
        case Side::kOutside:
            return "outside";
        case Side::kInside:
            return "inside";
        case Side::kUnknown:
            break;
    }
    return "unknown";
}

Result<DistanceQuery, std::string> parse_distance_query(
    const std::function<std::optional<std::string>(std::string_view)>& param) {
    DistanceQuery q;
    if (auto v = param(kQueryMaxDistance)) {
        float value = 0.0f;
        const char* end = v->data() + v->size();
        const auto [stop, ec] = std::from_chars(v->data(), end, value);
        const bool is_inf = *v == "inf";
        if (!is_inf && (ec != std::errc{} || stop != end || v->empty() || !(value >= 0.0f) ||
                        !std::isfinite(value))) {
            return Err{"query parameter max_distance is " + quote_value(*v) +
                       " (expected a finite number >= 0, or inf)"};
        }
        q.max_distance = is_inf ? std::numeric_limits<float>::infinity() : value;
    }
    if (auto v = param(kQuerySigned)) {
        if (*v == "true" || *v == "1") {
            q.signed_query = true;
        } else if (*v == "false" || *v == "0") {
            q.signed_query = false;
        } else {
            return Err{"query parameter signed is " + quote_value(*v) +
                       " (expected true or false)"};
        }
    }
    return q;
}

std::string distance_query_string(const DistanceQuery& q) {
    std::string s(kQuerySigned);
    s += q.signed_query ? "=true" : "=false";
    if (std::isfinite(q.max_distance)) {
        s += '&';
        s += kQueryMaxDistance;
        s += '=';
        s += float_text(q.max_distance);
    }
    return s;
}

Result<std::vector<Vec3>, std::string> parse_points_text(std::string_view text) {
    std::vector<Vec3> points;
    size_t line_number = 0;
    bool first_content = true;
    while (!text.empty()) {
        ++line_number;
        const size_t nl = text.find('\n');
        std::string_view line = text.substr(0, nl);
        text = nl == std::string_view::npos ? std::string_view{} : text.substr(nl + 1);
        if (!line.empty() && line.back() == '\r') line.remove_suffix(1);
        const size_t start = line.find_first_not_of(" \t");
        if (start == std::string_view::npos || line[start] == '#') continue;
        line.remove_prefix(start);
        float xyz[3];
        int got = 0;
        const char* p = line.data();
        const char* end = line.data() + line.size();
        while (got < 3 && p < end) {
            while (p < end && (*p == ' ' || *p == '\t' || *p == ',')) ++p;
            if (p == end) break;
            const auto [stop, ec] = std::from_chars(p, end, xyz[got]);
            if (ec != std::errc{}) break;
            ++got;
            p = stop;
            if (p < end && *p != ' ' && *p != '\t' && *p != ',') {
                got = -1;  // a number followed by junk ("1.5x")
                break;
            }
        }
        if (got != 3) {
            if (first_content && got == 0) {  // a CSV header line ("x,y,z")
                first_content = false;
                continue;
            }
            return Err{"line " + std::to_string(line_number) +
                       ": expected three numbers x y z (separated by spaces, tabs or commas)"};
        }
        first_content = false;
        for (int a = 0; a < 3; ++a) {
            if (!std::isfinite(xyz[a])) {
                std::string error = "line " + std::to_string(line_number) + ": coordinate ";
                error += kAxisNames[a];
                error += " is not finite";
                return Err{std::move(error)};
            }
        }
        points.push_back({xyz[0], xyz[1], xyz[2]});
    }
    return points;
}

std::string distances_csv(std::span<const Vec3> queries, std::span<const ClosestPoint> answers,
                          std::span<const uint32_t> geometry_ids) {
    const bool scene = !geometry_ids.empty();
    if (queries.size() != answers.size() || (scene && geometry_ids.size() != answers.size()))
        throw std::invalid_argument("distances_csv: one answer per query point");
    std::string out = scene ? "x,y,z,distance,signed_distance,side,prim,u,v,px,py,pz,feature,"
                              "geometry_id\n"
                            : "x,y,z,distance,signed_distance,side,prim,u,v,px,py,pz,feature\n";
    for (size_t i = 0; i < answers.size(); ++i) {
        const ClosestPoint& c = answers[i];
        const Vec3& q = queries[i];
        auto field = [&out](const std::string& text) {
            out += text;
            out += ',';
        };
        field(float_text(q.x));
        field(float_text(q.y));
        field(float_text(q.z));
        field(float_text(c.distance));
        field(c.side != Side::kUnknown ? float_text(c.signed_distance()) : std::string());
        field(std::string(side_name(c.side)));
        if (c.found()) {
            field(std::to_string(c.prim));
            for (float f : {c.u, c.v, c.point.x, c.point.y, c.point.z}) field(float_text(f));
        } else {
            out += ",,,,,,";
        }
        out += feature_name(c.feature);
        if (scene) {
            out += ',';
            if (c.found()) out += std::to_string(geometry_ids[i]);
        }
        out += '\n';
    }
    return out;
}

}  // namespace kdrt::proto
