#pragma once
/// The web viewer's static files (server/web/), embedded in the binary at build time by
/// server/embed_web.cmake: served by Routes::web_file at / and /ui/<name>.

#include <span>
#include <string_view>

namespace kdrt::server {

struct WebAsset {
    std::string_view name;          ///< file name in server/web/, e.g. "viewer.js"
    std::string_view content_type;  ///< e.g. "text/javascript; charset=utf-8"
    std::string_view etag;          ///< a strong ETag, quoted: a hash of the bytes
    std::span<const unsigned char> bytes;
};

/// Every embedded file, in the order server/CMakeLists.txt lists them.
[[nodiscard]] std::span<const WebAsset> web_assets() noexcept;

}  // namespace kdrt::server
