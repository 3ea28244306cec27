// The scan request JSON (POST /v1/meshes/{id}/scan).

#include <cmath>
#include <limits>
#include <nlohmann/json.hpp>
#include <string>

#include "json_strict.h"
#include "kdrt/proto/errors.h"
#include "kdrt/proto/scan.h"
#include "kdrt/proto/text.h"

namespace kdrt::proto {
namespace {

using nlohmann::json;

/// A parse failure on its way out: the field and why.
struct Failure {
    ScanRequestError error;
};

[[noreturn]] void fail(std::string field, std::string detail, bool over_limit = false) {
    throw Failure{ScanRequestError{std::move(field), std::move(detail), over_limit}};
}

/// The members of one object, refusing unknown ones.
class Members {
public:
    Members(const json& object, std::string prefix, std::initializer_list<const char*> known)
        : object_(object), prefix_(std::move(prefix)) {
        if (!object.is_object()) fail(trimmed(), quote_value(trimmed()) + " must be an object");
        for (const auto& [key, value] : object.items()) {
            bool ok = false;
            for (const char* k : known) ok = ok || key == k;
            if (ok) continue;
            std::string message = "unknown member " + quote_value(prefix_ + key) + " (expected ";
            for (size_t i = 0; const char* k : known) {
                if (i++ > 0) message += ", ";
                message += k;
            }
            fail(prefix_ + key, message + ')');
        }
    }

    [[nodiscard]] const json* find(const char* key) const {
        const auto it = object_.find(key);
        return it == object_.end() ? nullptr : &*it;
    }
    [[nodiscard]] std::string name(const char* key) const { return prefix_ + key; }
    [[nodiscard]] const json& required(const char* key) const {
        const json* v = find(key);
        if (!v) fail(name(key), "missing member " + quote_value(name(key)));
        return *v;
    }

