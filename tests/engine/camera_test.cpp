#include "kdrt/camera.h"

#include <gtest/gtest.h>

#include <algorithm>
#include <array>
#include <cmath>
#include <limits>
#include <numbers>
#include <string>

namespace kdrt {
namespace {

constexpr float kInf = std::numeric_limits<float>::infinity();
constexpr float kNaN = std::numeric_limits<float>::quiet_NaN();

Vec3 direction(const Ray& r) { return {r.dx, r.dy, r.dz}; }
Vec3 origin(const Ray& r) { return {r.ox, r.oy, r.oz}; }
float length(Vec3 v) { return std::sqrt(dot(v, v)); }
Vec3 unit(Vec3 v) { return v * (1.0f / length(v)); }

double degrees_between(Vec3 a, Vec3 b) {
    const double c = dot(a, b) / (static_cast<double>(length(a)) * length(b));
    return std::acos(std::clamp(c, -1.0, 1.0)) * 180.0 / std::numbers::pi;
}

CameraSpec front_spec() {
    CameraSpec spec;
    spec.eye = {0, 0, 5};
    spec.look_at = {0, 0, 0};
    spec.up = {0, 1, 0};
    spec.fov_deg = 60.0f;
    return spec;
}

/// Asserts that Camera(spec, width, height) throws CameraError whose message contains `field`.
void expect_camera_error(const CameraSpec& spec, uint32_t width, uint32_t height,
                         const std::string& field) {
    try {
        const Camera camera(spec, width, height);
        ADD_FAILURE() << "no CameraError; expected one naming '" << field << "'";
    } catch (const CameraError& e) {
        EXPECT_NE(std::string(e.what()).find(field), std::string::npos)
            << "message '" << e.what() << "' does not name '" << field << "'";
    }
}

TEST(Camera, CentreRayPointsAtLookAt) {
    CameraSpec spec;
    spec.eye = {3.0f, -2.0f, 7.5f};
    spec.look_at = {-1.0f, 4.0f, 0.25f};
    spec.up = {0.2f, 1.0f, -0.1f};
    const Camera camera(spec, 640, 480);
    const Ray r = camera.ray(320.0f, 240.0f);
    EXPECT_EQ(origin(r), spec.eye);
    EXPECT_EQ(r.tmin, 0.0f);
    EXPECT_EQ(r.tmax, kInf);
    const Vec3 want = unit(spec.look_at - spec.eye);
    EXPECT_NEAR(r.dx, want.x, 1e-6f);
    EXPECT_NEAR(r.dy, want.y, 1e-6f);
    EXPECT_NEAR(r.dz, want.z, 1e-6f);
}

TEST(Camera, PerspectiveDirectionsAreNormalised) {
    const Camera camera(front_spec(), 37, 23);
    for (float py : {0.0f, 0.5f, 11.5f, 23.0f}) {
        for (float px : {0.0f, 0.5f, 18.5f, 37.0f}) {
            EXPECT_NEAR(length(direction(camera.ray(px, py))), 1.0f, 1e-6f) << px << "," << py;
        }
    }
}

TEST(Camera, CornerRaysAreSymmetric) {
    const Camera camera(front_spec(), 200, 100);
    const Vec3 top_left = direction(camera.ray(0, 0));
    const Vec3 top_right = direction(camera.ray(200, 0));
    const Vec3 bottom_left = direction(camera.ray(0, 100));
    const Vec3 bottom_right = direction(camera.ray(200, 100));
    // Looking down -z with +y up: right is +x, and pixel row 0 is the top (+y).
    EXPECT_LT(top_left.x, 0.0f);
    EXPECT_GT(top_left.y, 0.0f);
    EXPECT_GT(bottom_right.x, 0.0f);
    EXPECT_LT(bottom_right.y, 0.0f);
    EXPECT_FLOAT_EQ(top_left.x, -top_right.x);
    EXPECT_FLOAT_EQ(top_left.y, top_right.y);
    EXPECT_FLOAT_EQ(top_left.x, bottom_left.x);
    EXPECT_FLOAT_EQ(top_left.y, -bottom_left.y);
    EXPECT_FLOAT_EQ(bottom_right.x, -bottom_left.x);
    for (const Vec3& d : {top_left, top_right, bottom_left, bottom_right}) {
        EXPECT_FLOAT_EQ(d.z, top_left.z);
        EXPECT_LT(d.z, 0.0f);
    }
}

TEST(Camera, FieldOfViewAndAspect) {
    CameraSpec spec = front_spec();
    spec.fov_deg = 50.0f;
    const Camera camera(spec, 300, 100);
    const Vec3 forward{0, 0, -1};
    // Top and bottom edge centres are fov/2 from the view direction.
    EXPECT_NEAR(degrees_between(direction(camera.ray(150, 0)), forward), 25.0, 1e-4);
    EXPECT_NEAR(degrees_between(direction(camera.ray(150, 100)), forward), 25.0, 1e-4);
    // The horizontal half-extent is aspect times the vertical one on the image plane.
    const Vec3 right_edge = direction(camera.ray(300, 50));
    const double want = 3.0 * std::tan(25.0 * std::numbers::pi / 180.0);
    EXPECT_NEAR(right_edge.x / -right_edge.z, want, 1e-5);
    EXPECT_NEAR(right_edge.y, 0.0f, 1e-7f);
}

TEST(Camera, OrthographicBasisIsOrthonormal) {
    CameraSpec spec;
    spec.eye = {1.0f, 2.0f, 3.0f};
    spec.look_at = {-4.0f, 0.5f, -2.0f};
    spec.up = {0.3f, 0.9f, 0.1f};  // not perpendicular to the view: the camera must fix it
    spec.ortho_height = 4.0f;
    spec.projection = Projection::kOrthographic;
    const Camera camera(spec, 160, 80);

    const Ray centre = camera.ray(80, 40);
    EXPECT_EQ(origin(centre), spec.eye);
    const Vec3 forward = direction(centre);
    // On the image border the origin moves by right * half_width and up * half_height.
    const Vec3 right = (origin(camera.ray(160, 40)) - spec.eye) * (1.0f / 4.0f);  // half width 4
    const Vec3 up = (origin(camera.ray(80, 0)) - spec.eye) * (1.0f / 2.0f);       // half height 2
    EXPECT_NEAR(length(forward), 1.0f, 1e-6f);
    EXPECT_NEAR(length(right), 1.0f, 1e-6f);
    EXPECT_NEAR(length(up), 1.0f, 1e-6f);
    EXPECT_NEAR(dot(forward, right), 0.0f, 1e-6f);
    EXPECT_NEAR(dot(forward, up), 0.0f, 1e-6f);
    EXPECT_NEAR(dot(right, up), 0.0f, 1e-6f);
    // Right-handed: right = forward x up; up leans towards the requested up.
    const Vec3 fxu = cross(forward, up);
    EXPECT_NEAR(fxu.x, right.x, 1e-5f);
    EXPECT_NEAR(fxu.y, right.y, 1e-5f);
    EXPECT_NEAR(fxu.z, right.z, 1e-5f);
    EXPECT_GT(dot(up, spec.up), 0.0f);
    // Every orthographic ray is parallel to the view direction.
    EXPECT_EQ(direction(camera.ray(3, 77)), forward);
    const Vec3 want = unit(spec.look_at - spec.eye);
    EXPECT_NEAR(forward.x, want.x, 1e-6f);
    EXPECT_NEAR(forward.y, want.y, 1e-6f);
    EXPECT_NEAR(forward.z, want.z, 1e-6f);
}

TEST(Camera, RejectsZeroImageSize) {
    expect_camera_error(front_spec(), 0, 10, "width");
    expect_camera_error(front_spec(), 10, 0, "height");
}

TEST(Camera, RejectsFovOutsideOpenRange) {
    for (float fov : {0.0f, -10.0f, 180.0f, 181.0f, kNaN, kInf}) {
        CameraSpec spec = front_spec();
        spec.fov_deg = fov;
        SCOPED_TRACE(fov);
        expect_camera_error(spec, 8, 8, "fov_deg");
    }
    CameraSpec ok = front_spec();
    ok.fov_deg = 179.0f;
    EXPECT_NO_THROW(Camera(ok, 8, 8));
}

TEST(Camera, RejectsNonPositiveOrthoHeight) {
    for (float height : {0.0f, -1.0f, kNaN, kInf}) {
        CameraSpec spec = front_spec();
        spec.projection = Projection::kOrthographic;
        spec.ortho_height = height;
        SCOPED_TRACE(height);
        expect_camera_error(spec, 8, 8, "ortho_height");
    }
    // fov is not used by an orthographic camera, so it is not checked either.
    CameraSpec spec = front_spec();
    spec.projection = Projection::kOrthographic;
    spec.fov_deg = 0.0f;
    EXPECT_NO_THROW(Camera(spec, 8, 8));
}

TEST(Camera, RejectsNonFiniteVectors) {
    CameraSpec spec = front_spec();
    spec.eye.y = kNaN;
    expect_camera_error(spec, 8, 8, "eye");
    spec = front_spec();
    spec.look_at.z = -kInf;
    expect_camera_error(spec, 8, 8, "look_at");
    spec = front_spec();
    spec.up.x = kInf;
    expect_camera_error(spec, 8, 8, "up");
}

TEST(Camera, RejectsEyeAtLookAt) {
    CameraSpec spec = front_spec();
    spec.look_at = spec.eye;
    expect_camera_error(spec, 8, 8, "look_at");
}

TEST(Camera, RejectsUpParallelToView) {
    CameraSpec spec = front_spec();
    spec.up = {0, 0, 2};  // along -view
    expect_camera_error(spec, 8, 8, "parallel");
    spec.up = {0, 0, -1};  // along view
    expect_camera_error(spec, 8, 8, "parallel");
    spec.up = {0, 0, 0};
    expect_camera_error(spec, 8, 8, "up");
}

/// Checks that every corner of `box` projects inside the image of `spec` at `aspect`, both in
/// perspective and with spec.ortho_height, and that the box fills the perspective image: some
/// corner comes close to the border.
void expect_box_in_view(const CameraSpec& spec, const Aabb& box, float aspect) {
    ASSERT_NO_THROW(Camera(spec, 64, 64));
    const Vec3 forward = unit(spec.look_at - spec.eye);
    const Vec3 right = unit(cross(forward, spec.up));
    const Vec3 up = cross(right, forward);
    const double tan_half = std::tan(spec.fov_deg * std::numbers::pi / 360.0);
    double fill = 0.0;  // largest corner position relative to the image border (1 = on it)
    for (int corner = 0; corner < 8; ++corner) {
        const Vec3 p{(corner & 1) ? box.hi.x : box.lo.x, (corner & 2) ? box.hi.y : box.lo.y,
                     (corner & 4) ? box.hi.z : box.lo.z};
        const Vec3 v = p - spec.eye;
        const double depth = dot(v, forward);
        ASSERT_GT(depth, 0.0) << "corner " << corner << " is behind the eye";
        const double x = std::fabs(dot(v, right)) / (depth * tan_half * aspect);
        const double y = std::fabs(dot(v, up)) / (depth * tan_half);
        EXPECT_LE(x, 1.0) << "corner " << corner;
        EXPECT_LE(y, 1.0) << "corner " << corner;
        fill = std::max({fill, x, y});
        const Vec3 w = p - spec.look_at;
        EXPECT_LE(std::fabs(dot(w, right)), 0.5f * spec.ortho_height * aspect * 1.0001f)
            << "corner " << corner;
        EXPECT_LE(std::fabs(dot(w, up)), 0.5f * spec.ortho_height * 1.0001f) << "corner " << corner;
    }
    const Vec3 ext = box.extent();
    if (ext.x > 0 || ext.y > 0 || ext.z > 0) {
        EXPECT_GT(fill, 0.85) << "the box is framed too loosely";
    }
}

TEST(DefaultCamera, FramesBoxesOfEveryShape) {
    const std::array<Aabb, 6> boxes = {
        Aabb{{-1, -2, -3}, {4, 5, 6}},  // ordinary
        Aabb{{-1, -1, 0}, {1, 1, 0}},   // flat, facing the camera
        Aabb{{-1, 0, -1}, {1, 0, 1}},   // flat floor
        Aabb{{0, 0, 0}, {0, 0, 10}},    // a line along the view axis
        Aabb{{2, 3, 4}, {2, 3, 4}},     // a point
        Aabb{{1e4f, 1e4f, 1e4f}, {1e4f + 1.0f, 1e4f + 1.0f, 1e4f + 1.0f}},  // far from the origin
    };
    for (float aspect : {1.0f, 2.0f, 0.5f}) {
        for (const Aabb& box : boxes) {
            SCOPED_TRACE(testing::Message() << "aspect " << aspect << " box lo.x " << box.lo.x);
            const CameraSpec spec = default_camera(box, aspect);
            EXPECT_EQ(spec.projection, Projection::kPerspective);
            EXPECT_GT(spec.eye.z, box.hi.z) << "the default view is from the front (+z)";
            EXPECT_GT(spec.eye.y, (box.lo.y + box.hi.y) / 2) << "and a little from above";
            expect_box_in_view(spec, box, aspect);
        }
    }
}

TEST(DefaultCamera, EmptyBoundsGiveAUnitView) {
    const CameraSpec spec = default_camera(Aabb{}, 1.0f);
    EXPECT_EQ(spec.look_at, (Vec3{0, 0, 0}));
    const float distance = length(spec.eye - spec.look_at);
    EXPECT_GT(distance, 0.5f);
    EXPECT_LT(distance, 10.0f);
    expect_box_in_view(spec, Aabb{{-0.5f, -0.5f, -0.5f}, {0.5f, 0.5f, 0.5f}}, 1.0f);
}

TEST(DefaultCamera, EyeIsOutsideTheBox) {
    const Aabb box{{-1, -1, -1}, {1, 1, 1}};
    for (float aspect : {1.0f, 8.0f, 0.125f}) {
        const Vec3 eye = default_camera(box, aspect).eye;
        EXPECT_TRUE(eye.x > 1 || eye.y > 1 || eye.z > 1) << "aspect " << aspect;
    }
}

TEST(DefaultCamera, RejectsBadAspect) {
    for (float aspect : {0.0f, -1.0f, kNaN, kInf}) {
        SCOPED_TRACE(aspect);
        try {
            (void)default_camera(Aabb{{0, 0, 0}, {1, 1, 1}}, aspect);
            ADD_FAILURE() << "no CameraError";
        } catch (const CameraError& e) {
            EXPECT_NE(std::string(e.what()).find("aspect"), std::string::npos) << e.what();
        }
    }
}

}  // namespace
}  // namespace kdrt
