#include "kdrt/proto/json_api.h"

#include <algorithm>
#include <cctype>
#include <cmath>
#include <limits>
#include <nlohmann/json.hpp>

#include "json_writer.h"

namespace kdrt::proto {
namespace {

using nlohmann::json;

std::string trim_lower(std::string_view s) {
    while (!s.empty() && (s.front() == ' ' || s.front() == '\t')) s.remove_prefix(1);
    while (!s.empty() && (s.back() == ' ' || s.back() == '\t')) s.remove_suffix(1);
    std::string out(s);
    std::transform(out.begin(), out.end(), out.begin(),
                   [](unsigned char c) { return static_cast<char>(std::tolower(c)); });
    return out;
}

void write_summary(detail::JsonWriter& w, const MeshSummary& s) {
    w.begin_object();
    w.key("id").string(s.id);
    w.key("triangles").number(s.triangles);
    w.key("vertices").number(s.vertices);
    w.key("bounds").begin_object();
    w.key("min").vec3(s.bounds.lo.x, s.bounds.lo.y, s.bounds.lo.z);
    w.key("max").vec3(s.bounds.hi.x, s.bounds.hi.y, s.bounds.hi.z);
    w.end_object();
    w.key("build_ms").number(s.tree.build_ms);
    w.key("tree").begin_object();
    w.key("nodes").number(s.tree.nodes);
    w.key("leaves").number(s.tree.leaves);
    w.key("empty_leaves").number(s.tree.empty_leaves);
    w.key("refs").number(s.tree.refs);
    w.key("max_depth").number(s.tree.max_depth);
    w.key("mean_leaf_depth").number(s.tree.mean_leaf_depth);
    w.key("mean_tris_per_leaf").number(s.tree.mean_tris_per_leaf);
    w.key("sah_cost").number(s.tree.sah_cost);
    w.key("bytes").number(s.tree.bytes);
    w.key("bytes_per_triangle").number(s.tree.bytes_per_triangle);
    w.end_object();
    if (s.in_memory) w.key("in_memory").boolean(*s.in_memory);
    if (!s.warnings.empty()) {
        w.key("warnings").begin_array();
        for (const std::string& warning : s.warnings) w.string(warning);
        w.end_array();
    }
    w.end_object();
}

/// Reads typed members out of a parsed object, remembering the first problem.
class Reader {
public:
    Reader(const json& object, std::string where) : object_(object), where_(std::move(where)) {}

