// JSON ray batches: a SAX decoder (no DOM: a 100k-ray batch is parsed in one pass into the ray
// array, and the ray limit stops the parse as soon as it is exceeded).

#include <charconv>
#include <cmath>
#include <limits>
#include <nlohmann/json.hpp>

#include "json_writer.h"
#include "kdrt/proto/json_api.h"
#include "kdrt/proto/problem.h"
#include "kdrt/proto/text.h"

namespace kdrt::proto {
namespace {

using nlohmann::json;

constexpr float kInf = std::numeric_limits<float>::infinity();

/// Field names of a ray's JSON numbers, in the order they are written.
constexpr const char* kFieldNames[8] = {"ox", "oy", "oz", "dx", "dy", "dz", "tmin", "tmax"};

class RaySax {
public:
    explicit RaySax(size_t max_rays) : max_rays_(max_rays) {}

    bool null() { return unexpected("null"); }
    bool boolean(bool value) {
        if (state_ == State::kOcclusionValue) {
            occlusion_ = value;
            state_ = State::kTopMembers;
            return true;
        }
        return unexpected(value ? "true" : "false");
    }
    // Integers arrive converted; their decimal text converts to f32 with one correct rounding.
    bool number_integer(json::number_integer_t v) { return number(std::to_string(v)); }
    bool number_unsigned(json::number_unsigned_t v) { return number(std::to_string(v)); }
    bool number_float(json::number_float_t, const json::string_t& text) { return number(text); }
    bool string(json::string_t&) { return unexpected("a string"); }
    bool binary(json::binary_t&) { return unexpected("binary data"); }

    bool start_object(std::size_t) {
        if (state_ == State::kStart) {
            state_ = State::kTopMembers;
            return true;
        }
        return unexpected("an object");
    }
    bool key(json::string_t& name) {
        if (name == "rays") {
            if (seen_rays_) return fail(JsonError::Code::kSchema, "duplicate member \"rays\"");
            seen_rays_ = true;
            state_ = State::kRaysValue;
            return true;
        }
        if (name == "occlusion") {
            if (seen_occlusion_)
                return fail(JsonError::Code::kSchema, "duplicate member \"occlusion\"");
            seen_occlusion_ = true;
            state_ = State::kOcclusionValue;
            return true;
        }
        return fail(JsonError::Code::kSchema,
                    "unknown member " + quote_value(name) +
                        " (expected \"rays\" and optionally \"occlusion\")");
    }
    bool end_object() {
        state_ = State::kDone;
        if (!seen_rays_) return fail(JsonError::Code::kSchema, "missing member \"rays\"");
        return true;
    }
    bool start_array(std::size_t) {
        if (state_ == State::kRaysValue) {
            state_ = State::kRays;
            return true;
        }
        if (state_ == State::kRays) {
            if (rays_.size() >= max_rays_)
                return fail(JsonError::Code::kTooMany,
                            "rays[" + std::to_string(rays_.size()) +
                                "]: " + std::string(api_errors::kTooManyJsonRays) +
                                " the limit of " + std::to_string(max_rays_) +
                                "; send larger batches as application/x-kdrt-rays");
            state_ = State::kRay;
            field_count_ = 0;
            return true;
        }
        return unexpected("an array");
    }
    bool end_array() {
        if (state_ == State::kRay) {
            if (field_count_ != 6 && field_count_ != 8)
                return fail(JsonError::Code::kSchema, where() + ": expected 6 or 8 numbers, got " +
                                                          std::to_string(field_count_));
            Ray ray{fields_[0], fields_[1], fields_[2], 0.0f,
                    fields_[3], fields_[4], fields_[5], kInf};
            if (field_count_ == 8) {
                ray.tmin = fields_[6];
                ray.tmax = fields_[7];
            }
            rays_.push_back(ray);
            state_ = State::kRays;
            return true;
        }
        state_ = State::kTopMembers;  // end of "rays"
        return true;
    }
    bool parse_error(std::size_t position, const std::string&,
                     const nlohmann::detail::exception& ex) {
        // nlohmann's message starts with "[json.exception.parse_error.101] parse error at line
        // 1, column 7: ..."; keep the part after the exception id.
        std::string what = ex.what();
        const size_t bracket = what.find("] ");
        if (bracket != std::string::npos) what.erase(0, bracket + 2);
        return fail(JsonError::Code::kSyntax, std::string(api_errors::kBadJson) + " at byte " +
                                                  std::to_string(position) + ": " + what);
    }

