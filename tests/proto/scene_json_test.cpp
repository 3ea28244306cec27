// The scene JSON documents (kdrt/proto/scene.h): create requests, stored revisions, pose
// updates and instance edits, each refusal naming the instance or pose index and the field.

#include <gtest/gtest.h>

#include <cmath>
#include <cstring>
#include <string>

#include "kdrt/proto/scene.h"

namespace kdrt::proto {
namespace {

const std::string kMeshA(64, 'a');
const std::string kMeshB(64, 'b');

std::string instance_json(const std::string& mesh, const std::string& transform,
                          const std::string& extra = "") {
    return "{\"mesh\":\"" + mesh + "\",\"transform\":" + transform + extra + "}";
}

SceneRequestError scene_error(const std::string& text, const SceneLimits& limits = {}) {
    auto r = decode_scene_json(text, limits);
    EXPECT_FALSE(r.ok()) << text;
    return r.ok() ? SceneRequestError{} : r.error();
}

TEST(SceneJson, DecodesTheThreeTransformShapesAndTheIdentityDefault) {
    const std::string text =
        "{\"instances\":[" +
        instance_json(kMeshA, "[1,0,0,5, 0,2,0,6, 0,0,3,7]", ",\"name\":\"a\"") + "," +
        instance_json(kMeshB, "[[1,0,0,5],[0,2,0,6],[0,0,3,7]]") + "," +
        instance_json(kMeshB, "[[1,0,0,5],[0,2,0,6],[0,0,3,7],[0,0,0,1]]") + ",{\"mesh\":\"" +
        kMeshA + "\"}]}";
    auto r = decode_scene_json(text);
    ASSERT_TRUE(r.ok()) << r.error().detail;
    ASSERT_EQ(r->instances.size(), 4u);
    const Transform expected{{1, 0, 0, 5, 0, 2, 0, 6, 0, 0, 3, 7}};
    for (size_t i = 0; i < 3; ++i) EXPECT_EQ(r->instances[i].transform, expected) << i;
    EXPECT_EQ(r->instances[3].transform, Transform{});
    EXPECT_EQ(r->instances[0].name, "a");
    EXPECT_EQ(r->instances[1].mesh, kMeshB);
    EXPECT_TRUE(r->instances[1].name.empty());
}

TEST(SceneJson, NamesTheInstanceAndEntryOfABadTransform) {
    // NaN cannot be written in JSON; a number beyond float range and a string can.
    auto e = scene_error("{\"instances\":[" + instance_json(kMeshA, "[1,0,0,0,0,1,0,0,0,0,1,0]") +
                         "," + instance_json(kMeshA, "[[1,0,0,0],[0,1,1e39,0],[0,0,1,0]]") + "]}");
    EXPECT_EQ(e.field, "instances[1].transform[1][2]");
    EXPECT_EQ(e.index, 1u);
    EXPECT_NE(e.detail.find("outside float range"), std::string::npos) << e.detail;

    e = scene_error("{\"instances\":[" + instance_json(kMeshA, "[1,0,0,0,0,1,0,0,0,0,\"x\",0]") +
                    "]}");
    EXPECT_EQ(e.field, "instances[0].transform[2][2]");

    e = scene_error("{\"instances\":[" + instance_json(kMeshA, "[1,0,0,0,0,1,0,0,0,0,1]") + "]}");
    EXPECT_EQ(e.field, "instances[0].transform");
    EXPECT_NE(e.detail.find("12 numbers"), std::string::npos) << e.detail;

    e = scene_error("{\"instances\":[" +
                    instance_json(kMeshA, "[[1,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,1,1]]") + "]}");
    EXPECT_EQ(e.field, "instances[0].transform[3]");

    e = scene_error("{\"instances\":[" + instance_json(kMeshA, "[[1,0,0],[0,1,0],[0,0,1]]") + "]}");
    EXPECT_EQ(e.field, "instances[0].transform[0]");
}

TEST(SceneJson, RefusesBadMeshIdsNamesAndMembers) {
    auto e =
        scene_error("{\"instances\":[" + instance_json("abc", "[1,0,0,0,0,1,0,0,0,0,1,0]") + "]}");
    EXPECT_EQ(e.field, "instances[0].mesh");
    EXPECT_NE(e.detail.find("not a mesh id"), std::string::npos);

    e = scene_error("{\"instances\":[" +
                    instance_json(std::string(64, 'A'), "[1,0,0,0,0,1,0,0,0,0,1,0]") + "]}");
    EXPECT_EQ(e.field, "instances[0].mesh");

    e = scene_error("{\"instances\":[{\"transform\":[1,0,0,0,0,1,0,0,0,0,1,0]}]}");
    EXPECT_EQ(e.field, "instances[0].mesh");

    e = scene_error("{\"instances\":[{\"mesh\":\"" + kMeshA + "\",\"name\":\"x\"},{\"mesh\":\"" +
                    kMeshB + "\",\"name\":\"x\"}]}");
    EXPECT_EQ(e.field, "instances[1].name");
    EXPECT_EQ(e.index, 1u);

    e = scene_error("{\"instances\":[{\"mesh\":\"" + kMeshA + "\",\"name\":\"a b\"}]}");
    EXPECT_EQ(e.field, "instances[0].name");

    e = scene_error("{\"instances\":[{\"mesh\":\"" + kMeshA + "\",\"colour\":1}]}");
    EXPECT_EQ(e.field, "instances[0].colour");

    e = scene_error("{\"instances\":[],\"instances\":[]}");
    EXPECT_TRUE(e.field.empty());
    EXPECT_NE(e.detail.find("duplicate"), std::string::npos);

    e = scene_error("{\"instances\":{}}");
    EXPECT_EQ(e.field, "instances");
    e = scene_error("{}");
    EXPECT_EQ(e.field, "instances");
    e = scene_error("[");
    EXPECT_NE(e.detail.find("invalid JSON"), std::string::npos);
    // A create request may not set what the server assigns.
    e = scene_error("{\"id\":\"" + std::string(32, '0') + "\",\"instances\":[]}");
    EXPECT_EQ(e.field, "id");
}

TEST(SceneJson, CountsInstancesAgainstTheLimitBeforeDecodingThem) {
    // The third instance is malformed, but the count is refused first.
    const std::string text = "{\"instances\":[{\"mesh\":\"" + kMeshA + "\"},{\"mesh\":\"" + kMeshA +
                             "\"},{\"mesh\":1}]}";
    auto e = scene_error(text, SceneLimits{2});
    EXPECT_EQ(e.field, "instances");
    EXPECT_TRUE(e.over_limit);
    EXPECT_NE(e.detail.find("max_instances (2)"), std::string::npos) << e.detail;
    e = scene_error(text, SceneLimits{3});
    EXPECT_EQ(e.field, "instances[2].mesh");
    EXPECT_FALSE(e.over_limit);
}

TEST(SceneJson, StoredDocumentsRoundTripEveryFloatBit) {
    SceneDocument doc;
    doc.id = "0123456789abcdef0123456789abcdef";
    doc.revision = 42;
    doc.instances.push_back(
        {kMeshA,
         Transform{{0.1f, -1e-38f, 1e-30f, 3.4e38f, 0, 1, 0, -7.25f, 0.3333333f, 0, 1, 1e7f}},
         "shelf-1"});
    doc.instances.push_back({kMeshB, Transform{}, ""});
    const std::string text = encode_scene_json(doc);
    auto back = decode_scene_json(text, {}, true);
    ASSERT_TRUE(back.ok()) << back.error().detail;
    EXPECT_EQ(*back, doc);
    // -0 is read as 0 (one transform, one spelling).
    auto zero = decode_scene_json("{\"instances\":[{\"mesh\":\"" + kMeshA +
                                  "\",\"transform\":[1,-0.0,0,0,0,1,0,0,0,0,1,0]}]}");
    ASSERT_TRUE(zero.ok());
    EXPECT_FALSE(std::signbit(zero->instances[0].transform.m[1]));
    // A stored document's geometry ids must be the indices.
    std::string wrong = text;
    wrong.replace(wrong.find("\"geometry_id\":1"), 15, "\"geometry_id\":7");
    auto bad = decode_scene_json(wrong, {}, true);
    ASSERT_FALSE(bad.ok());
    EXPECT_EQ(bad.error().field, "instances[1].geometry_id");
    // A create request may not carry them.
    EXPECT_FALSE(decode_scene_json(text).ok());
}

TEST(PoseJson, DecodesByIdOrNameAndNamesTheBadEntry) {
    auto r = decode_pose_json(
        "{\"poses\":[{\"geometry_id\":3,\"transform\":[1,0,0,1,0,1,0,2,0,0,1,3]},"
        "{\"name\":\"car\",\"transform\":[[1,0,0,0],[0,1,0,0],[0,0,1,0]]}]}");
    ASSERT_TRUE(r.ok()) << r.error().detail;
    ASSERT_EQ(r->size(), 2u);
    EXPECT_EQ((*r)[0].geometry_id, 3u);
    EXPECT_EQ((*r)[0].transform.m[11], 3.0f);
    EXPECT_EQ((*r)[1].name, "car");
    auto again = decode_pose_json(encode_pose_json(*r));
    ASSERT_TRUE(again.ok());
    EXPECT_EQ((*again)[0].transform, (*r)[0].transform);
    EXPECT_EQ((*again)[1].name, "car");

    auto e = decode_pose_json(
        "{\"poses\":[{\"geometry_id\":0,\"transform\":[1,0,0,0,0,1,0,0,0,0,1,0]},"
        "{\"geometry_id\":1,\"name\":\"x\",\"transform\":[1,0,0,0,0,1,0,0,0,0,1,0]}]}");
    ASSERT_FALSE(e.ok());
    EXPECT_EQ(e.error().field, "poses[1].name");
    EXPECT_EQ(e.error().index, 1u);
    e = decode_pose_json(
        "{\"poses\":[{\"geometry_id\":-1,\"transform\":[1,0,0,0,0,1,0,0,0,0,1,0]}]}");
    ASSERT_FALSE(e.ok());
    EXPECT_EQ(e.error().field, "poses[0].geometry_id");
    e = decode_pose_json("{\"poses\":[{\"geometry_id\":0}]}");
    ASSERT_FALSE(e.ok());
    EXPECT_EQ(e.error().field, "poses[0].transform");
    e = decode_pose_json(
        "{\"poses\":[{\"geometry_id\":0,\"transform\":[1,0,0,0,0,1,0,0,0,0,1,1e300]}]}");
    ASSERT_FALSE(e.ok());
    EXPECT_EQ(e.error().field, "poses[0].transform[2][3]");
    e = decode_pose_json("{\"poses\":[]}");
    ASSERT_FALSE(e.ok());
    EXPECT_EQ(e.error().field, "poses");
    e = decode_pose_json(
        "{\"poses\":[{\"geometry_id\":0,\"transform\":[1,0,0,0,0,1,0,0,0,0,1,0]},"
        "{\"geometry_id\":0,\"transform\":[1,0,0,0,0,1,0,0,0,0,1,0]}]}",
        SceneLimits{1});
    ASSERT_FALSE(e.ok());
    EXPECT_TRUE(e.error().over_limit);
}

SceneDocument three_instances() {
    SceneDocument doc;
    doc.id = std::string(32, 'c');
    doc.revision = 5;
    doc.instances = {{kMeshA, {}, "a"}, {kMeshB, {}, ""}, {kMeshA, {}, "c"}};
    return doc;
}

TEST(PoseJson, ResolvesIdsAndNamesAgainstTheScene) {
    const SceneDocument doc = three_instances();
    std::vector<PoseEntry> poses(2);
    poses[0].name = "c";
    poses[1].geometry_id = 1;
    auto r = resolve_poses(doc, poses);
    ASSERT_TRUE(r.ok());
    EXPECT_EQ((*r)[0].geometry_id, 2u);
    EXPECT_EQ((*r)[1].geometry_id, 1u);
    poses[1].geometry_id = 3;
    r = resolve_poses(doc, poses);
    ASSERT_FALSE(r.ok());
    EXPECT_EQ(r.error().field, "poses[1].geometry_id");
    EXPECT_TRUE(r.error().unknown_reference);
    poses[0].name = "zz";
    r = resolve_poses(doc, poses);
    ASSERT_FALSE(r.ok());
    EXPECT_EQ(r.error().field, "poses[0].name");
}

TEST(InstanceEdit, RemovesThenAppendsAndNamesBadEntries) {
    const SceneDocument doc = three_instances();
    auto edit = decode_instance_edit_json("{\"remove\":[\"a\",1],\"add\":[{\"mesh\":\"" + kMeshB +
                                          "\",\"name\":\"d\"}]}");
    ASSERT_TRUE(edit.ok()) << edit.error().detail;
    auto next = apply_instance_edit(doc, *edit);
    ASSERT_TRUE(next.ok()) << next.error().detail;
    ASSERT_EQ(next->instances.size(), 2u);
    EXPECT_EQ(next->instances[0].name, "c");
    EXPECT_EQ(next->instances[1].name, "d");
    EXPECT_EQ(next->id, doc.id);
    auto again = decode_instance_edit_json(encode_instance_edit_json(*edit));
    ASSERT_TRUE(again.ok());
    EXPECT_EQ(again->remove, edit->remove);
    EXPECT_EQ(again->add, edit->add);

    auto bad = apply_instance_edit(doc, *decode_instance_edit_json("{\"remove\":[0,\"a\"]}"));
    ASSERT_FALSE(bad.ok());
    EXPECT_EQ(bad.error().field, "remove[1]");
    bad = apply_instance_edit(doc, *decode_instance_edit_json("{\"remove\":[9]}"));
    ASSERT_FALSE(bad.ok());
    EXPECT_TRUE(bad.error().unknown_reference);
    bad = apply_instance_edit(doc, *decode_instance_edit_json("{\"add\":[{\"mesh\":\"" + kMeshA +
                                                              "\",\"name\":\"c\"}]}"));
    ASSERT_FALSE(bad.ok());
    EXPECT_EQ(bad.error().field, "add[0].name");
    bad = apply_instance_edit(
        doc, *decode_instance_edit_json("{\"add\":[{\"mesh\":\"" + kMeshA + "\"}]}"),
        SceneLimits{3});
    ASSERT_FALSE(bad.ok());
    EXPECT_TRUE(bad.error().over_limit);

    auto e = decode_instance_edit_json("{}");
    ASSERT_FALSE(e.ok());
    e = decode_instance_edit_json("{\"remove\":[true]}");
    ASSERT_FALSE(e.ok());
    EXPECT_EQ(e.error().field, "remove[0]");
    e = decode_instance_edit_json("{\"add\":[{\"mesh\":\"x\"}]}");
    ASSERT_FALSE(e.ok());
    EXPECT_EQ(e.error().field, "add[0].mesh");
}

TEST(SceneJson, CreateRequestListAndRevisionReadBack) {
    const std::vector<SceneInstanceSpec> instances = {
        {kMeshA, Transform{{0.5f, 0, 0, 1e-7f, 0, 1, 0, -3, 0, 0, 2, 0.1f}}, "a"},
        {kMeshB, Transform{}, ""}};
    auto doc = decode_scene_json(encode_scene_request(instances));
    ASSERT_TRUE(doc.ok()) << doc.error().detail;
    EXPECT_EQ(doc->instances, instances);
    EXPECT_TRUE(doc->id.empty());

    const std::vector<SceneListItem> items = {{std::string(32, 'a'), 3, 7},
                                              {std::string(32, 'b'), 1, 0}};
    auto list = decode_scene_list(encode_scene_list(items));
    ASSERT_TRUE(list.ok()) << list.error();
    ASSERT_EQ(list->size(), 2u);
    EXPECT_EQ((*list)[0].id, items[0].id);
    EXPECT_EQ((*list)[0].revision, 3u);
    EXPECT_EQ((*list)[1].instances, 0u);
    EXPECT_TRUE(decode_scene_list("{\"scenes\":[]}")->empty());
    auto revision = decode_scene_revision(encode_scene_revision(items[0]));
    ASSERT_TRUE(revision.ok()) << revision.error();
    EXPECT_EQ(revision->revision, 3u);
    EXPECT_EQ(revision->instances, 7u);
    // Bad answers say what and where.
    EXPECT_EQ(decode_scene_list("[]").error(), "scene list has no \"scenes\" array");
    EXPECT_EQ(
        decode_scene_list("{\"scenes\":[{\"id\":\"x\",\"revision\":1,\"instances\":1}]}").error(),
        "scenes[0]: \"id\" is not a scene id (32 lower-case hex digits)");
    EXPECT_EQ(decode_scene_revision("{\"id\":\"" + std::string(32, 'a') +
                                    "\",\"revision\":0,\"instances\":1}")
                  .error(),
              "scene revision: \"revision\" is not an integer >= 1");
    EXPECT_FALSE(decode_scene_revision("{").ok());
}

TEST(SceneText, InstancesOneALine) {
    const std::string text = "# a comment\n\n" + kMeshA + "\n" + kMeshB + " 1 2 3 named\r\n" +
                             kMeshA + ",0,-1,0,4, 1,0,0,5, 0,0,1,6\n\t" + kMeshB + "\tother";
    auto got = parse_scene_text(text);
    ASSERT_TRUE(got.ok()) << got.error();
    ASSERT_EQ(got->size(), 4u);
    EXPECT_EQ((*got)[0].mesh, kMeshA);
    EXPECT_EQ((*got)[0].transform, Transform{});
    EXPECT_EQ((*got)[1].transform, (Transform{{1, 0, 0, 1, 0, 1, 0, 2, 0, 0, 1, 3}}));
    EXPECT_EQ((*got)[1].name, "named");
    EXPECT_EQ((*got)[2].transform, (Transform{{0, -1, 0, 4, 1, 0, 0, 5, 0, 0, 1, 6}}));
    EXPECT_EQ((*got)[3].name, "other");
    EXPECT_TRUE(parse_scene_text("# nothing\n")->empty());

    auto error = [](const std::string& t, const SceneLimits& limits = {}) {
        auto r = parse_scene_text(t, limits);
        EXPECT_FALSE(r.ok()) << t;
        return r.ok() ? std::string() : r.error();
    };
    EXPECT_EQ(error("\n" + kMeshA + " 1 2\n"),
              "line 2: 2 transform numbers (expected 12, row-major 3 x 4; 3, a translation; or "
              "none)");
    EXPECT_EQ(error("nomesh 1 2 3\n"),
              "line 1: mesh \"nomesh\" is not a mesh id (64 lower-case hex digits)");
    EXPECT_EQ(error(kMeshA + " 1 nan 3"),
              "line 1: transform entry 1 \"nan\" is not a finite float");
    EXPECT_EQ(error(kMeshA + " 1 1e39 3"),
              "line 1: transform entry 1 \"1e39\" is not a finite float");
    EXPECT_EQ(error(kMeshA + " x\n" + kMeshB + " x"), "line 2: name \"x\" is given twice");
    EXPECT_EQ(error(kMeshA + " a\"b"),
              "line 1: name \"a\"b\" is not an instance name (1 to 128 characters from A-Z "
              "a-z 0-9 . _ : / -)");
    EXPECT_EQ(error(kMeshA + "\n" + kMeshA + "\n", SceneLimits{1}),
              "line 2: more than 1 instances (max_instances)");
}

TEST(SceneText, PosesOneALine) {
    auto got = parse_pose_text("3 1 2 3\ncar 1,0,0,0,0,1,0,0,0,0,1,9\n# end\n");
    ASSERT_TRUE(got.ok()) << got.error();
    ASSERT_EQ(got->size(), 2u);
    EXPECT_EQ((*got)[0].geometry_id, 3u);
    EXPECT_EQ((*got)[0].transform, (Transform{{1, 0, 0, 1, 0, 1, 0, 2, 0, 0, 1, 3}}));
    EXPECT_EQ((*got)[1].name, "car");
    EXPECT_FALSE((*got)[1].geometry_id);
    EXPECT_EQ((*got)[1].transform.m[11], 9.0f);
    EXPECT_EQ(parse_pose_text("").error(), "no poses (one pose a line: INSTANCE T)");
    EXPECT_EQ(parse_pose_text("car\n").error(),
              "line 1: no transform (expected 12 numbers, or 3: a translation)");
    EXPECT_EQ(parse_pose_text("a\"b 1 2 3").error(),
              "line 1: instance \"a\"b\" is neither a geometry id nor an instance name");
    EXPECT_EQ(parse_pose_text("1 1 2 inf").error(),
              "line 1: transform entry 2 \"inf\" is not a finite float");
}

// Found by scene_text_fuzz (corpus/scene_text/crash-*_comma_line): a line of separators only has
// no field, and the parsers read its first field (out of bounds). It is a blank line.
TEST(SceneText, LinesOfSeparatorsOnlyAreBlank) {
    auto scene = parse_scene_text(",\n" + kMeshA + " 1 2 3\n , ,\t,\r\n");
    ASSERT_TRUE(scene.ok()) << scene.error();
    ASSERT_EQ(scene->size(), 1u);
    EXPECT_EQ((*scene)[0].transform.m[11], 3.0f);
    EXPECT_TRUE(parse_scene_text(",").ok());
    EXPECT_TRUE(parse_scene_text(",")->empty());
    auto poses = parse_pose_text(",,\n2 1 2 3\n,");
    ASSERT_TRUE(poses.ok()) << poses.error();
    ASSERT_EQ(poses->size(), 1u);
    EXPECT_EQ((*poses)[0].geometry_id, 2u);
    EXPECT_EQ(parse_pose_text(", ,\n").error(), "no poses (one pose a line: INSTANCE T)");
}

TEST(SceneIds, SceneIdsAndInstanceNames) {
    EXPECT_TRUE(is_scene_id(std::string(32, 'f')));
    EXPECT_FALSE(is_scene_id(std::string(31, 'f')));
    EXPECT_FALSE(is_scene_id(std::string(32, 'F')));
    EXPECT_FALSE(is_scene_id(std::string(64, 'a')));
    EXPECT_TRUE(is_instance_name("robot/arm:1.link_2-a"));
    EXPECT_FALSE(is_instance_name(""));
    EXPECT_FALSE(is_instance_name(std::string(129, 'a')));
    EXPECT_FALSE(is_instance_name("a\"b"));
}

}  // namespace
}  // namespace kdrt::proto

