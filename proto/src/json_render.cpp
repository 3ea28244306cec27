// Render requests and job status documents.

#include <algorithm>
#include <cmath>
#include <limits>
#include <nlohmann/json.hpp>

#include "json_strict.h"
#include "json_writer.h"
#include "kdrt/proto/image_io.h"
#include "kdrt/proto/json_api.h"
#include "kdrt/proto/problem.h"
#include "kdrt/proto/text.h"

namespace kdrt::proto {
namespace {

using nlohmann::json;

/// Reads the members of one JSON object, refusing unknown ones; remembers the first error.
class ObjectReader {
public:
    ObjectReader(const json& object, std::string prefix, std::initializer_list<const char*> known)
        : object_(object), prefix_(std::move(prefix)) {
        for (const auto& [key, value] : object.items()) {
            bool ok = false;
            for (const char* k : known) ok = ok || key == k;
            if (!ok) {
                std::string message =
                    "unknown member " + quote_value(prefix_ + key) + " (expected ";
                for (size_t i = 0; const char* k : known) {
                    if (i++ > 0) message += ", ";
                    message += k;
                }
                message += ')';
                fail(std::move(message));
                return;
            }
        }
    }

    const json* find(const char* key) const {
        const auto it = object_.find(key);
        return it == object_.end() ? nullptr : &*it;
    }

    void text(const char* key, std::string& out) {
        if (const json* v = find(key)) {
            if (v->is_string())
                out = v->get<std::string>();
            else
                fail(quote_value(prefix_ + key) + " must be a string");
        }
    }

    /// An integer in [min, max]; `limit_name` names the server setting behind max, if any.
    template <class T>
    void integer(const char* key, T& out, uint64_t min, uint64_t max,
                 const char* limit_name = nullptr) {
        const json* v = find(key);
        if (!v) return;
        if (!v->is_number_unsigned()) {
            fail(quote_value(prefix_ + key) + " must be a non-negative integer");
            return;
        }
        const uint64_t value = v->get<uint64_t>();
        if (value < min || value > max) {
            std::string why = quote_value(prefix_ + key) + " is " + std::to_string(value) +
                              ", must be in " + std::to_string(min) + " .. " + std::to_string(max);
            if (limit_name) why += std::string(" (") + limit_name + ")";
            fail(why);
            return;
        }
        out = static_cast<T>(value);
    }

    void real(const char* key, float& out) {
        if (const json* v = find(key)) {
            if (v->is_number() && std::isfinite(static_cast<float>(v->get<double>())))
                out = static_cast<float>(v->get<double>());
            else
                fail(quote_value(prefix_ + key) + " must be a finite number");
        }
    }

    void vec3(const char* key, Vec3& out, bool required) {
        const json* v = find(key);
        if (!v) {
            if (required) fail("missing member " + quote_value(prefix_ + key));
            return;
        }
        if (!v->is_array() || v->size() != 3) {
            fail(quote_value(prefix_ + key) + " must be an array of 3 numbers");
            return;
        }
        for (int a = 0; a < 3; ++a) {
            const json& c = (*v)[static_cast<size_t>(a)];
            if (!c.is_number() || !std::isfinite(static_cast<float>(c.get<double>()))) {
                fail(quote_value(prefix_ + key) + " must be an array of 3 finite numbers");
                return;
            }
            out[a] = static_cast<float>(c.get<double>());
        }
    }

