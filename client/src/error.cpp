#include "kdrt/client/error.h"

#include "kdrt/proto/json_api.h"
#include "kdrt/proto/problem.h"

namespace kdrt {
namespace {

/// Body text kept in the detail of a non-problem error answer.
constexpr size_t kMaxDetailBytes = 300;

std::string_view reason_phrase(int status) noexcept {
    const std::string_view known = proto::http_reason_phrase(status);
    if (!known.empty()) return known;
    if (status >= 500) return "Server Error";
    if (status >= 400) return "Client Error";
    return "Unexpected Status";
}

/// The start of a body as one printable line.
std::string body_excerpt(std::string_view body) {
    std::string out(body.substr(0, kMaxDetailBytes));
    for (char& c : out)
        if (static_cast<unsigned char>(c) < 0x20 || c == 0x7f) c = ' ';
    while (!out.empty() && out.back() == ' ') out.pop_back();
    if (body.size() > kMaxDetailBytes) out += "...";
    return out;
}

}  // namespace

std::string_view error_kind_name(ErrorKind kind) noexcept {
    switch (kind) {
        case ErrorKind::kServer:
            return "server";
        case ErrorKind::kConnection:
            return "connection";
        case ErrorKind::kProtocol:
            return "protocol";
        case ErrorKind::kInput:
            return "input";
        case ErrorKind::kJobFailed:
            return "job_failed";
        case ErrorKind::kCancelled:
            return "cancelled";
    }
    return "unknown";
}

std::string Error::to_string() const {
    std::string out;
    if (kind == ErrorKind::kServer) out = std::to_string(status) + " ";
    out += title;
    if (!detail.empty()) out += (out.empty() ? "" : ": ") + detail;
    return out;
}

Error error_from_response(int status, std::string_view content_type, std::string_view body,
                          std::string_view request_id) {
    Error e;
    e.kind = ErrorKind::kServer;
    e.status = status;
    e.request_id = std::string(request_id);
    const bool problem_type = proto::media_type_essence(content_type) == proto::kProblemMediaType;
    // Only a body that claims to be problem+json, or looks like a JSON object, is decoded.
    const size_t first = body.find_first_not_of(" \t\r\n");
    if (problem_type || (first != std::string_view::npos && body[first] == '{')) {
        if (auto problem = proto::decode_problem(body)) {
            e.title = std::string(proto::problem_title(problem->kind));
            e.type = std::string(proto::problem_type(problem->kind));
            e.detail = problem->detail;
            e.code = problem->code;
            e.line = problem->line;
            e.byte_offset = problem->byte_offset;
            e.limit = problem->limit;
            e.field = problem->field;
            e.index = problem->index;
            e.retry_after = problem->retry_after;
            if (!problem->request_id.empty()) e.request_id = problem->request_id;
            return e;
        }
    }
    e.title = std::string(reason_phrase(status));
    e.detail = body_excerpt(body);
    return e;
}

Error make_client_error(ErrorKind kind, std::string title, std::string detail) {
    Error e;
    e.kind = kind;
    e.title = std::move(title);
    e.detail = std::move(detail);
    return e;
}

}  // namespace kdrt
