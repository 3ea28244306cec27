#pragma once
/// What the library's files other than http_client.cpp (distance.cpp) need of a Client's
/// transport: one POST of a binary body with the retries of every call, and the errors it makes.
/// Internal to kdrt_client; http_client.cpp defines it (the only file that includes httplib.h).

#include <atomic>
#include <cstddef>
#include <span>
#include <string>
#include <string_view>

#include "kdrt/client/client.h"

namespace kdrt::detail {

/// The 2xx answer of a POST: its body and the value of the answer header that was asked for
/// ("" when the server sent none).
struct PostAnswer {
    std::string body;
    std::string header;
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
    /// The most points per distance request this client has seen the server accept after a
    /// refusal for size (0: none seen yet); shared by the client's calls.
    [[nodiscard]] static std::atomic<size_t>& distance_chunk_limit(Client& client);
    /// The kProtocol error "bad response" for an answer to POST `path` that the API does not
    /// allow, saying `why`.
    [[nodiscard]] static Error bad_response(const Client& client, const std::string& path,
                                            const std::string& why);
};

}  // namespace kdrt::detail
