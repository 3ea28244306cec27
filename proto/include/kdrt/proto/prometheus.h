#pragma once
/// Prometheus text exposition format 0.0.4 (what GET /metrics answers). The caller collects
/// plain values; this encoder knows the syntax: # HELP / # TYPE lines, label escaping, histogram
/// _bucket{le=...} / _sum / _count series, +Inf/NaN spelling.

#include <cstdint>
#include <span>
#include <string>
#include <string_view>
#include <utility>
#include <vector>

namespace kdrt::proto {

inline constexpr std::string_view kPrometheusMediaType = "text/plain; version=0.0.4; charset=utf-8";

using MetricLabels = std::vector<std::pair<std::string, std::string>>;

struct MetricSample {
    MetricLabels labels;
    double value = 0;
};

/// One histogram series. `bucket_counts[i]` counts observations <= upper_bounds[i] and above the
/// previous bound (not cumulative); `bucket_counts` has one extra last entry for +Inf.
struct HistogramSample {
    MetricLabels labels;
    std::vector<double> upper_bounds;
    std::vector<uint64_t> bucket_counts;
    double sum = 0;
};

enum class MetricType { kCounter, kGauge, kHistogram };

/// A metric family: name (e.g. `kdrt_http_requests_total`), help text, type, and its samples
/// (`samples` for counters and gauges, `histograms` for histograms).
struct MetricFamily {
    std::string name;
    std::string help;
    MetricType type = MetricType::kGauge;
    std::vector<MetricSample> samples;
    std::vector<HistogramSample> histograms;
};

/// The exposition text of all families, in order. Label values are escaped (\\, \", \n).
[[nodiscard]] std::string encode_prometheus(std::span<const MetricFamily> families);

}  // namespace kdrt::proto
