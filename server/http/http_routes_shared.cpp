// The shared path of the routes: the mesh named by the path, and admission of a batch body
// against batch_memory_budget with its reading (read_batch), so each route is decode -> call ->
// encode.

#include <algorithm>

#include "http/http_front.h"
#include "http/http_routes.h"
#include "http/http_util.h"
#include "http/problems.h"

namespace kdrt::server {

namespace {

/// A chunked body's memory is taken for this many body bytes ahead of what has arrived when that
/// fits (fewer trips to the budget), else for what has arrived.
constexpr uint64_t kChunkedStepBytes = uint64_t{1} << 20;

/// Records a body of `body_bytes` has, or has begun.
uint64_t batch_records(const BatchBody& spec, uint64_t body_bytes) {
    const uint64_t record_bytes = body_bytes - std::min(body_bytes, spec.header_bytes);
    return (record_bytes + spec.record_bytes - 1) / spec.record_bytes;
}

/// Memory a batch of `body_bytes` holds.
uint64_t batch_memory(const BatchBody& spec, uint64_t body_bytes) {
    return spec.memory_fixed + batch_records(spec, body_bytes) * spec.memory_per_record;
}

}  // namespace

std::shared_ptr<const KdTree> Routes::acquire_tree(const httplib::Request& req,
                                                   httplib::Response& res) {
    const std::string id = req.matches[1];
    auto tree = svc_.cache.acquire(id);
    if (tree) return std::move(tree).value();
    reply_problem(req, res, mesh_lookup_problem(tree.error(), id));
    return nullptr;
}

std::unique_ptr<RequestBody> Routes::read_batch(const httplib::Request& req, httplib::Response& res,
                                                const httplib::ContentReader& reader,
                                                const BatchBody& spec) {
    std::unique_ptr<RequestBody> body;
    read_batch(req, res, spec, [&](const BodyProgress& grow) {
        body = read_body(req, res, reader, spec.limit, spec.limit, svc_.store.tmp_dir().string(),
                         spec.what, {}, grow);
        return body != nullptr;
    });
    return body;
}

bool Routes::read_batch(const httplib::Request& req, httplib::Response& res, const BatchBody& spec,
                        const BatchReader& read) {
    const std::optional<uint64_t> declared = declared_body_bytes(req);
    if (declared && *declared > spec.limit) {
        reply_problem(req, res, body_too_large_problem(spec.limit, spec.what));
        return false;
    }
    // Declared: all of its memory now, before the body (or its 100 Continue). Chunked: the
    // fixed part now, the rest as the body arrives.
    const uint64_t first = declared ? batch_memory(spec, *declared) : spec.memory_fixed;
    const auto subject = [&](uint64_t body_bytes) {
        return "this batch of up to " + std::to_string(batch_records(spec, body_bytes)) + " " +
               spec.records;
    };
    auto hold = svc_.batch_budget.try_take(first);
    if (!hold) {
        reply_problem(req, res,
                      budget_problem(svc_.batch_budget, first, subject(declared.value_or(0)),
                                     spec.advice, "this batch"));
        return false;
    }
    ByteBudget::Hold& held = *hold;
    const BodyProgress grow = [&](uint64_t received) -> std::optional<proto::Problem> {
        const uint64_t needed = batch_memory(spec, received);
        if (needed <= held.bytes()) return std::nullopt;
        // A step ahead when it fits, else just what has arrived.
        const uint64_t ahead =
            batch_memory(spec, std::min(spec.limit, received + kChunkedStepBytes));
        if (held.grow(ahead - held.bytes()) || held.grow(needed - held.bytes()))
            return std::nullopt;
        return budget_problem(svc_.batch_budget, needed, subject(received), spec.advice,
                              "this batch");
    };
    const bool answered = read(declared ? BodyProgress() : grow);
    if (answered) keep_until_sent(std::make_shared<ByteBudget::Hold>(std::move(held)));
    return answered;
}

}  // namespace kdrt::server
