// The JSON request bodies (render requests, JSON ray batches) and the JSON documents the client
// reads (mesh summaries and lists, problem+json errors, job status, JSON hits). The first byte
// picks the decoder.
// Oracles: a refusal says why; an accepted render request respects the limits it was decoded
// with (defaults included) and re-encodes to a request that decodes to the same settings; an
// accepted ray batch is within its limit.

#include <string_view>

#include "fuzz_check.h"
#include "kdrt/proto/json_api.h"
#include "kdrt/proto/problem.h"
#include "kdrt/proto/scan.h"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
    using namespace kdrt;
    if (size == 0) return 0;
    const std::string_view text(reinterpret_cast<const char*>(data) + 1, size - 1);
    switch (data[0] % 6) {
        case 0: {
            const proto::RenderLimits limits{.max_width = 96, .max_height = 64, .max_spp = 8};
            const auto request = proto::decode_render_request(text, limits);
            if (!request) {
                fuzz::require(!request.error().detail.empty());
                break;
            }
            const RenderSettings& s = request->settings;
            fuzz::require(s.width >= 1 && s.width <= limits.max_width);
            fuzz::require(s.height >= 1 && s.height <= limits.max_height);
            fuzz::require(s.spp >= 1 && s.spp <= limits.max_spp);
            const auto again =
                proto::decode_render_request(proto::encode_render_request(*request), limits);
            fuzz::require(again.ok());
            fuzz::require(again->mesh == request->mesh && again->settings.width == s.width &&
                          again->settings.height == s.height && again->settings.spp == s.spp &&
                          again->settings.seed == s.seed && again->format == request->format);
            break;
        }
        case 1: {
            const auto rays = proto::decode_json_rays(text, 64);
            if (rays)
                fuzz::require(rays->rays.size() <= 64);
            else
                fuzz::require(!rays.error().detail.empty());
            break;
        }
        case 2: {
            const auto summary = proto::decode_mesh_summary(text);
            if (summary) {
                const auto again = proto::decode_mesh_summary(proto::encode_mesh_summary(*summary));
                fuzz::require(again.ok() && *again == *summary);
            }
            break;
        }
        case 3: {
            (void)proto::decode_mesh_list(text);
            // The problem+json bodies every client reads: a decoded problem re-encodes to one
            // that decodes the same.
            const auto problem = proto::decode_problem(text);
            if (problem) {
                const auto again = proto::decode_problem(proto::encode_problem(*problem));
                fuzz::require(again.ok());
                fuzz::require(again->kind == problem->kind && again->detail == problem->detail &&
                              again->code == problem->code && again->line == problem->line &&
                              again->limit == problem->limit &&
                              again->retry_after == problem->retry_after &&
                              again->request_id == problem->request_id);
            } else {
                fuzz::require(!problem.error().empty());
            }
            break;
        }
        case 4: {
            (void)proto::decode_job_status(text);
            // Scan requests share this slot: an accepted one respects the limits and re-encodes
            // to a request that encodes the same again.
            const proto::ScanLimits limits{.max_width = 64,
                                           .max_height = 64,
                                           .max_beams = 4096,
                                           .max_points = 8192,
                                           .max_returns = 4};
            const auto scan = proto::decode_scan_request(text, limits);
            if (scan) {
                const std::string once = proto::encode_scan_request(*scan);
                const auto again = proto::decode_scan_request(once, limits);
                fuzz::require(again && proto::encode_scan_request(*again) == once);
                fuzz::require(!scan->lidar || scan->lidar_spec.returns <= limits.max_returns);
            } else {
                fuzz::require(!scan.error().detail.empty());
            }
            break;
        }
        default:
            (void)proto::decode_json_hits(text);
            (void)proto::decode_json_occlusion(text);
            break;
    }
    return 0;
}
