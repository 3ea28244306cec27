// The scene JSON documents: a scene (create request and stored revision), a pose update and an
// instance edit (kdrt/proto/scene.h).

#include <cmath>
#include <cstring>
#include <nlohmann/json.hpp>
#include <string>
#include <unordered_set>

#include "json_strict.h"
#include "json_writer.h"
#include "kdrt/proto/mesh_id.h"
#include "kdrt/proto/scene.h"
#include "kdrt/proto/text.h"

namespace kdrt::proto {
namespace {

using nlohmann::json;

/// A parse failure on its way out.
struct Failure {
    SceneRequestError error;
};

[[noreturn]] void fail(std::string field, std::optional<uint32_t> index, std::string detail,
                       bool over_limit = false) {
    SceneRequestError e;
    e.field = std::move(field);
    e.index = index;
    e.detail = std::move(detail);
    e.over_limit = over_limit;
    throw Failure{std::move(e)};
}

/// Refuses members of `object` (named `where`) outside `known`.
void only_members(const json& object, const std::string& where, std::optional<uint32_t> index,
                  std::initializer_list<const char*> known) {
    if (!object.is_object())
        fail(where, index, in_quotes(where.empty() ? "request" : where) + " must be an object");
    for (const auto& item : object.items()) {
        bool ok = false;
        for (const char* k : known) ok = ok || item.key() == k;
        if (ok) continue;
        const std::string name = where.empty() ? item.key() : where + "." + item.key();
        std::string message = "unknown member " + in_quotes(name) + " (expected ";
        for (size_t i = 0; const char* k : known) {
            if (i++ > 0) message += ", ";
            message += k;
        }
        fail(name, index, message + ')');
    }
}

[[nodiscard]] const json* member(const json& object, const char* key) {
    const auto it = object.find(key);
    return it == object.end() ? nullptr : &*it;
}

[[nodiscard]] std::string dotted(const std::string& where, const char* key) {
    return where.empty() ? std::string(key) : where + "." + key;
}

/// One transform entry as a float: a finite number within float range.
float entry(const json& v, const std::string& field, std::optional<uint32_t> index) {
    if (!v.is_number()) fail(field, index, in_quotes(field) + " must be a number");
    const double d = v.get<double>();
    if (!std::isfinite(d)) fail(field, index, in_quotes(field) + " is " + non_finite_name(d));
    const auto f = static_cast<float>(d);
    if (!std::isfinite(f))
        fail(field, index, in_quotes(field) + " is " + json(d).dump() + ", outside float range");
    return f == 0.0f ? 0.0f
                     : f;  // -0 reads as 0 (JSON integers have no -0): one transform, one spelling
}

/// 12 numbers (row-major 3 x 4), 3 rows of 4, or 4 rows of 4 ending 0 0 0 1.
Transform transform(const json& v, const std::string& field, std::optional<uint32_t> index) {
    const std::string shape =
        in_quotes(field) +
        " must be 12 numbers (row-major 3 x 4), 3 rows of 4 numbers, or 4 rows of 4 numbers "
        "whose last row is [0, 0, 0, 1]";
    Transform t;
    if (!v.is_array()) fail(field, index, shape);
    const auto at = [&](size_t r, size_t c) {
        return field + "[" + std::to_string(r) + "][" + std::to_string(c) + "]";
    };
    if (v.size() == 12 && !v[0].is_array()) {
        for (size_t k = 0; k < 12; ++k) t.m[k] = entry(v[k], at(k / 4, k % 4), index);
        return t;
    }
    if (v.size() != 3 && v.size() != 4)
        fail(field, index, shape + " (it has " + std::to_string(v.size()) + " entries)");
    for (size_t r = 0; r < v.size(); ++r) {
        const json& row = v[r];
        const std::string row_name = field + "[" + std::to_string(r) + "]";
        if (!row.is_array() || row.size() != 4)
            fail(row_name, index, in_quotes(row_name) + " must be a row of 4 numbers");
        for (size_t c = 0; c < 4; ++c) {
            const float f = entry(row[c], at(r, c), index);
            if (r < 3) {
                t.m[4 * r + c] = f;
            } else if (f != (c == 3 ? 1.0f : 0.0f)) {
                fail(row_name, index,
                     in_quotes(row_name) + " must be [0, 0, 0, 1] (an affine transform)");
            }
        }
    }
    return t;
}

/// The array member `key` of `object` with its size checked against the limit before any entry
/// is decoded.
const json& array_member(const json& object, const char* key, uint64_t max, bool required,
                         const char* limit_name) {
    static const json kEmpty = json::array();
    const json* v = member(object, key);
    if (!v) {
        if (required) fail(key, std::nullopt, "missing member " + in_quotes(key));
        return kEmpty;
    }
    if (!v->is_array()) fail(key, std::nullopt, in_quotes(key) + " must be an array");
    if (v->size() > max)
        fail(key, std::nullopt,
             in_quotes(key) + " has " + std::to_string(v->size()) + " entries, more than " +
                 limit_name + " (" + std::to_string(max) + ")",
             true);
    return *v;
}

SceneInstanceSpec instance(const json& v, const std::string& where, uint32_t index, bool stored) {
    if (stored)
        only_members(v, where, index, {"mesh", "transform", "name", "geometry_id"});
    else
        only_members(v, where, index, {"mesh", "transform", "name"});
    SceneInstanceSpec out;
    const json* mesh = member(v, "mesh");
    const std::string mesh_field = dotted(where, "mesh");
    if (!mesh) fail(mesh_field, index, "missing member " + in_quotes(mesh_field));
    if (!mesh->is_string())
        fail(mesh_field, index, in_quotes(mesh_field) + " must be a string (a mesh id)");
    out.mesh = mesh->get<std::string>();
    if (!is_mesh_id(out.mesh))
        fail(mesh_field, index,
             in_quotes(mesh_field) + " is " + json(out.mesh).dump() +
                 ", not a mesh id (64 lower-case hex digits, as POST /v1/meshes answers)");
    if (const json* t = member(v, "transform"))
        out.transform = transform(*t, dotted(where, "transform"), index);
    if (const json* n = member(v, "name")) {
        const std::string field = dotted(where, "name");
        if (!n->is_string() || !is_instance_name(n->get<std::string>()))
            fail(field, index,
                 in_quotes(field) +
                     " must be a string of 1 to 128 characters from "
                     "A-Z a-z 0-9 . _ : / -");
        out.name = n->get<std::string>();
    }
    if (const json* g = member(v, "geometry_id")) {
        const std::string field = dotted(where, "geometry_id");
        if (!g->is_number_unsigned() || g->get<uint64_t>() != index)
            fail(
                field, index,
                in_quotes(field) + " must be " + std::to_string(index) + " (the instance's index)");
    }
    return out;
}

/// Decodes `text` with `body`, mapping failures to a SceneRequestError.
template <class T, class F>
Result<T, SceneRequestError> decode(std::string_view text, F&& body) {
    auto parsed = detail::parse_json_strict<json>(text);
    if (!parsed) {
        SceneRequestError e;
        e.detail = parsed.error();
        return Err{std::move(e)};
    }
    try {
        return body(*parsed);
    } catch (const Failure& f) {
        return Err{f.error};
    }
}

void write_transform(detail::JsonWriter& w, const Transform& t) {
    w.begin_array();
    for (const float v : t.m) w.number(v);
    w.end_array();
}

void write_instance(detail::JsonWriter& w, const SceneInstanceSpec& inst,
                    std::optional<uint32_t> geometry_id) {
    w.begin_object();
    if (geometry_id) w.key("geometry_id").number(*geometry_id);
    w.key("mesh").string(inst.mesh);
    w.key("transform");
    write_transform(w, inst.transform);
    if (!inst.name.empty()) w.key("name").string(inst.name);
    w.end_object();
}

}  // namespace

Result<SceneDocument, SceneRequestError> decode_scene_json(std::string_view text,
                                                           const SceneLimits& limits, bool stored) {
    return decode<SceneDocument>(text, [&](const json& doc) {
        if (stored)
            only_members(doc, "", std::nullopt, {"format", "id", "revision", "instances"});
        else
            only_members(doc, "", std::nullopt, {"instances"});
        SceneDocument out;
        if (stored) {
            const json* format = member(doc, "format");
            if (!format || *format != "kdrt-scene")
                fail("format", std::nullopt, "\"format\" must be \"kdrt-scene\"");
            const json* id = member(doc, "id");
            if (!id || !id->is_string() || !is_scene_id(id->get<std::string>()))
                fail("id", std::nullopt, "\"id\" must be a scene id (32 lower-case hex digits)");
            out.id = id->get<std::string>();
            const json* revision = member(doc, "revision");
            if (!revision || !revision->is_number_unsigned() || revision->get<uint64_t>() == 0)
                fail("revision", std::nullopt, "\"revision\" must be an integer >= 1");
            out.revision = revision->get<uint64_t>();
        }
        const json& instances =
            array_member(doc, "instances", limits.max_instances, true, "max_instances");
        out.instances.reserve(instances.size());
        std::unordered_set<std::string> names;
        for (size_t i = 0; i < instances.size(); ++i) {
            const auto index = static_cast<uint32_t>(i);
            const std::string where = "instances[" + std::to_string(i) + "]";
            out.instances.push_back(instance(instances[i], where, index, stored));
            const std::string& name = out.instances.back().name;
            if (!name.empty() && !names.insert(name).second)
                fail(where + ".name", index,
                     in_quotes(where + ".name") + " is " + in_quotes(name) +
                         ", which an earlier instance already has (names are unique in a scene)");
        }
        return out;
    });
}

Result<SceneDocument, std::string> decode_stored_scene(std::span<const std::byte> bytes) {
    if (bytes.size() >= 4 && std::memcmp(bytes.data(), kSceneFileMagic.data(), 4) == 0) {
        auto doc = decode_scene_file(bytes);
        if (!doc) return Err{"KDRS: " + doc.error()};
        return doc;
    }
    // Stores written before KDRS hold the JSON document, read without the instance limit.
    const std::string_view text(reinterpret_cast<const char*>(bytes.data()), bytes.size());
    auto doc = decode_scene_json(text, SceneLimits{UINT32_MAX}, true);
    if (!doc) {
        std::string why = "JSON: ";
        if (!doc.error().field.empty()) why += doc.error().field + ": ";
        return Err{why + doc.error().detail};
    }
    return std::move(doc).value();
}

std::string encode_scene_request(std::span<const SceneInstanceSpec> instances) {
    detail::JsonWriter w(32 + 200 * instances.size());
    w.begin_object();
    w.key("instances").begin_array();
    for (const SceneInstanceSpec& inst : instances) write_instance(w, inst, std::nullopt);
    w.end_array();
    w.end_object();
    return w.take();
}

std::string encode_scene_json(const SceneDocument& scene) {
    detail::JsonWriter w(128 + 200 * scene.instances.size());
    w.begin_object();
    w.key("format").string("kdrt-scene");
    w.key("id").string(scene.id);
    w.key("revision").number(scene.revision);
    w.key("instances").begin_array();
    for (size_t g = 0; g < scene.instances.size(); ++g)
        write_instance(w, scene.instances[g], static_cast<uint32_t>(g));
    w.end_array();
    w.end_object();
    return w.take();
}

Result<std::vector<PoseEntry>, SceneRequestError> decode_pose_json(std::string_view text,
                                                                   const SceneLimits& limits) {
    return decode<std::vector<PoseEntry>>(text, [&](const json& doc) {
        only_members(doc, "", std::nullopt, {"poses"});
        const json& poses = array_member(doc, "poses", limits.max_instances, true, "max_instances");
        if (poses.empty()) fail("poses", std::nullopt, "\"poses\" must have at least one entry");
        std::vector<PoseEntry> out(poses.size());
        for (size_t i = 0; i < poses.size(); ++i) {
            const auto index = static_cast<uint32_t>(i);
            const std::string where = "poses[" + std::to_string(i) + "]";
            const json& p = poses[i];
            only_members(p, where, index, {"geometry_id", "name", "transform"});
            const json* g = member(p, "geometry_id");
            const json* n = member(p, "name");
            if ((g != nullptr) == (n != nullptr))
                fail(where + (g ? ".name" : ".geometry_id"), index,
                     in_quotes(where) + " needs exactly one of \"geometry_id\" and \"name\"");
            if (g) {
                if (!g->is_number_unsigned() || g->get<uint64_t>() >= kNoGeometry)
                    fail(where + ".geometry_id", index,
                         in_quotes(where + ".geometry_id") + " must be a non-negative integer");
                out[i].geometry_id = static_cast<uint32_t>(g->get<uint64_t>());
            } else {
                if (!n->is_string() || !is_instance_name(n->get<std::string>()))
                    fail(where + ".name", index,
                         in_quotes(where + ".name") + " must be an instance name");
                out[i].name = n->get<std::string>();
            }
            const json* t = member(p, "transform");
            if (!t)
                fail(where + ".transform", index,
                     "missing member " + in_quotes(where + ".transform"));
            out[i].transform = transform(*t, where + ".transform", index);
        }
        return out;
    });
}

std::string encode_pose_json(std::span<const PoseEntry> poses) {
    detail::JsonWriter w(64 + 160 * poses.size());
    w.begin_object().key("poses").begin_array();
    for (const PoseEntry& p : poses) {
        w.begin_object();
        if (p.geometry_id)
            w.key("geometry_id").number(*p.geometry_id);
        else
            w.key("name").string(p.name);
        w.key("transform");
        write_transform(w, p.transform);
        w.end_object();
    }
    w.end_array().end_object();
    return w.take();
}

Result<InstanceEdit, SceneRequestError> decode_instance_edit_json(std::string_view text,
                                                                  const SceneLimits& limits) {
    return decode<InstanceEdit>(text, [&](const json& doc) {
        only_members(doc, "", std::nullopt, {"add", "remove"});
        const json& remove =
            array_member(doc, "remove", limits.max_instances, false, "max_instances");
        const json& add = array_member(doc, "add", limits.max_instances, false, "max_instances");
        if (remove.empty() && add.empty())
            fail("add", std::nullopt,
                 "an instance edit needs at least one entry in \"add\" or \"remove\"");
        InstanceEdit out;
        for (size_t i = 0; i < remove.size(); ++i) {
            const std::string where = "remove[" + std::to_string(i) + "]";
            const auto index = static_cast<uint32_t>(i);
            const json& r = remove[i];
            if (r.is_number_unsigned() && r.get<uint64_t>() < kNoGeometry)
                out.remove.emplace_back(static_cast<uint32_t>(r.get<uint64_t>()));
            else if (r.is_string() && is_instance_name(r.get<std::string>()))
                out.remove.emplace_back(r.get<std::string>());
            else
                fail(where, index,
                     in_quotes(where) + " must be a geometry id (an integer) or an instance name");
        }
        for (size_t i = 0; i < add.size(); ++i)
            out.add.push_back(instance(add[i], "add[" + std::to_string(i) + "]",
                                       static_cast<uint32_t>(i), false));
        return out;
    });
}

std::string encode_instance_edit_json(const InstanceEdit& edit) {
    detail::JsonWriter w(64 + 200 * (edit.add.size() + edit.remove.size()));
    w.begin_object();
    w.key("remove").begin_array();
    for (const auto& r : edit.remove) {
        if (const auto* id = std::get_if<uint32_t>(&r))
            w.number(*id);
        else
            w.string(std::get<std::string>(r));
    }
    w.end_array();
    w.key("add").begin_array();
    for (const SceneInstanceSpec& inst : edit.add) write_instance(w, inst, std::nullopt);
    w.end_array();
    w.end_object();
    return w.take();
}

namespace {
void write_list_item(detail::JsonWriter& w, const SceneListItem& item) {
    w.begin_object();
    w.key("id").string(item.id);
    w.key("revision").number(item.revision);
    w.key("instances").number(item.instances);
    w.end_object();
}
}  // namespace

std::string encode_scene_list(std::span<const SceneListItem> scenes) {
    detail::JsonWriter w(32 + 96 * scenes.size());
    w.begin_object().key("scenes").begin_array();
    for (const SceneListItem& item : scenes) write_list_item(w, item);
    w.end_array().end_object();
    return w.take();
}

std::string encode_scene_revision(const SceneListItem& scene) {
    detail::JsonWriter w(96);
    write_list_item(w, scene);
    return w.take();
}

namespace {

/// One {"id", "revision", "instances"} object; `where` prefixes the error ("scenes[2]: ").
Result<SceneListItem, std::string> list_item(const json& item, const std::string& where) {
    if (!item.is_object()) return Err{where + "not an object"};
    SceneListItem out;
    const json* id = member(item, "id");
    if (id == nullptr || !id->is_string() || !is_scene_id(id->get<std::string>()))
        return Err{where + "\"id\" is not a scene id (32 lower-case hex digits)"};
    out.id = id->get<std::string>();
    const json* revision = member(item, "revision");
    if (revision == nullptr || !revision->is_number_unsigned() || revision->get<uint64_t>() == 0)
        return Err{where + "\"revision\" is not an integer >= 1"};
    out.revision = revision->get<uint64_t>();
    const json* instances = member(item, "instances");
    if (instances == nullptr || !instances->is_number_unsigned())
        return Err{where + "\"instances\" is not an integer >= 0"};
    out.instances = instances->get<uint64_t>();
    return out;
}

}  // namespace

Result<std::vector<SceneListItem>, std::string> decode_scene_list(std::string_view text) {
    const json doc = json::parse(text, nullptr, /*allow_exceptions=*/false);
    if (doc.is_discarded()) return Err{std::string("scene list is not valid JSON")};
    const json* scenes = doc.is_object() ? member(doc, "scenes") : nullptr;
    if (scenes == nullptr || !scenes->is_array())
        return Err{std::string("scene list has no \"scenes\" array")};
    std::vector<SceneListItem> out;
    out.reserve(scenes->size());
    for (size_t i = 0; i < scenes->size(); ++i) {
        auto item = list_item((*scenes)[i], "scenes[" + std::to_string(i) + "]: ");
        if (!item) return Err{std::move(item).error()};
        out.push_back(std::move(*item));
    }
    return out;
}

Result<SceneListItem, std::string> decode_scene_revision(std::string_view text) {
    const json doc = json::parse(text, nullptr, /*allow_exceptions=*/false);
    if (doc.is_discarded()) return Err{std::string("scene revision is not valid JSON")};
    return list_item(doc, "scene revision: ");
}

}  // namespace kdrt::proto
