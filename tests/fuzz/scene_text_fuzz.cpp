// The scene and pose text files of `kdrt scene create FILE` and `kdrt scene poses ID FILE`
// (proto::parse_scene_text, parse_pose_text). The first byte picks the parser: even the scene
// text, odd the pose text. A refusal names its line ("line N: ...", or the empty pose file); what
// parses is within the limit, has mesh ids, instance names (unique in a scene) and finite
// transforms, and written back as text (each float with 9 significant digits) parses to the same
// value.

#include <cmath>
#include <cstdio>
#include <set>
#include <string>
#include <string_view>

#include "fuzz_check.h"
#include "kdrt/proto/mesh_id.h"
#include "kdrt/proto/scene.h"

namespace {

/// The 12 entries of `t` as text, exactly (9 significant digits round-trip a float).
std::string transform_text(const kdrt::proto::Transform& t) {
    std::string out;
    char number[32];
    for (const float f : t.m) {
        std::snprintf(number, sizeof number, " %.9g", static_cast<double>(f));
        out += number;
    }
    return out;
}

bool names_a_line(const std::string& error) {
    return error.rfind("line ", 0) == 0 && error.find(": ") != std::string::npos;
}

bool finite(const kdrt::proto::Transform& t) {
    for (const float f : t.m)
        if (!std::isfinite(f)) return false;
    return true;
}

}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
    using namespace kdrt;
    if (size == 0) return 0;
    const std::string_view text(reinterpret_cast<const char*>(data + 1), size - 1);
    const proto::SceneLimits limits{16};
    if (data[0] % 2 == 0) {
        const auto scene = proto::parse_scene_text(text, limits);
        if (!scene) {
            fuzz::require(names_a_line(scene.error()));
            return 0;
        }
        fuzz::require(scene->size() <= limits.max_instances);
        std::set<std::string> names;
        std::string again;
        for (const proto::SceneInstanceSpec& inst : *scene) {
            fuzz::require(proto::is_mesh_id(inst.mesh) && finite(inst.transform));
            if (!inst.name.empty())
                fuzz::require(proto::is_instance_name(inst.name) && names.insert(inst.name).second);
            again += inst.mesh + transform_text(inst.transform) + " " + inst.name + "\n";
        }
        const auto back = proto::parse_scene_text(again, limits);
        fuzz::require(back.ok() && *back == *scene);
    } else {
        const auto poses = proto::parse_pose_text(text, limits);
        if (!poses) {
            fuzz::require(names_a_line(poses.error()) || poses.error().rfind("no poses", 0) == 0);
            return 0;
        }
        fuzz::require(!poses->empty() && poses->size() <= limits.max_instances);
        std::string again;
        for (const proto::PoseEntry& p : *poses) {
            fuzz::require(p.geometry_id.has_value() == p.name.empty() && finite(p.transform));
            if (!p.name.empty()) fuzz::require(proto::is_instance_name(p.name));
            again += (p.geometry_id ? std::to_string(*p.geometry_id) : p.name) +
                     transform_text(p.transform) + "\n";
        }
        const auto back = proto::parse_pose_text(again, limits);
        fuzz::require(back.ok() && back->size() == poses->size());
        for (size_t i = 0; i < poses->size(); ++i)
            fuzz::require((*back)[i].geometry_id == (*poses)[i].geometry_id &&
                          (*back)[i].name == (*poses)[i].name &&
                          (*back)[i].transform == (*poses)[i].transform);
    }
    return 0;
}
