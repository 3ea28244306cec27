// GET / and /ui/<name>: the web viewer's embedded static files (web_assets.h).

#include <string>
#include <string_view>

#include "http/http_routes.h"
#include "http/http_util.h"
#include "http/problems.h"
#include "http/web_assets.h"

namespace kdrt::server {
namespace {

/// Scripts, styles and images from this origin only; no inline script or style, no eval; API
/// calls to this origin only; rendered frames are shown from blob: URLs. The page cannot be
/// framed, and forms and <base> cannot send anything anywhere.
constexpr const char* kContentSecurityPolicy =
    "default-src 'none'; script-src 'self'; style-src 'self'; img-src 'self' blob: data:; "
    "connect-src 'self'; base-uri 'none'; form-action 'none'; frame-ancestors 'none'";

/// True when an If-None-Match header names `etag` (or is "*").
bool etag_matches(std::string_view if_none_match, std::string_view etag) {
    if (if_none_match == "*") return true;
    size_t at = 0;
    while ((at = if_none_match.find(etag, at)) != std::string_view::npos) {
        const bool starts = at == 0 || if_none_match[at - 1] == ' ' ||
                            if_none_match[at - 1] == ',' || if_none_match[at - 1] == '/';
        const size_t end = at + etag.size();
        const bool ends =
            end == if_none_match.size() || if_none_match[end] == ',' || if_none_match[end] == ' ';
        if (starts && ends) return true;
        at = end;
    }
    return false;
}

/// A viewer path with no file: the files there are (the problem's instance is the path).
proto::Problem no_web_file_problem() {
    std::string names;
    for (const WebAsset& asset : web_assets())
        names += (names.empty() ? "" : ", ") + std::string(asset.name);
    return make_problem(
        proto::ProblemKind::kNotFound,
        "the web viewer has no file at this path (its files: /, /ui/ + one of " + names + ")");
}

}  // namespace

void Routes::web_file(const httplib::Request& req, httplib::Response& res) {
    // "/" has no capture: index.html.
    const std::string wanted = req.matches.size() > 1 ? req.matches[1].str() : "index.html";
    const WebAsset* found = nullptr;
    for (const WebAsset& asset : web_assets())
        if (asset.name == wanted) found = &asset;
    // The path is the problem's instance; the detail does not repeat it.
    if (!found) return reply_problem(req, res, no_web_file_problem());
    // The viewer's file names are not versioned, so the browser revalidates every file on each
    // load (no-cache) and gets 304 while the ETag (a hash of the bytes) is unchanged.
    res.set_header("Cache-Control", "no-cache");
    res.set_header("ETag", std::string(found->etag));
    res.set_header("Content-Security-Policy", kContentSecurityPolicy);
    res.set_header("Referrer-Policy", "no-referrer");
    res.set_header("Cross-Origin-Opener-Policy", "same-origin");
    if (etag_matches(req.get_header_value("If-None-Match"), found->etag)) {
        res.status = 304;
        return;
    }
    res.status = 200;
    res.set_content(reinterpret_cast<const char*>(found->bytes.data()), found->bytes.size(),
                    std::string(found->content_type));
}

}  // namespace kdrt::server
