#include "kdrt/proto/problem.h"

#include <array>
#include <nlohmann/json.hpp>

#include "json_writer.h"
#include "kdrt/proto/text.h"

namespace kdrt::proto {
namespace {

struct KindInfo {
    ProblemKind kind;
    int status;
    std::string_view title;
    std::string_view type;
};

constexpr std::array<KindInfo, 26> kKinds = {{
    {ProblemKind::kBadRequest, 400, "Bad request", "urn:kdrt:problem:bad-request"},
    {ProblemKind::kBadRayBatch, 400, "Malformed ray batch", "urn:kdrt:problem:bad-ray-batch"},
    {ProblemKind::kUnauthorized, 401, "Unauthorized", "urn:kdrt:problem:unauthorized"},
    {ProblemKind::kForbidden, 403, "Forbidden", "urn:kdrt:problem:forbidden"},
    {ProblemKind::kNotFound, 404, "Not found", "urn:kdrt:problem:not-found"},
    {ProblemKind::kUnknownMesh, 404, "Unknown mesh", "urn:kdrt:problem:unknown-mesh"},
    {ProblemKind::kUnknownJob, 404, "Unknown job", "urn:kdrt:problem:unknown-job"},
    {ProblemKind::kMethodNotAllowed, 405, "Method not allowed",
     "urn:kdrt:problem:method-not-allowed"},
    {ProblemKind::kRequestTimeout, 408, "Request timeout", "urn:kdrt:problem:request-timeout"},
    {ProblemKind::kJobNotDone, 409, "Job has no result", "urn:kdrt:problem:job-not-done"},
    {ProblemKind::kPayloadTooLarge, 413, "Payload too large", "urn:kdrt:problem:payload-too-large"},
    {ProblemKind::kUnsupportedMediaType, 415, "Unsupported media type",
     "urn:kdrt:problem:unsupported-media-type"},
    {ProblemKind::kHeadersTooLarge, 431, "Request header fields too large",
     "urn:kdrt:problem:headers-too-large"},
    {ProblemKind::kMeshParseError, 422, "Mesh parse error", "urn:kdrt:problem:mesh-parse-error"},
    {ProblemKind::kInvalidMesh, 422, "Invalid mesh", "urn:kdrt:problem:invalid-mesh"},
    {ProblemKind::kInternal, 500, "Internal server error", "urn:kdrt:problem:internal"},
    {ProblemKind::kOverCapacity, 503, "Over capacity", "urn:kdrt:problem:over-capacity"},
    {ProblemKind::kNotReady, 503, "Not ready", "urn:kdrt:problem:not-ready"},
    {ProblemKind::kInsufficientStorage, 507, "Insufficient storage",
     "urn:kdrt:problem:insufficient-storage"},
    {ProblemKind::kStoredMeshDamaged, 500, "Stored mesh damaged",
     "urn:kdrt:problem:stored-mesh-damaged"},
    {ProblemKind::kUnknownScene, 404, "Unknown scene", "urn:kdrt:problem:unknown-scene"},
    {ProblemKind::kUnknownReference, 422, "Unknown reference",
     "urn:kdrt:problem:unknown-reference"},
    {ProblemKind::kMeshInUse, 409, "Mesh in use", "urn:kdrt:problem:mesh-in-use"},
    {ProblemKind::kStaleRevision, 412, "Stale revision", "urn:kdrt:problem:stale-revision"},
    {ProblemKind::kSceneMeshDeleted, 409, "Scene mesh deleted",
     "urn:kdrt:problem:scene-mesh-deleted"},
    {ProblemKind::kStoredSceneDamaged, 500, "Stored scene damaged",
     "urn:kdrt:problem:stored-scene-damaged"},
}};

const KindInfo& info(ProblemKind kind) noexcept {
    for (const KindInfo& k : kKinds)
        if (k.kind == kind) return k;
    for (const KindInfo& k : kKinds)
        if (k.kind == ProblemKind::kInternal) return k;
    return kKinds.front();
}

}  // namespace

int problem_status(ProblemKind kind) noexcept { return info(kind).status; }
std::string_view problem_title(ProblemKind kind) noexcept { return info(kind).title; }
std::string_view problem_type(ProblemKind kind) noexcept { return info(kind).type; }

std::string encode_problem(const Problem& problem) {
    detail::JsonWriter w;
    w.begin_object();
    w.key("type").string(problem_type(problem.kind));
    w.key("title").string(problem_title(problem.kind));
    w.key("status").number(problem.status());
    w.key("detail").string(problem.detail);
    if (!problem.instance.empty()) w.key("instance").string(problem.instance);
    if (!problem.code.empty()) w.key("code").string(problem.code);
    if (problem.line) w.key("line").number(*problem.line);
    if (problem.byte_offset) w.key("byte_offset").number(*problem.byte_offset);
    if (problem.limit) w.key("limit").number(*problem.limit);
    if (problem.retry_after) w.key("retry_after").number(*problem.retry_after);
    if (!problem.request_id.empty()) w.key("request_id").string(problem.request_id);
    if (!problem.field.empty()) w.key("field").string(problem.field);
    if (problem.index) w.key("index").number(*problem.index);
    w.end_object();
    return w.take();
}

Result<Problem, std::string> decode_problem(std::string_view body) {
    const auto doc = nlohmann::json::parse(body, nullptr, /*allow_exceptions=*/false);
    if (doc.is_discarded()) return Err{std::string("problem body is not valid JSON")};
    if (!doc.is_object()) return Err{std::string("problem body is not a JSON object")};
    Problem p;
    const auto type = doc.find("type");
    if (type == doc.end() || !type->is_string())
        return Err{std::string("problem body has no string \"type\"")};
    bool known = false;
    for (const KindInfo& k : kKinds) {
        if (k.type == type->get_ref<const std::string&>()) {
            p.kind = k.kind;
            known = true;
        }
    }
    if (!known) return Err{"unknown problem type " + quote_value(type->get<std::string>())};
    const auto status = doc.find("status");
    if (status == doc.end() || !status->is_number_integer() || status->get<int>() != p.status())
        return Err{std::string("problem \"status\" is missing or does not match its type")};
    const auto text = [&](const char* key, std::string& out) {
        const auto it = doc.find(key);
        if (it != doc.end() && it->is_string()) out = it->get<std::string>();
    };
    const auto number = [&](const char* key, auto& out) {
        const auto it = doc.find(key);
        if (it != doc.end() && it->is_number_unsigned()) out = it->get<uint64_t>();
    };
    text("detail", p.detail);
    if (doc.find("detail") == doc.end()) return Err{std::string("problem body has no \"detail\"")};
    text("instance", p.instance);
    text("code", p.code);
    text("request_id", p.request_id);
    text("field", p.field);
    if (const auto index = doc.find("index");
        index != doc.end() && index->is_number_unsigned() && index->get<uint64_t>() <= UINT32_MAX)
        p.index = index->get<uint32_t>();
    number("line", p.line);
    number("byte_offset", p.byte_offset);
    number("limit", p.limit);
    const auto retry = doc.find("retry_after");
    if (retry != doc.end() && retry->is_number_unsigned()) p.retry_after = retry->get<uint32_t>();
    return p;
}

std::string_view http_reason_phrase(int status) noexcept {
    switch (status) {
        case 100:
            return "Continue";
        case 200:
            return "OK";
        case 201:
            return "Created";
        case 202:
            return "Accepted";
        case 204:
            return "No Content";
        case 206:
            return "Partial Content";
        case 301:
            return "Moved Permanently";
        case 302:
            return "Found";
        case 303:
            return "See Other";
        case 304:
            return "Not Modified";
        case 307:
            return "Temporary Redirect";
        case 308:
            return "Permanent Redirect";
        case 400:
            return "Bad Request";
        case 401:
            return "Unauthorized";
        case 403:
            return "Forbidden";
        case 404:
            return "Not Found";
        case 405:
            return "Method Not Allowed";
        case 406:
            return "Not Acceptable";
        case 408:
            return "Request Timeout";
        case 409:
            return "Conflict";
        case 410:
            return "Gone";
        case 411:
            return "Length Required";
        case 412:
            return "Precondition Failed";
        case 413:
            return "Content Too Large";
        case 414:
            return "URI Too Long";
        case 415:
            return "Unsupported Media Type";
        case 416:
            return "Range Not Satisfiable";
        case 417:
            return "Expectation Failed";
        case 422:
            return "Unprocessable Content";
        case 429:
            return "Too Many Requests";
        case 431:
            return "Request Header Fields Too Large";
        case 500:
            return "Internal Server Error";
        case 501:
            return "Not Implemented";
        case 502:
            return "Bad Gateway";
        case 503:
            return "Service Unavailable";
        case 504:
            return "Gateway Timeout";
        case 505:
            return "HTTP Version Not Supported";
        case 507:
            return "Insufficient Storage";
        default:
            return "";
    }
}

}  // namespace kdrt::proto
