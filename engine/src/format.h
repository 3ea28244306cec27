#pragma once
// Internal: numbers in the engine's error messages.

#include <cstdio>
#include <string>

#include "kdrt/types.h"

namespace kdrt::detail {

/// `value` as printf's "%g" (shortest of 6 significant digits): "0.25", "1e+30", "nan".
inline std::string format_float(float value) {
    char text[32];
    std::snprintf(text, sizeof text, "%g", static_cast<double>(value));
    return text;
}

/// "(x, y, z)" with format_float's components (render settings messages).
inline std::string format_vec(Vec3 v) {
    // Appended piecewise: GCC 12 warns (-Wrestrict, a false positive) on "(" + std::string.
    std::string text(1, '(');
    text += format_float(v.x);
    text += ", ";
    text += format_float(v.y);
    text += ", ";
    text += format_float(v.z);
    text += ')';
    return text;
}

/// "(x, y, z)" with std::to_string's six decimals, "(0.000000, 1.000000, nan)": the camera's
/// messages (CameraError texts reach clients unchanged, so their format is kept).
inline std::string format_vec_fixed(Vec3 v) {
    // Appended piecewise, as format_vec.
    std::string text(1, '(');
    text += std::to_string(v.x);
    text += ", ";
    text += std::to_string(v.y);
    text += ", ";
    text += std::to_string(v.z);
    text += ')';
    return text;
}

}  // namespace kdrt::detail
