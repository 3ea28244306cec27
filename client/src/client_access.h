#pragma once
/// What the library's files other than http_client.cpp (distance.cpp, scene.cpp) need of a
/// Client's transport: one request with the retries of every call, and the errors it makes.
/// Internal to kdrt_client; http_client.cpp defines it (the only file that includes httplib.h).

#include <atomic>
#include <cstddef>
#include <span>
#include <string>
#include <string_view>
#include <utility>
#include <vector>

#include "kdrt/client/client.h"

namespace kdrt::detail {

/// The 2xx answer of a POST: its body and the value of the answer header that was asked for
/// ("" when the server sent none).
struct PostAnswer {
    std::string body;
    std::string header;
};

/// One API request as ClientAccess::request sends it.
struct ApiRequest {
    std::string_view method = "GET";                                ///< GET, DELETE, POST or PATCH
    std::string path = {};                                          ///< from api_path
    std::vector<std::pair<std::string, std::string>> headers = {};  ///< besides the client's own
    std::string_view content_type = {};                             ///< of `body` (POST, PATCH)
    std::span<const std::byte> body = {};
    std::string_view answer_header = {};  ///< the answer header PostAnswer::header gets
    /// May the request be sent again after the connection failed once it was (maybe) sent, and
    /// after a 502/504? False for a request that must not happen twice (one creating a scene).
    bool idempotent = true;
};

struct ClientAccess {
    /// The API path `path` under the server URL's base path, with `id` percent-encoded as one
    /// path segment in place of "{id}".
    [[nodiscard]] static std::string api_path(const Client& client, std::string_view path,
                                              std::string_view id);
    /// POSTs `body` (Content-Type `content_type`) to the API path `path` on a pooled keep-alive
    /// connection, retried like every idempotent call (connection errors, 502, 503, 504).
    /// A non-2xx answer is its Error.
    [[nodiscard]] static Result<PostAnswer> post(Client& client, const std::string& path,
                                                 std::string_view content_type,
                                                 std::span<const std::byte> body,
                                                 std::string_view answer_header);
    /// Sends `request` on a pooled keep-alive connection with the retries of every call (those
    /// after a maybe-sent request only when it is idempotent). A non-2xx answer is its Error.
    [[nodiscard]] static Result<PostAnswer> request(Client& client, const ApiRequest& request);
    /// The most points per distance request this client has seen the server accept after a
    /// refusal for size (0: none seen yet); shared by the client's calls.
    [[nodiscard]] static std::atomic<size_t>& distance_chunk_limit(Client& client);
    /// The kProtocol error "bad response" for an answer to POST `path` that the API does not
    /// allow, saying `why`.
    [[nodiscard]] static Error bad_response(const Client& client, const std::string& path,
                                            const std::string& why);
};

/// After a 413 for a distance chunk of `count` points: the points to send at once from now on,
/// smaller than `count`. The server's `limit` is the most points (code too_many_rays) or the most
/// body bytes (a declared size over the KDRP size of max_distance_points); without a usable one,
/// half (distance.cpp; Client::distance and scene_distance).
[[nodiscard]] size_t smaller_point_chunk(const Error& refusal, size_t count);

}  // namespace kdrt::detail
