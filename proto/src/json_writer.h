#pragma once
// A small streaming JSON writer for the encoders in this directory: shortest round-trip numbers
// (std::to_chars), RFC 8259 string escaping (kdrt/proto/text.h), commas tracked per nesting level.
// Internal to kdrt_proto_json; callers see only the typed encoders.

#include <cstdint>
#include <string>
#include <string_view>
#include <vector>

namespace kdrt::proto::detail {

/// Appends the shortest decimal that reads back to the same float; NaN/Inf become `null`.
void append_json_float(std::string& out, float value);
/// Same for doubles.
void append_json_double(std::string& out, double value);

class JsonWriter {
public:
    explicit JsonWriter(size_t reserve_bytes = 256) { out_.reserve(reserve_bytes); }

    JsonWriter& begin_object();
    JsonWriter& end_object();
    JsonWriter& begin_array();
    JsonWriter& end_array();
    /// The next value is the member `name` of the current object.
    JsonWriter& key(std::string_view name);

    JsonWriter& string(std::string_view value);
    JsonWriter& boolean(bool value);
    JsonWriter& null();
    JsonWriter& number(uint64_t value);
    JsonWriter& number(int64_t value);
    JsonWriter& number(uint32_t value) { return number(static_cast<uint64_t>(value)); }
    JsonWriter& number(int value) { return number(static_cast<int64_t>(value)); }
    JsonWriter& number(double value);
    JsonWriter& number(float value);
    /// [x, y, z] as floats.
    JsonWriter& vec3(float x, float y, float z);

    [[nodiscard]] std::string take() { return std::move(out_); }
    [[nodiscard]] std::string& buffer() noexcept { return out_; }

private:
    void before_value();

    std::string out_;
    // One entry per open container: true once it has a first element.
    std::vector<bool> has_element_;
    bool after_key_ = false;
};

}  // namespace kdrt::proto::detail