    [[nodiscard]] bool failed() const noexcept { return error_.has_value(); }
    [[nodiscard]] JsonError take_error() { return std::move(*error_); }
    [[nodiscard]] JsonRayRequest take_request() { return {std::move(rays_), occlusion_}; }

private:
    enum class State { kStart, kTopMembers, kRaysValue, kOcclusionValue, kRays, kRay, kDone };

    bool number(const std::string& text) {
        if (state_ != State::kRay) return unexpected("a number");
        if (field_count_ >= 8)
            return fail(JsonError::Code::kSchema,
                        where() + ": expected 6 or 8 numbers, got more than 8");
        float value = 0.0f;
        const char* first = text.data();
        const char* last = text.data() + text.size();
        const auto [ptr, ec] = std::from_chars(first, last, value);
        if (ec == std::errc::result_out_of_range || (ec == std::errc() && std::isinf(value))) {
            // Overflow or underflow: decide by the magnitude of the double.
            double wide = 0.0;
            std::from_chars(first, last, wide);
            if (std::fabs(wide) < 1.0) {
                value = std::signbit(wide) ? -0.0f : 0.0f;
            } else if (field_count_ >= 6) {
                value = wide > 0 ? kInf : -kInf;
            } else {
                return fail(JsonError::Code::kSchema, where() + "[" + std::to_string(field_count_) +
                                                          "] (" + kFieldNames[field_count_] +
                                                          "): " + text +
                                                          " does not fit a 32-bit float");
            }
        } else if (ec != std::errc() || ptr != last) {
            return fail(JsonError::Code::kSchema, where() + ": cannot read number " + text);
        }
        fields_[field_count_++] = value;
        return true;
    }

    bool unexpected(const std::string& what) {
        switch (state_) {
            case State::kStart:
                return fail(JsonError::Code::kSchema, "expected a JSON object, got " + what);
            case State::kRaysValue:
                return fail(JsonError::Code::kSchema,
                            "\"rays\" must be an array of rays, got " + what);
            case State::kOcclusionValue:
                return fail(JsonError::Code::kSchema,
                            "\"occlusion\" must be true or false, got " + what);
            case State::kRays:
                return fail(JsonError::Code::kSchema,
                            where() + ": expected an array of 6 or 8 numbers, got " + what);
            case State::kRay:
                return fail(JsonError::Code::kSchema, where() + "[" + std::to_string(field_count_) +
                                                          "]: expected a number, got " + what);
            default:
                return fail(JsonError::Code::kSchema, "unexpected " + what);
        }
    }

    bool fail(JsonError::Code code, std::string detail) {
        if (!error_) error_ = JsonError{code, std::move(detail)};
        return false;
    }

    [[nodiscard]] std::string where() const { return "rays[" + std::to_string(rays_.size()) + "]"; }

    size_t max_rays_;
    State state_ = State::kStart;
    bool seen_rays_ = false;
    bool seen_occlusion_ = false;
    bool occlusion_ = false;
    std::vector<Ray> rays_;
    float fields_[8] = {};
    int field_count_ = 0;
    std::optional<JsonError> error_;
};

}  // namespace

Result<JsonRayRequest, JsonError> decode_json_rays(std::string_view text, size_t max_rays) {
    RaySax sax(max_rays);
    const bool ok = json::sax_parse(text.begin(), text.end(), &sax, json::input_format_t::json,
                                    /*strict=*/true);
    if (sax.failed()) return Err{sax.take_error()};
    if (!ok) return Err{JsonError{JsonError::Code::kSyntax, std::string(api_errors::kBadJson)}};
    return sax.take_request();
}

std::string encode_json_rays(std::span<const Ray> rays, bool occlusion) {
    std::string out;
    out.reserve(32 + rays.size() * 96);
    out += "{\"rays\":[";
    for (size_t i = 0; i < rays.size(); ++i) {
        if (i) out.push_back(',');
        const Ray& r = rays[i];
        const float values[8] = {r.ox, r.oy, r.oz, r.dx, r.dy, r.dz, r.tmin, r.tmax};
        out.push_back('[');
        for (int k = 0; k < 8; ++k) {
            if (k) out.push_back(',');
            if (std::isinf(values[k]))
                out += values[k] > 0 ? "1e39" : "-1e39";
            else if (values[k] == 0.0f && std::signbit(values[k]))
                out += "-0.0";  // "-0" would be read as the integer 0 and lose the sign
            else
                detail::append_json_float(out, values[k]);
        }
        out.push_back(']');
    }
    out += "],\"occlusion\":";
    out += occlusion ? "true" : "false";
    out.push_back('}');
    return out;
}

}  // namespace kdrt::proto
