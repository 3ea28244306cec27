#include "kdrt/proto/json_api.h"

#include <gtest/gtest.h>

#include <bit>
#include <cmath>
#include <limits>

#include "kdrt/proto/config_json.h"
#include "test_util.h"

namespace kdrt::proto {
namespace {

constexpr float kInf = std::numeric_limits<float>::infinity();

MeshSummary sample_summary() {
    MeshSummary s;
    s.id = std::string(64, 'a');
    s.triangles = 69451;
    s.vertices = 35947;
    s.bounds = {{-0.0946899f, 0.0329874f, -0.0618736f}, {0.0610091f, 0.187321f, 0.0587997f}};
    s.tree.triangles = 69451;
    s.tree.nodes = 1001;
    s.tree.leaves = 501;
    s.tree.empty_leaves = 100;
    s.tree.refs = 123456;
    s.tree.max_depth = 40;
    s.tree.mean_leaf_depth = 20.125;
    s.tree.mean_tris_per_leaf = 3.3;
    s.tree.sah_cost = 61.7;
    s.tree.bytes = 5000000;
    s.tree.bytes_per_triangle = 71.99;
    s.tree.build_ms = 41.5;
    return s;
}

TEST(JsonApi, MeshSummaryRoundTripsExactly) {
    MeshSummary s = sample_summary();
    auto back = decode_mesh_summary(encode_mesh_summary(s));
    ASSERT_TRUE(back) << back.error();
    EXPECT_EQ(*back, s);
    s.in_memory = true;
    const std::string json = encode_mesh_summary(s);
    EXPECT_NE(json.find("\"bounds\":{\"min\":[-0.0946899,0.0329874,-0.0618736],"),
              std::string::npos)
        << json;
    EXPECT_NE(json.find("\"build_ms\":41.5"), std::string::npos) << json;
    EXPECT_NE(json.find(",\"in_memory\":true}"), std::string::npos) << json;
    back = decode_mesh_summary(json);
    ASSERT_TRUE(back);
    EXPECT_EQ(*back, s);
}

TEST(JsonApi, EmptyBoundsRoundTrip) {
    MeshSummary s = sample_summary();
    s.bounds = Aabb{};
    const std::string json = encode_mesh_summary(s);
    EXPECT_NE(json.find("\"min\":[null,null,null]"), std::string::npos);
    auto back = decode_mesh_summary(json);
    ASSERT_TRUE(back);
    EXPECT_TRUE(back->bounds.empty());
    EXPECT_EQ(back->bounds, Aabb{});
}

TEST(JsonApi, MeshListRoundTripsAndNamesBadEntries) {
    std::vector<MeshSummary> list = {sample_summary(), sample_summary()};
    list[1].id = std::string(64, 'b');
    auto back = decode_mesh_list(encode_mesh_list(list));
    ASSERT_TRUE(back) << back.error();
    EXPECT_EQ(*back, list);
    EXPECT_EQ(encode_mesh_list({}), "{\"meshes\":[]}");
    auto bad = decode_mesh_list("{\"meshes\":[{\"id\":\"x\"}]}");
    ASSERT_FALSE(bad);
    EXPECT_EQ(bad.error(), "meshes[0]: missing \"triangles\"");
    EXPECT_FALSE(decode_mesh_summary("{\"id\": 5}"));
}

TEST(JsonRays, RoundTripIsBitExact) {
    test::Rng rng(test::test_seed());
    std::vector<Ray> rays(1000);
    for (Ray& r : rays) {
        const Vec3 o = rng.on_sphere() * 1e3f, d = rng.on_sphere() * 1e-3f;
        r = Ray{o.x, o.y, o.z, rng.uniform(), d.x, d.y, d.z, rng.uniform(1.0f, 1e30f)};
    }
    rays[0] = Ray{-0.0f, 0.0f, 1e-40f, 0.0f, 0.0f, -0.0f, -1.0f, kInf};
    rays[1].tmin = -kInf;
    for (bool occlusion : {false, true}) {
        auto back = decode_json_rays(encode_json_rays(rays, occlusion));
        ASSERT_TRUE(back) << back.error().detail;
        EXPECT_EQ(back->occlusion, occlusion);
        ASSERT_EQ(back->rays.size(), rays.size());
        for (size_t i = 0; i < rays.size(); ++i)
            for (int f = 0; f < 8; ++f)
                ASSERT_EQ(std::bit_cast<uint32_t>((&back->rays[i].ox)[f]),
                          std::bit_cast<uint32_t>((&rays[i].ox)[f]))
                    << "ray " << i << " field " << f;
    }
}

TEST(JsonRays, SixNumbersMeanAnOpenRay) {
    auto r = decode_json_rays("{\"rays\":[[1,2,3,4,5,6],[1,2,3,4,5,6,0.5,1e39]]}");
    ASSERT_TRUE(r) << r.error().detail;
    ASSERT_EQ(r->rays.size(), 2u);
    EXPECT_FALSE(r->occlusion);
    EXPECT_EQ(r->rays[0].tmin, 0.0f);
    EXPECT_EQ(r->rays[0].tmax, kInf);
    EXPECT_EQ(r->rays[0].dz, 6.0f);
    EXPECT_EQ(r->rays[1].tmin, 0.5f);
    EXPECT_EQ(r->rays[1].tmax, kInf);
    // Numbers are parsed from their text as f32 (no double rounding).
    auto p = decode_json_rays("{\"rays\":[[0.1,16777217,-2.5e-3,1,0,0]]}");
    ASSERT_TRUE(p);
    EXPECT_EQ(p->rays[0].ox, 0.1f);
    EXPECT_EQ(p->rays[0].oy, 16777216.0f);
    EXPECT_EQ(p->rays[0].oz, -2.5e-3f);
    auto empty = decode_json_rays("{\"occlusion\": true, \"rays\": []}");
    ASSERT_TRUE(empty);
    EXPECT_TRUE(empty->occlusion);
    EXPECT_TRUE(empty->rays.empty());
}

TEST(JsonRays, ErrorsNameTheMember) {
    struct Case {
        const char* json;
        JsonError::Code code;
        const char* detail;
    };
    const Case cases[] = {
        {"", JsonError::Code::kSyntax, "invalid JSON at byte 1: "},
        {"{\"rays\": [}", JsonError::Code::kSyntax, "invalid JSON at byte 11: "},
        {"{\"rays\": []} x", JsonError::Code::kSyntax, "invalid JSON at byte 14: "},
        {"[]", JsonError::Code::kSchema, "expected a JSON object, got an array"},
        {"{\"rays\": {}}", JsonError::Code::kSchema,
         "\"rays\" must be an array of rays, got an object"},
        {"{\"rays\": [1]}", JsonError::Code::kSchema,
         "rays[0]: expected an array of 6 or 8 numbers, got a number"},
        {"{\"rays\": [[1,2,3,4,5,6,7]]}", JsonError::Code::kSchema,
         "rays[0]: expected 6 or 8 numbers, got 7"},
        {"{\"rays\": [[1,2,3,4,5,6,7,8,9]]}", JsonError::Code::kSchema,
         "rays[0]: expected 6 or 8 numbers, got more than 8"},
        {"{\"rays\": [[1,2,3,4,5,6],[1,null,3,4,5,6]]}", JsonError::Code::kSchema,
         "rays[1][1]: expected a number, got null"},
        {"{\"rays\": [[1,2,3,[4],5,6]]}", JsonError::Code::kSchema,
         "rays[0][3]: expected a number, got an array"},
        {"{\"rays\": [], \"occlusion\": \"yes\"}", JsonError::Code::kSchema,
         "\"occlusion\" must be true or false, got a string"},
        {"{\"rays\": [], \"rays\": []}", JsonError::Code::kSchema, "duplicate member \"rays\""},
        {"{\"rays\": [], \"extra\": 1}", JsonError::Code::kSchema, "unknown member \"extra\""},
        {"{\"occlusion\": false}", JsonError::Code::kSchema, "missing member \"rays\""},
        {"{\"rays\": [[0,0,0,-3e38,0,1e39]]}", JsonError::Code::kSchema,
         "rays[0][5] (dz): 1e39 does not fit a 32-bit float"},
        {"{\"rays\": [[1,2,3,4,5,6],[1,2,3,4,5,6],[1,2,3,4,5,6]]}", JsonError::Code::kTooMany,
         "rays[2]: rays in a JSON batch exceed the limit of 2; send larger batches as "
         "application/x-kdrt-rays"},
    };
    for (const Case& c : cases) {
        SCOPED_TRACE(c.json);
        auto r = decode_json_rays(c.json, 2);
        ASSERT_FALSE(r);
        EXPECT_EQ(r.error().code, c.code);
        EXPECT_EQ(r.error().detail.rfind(c.detail, 0), 0u) << r.error().detail;
    }
}

TEST(JsonHits, EncodeIsCompactAndDecodes) {
    const Hit hits[3] = {{1.5f, 12, 0.25f, 0.5f}, Hit{}, {0.1f, 0, 0.0f, 1.0f}};
    const std::string json = encode_json_hits(hits);
    EXPECT_EQ(json,
              "{\"hits\":[{\"t\":1.5,\"prim\":12,\"u\":0.25,\"v\":0.5},null,{\"t\":0.1,\"prim\":0,"
              "\"u\":0,\"v\":1}]}");
    auto back = decode_json_hits(json);
    ASSERT_TRUE(back) << back.error();
    ASSERT_EQ(back->size(), 3u);
    EXPECT_EQ((*back)[0].t, 1.5f);
    EXPECT_EQ((*back)[0].prim, 12u);
    EXPECT_FALSE((*back)[1].is_hit());
    EXPECT_EQ((*back)[1].t, kInf);
    EXPECT_EQ((*back)[2].t, 0.1f);
    EXPECT_EQ(encode_json_hits({}), "{\"hits\":[]}");
    EXPECT_FALSE(decode_json_hits("{\"hits\":[{\"t\":1}]}"));
}

TEST(JsonHits, Occlusion) {
    const uint8_t flags[3] = {1, 0, 7};
    EXPECT_EQ(encode_json_occlusion(flags), "{\"occluded\":[true,false,true]}");
    auto back = decode_json_occlusion("{\"occluded\":[true,false]}");
    ASSERT_TRUE(back);
    EXPECT_EQ(*back, (std::vector<uint8_t>{1, 0}));
    EXPECT_FALSE(decode_json_occlusion("{\"occluded\":[1]}"));
}

TEST(JsonRender, ShadingSettingsDecodeAndRoundTrip) {
    const std::string mesh = "\"mesh\":\"" + std::string(64, 'b') + "\"";
    auto plain = decode_render_request("{" + mesh + "}");
    ASSERT_TRUE(plain) << plain.error().detail;
    const RenderSettings defaults;
    EXPECT_EQ(plain->settings.ao_samples, defaults.ao_samples);
    EXPECT_EQ(plain->settings.background, defaults.background);
    // Members at their defaults are not written: an older server understands the request.
    const std::string plain_json = encode_render_request(*plain);
    for (const char* key : {"\"ao_samples\"", "\"ao_distance\"", "\"light\"", "\"bounces\"",
                            "\"sky\"", "\"background\""})
        EXPECT_EQ(plain_json.find(key), std::string::npos) << key << " in " << plain_json;

    auto r = decode_render_request(
        "{" + mesh +
        R"(,"shading":"diffuse","ao_samples":7,"ao_distance":0.125,"light":{"direction":[-1,2,0.5],)"
        R"("intensity":0.625},"bounces":3,"sky":0.375,"background":[0.25,0.5,0.75]})");
    ASSERT_TRUE(r) << r.error().detail;
    const RenderSettings& s = r->settings;
    EXPECT_EQ(s.ao_samples, 7u);
    EXPECT_EQ(s.ao_distance, 0.125f);
    EXPECT_EQ(s.light.direction, (Vec3{-1.0f, 2.0f, 0.5f}));
    EXPECT_EQ(s.light.intensity, 0.625f);
    EXPECT_EQ(s.bounces, 3u);
    EXPECT_EQ(s.sky, 0.375f);
    EXPECT_EQ(s.background, (Vec3{0.25f, 0.5f, 0.75f}));
    auto again = decode_render_request(encode_render_request(*r));
    ASSERT_TRUE(again) << again.error().detail;
    EXPECT_EQ(again->settings.ao_samples, s.ao_samples);
    EXPECT_EQ(again->settings.ao_distance, s.ao_distance);
    EXPECT_EQ(again->settings.light.direction, s.light.direction);
    EXPECT_EQ(again->settings.light.intensity, s.light.intensity);
    EXPECT_EQ(again->settings.bounces, s.bounces);
    EXPECT_EQ(again->settings.sky, s.sky);
    EXPECT_EQ(again->settings.background, s.background);
}

TEST(JsonRender, BadShadingSettingsNameTheMember) {
    const std::string mesh = "\"mesh\":\"" + std::string(64, 'b') + "\",";
    const std::pair<std::string, std::string> cases[] = {
        {R"("ao_samples":0)", "\"ao_samples\" is 0, must be in 1 .. 4096"},
        {R"("ao_samples":5000)", "\"ao_samples\" is 5000"},
        {R"("ao_distance":0)", "\"ao_distance\" must be > 0"},
        {R"("ao_distance":"far")", "\"ao_distance\" must be a finite number"},
        {R"("light":[1,1,1])", "\"light\" must be an object"},
        {R"("light":{})", "missing member \"light.direction\""},
        {R"("light":{"direction":[0,0,0]})", "\"light.direction\" must not be the zero vector"},
        {R"("light":{"direction":[1,1]})", "\"light.direction\" must be an array of 3 numbers"},
        {R"("light":{"direction":[1,1,1],"colour":1})", "unknown member \"light.colour\""},
        {R"("bounces":65)", "\"bounces\" is 65, must be in 0 .. 64"},
        {R"("sky":-1)", "\"sky\" must be >= 0"},
        {R"("light":{"direction":[1,1,1],"intensity":-2})", "\"light.intensity\" must be >= 0"},
        {R"("background":[0,0])", "\"background\" must be an array of 3 numbers"},
        {R"("background":[0,1e40,0])", "\"background\" must be an array of 3 finite numbers"},
    };
    for (const auto& [member, detail] : cases) {
        SCOPED_TRACE(member);
        auto r = decode_render_request("{" + mesh + member + "}");
        ASSERT_FALSE(r);
        EXPECT_EQ(r.error().code, JsonError::Code::kSchema);
        EXPECT_NE(r.error().detail.find(detail), std::string::npos) << r.error().detail;
    }
}

TEST(JsonApi, MediaTypes) {
    EXPECT_EQ(mesh_format_from_media_type("model/obj"), MeshFormat::kObj);
    EXPECT_EQ(mesh_format_from_media_type("Model/STL"), MeshFormat::kStl);
    EXPECT_EQ(mesh_format_from_media_type("application/ply"), MeshFormat::kPly);
    EXPECT_EQ(mesh_format_from_media_type("application/x-off; charset=utf-8"), MeshFormat::kOff);
    EXPECT_EQ(mesh_format_from_media_type(" application/x-kdrt-mesh "), MeshFormat::kRaw);
    EXPECT_EQ(mesh_format_from_media_type("application/octet-stream"), std::nullopt);
    EXPECT_EQ(mesh_format_from_media_type(""), std::nullopt);
    for (const MeshFormat f :
         {MeshFormat::kObj, MeshFormat::kPly, MeshFormat::kOff, MeshFormat::kStl, MeshFormat::kRaw})
        EXPECT_EQ(mesh_format_from_media_type(mesh_media_type(f)), f);
    EXPECT_EQ(media_type_essence("Application/JSON ; charset=UTF-8"), "application/json");
}

TEST(JsonApi, FlatObject) {
    const JsonField fields[] = {{"msg", std::string_view("a \"quoted\"\tword")},
                                {"n", int64_t{-3}},
                                {"u", uint64_t{7}},
                                {"x", 0.5},
                                {"b", true},
                                {"s", std::string("\x01")}};
    EXPECT_EQ(encode_flat_object(fields),
              "{\"msg\":\"a "
              "\\\"quoted\\\"\\tword\",\"n\":-3,\"u\":7,\"x\":0.5,\"b\":true,\"s\":\"\\u0001\"}");
}

TEST(ConfigJson, CommentsScalarsAndLists) {
    auto entries = parse_config_object(
        "// leading comment\n{\n  \"a\": 1, /* block */\n  \"b\": \"x\",\n  \"c\": [\"p\", "
        "\"q\"],\n  \"d\": true,\n"
        "  \"e\": 0.5\n}\n");
    ASSERT_TRUE(entries) << entries.error();
    ASSERT_EQ(entries->size(), 5u);
    EXPECT_EQ((*entries)[0].key, "a");
    EXPECT_EQ(std::get<int64_t>((*entries)[0].value), 1);
    EXPECT_EQ(std::get<std::string>((*entries)[1].value), "x");
    EXPECT_EQ(std::get<std::vector<std::string>>((*entries)[2].value),
              (std::vector<std::string>{"p", "q"}));
    EXPECT_TRUE(std::get<bool>((*entries)[3].value));
    EXPECT_EQ(std::get<double>((*entries)[4].value), 0.5);
}

TEST(ConfigJson, Errors) {
    auto r = parse_config_object("{\"a\": }");
    ASSERT_FALSE(r);
    EXPECT_EQ(r.error().rfind("invalid JSON at byte 7: parse error at line 1, column 7", 0), 0u)
        << r.error();
    // A number beyond a double names its member (it used to escape as an exception: abort).
    EXPECT_EQ(
        parse_config_object("{\"memory_budget\": 1e400}").error().rfind("\"memory_budget\": ", 0),
        0u);
    EXPECT_EQ(parse_config_object("{\"a\": 1, \"a\": 2}").error(),
              "duplicate member \"a\" (each member may appear once)");
    EXPECT_EQ(parse_config_object("[1]").error(), "the configuration must be a JSON object");
    EXPECT_EQ(parse_config_object("{\"a\": null}").error(),
              "\"a\": expected a boolean, number, string or array of strings, got null");
    EXPECT_EQ(parse_config_object("{\"a\": [1]}").error(), "\"a\": every element must be a string");
    EXPECT_EQ(parse_config_object("{\"a\": {\"b\": 1}}").error(),
              "\"a\": expected a boolean, number, string or array of strings, got object");
}

}  // namespace
}  // namespace kdrt::proto