    void fail(std::string message) {
        if (error_.empty()) error_ = std::move(message);
    }
    [[nodiscard]] const std::string& error() const noexcept { return error_; }

private:
    const json& object_;
    std::string prefix_;
    std::string error_;
};

Err<JsonError> schema_error(std::string detail) {
    return Err{JsonError{JsonError::Code::kSchema, std::move(detail)}};
}

}  // namespace

Result<RenderRequest, JsonError> decode_render_request(std::string_view text,
                                                       const RenderLimits& limits, bool scene) {
    auto parsed = detail::parse_json_strict<json>(text);
    if (!parsed) {
        const bool syntax = parsed.error().rfind("invalid JSON", 0) == 0;
        std::string detail = parsed.error();
        if (syntax) detail.replace(0, 12, std::string(api_errors::kBadJson));
        return Err{JsonError{syntax ? JsonError::Code::kSyntax : JsonError::Code::kSchema,
                             std::move(detail)}};
    }
    const json& doc = *parsed;
    if (!doc.is_object())
        return schema_error("expected a JSON object, got " + std::string(doc.type_name()));
    RenderRequest req;
    ObjectReader r = scene ? ObjectReader(doc, "",
                                          {"camera", "width", "height", "spp", "seed", "shading",
                                           "format", "compression", "tile", "ao_samples",
                                           "ao_distance", "light", "bounces", "sky", "background"})
                           : ObjectReader(doc, "",
                                          {"mesh", "camera", "width", "height", "spp", "seed",
                                           "shading", "format", "compression", "tile", "ao_samples",
                                           "ao_distance", "light", "bounces", "sky", "background"});
    if (!scene) {
        if (!r.find("mesh")) r.fail("missing member \"mesh\"");
        r.text("mesh", req.mesh);
    }
    // A default never exceeds the server's limit (a 128-pixel limit renders 128 wide by default).
    req.settings.width = std::min(req.settings.width, limits.max_width);
    req.settings.height = std::min(req.settings.height, limits.max_height);
    req.settings.spp = std::min(req.settings.spp, limits.max_spp);
    r.integer("width", req.settings.width, 1, limits.max_width, "max_image_width");
    r.integer("height", req.settings.height, 1, limits.max_height, "max_image_height");
    r.integer("spp", req.settings.spp, 1, limits.max_spp, "max_spp");
    r.integer("seed", req.settings.seed, 0, std::numeric_limits<uint64_t>::max());
    std::string shading = "eyelight";
    r.text("shading", shading);
    if (const auto parsed = parse_shading(shading))
        req.settings.shading = *parsed;
    else
        r.fail("unknown shading " + quote_value(shading) +
               " (expected normals, eyelight, ao, diffuse, depth, primid or geomid)");
    r.integer("ao_samples", req.settings.ao_samples, 1, kMaxAoSamples);
    r.real("ao_distance", req.settings.ao_distance);
    if (r.find("ao_distance") && !(req.settings.ao_distance > 0.0f))
        r.fail("\"ao_distance\" must be > 0 (a share of the mesh's bounding-box diagonal)");
    r.integer("bounces", req.settings.bounces, 0, kMaxBounces);
    r.real("sky", req.settings.sky);
    if (req.settings.sky < 0.0f) r.fail("\"sky\" must be >= 0 (a radiance)");
    r.vec3("background", req.settings.background, false);
    r.text("format", req.format);
    if (req.format != "png" && req.format != "jpg" && req.format != "jpeg" && req.format != "exr" &&
        req.format != "raw")
        r.fail("unknown format " + quote_value(req.format) + " (expected png, jpg, exr or raw)");
    if (r.find("compression")) {
        int level = 0;
        r.integer("compression", level, 0, kMaxPngCompression);
        if (req.format != "png")
            r.fail("\"compression\" applies to png only, not " + quote_value(req.format));
        req.compression = level;
    }
    if (!r.error().empty()) return schema_error(r.error());

    if (const json* camera = r.find("camera")) {
        if (!camera->is_object()) return schema_error("\"camera\" must be an object");
        CameraSpec spec;
        ObjectReader c(*camera, "camera.",
                       {"eye", "look_at", "up", "fov", "projection", "ortho_height"});
        c.vec3("eye", spec.eye, true);
        c.vec3("look_at", spec.look_at, true);
        c.vec3("up", spec.up, false);
        c.real("fov", spec.fov_deg);
        c.real("ortho_height", spec.ortho_height);
        std::string projection = "perspective";
        c.text("projection", projection);
        if (projection == "perspective")
            spec.projection = Projection::kPerspective;
        else if (projection == "orthographic")
            spec.projection = Projection::kOrthographic;
        else
            c.fail("unknown camera.projection " + quote_value(projection) +
                   " (expected perspective or orthographic)");
        if (!c.error().empty()) return schema_error(c.error());
        req.settings.camera = spec;
    }
    if (const json* light = r.find("light")) {
        if (!light->is_object()) return schema_error("\"light\" must be an object");
        ObjectReader l(*light, "light.", {"direction", "intensity"});
        Vec3& d = req.settings.light.direction;
        l.vec3("direction", d, true);
        if (l.error().empty() && !(d.x * d.x + d.y * d.y + d.z * d.z > 0.0f))
            l.fail("\"light.direction\" must not be the zero vector");
        l.real("intensity", req.settings.light.intensity);
        if (req.settings.light.intensity < 0.0f)
            l.fail("\"light.intensity\" must be >= 0 (a radiance)");
        if (!l.error().empty()) return schema_error(l.error());
    }
    if (const json* tile = r.find("tile")) {
        if (!tile->is_object()) return schema_error("\"tile\" must be an object");
        PixelRegion region;
        ObjectReader t(*tile, "tile.", {"x", "y", "w", "h"});
        for (const char* key : {"x", "y", "w", "h"})
            if (!t.find(key)) t.fail("missing member " + quote_value(std::string("tile.") + key));
        t.integer("x", region.x, 0, req.settings.width - 1);
        t.integer("y", region.y, 0, req.settings.height - 1);
        t.integer("w", region.width, 1, req.settings.width - region.x);
        t.integer("h", region.height, 1, req.settings.height - region.y);
        if (!t.error().empty())
            return schema_error(t.error() + " (the tile must lie inside the " +
                                std::to_string(req.settings.width) + " x " +
                                std::to_string(req.settings.height) + " frame)");
        req.settings.region = region;
    }
    return req;
}

std::string encode_render_request(const RenderRequest& request) {
    detail::JsonWriter w;
    const RenderSettings& s = request.settings;
    w.begin_object();
    w.key("mesh").string(request.mesh);
    if (s.camera) {
        const CameraSpec& c = *s.camera;
        w.key("camera").begin_object();
        w.key("eye").vec3(c.eye.x, c.eye.y, c.eye.z);
        w.key("look_at").vec3(c.look_at.x, c.look_at.y, c.look_at.z);
        w.key("up").vec3(c.up.x, c.up.y, c.up.z);
        w.key("fov").number(c.fov_deg);
        w.key("projection")
            .string(c.projection == Projection::kOrthographic ? "orthographic" : "perspective");
        w.key("ortho_height").number(c.ortho_height);
        w.end_object();
    }
    w.key("width").number(s.width);
    w.key("height").number(s.height);
    w.key("spp").number(s.spp);
    w.key("seed").number(s.seed);
    w.key("shading").string(shading_name(s.shading));
    // Members at their defaults are left out (a request an older server also understands).
    const RenderSettings defaults;
    if (s.ao_samples != defaults.ao_samples) w.key("ao_samples").number(s.ao_samples);
    if (s.ao_distance != defaults.ao_distance) w.key("ao_distance").number(s.ao_distance);
    if (!(s.light.direction == defaults.light.direction) ||
        s.light.intensity != defaults.light.intensity) {
        const Vec3& d = s.light.direction;
        w.key("light").begin_object().key("direction").vec3(d.x, d.y, d.z);
        if (s.light.intensity != defaults.light.intensity)
            w.key("intensity").number(s.light.intensity);
        w.end_object();
    }
    if (s.bounces != defaults.bounces) w.key("bounces").number(s.bounces);
    if (s.sky != defaults.sky) w.key("sky").number(s.sky);
    if (!(s.background == defaults.background)) {
        const Vec3& b = s.background;
        w.key("background").vec3(b.x, b.y, b.z);
    }
    w.key("format").string(request.format);
    if (request.compression) w.key("compression").number(*request.compression);
    if (s.region) {
        w.key("tile").begin_object();
        w.key("x").number(s.region->x).key("y").number(s.region->y);
        w.key("w").number(s.region->width).key("h").number(s.region->height);
        w.end_object();
    }
    w.end_object();
    return w.take();
}

std::string_view job_state_name(JobState state) noexcept {
    switch (state) {
        case JobState::kQueued:
            return "queued";
        case JobState::kRunning:
            return "running";
        case JobState::kDone:
            return "done";
        case JobState::kFailed:
            return "failed";
        case JobState::kCancelled:
            return "cancelled";
    }
    return "unknown";
}

std::optional<JobState> parse_job_state(std::string_view name) noexcept {
    for (const JobState s : {JobState::kQueued, JobState::kRunning, JobState::kDone,
                             JobState::kFailed, JobState::kCancelled})
        if (job_state_name(s) == name) return s;
    return std::nullopt;
}

std::string encode_job_status(const JobStatus& status) {
    detail::JsonWriter w;
    w.begin_object();
    w.key("id").string(status.id);
    w.key("state").string(job_state_name(status.state));
    w.key("progress").number(status.progress);
    if (status.scene.empty()) {
        w.key("mesh").string(status.mesh);
    } else {
        w.key("scene").string(status.scene);
        w.key("revision").number(status.revision);
    }
    w.key("format").string(status.format);
    w.key("created").number(status.created);
    w.key("cancel_requested").boolean(status.cancel_requested);
    if (status.render_ms) w.key("render_ms").number(*status.render_ms);
    if (status.state == JobState::kDone) {
        w.key("result").string("/v1/jobs/" + status.id + "/result");
        w.key("result_bytes").number(status.result_bytes);
    }
    if (!status.error.empty()) w.key("error").string(status.error);
    w.end_object();
    return w.take();
}

Result<JobStatus, std::string> decode_job_status(std::string_view text) {
    const json doc = json::parse(text, nullptr, /*allow_exceptions=*/false);
    if (doc.is_discarded() || !doc.is_object())
        return Err{std::string("job status is not a JSON object")};
    JobStatus s;
    try {
        s.id = doc.at("id").get<std::string>();
        const auto state = parse_job_state(doc.at("state").get<std::string>());
        if (!state)
            return Err{"unknown job state " + quote_value(doc.at("state").get<std::string>())};
        s.state = *state;
        s.progress = doc.at("progress").get<double>();
        if (doc.contains("scene")) {
            s.scene = doc["scene"].get<std::string>();
            s.revision = doc.at("revision").get<uint64_t>();
        } else {
            s.mesh = doc.at("mesh").get<std::string>();
        }
        s.format = doc.at("format").get<std::string>();
        s.created = doc.at("created").get<double>();
        s.cancel_requested = doc.at("cancel_requested").get<bool>();
        if (doc.contains("render_ms")) s.render_ms = doc["render_ms"].get<double>();
        if (doc.contains("result_bytes")) s.result_bytes = doc["result_bytes"].get<uint64_t>();
        if (doc.contains("error")) s.error = doc["error"].get<std::string>();
    } catch (const json::exception& e) {
        return Err{std::string("job status: ") + e.what()};
    }
    return s;
}

}  // namespace kdrt::proto
