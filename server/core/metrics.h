#pragma once
/// Process-wide counters and histograms behind GET /metrics. Recording is thread-safe and cheap
/// (atomics, or a short mutex for labelled series); the text is produced by
/// proto::encode_prometheus at scrape time.

#include <atomic>
#include <cstdint>
#include <functional>
#include <map>
#include <mutex>
#include <optional>
#include <string>
#include <tuple>
#include <vector>

#include "kdrt/proto/prometheus.h"

namespace kdrt::server {

/// The method label of a request: the method when it is one of the standard HTTP methods, else
/// "other" (so a client cannot create a series per invented method token).
[[nodiscard]] std::string method_label(const std::string& method);

/// A fixed-bucket histogram (upper bounds in seconds).
class Histogram {
public:
    explicit Histogram(std::vector<double> upper_bounds);
    void observe(double value);
    [[nodiscard]] proto::HistogramSample sample(proto::MetricLabels labels) const;

private:
    std::vector<double> upper_bounds_;
    mutable std::mutex mutex_;
    std::vector<uint64_t> counts_;  // upper_bounds_.size() + 1 (the last is +Inf)
    double sum_ = 0;
};

/// A counter family with one label set per sample (few, fixed label values: reasons, kinds).
class LabelledCounter {
public:
    void add(const proto::MetricLabels& labels, uint64_t n = 1);
    [[nodiscard]] uint64_t value(const proto::MetricLabels& labels) const;
    /// Sum over every label set.
    [[nodiscard]] uint64_t total() const;
    [[nodiscard]] std::vector<proto::MetricSample> samples() const;

private:
    mutable std::mutex mutex_;
    std::map<proto::MetricLabels, uint64_t> counts_;
};

class Metrics {
public:
    Metrics();

    /// One finished HTTP request. `route` is the route template ("/v1/meshes/{id}").
    void record_request(const std::string& route, const std::string& method, int status,
                        double seconds, uint64_t bytes_in, uint64_t bytes_out);
    void add_rays(uint64_t count, bool occlusion);
    /// One finished render (sync or job): counts it, its rays (kind="render") and its time;
    /// `queue_seconds` is how long a job waited before it started (nullopt for sync renders).
    void record_render(uint64_t rays, double seconds, std::optional<double> queue_seconds);
    /// One kD-tree build (upload, or rebuild of a corrupt cache file).
    void record_build(double seconds);

    std::atomic<uint64_t> cache_hits{0};       ///< tree requested and resident
    std::atomic<uint64_t> cache_misses{0};     ///< tree requested and loaded from disk
    std::atomic<uint64_t> cache_evictions{0};  ///< trees dropped from memory
    /// Trees rebuilt from the stored mesh, by {reason} (the TreeFileProblem reason label).
    LabelledCounter cache_rebuilds;
    /// Damage found in stored files, by {file="mesh"|"tree"|"summary", reason}.
    LabelledCounter store_problems;
    /// Stored files rewritten from what remained, by {file}.
    LabelledCounter store_repairs;
    std::atomic<uint64_t> uploads_deduplicated{0};  ///< uploads of a mesh already stored
    std::atomic<uint64_t> renders{0};

    /// Adds families computed at scrape time (cache sizes, job counts). Called under no lock of
    /// this class; must be thread-safe.
    void add_collector(std::function<void(std::vector<proto::MetricFamily>&)> collector);

    /// Labels of kdrt_build_info (version, library versions). Set once before serving.
    void set_build_info(proto::MetricLabels labels);

    /// The whole exposition text.
    [[nodiscard]] std::string render() const;

    /// Request counts by route/method/status, for tests and logs.
    [[nodiscard]] uint64_t builds() const noexcept { return builds_.load(); }

private:
    struct Route {
        std::map<std::tuple<std::string, int>, uint64_t> by_method_status;
        std::map<std::string, Histogram> duration_by_method;
        uint64_t bytes_in = 0, bytes_out = 0;
    };

    mutable std::mutex mutex_;
    std::map<std::string, Route> routes_;
    std::vector<std::function<void(std::vector<proto::MetricFamily>&)>> collectors_;

    std::atomic<uint64_t> rays_closest_{0};
    std::atomic<uint64_t> rays_occlusion_{0};
    std::atomic<uint64_t> rays_render_{0};
    Histogram render_seconds_, queue_seconds_;
    std::atomic<uint64_t> builds_{0};
    Histogram build_seconds_;
    proto::MetricLabels build_info_;
    const double start_time_;
};

}  // namespace kdrt::server
