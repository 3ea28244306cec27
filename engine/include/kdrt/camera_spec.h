#pragma once
/// Where a camera is and how it projects: a value type (no function here needs kdrt_engine).
/// kdrt/camera.h turns a CameraSpec into rays.

#include <cstdint>

#include "kdrt/types.h"

namespace kdrt {

enum class Projection : uint32_t { kPerspective = 0, kOrthographic = 1 };

/// Where the camera is and how it projects.
struct CameraSpec {
    Vec3 eye{0, 0, 1};
    Vec3 look_at{0, 0, 0};
    Vec3 up{0, 1, 0};
    float fov_deg = 40.0f;      ///< vertical field of view (perspective), in (0, 180)
    float ortho_height = 1.0f;  ///< height of the view in world units (orthographic), > 0
    Projection projection = Projection::kPerspective;
};

}  // namespace kdrt