// ---- KDRS, the stored revision file -------------------------------------------------------------

namespace kdrt::proto {
namespace {

SceneDocument stored_scene() {
    SceneDocument doc;
    doc.id = "0123456789abcdef0123456789abcdef";
    doc.revision = 42;
    doc.instances = {{kMeshB, Transform{{0, -1, 0, 1.5f, 1, 0, 0, -2, 0, 0, 1, 1e-30f}}, "car-1"},
                     {kMeshA, Transform{}, ""},
                     {kMeshB, Transform{{2, 0, 0, 0, 0, -2, 0, 0, 0, 0, 2, 0}}, "b"}};
    return doc;
}

TEST(SceneFile, RoundTripsEveryFieldAndListsEachMeshOnce) {
    const SceneDocument doc = stored_scene();
    const auto bytes = encode_scene_file(doc);
    // Header, two distinct mesh ids, 53 bytes an instance, the names, the checksum.
    ASSERT_EQ(bytes.size(), 64u + 2 * 64 + 3 * 53 + 5 + 1 + 8);
    auto back = decode_scene_file(bytes);
    ASSERT_TRUE(back.ok()) << back.error();
    EXPECT_EQ(*back, doc);
    auto stored = decode_stored_scene(bytes);
    ASSERT_TRUE(stored.ok()) << stored.error();
    EXPECT_EQ(*stored, doc);
    SceneDocument empty;
    empty.id = doc.id;
    empty.revision = 1;
    auto none = decode_scene_file(encode_scene_file(empty));
    ASSERT_TRUE(none.ok()) << none.error();
    EXPECT_EQ(*none, empty);
}

TEST(SceneFile, APoseUpdateEncodedFromItsBaseIsTheUpdatedDocumentsBytes) {
    const SceneDocument base = stored_scene();
    // Instance 2 posed twice (the later entry wins), instance 1 once, instance 0 left alone.
    const std::vector<ResolvedPose> poses = {
        {2, Transform{{1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12}}},
        {1, Transform{{0, 0, -1, 7, 0, 1, 0, -3.25f, 1, 0, 0, 1e-20f}}},
        {2, Transform{{-0.5f, 0, 0, 1, 0, 0.5f, 0, 2, 0, 0, 3, -1}}}};
    SceneDocument updated = base;
    updated.revision = base.revision + 1;
    for (const ResolvedPose& p : poses) updated.instances[p.geometry_id].transform = p.transform;
    ASSERT_NE(encode_scene_file(updated), encode_scene_file(base));
    const auto bytes = encode_scene_file(base, base.revision + 1, poses);
    EXPECT_EQ(bytes, encode_scene_file(updated));
    auto back = decode_scene_file(bytes);
    ASSERT_TRUE(back.ok()) << back.error();
    EXPECT_EQ(*back, updated);
    // No pose: the base under the new revision.
    SceneDocument renumbered = base;
    renumbered.revision = 9;
    EXPECT_EQ(encode_scene_file(base, 9, {}), encode_scene_file(renumbered));
    // Many instances of three meshes, every pose changed.
    SceneDocument many;
    many.id = base.id;
    many.revision = 4;
    std::vector<ResolvedPose> all;
    for (uint32_t i = 0; i < 300; ++i) {
        many.instances.push_back({i % 7 < 5 ? kMeshA : (i % 2 ? kMeshB : std::string(64, 'c')),
                                  Transform{}, i % 3 == 0 ? "i" + std::to_string(i) : ""});
        Transform t;
        for (size_t k = 0; k < 12; ++k)
            t.m[k] = 0.25f * static_cast<float>(i) - static_cast<float>(k);
        all.push_back({299 - i, t});
    }
    SceneDocument moved = many;
    moved.revision = 5;
    for (const ResolvedPose& p : all) moved.instances[p.geometry_id].transform = p.transform;
    EXPECT_EQ(encode_scene_file(many, 5, all), encode_scene_file(moved));
}

TEST(SceneFile, TheHeaderAloneGivesTheRevisionAndTheSizeOfEachRecordOfALog) {
    // Records back to back, as the server's revision log holds them: each header says where the
    // next record starts.
    SceneDocument a = stored_scene(), b = stored_scene(), c = stored_scene();
    b.revision = 43;
    b.instances.pop_back();
    c.revision = 44;
    c.instances.clear();
    std::vector<std::byte> log;
    for (const SceneDocument* d : {&a, &b, &c}) {
        const auto bytes = encode_scene_file(*d);
        log.insert(log.end(), bytes.begin(), bytes.end());
    }
    size_t at = 0;
    for (const SceneDocument* d : {&a, &b, &c}) {
        auto header = read_scene_file_header(std::span<const std::byte>(log).subspan(at));
        ASSERT_TRUE(header.ok()) << header.error();
        EXPECT_EQ(header->revision, d->revision);
        EXPECT_EQ(header->size, encode_scene_file(*d).size());
        const auto record = std::span<const std::byte>(log).subspan(at, header->size);
        EXPECT_TRUE(scene_file_checksum_matches(record));
        EXPECT_EQ(*decode_scene_file(record), *d);
        at += header->size;
    }
    EXPECT_EQ(at, log.size());
    // A cut record, a flipped byte, a short or wrong header.
    const auto whole = encode_scene_file(a);
    EXPECT_FALSE(scene_file_checksum_matches(std::span(whole).first(whole.size() - 1)));
    auto flipped = whole;
    flipped[100] ^= std::byte{4};
    EXPECT_FALSE(scene_file_checksum_matches(flipped));
    EXPECT_FALSE(read_scene_file_header(std::span(whole).first(63)).ok());
    auto zeros = std::vector<std::byte>(64);
    EXPECT_EQ(read_scene_file_header(zeros).error(), "offset 0: the magic is not \"KDRS\"");
    auto unrevised = whole;
    std::memset(unrevised.data() + 8, 0, 8);
    EXPECT_EQ(read_scene_file_header(unrevised).error(), "offset 8: revision must be >= 1");
    auto meshes = whole;
    meshes[52] = std::byte{9};  // 9 meshes for 3 instances
    EXPECT_EQ(read_scene_file_header(meshes).error(), "offset 52: 9 meshes for 3 instances");
}

TEST(SceneFile, StoresWrittenBeforeKdrsStillRead) {
    // What the server wrote before KDRS: the stored JSON document, under the same file name.
    const SceneDocument doc = stored_scene();
    const std::string json = encode_scene_json(doc);
    auto back = decode_stored_scene(
        std::span(reinterpret_cast<const std::byte*>(json.data()), json.size()));
    ASSERT_TRUE(back.ok()) << back.error();
    EXPECT_EQ(*back, doc);
    const std::string cut = json.substr(0, json.size() / 2);
    auto bad =
        decode_stored_scene(std::span(reinterpret_cast<const std::byte*>(cut.data()), cut.size()));
    ASSERT_FALSE(bad.ok());
    EXPECT_EQ(bad.error().rfind("JSON: ", 0), 0u) << bad.error();
}

TEST(SceneFile, RefusesDamageNamingTheOffset) {
    const auto good = encode_scene_file(stored_scene());
    const auto error_of = [](std::vector<std::byte> bytes) {
        auto r = decode_stored_scene(bytes);
        EXPECT_FALSE(r.ok());
        return r.ok() ? std::string() : r.error();
    };
    // Every single flipped bit is caught (the checksum, or a field check before it).
    for (size_t i = 0; i < good.size(); i += 7) {
        auto bytes = good;
        bytes[i] ^= std::byte{0x10};
        EXPECT_FALSE(decode_scene_file(bytes).ok()) << "byte " << i;
    }
    auto v2 = good;
    v2[4] = std::byte{2};
    EXPECT_EQ(error_of(v2), "KDRS: offset 4: version 2, this build reads version 1");
    auto cut = good;
    cut.pop_back();
    EXPECT_NE(error_of(cut).find("but the file has " + std::to_string(good.size() - 1)),
              std::string::npos);
    auto flipped = good;
    flipped[64 + 2 * 64 + 12 + 4] ^= std::byte{1};  // instance 0's transform[0][1]
    EXPECT_EQ(error_of(flipped), "KDRS: offset " + std::to_string(good.size() - 8) +
                                     ": checksum mismatch (the file is damaged)");
    // Valid checksums over bad content: each field is checked by itself.
    const auto resealed = [](std::vector<std::byte> bytes) {
        const uint64_t sum =
            scene_file_checksum(std::span<const std::byte>(bytes).first(bytes.size() - 8));
        std::memcpy(bytes.data() + bytes.size() - 8, &sum, 8);
        return bytes;
    };
    auto index = good;
    index[64 + 2 * 64 + 4] = std::byte{2};  // instance 1 names mesh 2 of 2
    EXPECT_EQ(error_of(resealed(index)), "KDRS: offset " + std::to_string(64 + 2 * 64 + 4) +
                                             ": instance 1: mesh index 2 of 2");
    auto inf = good;
    const float infinity = INFINITY;
    std::memcpy(inf.data() + 64 + 2 * 64 + 12 + 48 + 4 * 7, &infinity, 4);
    EXPECT_NE(error_of(resealed(inf)).find("instance 1: transform[1][3] is not finite"),
              std::string::npos);
    auto name = good;
    name[64 + 2 * 64 + 12 + 3 * 48 + 3 + 5] = std::byte{0x21};  // instance 2: "b" -> "!"
    EXPECT_NE(error_of(resealed(name)).find("instance 2: the name is not a valid instance name"),
              std::string::npos);
}

}  // namespace
}  // namespace kdrt::proto