    const json* member(const char* key) {
        const auto it = object_.find(key);
        if (it == object_.end()) {
            fail(std::string("missing \"") + key + "\"");
            return nullptr;
        }
        return &*it;
    }
    void get(const char* key, uint64_t& out) {
        if (const json* v = member(key)) {
            if (v->is_number_unsigned())
                out = v->get<uint64_t>();
            else
                fail(std::string("\"") + key + "\" is not a non-negative integer");
        }
    }
    void get(const char* key, uint32_t& out) {
        uint64_t wide = 0;
        get(key, wide);
        if (wide > std::numeric_limits<uint32_t>::max())
            fail(std::string("\"") + key + "\" is too large");
        out = static_cast<uint32_t>(wide);
    }
    void get(const char* key, double& out) {
        if (const json* v = member(key)) {
            if (v->is_number())
                out = v->get<double>();
            else if (v->is_null())
                out = std::numeric_limits<double>::quiet_NaN();  // written for a non-finite value
            else
                fail(std::string("\"") + key + "\" is not a number");
        }
    }
    void get(const char* key, std::string& out) {
        if (const json* v = member(key)) {
            if (v->is_string())
                out = v->get<std::string>();
            else
                fail(std::string("\"") + key + "\" is not a string");
        }
    }
    void get_vec3(const json& object, const char* key, Vec3& out) {
        const auto it = object.find(key);
        if (it == object.end() || !it->is_array() || it->size() != 3) {
            fail(std::string("\"") + key + "\" is not an array of 3 numbers");
            return;
        }
        for (int a = 0; a < 3; ++a) {
            const json& v = (*it)[static_cast<size_t>(a)];
            if (v.is_number())
                // The encoder wrote the float's shortest form; double -> float of it is exact.
                out[a] = static_cast<float>(v.get<double>());
            else if (v.is_null())
                // An empty box is written with nulls: lo = +inf, hi = -inf.
                out[a] = std::string_view(key) == "min" ? std::numeric_limits<float>::infinity()
                                                        : -std::numeric_limits<float>::infinity();
            else
                fail(std::string("\"") + key + "\" is not an array of 3 numbers");
        }
    }
    void fail(const std::string& message) {
        if (error_.empty()) error_ = where_ + message;
    }
    [[nodiscard]] const std::string& error() const noexcept { return error_; }

private:
    const json& object_;
    std::string where_;
    std::string error_;
};

Result<MeshSummary, std::string> summary_from_json(const json& doc, const std::string& where) {
    if (!doc.is_object()) return Err{where + "is not a JSON object"};
    MeshSummary s;
    Reader r(doc, where);
    r.get("id", s.id);
    r.get("triangles", s.triangles);
    r.get("vertices", s.vertices);
    if (const json* bounds = r.member("bounds")) {
        if (bounds->is_object()) {
            r.get_vec3(*bounds, "min", s.bounds.lo);
            r.get_vec3(*bounds, "max", s.bounds.hi);
        } else {
            r.fail("\"bounds\" is not an object");
        }
    }
    r.get("build_ms", s.tree.build_ms);
    if (const json* tree = r.member("tree")) {
        if (!tree->is_object()) return Err{where + "\"tree\" is not an object"};
        Reader t(*tree, where + "tree: ");
        t.get("nodes", s.tree.nodes);
        t.get("leaves", s.tree.leaves);
        t.get("empty_leaves", s.tree.empty_leaves);
        t.get("refs", s.tree.refs);
        t.get("max_depth", s.tree.max_depth);
        t.get("mean_leaf_depth", s.tree.mean_leaf_depth);
        t.get("mean_tris_per_leaf", s.tree.mean_tris_per_leaf);
        t.get("sah_cost", s.tree.sah_cost);
        t.get("bytes", s.tree.bytes);
        t.get("bytes_per_triangle", s.tree.bytes_per_triangle);
        if (!t.error().empty()) return Err{t.error()};
    }
    s.tree.triangles = s.triangles;
    const auto in_memory = doc.find("in_memory");
    if (in_memory != doc.end()) {
        if (!in_memory->is_boolean()) return Err{where + "\"in_memory\" is not a boolean"};
        s.in_memory = in_memory->get<bool>();
    }
    if (const auto warnings = doc.find("warnings"); warnings != doc.end()) {
        if (!warnings->is_array()) return Err{where + "\"warnings\" is not an array"};
        for (const auto& warning : *warnings) {
            if (!warning.is_string()) return Err{where + "\"warnings\" holds a non-string"};
            s.warnings.push_back(warning.get<std::string>());
        }
    }
    if (!r.error().empty()) return Err{r.error()};
    return s;
}

json parse_or_discard(std::string_view text) {
    return json::parse(text, nullptr, /*allow_exceptions=*/false);
}

}  // namespace

bool operator==(const MeshSummary& a, const MeshSummary& b) noexcept {
    const TreeStats& s = a.tree;
    const TreeStats& t = b.tree;
    return a.id == b.id && a.triangles == b.triangles && a.vertices == b.vertices &&
           a.bounds == b.bounds && a.in_memory == b.in_memory && a.warnings == b.warnings &&
           s.triangles == t.triangles && s.nodes == t.nodes && s.leaves == t.leaves &&
           s.empty_leaves == t.empty_leaves && s.refs == t.refs && s.max_depth == t.max_depth &&
           s.mean_leaf_depth == t.mean_leaf_depth && s.mean_tris_per_leaf == t.mean_tris_per_leaf &&
           s.sah_cost == t.sah_cost && s.bytes == t.bytes &&
           s.bytes_per_triangle == t.bytes_per_triangle && s.build_ms == t.build_ms;
}

std::string media_type_essence(std::string_view content_type) {
    const size_t semicolon = content_type.find(';');
    return trim_lower(content_type.substr(0, semicolon));
}

std::optional<MeshFormat> mesh_format_from_media_type(std::string_view content_type) {
    const std::string type = media_type_essence(content_type);
    if (type == "model/obj") return MeshFormat::kObj;
    if (type == "model/stl" || type == "application/sla") return MeshFormat::kStl;
    if (type == "application/ply" || type == "model/ply" || type == "application/x-ply")
        return MeshFormat::kPly;
    if (type == "application/x-off" || type == "model/off") return MeshFormat::kOff;
    if (type == kRawMeshMediaType) return MeshFormat::kRaw;
    return std::nullopt;
}

std::string_view mesh_media_type(MeshFormat format) noexcept {
    switch (format) {
        case MeshFormat::kObj:
            return "model/obj";
        case MeshFormat::kStl:
            return "model/stl";
        case MeshFormat::kPly:
            return "application/ply";
        case MeshFormat::kOff:
            return "application/x-off";
        case MeshFormat::kRaw:
            return kRawMeshMediaType;
    }
    return "application/octet-stream";
}

std::string encode_mesh_summary(const MeshSummary& summary) {
    detail::JsonWriter w(512);
    write_summary(w, summary);
    return w.take();
}

Result<MeshSummary, std::string> decode_mesh_summary(std::string_view text) {
    const json doc = parse_or_discard(text);
    if (doc.is_discarded()) return Err{std::string("mesh summary is not valid JSON")};
    return summary_from_json(doc, "mesh summary: ");
}

std::string encode_mesh_list(std::span<const MeshSummary> meshes) {
    detail::JsonWriter w(64 + 512 * meshes.size());
    w.begin_object().key("meshes").begin_array();
    for (const MeshSummary& s : meshes) write_summary(w, s);
    w.end_array().end_object();
    return w.take();
}

Result<std::vector<MeshSummary>, std::string> decode_mesh_list(std::string_view text) {
    const json doc = parse_or_discard(text);
    if (doc.is_discarded()) return Err{std::string("mesh list is not valid JSON")};
    const auto it = doc.is_object() ? doc.find("meshes") : doc.end();
    if (!doc.is_object() || it == doc.end() || !it->is_array())
        return Err{std::string("mesh list has no \"meshes\" array")};
    std::vector<MeshSummary> out;
    for (size_t i = 0; i < it->size(); ++i) {
        auto s = summary_from_json((*it)[i], "meshes[" + std::to_string(i) + "]: ");
        if (!s) return Err{std::move(s).error()};
        out.push_back(std::move(*s));
    }
    return out;
}

std::string encode_json_hits(std::span<const Hit> hits) {
    std::string out;
    out.reserve(16 + hits.size() * 56);
    out += "{\"hits\":[";
    for (size_t i = 0; i < hits.size(); ++i) {
        if (i) out.push_back(',');
        const Hit& h = hits[i];
        if (!h.is_hit()) {
            out += "null";
            continue;
        }
        out += "{\"t\":";
        detail::append_json_float(out, h.t);
        out += ",\"prim\":";
        out += std::to_string(h.prim);
        out += ",\"u\":";
        detail::append_json_float(out, h.u);
        out += ",\"v\":";
        detail::append_json_float(out, h.v);
        out.push_back('}');
    }
    out += "]}";
    return out;
}

Result<std::vector<Hit>, std::string> decode_json_hits(std::string_view text) {
    const json doc = parse_or_discard(text);
    if (doc.is_discarded()) return Err{std::string("hits are not valid JSON")};
    const auto it = doc.is_object() ? doc.find("hits") : doc.end();
    if (!doc.is_object() || it == doc.end() || !it->is_array())
        return Err{std::string("no \"hits\" array")};
    std::vector<Hit> hits(it->size());
    for (size_t i = 0; i < hits.size(); ++i) {
        const json& h = (*it)[i];
        if (h.is_null()) continue;
        const std::string where = "hits[" + std::to_string(i) + "]";
        if (!h.is_object()) return Err{where + " is neither an object nor null"};
        const auto num = [&](const char* key, float& out) -> bool {
            const auto m = h.find(key);
            if (m == h.end() || !m->is_number()) return false;
            out = static_cast<float>(m->get<double>());
            return true;
        };
        const auto prim = h.find("prim");
        if (!num("t", hits[i].t) || !num("u", hits[i].u) || !num("v", hits[i].v) ||
            prim == h.end() || !prim->is_number_unsigned() || prim->get<uint64_t>() >= kNoHit)
            return Err{where + " needs numbers t, u, v and an integer prim"};
        hits[i].prim = prim->get<uint32_t>();
    }
    return hits;
}

std::string encode_json_occlusion(std::span<const uint8_t> occluded) {
    std::string out;
    out.reserve(16 + occluded.size() * 6);
    out += "{\"occluded\":[";
    for (size_t i = 0; i < occluded.size(); ++i) {
        if (i) out.push_back(',');
        out += occluded[i] ? "true" : "false";
    }
    out += "]}";
    return out;
}

Result<std::vector<uint8_t>, std::string> decode_json_occlusion(std::string_view text) {
    const json doc = parse_or_discard(text);
    if (doc.is_discarded()) return Err{std::string("occlusion answer is not valid JSON")};
    const auto it = doc.is_object() ? doc.find("occluded") : doc.end();
    if (!doc.is_object() || it == doc.end() || !it->is_array())
        return Err{std::string("no \"occluded\" array")};
    std::vector<uint8_t> out(it->size());
    for (size_t i = 0; i < out.size(); ++i) {
        if (!(*it)[i].is_boolean())
            return Err{"occluded[" + std::to_string(i) + "] is not a boolean"};
        out[i] = (*it)[i].get<bool>() ? 1 : 0;
    }
    return out;
}

std::string encode_flat_object(std::span<const JsonField> fields) {
    detail::JsonWriter w(64 + 32 * fields.size());
    w.begin_object();
    for (const JsonField& f : fields) {
        w.key(f.key);
        std::visit(
            [&](const auto& v) {
                using V = std::decay_t<decltype(v)>;
                if constexpr (std::is_same_v<V, std::string> || std::is_same_v<V, std::string_view>)
                    w.string(v);
                else if constexpr (std::is_same_v<V, bool>)
                    w.boolean(v);
                else
                    w.number(v);
            },
            f.value);
    }
    w.end_object();
    return w.take();
}

}  // namespace kdrt::proto
