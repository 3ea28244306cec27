// The scene documents and binaries (kdrt/proto/scene.h). The first byte picks the decoder:
// 0 a create request, 1 a stored revision (as JSON, and as a revision file: KDRS or JSON),
// 2 a pose update (JSON), 3 an instance edit, 4 a KDRX pose batch, 5 a scene answer's
// geometry-id plane. What decodes re-encodes to something that decodes to the same value;
// refusals carry a detail; limits hold.

#include <string_view>

#include "fuzz_check.h"
#include "kdrt/proto/scene.h"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
    using namespace kdrt;
    if (size == 0) return 0;
    const std::string_view text(reinterpret_cast<const char*>(data + 1), size - 1);
    const auto bytes = fuzz::as_bytes(data + 1, size - 1);
    const proto::SceneLimits limits{64};
    switch (data[0] % 6) {
        case 0:
        case 1: {
            const bool stored = data[0] % 6 == 1;
            if (stored) {  // a stored revision file: KDRS, or the JSON of older stores
                const auto file = proto::decode_stored_scene(bytes);
                if (file) {
                    const auto again = proto::decode_scene_file(proto::encode_scene_file(*file));
                    fuzz::require(again.ok() && *again == *file);
                } else {
                    fuzz::require(!file.error().empty());
                }
            }
            const auto scene = proto::decode_scene_json(text, limits, stored);
            if (!scene) {
                fuzz::require(!scene.error().detail.empty());
                break;
            }
            fuzz::require(scene->instances.size() <= limits.max_instances);
            proto::SceneDocument doc = *scene;
            if (!stored) {
                doc.id = std::string(proto::kSceneIdLength, 'a');
                doc.revision = 1;
            }
            const auto again =
                proto::decode_scene_json(proto::encode_scene_json(doc), limits, true);
            fuzz::require(again.ok() && *again == doc);
            break;
        }
        case 2: {
            const auto poses = proto::decode_pose_json(text, limits);
            if (!poses) {
                fuzz::require(!poses.error().detail.empty());
                break;
            }
            fuzz::require(!poses->empty() && poses->size() <= limits.max_instances);
            const auto again = proto::decode_pose_json(proto::encode_pose_json(*poses), limits);
            fuzz::require(again.ok() && again->size() == poses->size());
            for (size_t i = 0; i < poses->size(); ++i)
                fuzz::require((*again)[i].transform == (*poses)[i].transform &&
                              (*again)[i].geometry_id == (*poses)[i].geometry_id &&
                              (*again)[i].name == (*poses)[i].name);
            break;
        }
        case 3: {
            const auto edit = proto::decode_instance_edit_json(text, limits);
            if (!edit) {
                fuzz::require(!edit.error().detail.empty());
                break;
            }
            const auto again =
                proto::decode_instance_edit_json(proto::encode_instance_edit_json(*edit), limits);
            fuzz::require(again.ok() && again->remove == edit->remove && again->add == edit->add);
            proto::SceneDocument scene;
            const std::string mesh(64, 'b');
            scene.instances = {{mesh, {}, ""}, {mesh, {}, std::string(1, 'a')}, {mesh, {}, ""}};
            const auto next = proto::apply_instance_edit(scene, *edit, limits);
            if (next)
                fuzz::require(next->instances.size() <= limits.max_instances);
            else
                fuzz::require(!next.error().detail.empty());
            break;
        }
        case 4: {
            const auto poses = proto::decode_pose_batch(bytes, limits);
            if (!poses) {
                fuzz::require(!poses.error().detail.empty());
                break;
            }
            const auto again = proto::encode_pose_batch(*poses);
            const auto back = proto::decode_pose_batch(again, limits);
            fuzz::require(back.ok() && back->size() == poses->size());
            break;
        }
        default: {
            kdrt::proto::DecodeLimits decode;
            decode.max_rays = 1u << 16;
            const auto split = proto::split_geometry_ids(bytes, decode);
            if (!split) {
                fuzz::require(!split.error().detail.empty());
                break;
            }
            fuzz::require(split->mesh_body.size() + 4 * split->geometry_ids.size() == bytes.size());
            std::vector<std::byte> again = split->mesh_body;
            proto::append_geometry_ids(again, split->geometry_ids);
            fuzz::require(std::equal(again.begin(), again.end(), bytes.begin(), bytes.end()));
            break;
        }
    }
    return 0;
}