    double number(const json& v, const std::string& field) const {
        if (!v.is_number()) fail(field, quote_value(field) + " must be a number");
        const double d = v.get<double>();
        if (!std::isfinite(d)) fail(field, quote_value(field) + " must be finite");
        return d;
    }
    void real(const char* key, double& out) const {
        if (const json* v = find(key)) out = number(*v, name(key));
    }
    void real(const char* key, float& out) const {
        if (const json* v = find(key)) {
            const double d = number(*v, name(key));
            if (!std::isfinite(static_cast<float>(d)))
                fail(name(key), quote_value(name(key)) + " is outside the range of a float");
            out = static_cast<float>(d);
        }
    }
    /// An unsigned integer in [min, max]; `limit` names the server setting behind max.
    uint64_t integer(const char* key, uint64_t min, uint64_t max, const char* limit = nullptr,
                     bool required_member = true) const {
        const json* v = find(key);
        if (!v) {
            if (required_member) fail(name(key), "missing member " + quote_value(name(key)));
            return min;
        }
        if (!v->is_number_unsigned())
            fail(name(key), quote_value(name(key)) + " must be a non-negative integer");
        const uint64_t value = v->get<uint64_t>();
        if (value < min || value > max) {
            std::string why = quote_value(name(key)) + " is " + std::to_string(value) +
                              ", must be in " + std::to_string(min) + " .. " + std::to_string(max);
            if (limit) why += std::string(" (") + limit + ")";
            fail(name(key), why, limit != nullptr && value > max);
        }
        return value;
    }
    bool boolean(const char* key, bool fallback) const {
        const json* v = find(key);
        if (!v) return fallback;
        if (!v->is_boolean()) fail(name(key), quote_value(name(key)) + " must be true or false");
        return v->get<bool>();
    }
    std::string text(const char* key, std::string fallback) const {
        const json* v = find(key);
        if (!v) return fallback;
        if (!v->is_string()) fail(name(key), quote_value(name(key)) + " must be a string");
        return v->get<std::string>();
    }
    Vec3 vec3(const char* key, Vec3 fallback, bool required_member) const {
        const json* v = find(key);
        if (!v) {
            if (required_member) fail(name(key), "missing member " + quote_value(name(key)));
            return fallback;
        }
        if (!v->is_array() || v->size() != 3)
            fail(name(key), quote_value(name(key)) + " must be an array of 3 numbers");
        Vec3 out;
        for (int a = 0; a < 3; ++a) {
            const double d = number((*v)[static_cast<size_t>(a)], name(key));
            out[a] = static_cast<float>(d);
            if (!std::isfinite(out[a]))
                fail(name(key), quote_value(name(key)) + " is outside the range of a float");
        }
        return out;
    }
    Pose pose(const char* key, bool required_member) const {
        const json* v = find(key);
        Pose pose;
        if (!v) {
            if (required_member) fail(name(key), "missing member " + quote_value(name(key)));
            return pose;
        }
        const std::string field = name(key);
        const std::string shape = quote_value(field) + " must be 4 rows of 4 numbers (row-major)";
        if (!v->is_array() || v->size() != 4) fail(field, shape);
        for (size_t r = 0; r < 4; ++r) {
            const json& row = (*v)[r];
            if (!row.is_array() || row.size() != 4) fail(field, shape);
            for (size_t c = 0; c < 4; ++c) {
                if (!row[c].is_number()) fail(field, shape);
                const double d = row[c].get<double>();  // finiteness: kdrt::validate_pose
                // A finite value beyond a float's range would make every beam miss (issue 25).
                if (std::isfinite(d) && std::fabs(d) > std::numeric_limits<float>::max())
                    fail(field, quote_value(field) + " row " + std::to_string(r) + " column " +
                                    std::to_string(c) + " is outside the range of a float");
                pose.m[4 * r + c] = d;
            }
        }
        return pose;
    }

private:
    [[nodiscard]] std::string trimmed() const {
        return prefix_.empty() ? std::string("request") : prefix_.substr(0, prefix_.size() - 1);
    }
    const json& object_;
    std::string prefix_;
};

void range_window(const Members& m, float& min_range, float& max_range) {
    m.real("min_range", min_range);
    if (const json* v = m.find("max_range"); v && !v->is_null()) m.real("max_range", max_range);
}

void check_points(uint64_t points, const std::string& field, const char* what,
                  const ScanLimits& limits) {
    if (points > limits.max_points)
        fail(field,
             std::string(what) + " " + std::to_string(points) + " " +
                 std::string(errors::kLimitExceeded) + " of " + std::to_string(limits.max_points) +
                 " (max_scan_points)",
             true);
}

void decode_pinhole(const json& doc, ScanRequest& req, const ScanLimits& limits) {
    const Members m(doc, "pinhole.",
                    {"intrinsics", "pose", "camera", "width", "height", "output", "normals",
                     "min_range", "max_range"});
    PinholeSpec& spec = req.pinhole;
    if (m.find("camera")) {
        for (const char* k : {"intrinsics", "pose"})
            if (m.find(k))
                fail(m.name(k),
                     "give either \"pinhole.camera\" (with width and height) or "
                     "\"pinhole.intrinsics\" and \"pinhole.pose\", not both");
        req.look_at = true;
        const Members c(*m.find("camera"), "pinhole.camera.", {"eye", "look_at", "up", "fov"});
        req.camera.eye = c.vec3("eye", {}, true);
        req.camera.look_at = c.vec3("look_at", {}, true);
        req.camera.up = c.vec3("up", {0, 1, 0}, false);
        c.real("fov", req.camera.fov_deg);
        req.camera.projection = Projection::kPerspective;
        req.camera_width =
            static_cast<uint32_t>(m.integer("width", 1, limits.max_width, "max_image_width"));
        req.camera_height =
            static_cast<uint32_t>(m.integer("height", 1, limits.max_height, "max_image_height"));
        check_points(uint64_t{req.camera_width} * req.camera_height, "pinhole.width",
                     "width x height", limits);
    } else {
        for (const char* k : {"width", "height"})
            if (m.find(k))
                fail(m.name(k), quote_value(m.name(k)) +
                                    " goes with \"pinhole.camera\"; with intrinsics it is "
                                    "\"pinhole.intrinsics." +
                                    k + "\"");
        const Members k(m.required("intrinsics"), "pinhole.intrinsics.",
                        {"fx", "fy", "cx", "cy", "width", "height"});
        for (const char* key : {"fx", "fy", "cx", "cy"}) (void)k.required(key);
        k.real("fx", spec.intrinsics.fx);
        k.real("fy", spec.intrinsics.fy);
        k.real("cx", spec.intrinsics.cx);
        k.real("cy", spec.intrinsics.cy);
        spec.intrinsics.width =
            static_cast<uint32_t>(k.integer("width", 1, limits.max_width, "max_image_width"));
        spec.intrinsics.height =
            static_cast<uint32_t>(k.integer("height", 1, limits.max_height, "max_image_height"));
        check_points(uint64_t{spec.intrinsics.width} * spec.intrinsics.height,
                     "pinhole.intrinsics.width", "width x height", limits);
        spec.pose = m.pose("pose", true);
    }
    const std::string output = m.text("output", "depth");
    if (output == "depth")
        spec.kind = DepthKind::kDepth;
    else if (output == "range")
        spec.kind = DepthKind::kRange;
    else
        fail("pinhole.output",
             "unknown pinhole.output " + quote_value(output) + " (expected depth or range)");
    spec.normals = m.boolean("normals", false);
    range_window(m, spec.min_range, spec.max_range);
}

void decode_lidar(const json& doc, ScanRequest& req, const ScanLimits& limits) {
    const Members m(doc, "lidar.",
                    {"elevation_deg", "vertical_fov", "channels", "azimuth_steps", "min_range",
                     "max_range", "returns", "pose"});
    LidarSpec& spec = req.lidar_spec;
    uint64_t channels = 0;
    if (const json* e = m.find("elevation_deg")) {
        for (const char* k : {"vertical_fov", "channels"})
            if (m.find(k))
                fail(m.name(k),
                     "give either \"lidar.elevation_deg\" or \"lidar.vertical_fov\" "
                     "with \"lidar.channels\", not both");
        if (!e->is_array() || e->empty())
            fail("lidar.elevation_deg",
                 "\"lidar.elevation_deg\" must be a non-empty array of numbers (degrees)");
        if (e->size() > limits.max_beams)
            fail("lidar.elevation_deg",
                 "\"lidar.elevation_deg\" has " + std::to_string(e->size()) +
                     " channels, more than max_sensor_beams (" + std::to_string(limits.max_beams) +
                     ")",
                 true);
        for (size_t c = 0; c < e->size(); ++c)
            spec.elevation_deg.push_back(
                m.number((*e)[c], "lidar.elevation_deg[" + std::to_string(c) + "]"));
        channels = e->size();
    } else {
        const json& fov = m.required("vertical_fov");
        if (!fov.is_array() || fov.size() != 2)
            fail("lidar.vertical_fov", "\"lidar.vertical_fov\" must be [lower, upper] in degrees");
        req.vertical_fov = true;
        req.fov_lower = m.number(fov[0], "lidar.vertical_fov");
        req.fov_upper = m.number(fov[1], "lidar.vertical_fov");
        channels = m.integer("channels", 1, limits.max_beams, "max_sensor_beams");
        req.channels = static_cast<uint32_t>(channels);
    }
    const uint64_t steps = m.integer("azimuth_steps", 1, limits.max_beams, "max_sensor_beams");
    spec.azimuth_steps = static_cast<uint32_t>(steps);
    if (channels * steps > limits.max_beams)
        fail("lidar.azimuth_steps",
             "channels x azimuth_steps = " + std::to_string(channels * steps) + " beams " +
                 std::string(errors::kLimitExceeded) + " of " + std::to_string(limits.max_beams) +
                 " (max_sensor_beams)",
             true);
    spec.returns = static_cast<uint32_t>(
        m.integer("returns", 1, limits.max_returns, "max_hits_per_ray", false));
    if (!m.find("returns")) spec.returns = 1;
    check_points(channels * steps * spec.returns, "lidar.returns", "beams x returns", limits);
    range_window(m, spec.min_range, spec.max_range);
    spec.pose = m.pose("pose", false);
}

}  // namespace

Result<ScanRequest, ScanRequestError> decode_scan_request(std::string_view text,
                                                          const ScanLimits& limits) {
    auto parsed = detail::parse_json_strict<json>(text);
    if (!parsed) return Err{ScanRequestError{"", parsed.error(), false}};
    try {
        const json& doc = *parsed;
        const Members top(doc, "", {"pinhole", "lidar", "format"});
        ScanRequest req;
        const json* pinhole = top.find("pinhole");
        const json* lidar = top.find("lidar");
        if ((pinhole != nullptr) == (lidar != nullptr))
            fail(pinhole ? "lidar" : "pinhole",
                 "a scan request needs exactly one of \"pinhole\" and \"lidar\"");
        req.lidar = lidar != nullptr;
        if (lidar)
            decode_lidar(*lidar, req, limits);
        else
            decode_pinhole(*pinhole, req, limits);
        const std::string format = top.text("format", "binary");
        if (format == "binary")
            req.format = ScanFormat::kBinary;
        else if (format == "exr" && !req.lidar)
            req.format = ScanFormat::kExr;
        else if (format == "ply" && req.lidar)
            req.format = ScanFormat::kPly;
        else if (format == "ranges" && req.lidar)
            req.format = ScanFormat::kRanges;
        else
            fail("format", "unknown format " + quote_value(format) + " for a " +
                               (req.lidar ? "lidar scan (expected binary, ply or ranges)"
                                          : "pinhole scan (expected binary or exr)"));
        return req;
    } catch (const Failure& f) {
        ScanRequestError e = f.error;
        // Every detail names its field, quoted as the request spells it.
        if (!e.field.empty() && e.detail.find(quote_value(e.field)) == std::string::npos)
            e.detail = quote_value(e.field) + ": " + e.detail;
        return Err{std::move(e)};
    }
}

std::string encode_scan_request(const ScanRequest& req) {
    json doc = json::object();
    auto pose = [](const Pose& p) {
        json rows = json::array();
        for (int r = 0; r < 4; ++r) {
            json row = json::array();
            for (int c = 0; c < 4; ++c) row.push_back(p.m[4 * r + c]);
            rows.push_back(row);
        }
        return rows;
    };
    auto window = [](json& o, float min_range, float max_range) {
        o["min_range"] = min_range;
        if (std::isfinite(max_range)) o["max_range"] = max_range;
    };
    if (req.lidar) {
        const LidarSpec& s = req.lidar_spec;
        json o = json::object();
        if (req.vertical_fov) {
            o["vertical_fov"] = {req.fov_lower, req.fov_upper};
            o["channels"] = req.channels;
        } else {
            o["elevation_deg"] = s.elevation_deg;
        }
        o["azimuth_steps"] = s.azimuth_steps;
        o["returns"] = s.returns;
        window(o, s.min_range, s.max_range);
        o["pose"] = pose(s.pose);
        doc["lidar"] = o;
    } else {
        const PinholeSpec& s = req.pinhole;
        json o = json::object();
        if (req.look_at) {
            const auto v = [](Vec3 x) { return json{x.x, x.y, x.z}; };
            o["camera"] = {{"eye", v(req.camera.eye)},
                           {"look_at", v(req.camera.look_at)},
                           {"up", v(req.camera.up)},
                           {"fov", req.camera.fov_deg}};
            o["width"] = req.camera_width;
            o["height"] = req.camera_height;
        } else {
            o["intrinsics"] = {{"fx", s.intrinsics.fx},       {"fy", s.intrinsics.fy},
                               {"cx", s.intrinsics.cx},       {"cy", s.intrinsics.cy},
                               {"width", s.intrinsics.width}, {"height", s.intrinsics.height}};
            o["pose"] = pose(s.pose);
        }
        o["output"] = s.kind == DepthKind::kRange ? "range" : "depth";
        o["normals"] = s.normals;
        window(o, s.min_range, s.max_range);
        doc["pinhole"] = o;
    }
    doc["format"] = std::string(scan_format_name(req.format));
    return doc.dump();
}

std::string_view scan_field_prefix(const ScanRequest& request) noexcept {
    return request.lidar ? "lidar." : "pinhole.";
}

}  // namespace kdrt::proto
