// The server's config file: parse_config_object (proto) and every setting applied over the
// defaults (server/core/config.cpp). Oracles: no crash or abort for any text (1e400 used to abort);
// a refusal names the problem; an accepted file leaves every limit inside its documented range.

#include <string_view>

#include "core/config.h"
#include "fuzz_check.h"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
    using namespace kdrt;
    const std::string_view text(reinterpret_cast<const char*>(data), size);
    server::ServerConfig config;
    const auto applied = server::apply_config_text(text, "fuzz.json", config);
    if (!applied) {
        fuzz::require(!applied.error().empty());
        return 0;
    }
    fuzz::require(config.max_image_width >= 1 && config.max_image_height >= 1);
    fuzz::require(config.max_spp >= 1 && config.max_rays >= 1);
    return 0;
}
