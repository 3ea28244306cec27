#pragma once
/// A rendered image as linear floats: what render() returns and proto encodes. Value type only.

#include <cstdint>
#include <vector>

namespace kdrt {

/// A linear float image, row-major, top row first, `channels` interleaved floats per pixel:
/// 3 = RGB, 4 = RGBA. pixels.size() == width * height * channels.
struct Image {
    uint32_t width = 0;
    uint32_t height = 0;
    uint32_t channels = 0;
    std::vector<float> pixels;
};

}  // namespace kdrt
