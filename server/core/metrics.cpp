#include "core/metrics.h"

#include <sys/resource.h>
#include <unistd.h>

#include <chrono>
#include <filesystem>
#include <fstream>
#include <iterator>
#include <sstream>

namespace kdrt::server {
namespace {

std::vector<double> request_buckets() {
    return {0.0001, 0.00025, 0.0005, 0.001, 0.0025, 0.005, 0.01, 0.025, 0.05,
            0.1,    0.25,    0.5,    1,     2.5,    5,     10,   30};
}
std::vector<double> build_buckets() {
    return {0.001, 0.01, 0.05, 0.1, 0.25, 0.5, 1, 2.5, 5, 10, 30, 60, 120, 300};
}

double now_seconds() {
    return std::chrono::duration<double>(std::chrono::system_clock::now().time_since_epoch())
        .count();
}

proto::MetricFamily family(std::string name, std::string help, proto::MetricType type) {
    proto::MetricFamily f;
    f.name = std::move(name);
    f.help = std::move(help);
    f.type = type;
    return f;
}

/// The standard process_* families (as the Prometheus client libraries export them), from /proc.
void process_families(std::vector<proto::MetricFamily>& families, double start_time) {
    const auto gauge = [&](const char* name, const char* help, proto::MetricType type,
                           double value) {
        auto f = family(name, help, type);
        f.samples.push_back({{}, value});
        families.push_back(std::move(f));
    };
    const double page = static_cast<double>(::sysconf(_SC_PAGESIZE));
    const double ticks = static_cast<double>(::sysconf(_SC_CLK_TCK));
    std::ifstream stat("/proc/self/stat");
    std::string line;
    if (std::getline(stat, line)) {
        // Fields after the parenthesised command: state is field 3; utime 14, stime 15,
        // vsize 23, rss 24 (1-based, as in proc(5)).
        std::istringstream rest(line.substr(line.rfind(')') + 2));
        const std::vector<std::string> fields{std::istream_iterator<std::string>(rest),
                                              std::istream_iterator<std::string>()};
        const auto field = [&](size_t n) {
            return n - 3 < fields.size() ? std::stod(fields[n - 3]) : 0.0;
        };
        gauge("process_cpu_seconds_total", "Total user and system CPU time spent in seconds.",
              proto::MetricType::kCounter, (field(14) + field(15)) / ticks);
        gauge("process_virtual_memory_bytes", "Virtual memory size in bytes.",
              proto::MetricType::kGauge, field(23));
        gauge("process_resident_memory_bytes", "Resident memory size in bytes.",
              proto::MetricType::kGauge, field(24) * page);
    }
    std::error_code ec;
    double fds = 0;
    for (auto it = std::filesystem::directory_iterator("/proc/self/fd", ec);
         !ec && it != std::filesystem::directory_iterator(); it.increment(ec))
        ++fds;
    gauge("process_open_fds", "Number of open file descriptors.", proto::MetricType::kGauge,
          fds - 1);  // less the one listing the directory
    rlimit limit{};
    if (::getrlimit(RLIMIT_NOFILE, &limit) == 0)
        gauge("process_max_fds", "Maximum number of open file descriptors.",
              proto::MetricType::kGauge, static_cast<double>(limit.rlim_cur));
    gauge("process_start_time_seconds", "Start time of the process since unix epoch in seconds.",
          proto::MetricType::kGauge, start_time);
}

}  // namespace

Histogram::Histogram(std::vector<double> upper_bounds)
    : upper_bounds_(std::move(upper_bounds)), counts_(upper_bounds_.size() + 1, 0) {}

void Histogram::observe(double value) {
    size_t i = 0;
    while (i < upper_bounds_.size() && value > upper_bounds_[i]) ++i;
    std::lock_guard lock(mutex_);
    ++counts_[i];
    sum_ += value;
}

proto::HistogramSample Histogram::sample(proto::MetricLabels labels) const {
    proto::HistogramSample s;
    s.labels = std::move(labels);
    s.upper_bounds = upper_bounds_;
    std::lock_guard lock(mutex_);
    s.bucket_counts = counts_;
    s.sum = sum_;
    return s;
}

void LabelledCounter::add(const proto::MetricLabels& labels, uint64_t n) {
    std::lock_guard lock(mutex_);
    counts_[labels] += n;
}

uint64_t LabelledCounter::value(const proto::MetricLabels& labels) const {
    std::lock_guard lock(mutex_);
    const auto it = counts_.find(labels);
    return it == counts_.end() ? 0 : it->second;
}

uint64_t LabelledCounter::total() const {
    std::lock_guard lock(mutex_);
    uint64_t sum = 0;
    for (const auto& [labels, n] : counts_) sum += n;
    return sum;
}

std::vector<proto::MetricSample> LabelledCounter::samples() const {
    std::lock_guard lock(mutex_);
    std::vector<proto::MetricSample> out;
    for (const auto& [labels, n] : counts_) out.push_back({labels, static_cast<double>(n)});
    return out;
}

std::string method_label(const std::string& method) {
    for (const char* known :
         {"GET", "HEAD", "POST", "PUT", "DELETE", "PATCH", "OPTIONS", "TRACE", "CONNECT"})
        if (method == known) return method;
    return "other";
}

Metrics::Metrics()
    : render_seconds_(build_buckets()),
      queue_seconds_(build_buckets()),
      build_seconds_(build_buckets()),
      start_time_(now_seconds()) {
    // Every reason is exported from the start (at 0), so rate() and alerts see the series.
    for (const char* reason :
         {"missing", "unreadable", "truncated", "corrupt", "format_version", "other_mesh"})
        cache_rebuilds.add({{"reason", reason}}, 0);
}

void Metrics::record_request(const std::string& route, const std::string& method, int status,
                             double seconds, uint64_t bytes_in, uint64_t bytes_out) {
    const std::string label = method_label(method);
    std::lock_guard lock(mutex_);
    Route& r = routes_[route];
    ++r.by_method_status[{label, status}];
    r.duration_by_method.try_emplace(label, request_buckets()).first->second.observe(seconds);
    r.bytes_in += bytes_in;
    r.bytes_out += bytes_out;
}

void Metrics::add_rays(uint64_t count, bool occlusion) {
    (occlusion ? rays_occlusion_ : rays_closest_).fetch_add(count, std::memory_order_relaxed);
}

void Metrics::record_render(uint64_t rays, double seconds, std::optional<double> queue_seconds) {
    renders.fetch_add(1);
    rays_render_.fetch_add(rays, std::memory_order_relaxed);
    render_seconds_.observe(seconds);
    if (queue_seconds) queue_seconds_.observe(*queue_seconds);
}

void Metrics::record_build(double seconds) {
    builds_.fetch_add(1);
    build_seconds_.observe(seconds);
}

void Metrics::set_build_info(proto::MetricLabels labels) {
    std::lock_guard lock(mutex_);
    build_info_ = std::move(labels);
}

void Metrics::add_collector(std::function<void(std::vector<proto::MetricFamily>&)> collector) {
    std::lock_guard lock(mutex_);
    collectors_.push_back(std::move(collector));
}

std::string Metrics::render() const {
    using proto::MetricType;
    std::vector<proto::MetricFamily> families;
    std::vector<std::function<void(std::vector<proto::MetricFamily>&)>> collectors;
    {
        std::lock_guard lock(mutex_);
        auto requests =
            family("kdrt_http_requests_total",
                   "HTTP requests by route template, method and status.", MetricType::kCounter);
        auto durations = family(
            "kdrt_http_request_duration_seconds",
            "Time from reading the request headers to writing the response, by route and method.",
            MetricType::kHistogram);
        auto bytes_in = family("kdrt_http_request_bytes_total", "Request body bytes by route.",
                               MetricType::kCounter);
        auto bytes_out = family("kdrt_http_response_bytes_total", "Response body bytes by route.",
                                MetricType::kCounter);
        for (const auto& [route, r] : routes_) {
            for (const auto& [key, count] : r.by_method_status)
                requests.samples.push_back({{{"route", route},
                                             {"method", std::get<0>(key)},
                                             {"status", std::to_string(std::get<1>(key))}},
                                            static_cast<double>(count)});
            for (const auto& [method, histogram] : r.duration_by_method)
                durations.histograms.push_back(
                    histogram.sample({{"route", route}, {"method", method}}));
            bytes_in.samples.push_back({{{"route", route}}, static_cast<double>(r.bytes_in)});
            bytes_out.samples.push_back({{{"route", route}}, static_cast<double>(r.bytes_out)});
        }
        families.push_back(std::move(requests));
        families.push_back(std::move(durations));
        families.push_back(std::move(bytes_in));
        families.push_back(std::move(bytes_out));
        collectors = collectors_;
    }
    auto rays =
        family("kdrt_rays_traced_total", "Rays traced, by query kind.", MetricType::kCounter);
    rays.samples.push_back({{{"kind", "closest"}}, static_cast<double>(rays_closest_.load())});
    rays.samples.push_back({{{"kind", "occlusion"}}, static_cast<double>(rays_occlusion_.load())});
    rays.samples.push_back({{{"kind", "render"}}, static_cast<double>(rays_render_.load())});
    families.push_back(std::move(rays));
    auto render_seconds =
        family("kdrt_render_seconds", "Render time (tracing), per image.", MetricType::kHistogram);
    render_seconds.histograms.push_back(render_seconds_.sample({}));
    families.push_back(std::move(render_seconds));
    auto queue_seconds =
        family("kdrt_job_queue_wait_seconds", "Time an async render job waited before it started.",
               MetricType::kHistogram);
    queue_seconds.histograms.push_back(queue_seconds_.sample({}));
    families.push_back(std::move(queue_seconds));

    auto builds = family("kdrt_tree_builds_total", "kD-tree builds (uploads and rebuilds).",
                         MetricType::kCounter);
    builds.samples.push_back({{}, static_cast<double>(builds_.load())});
    families.push_back(std::move(builds));
    auto build_seconds =
        family("kdrt_tree_build_seconds", "kD-tree build time.", MetricType::kHistogram);
    build_seconds.histograms.push_back(build_seconds_.sample({}));
    families.push_back(std::move(build_seconds));

    const auto counter = [&](const char* name, const char* help,
                             const std::atomic<uint64_t>& value) {
        auto f = family(name, help, MetricType::kCounter);
        f.samples.push_back({{}, static_cast<double>(value.load())});
        families.push_back(std::move(f));
    };
    counter("kdrt_cache_hits_total", "Tree lookups answered from memory.", cache_hits);
    counter("kdrt_cache_misses_total", "Tree lookups that loaded the tree from disk.",
            cache_misses);
    counter("kdrt_cache_evictions_total", "Trees dropped from memory to stay within the budget.",
            cache_evictions);
    const auto labelled = [&](const char* name, const char* help, const LabelledCounter& value) {
        auto f = family(name, help, MetricType::kCounter);
        f.samples = value.samples();
        families.push_back(std::move(f));
    };
    labelled("kdrt_cache_rebuilds_total",
             "Trees rebuilt from the stored mesh because the tree file was refused, by reason.",
             cache_rebuilds);
    labelled("kdrt_store_problems_total",
             "Damage found in stored files (on read, at start-up or by a scrub), by file and "
             "reason.",
             store_problems);
    labelled("kdrt_store_repairs_total", "Stored files rewritten from what remained, by file.",
             store_repairs);
    counter("kdrt_uploads_deduplicated_total",
            "Uploads of a mesh that was already stored (not rebuilt).", uploads_deduplicated);
    counter("kdrt_renders_total", "Images rendered (synchronous and jobs).", renders);

    for (const auto& collect : collectors) collect(families);

    auto info =
        family("kdrt_build_info", "Build and version information (value 1).", MetricType::kGauge);
    {
        std::lock_guard lock(mutex_);
        info.samples.push_back({build_info_, 1});
    }
    families.push_back(std::move(info));
    auto start = family("kdrt_process_start_time_seconds",
                        "Start time of the process (Unix seconds).", MetricType::kGauge);
    start.samples.push_back({{}, start_time_});
    families.push_back(std::move(start));
    process_families(families, start_time_);
    return proto::encode_prometheus(families);
}

}  // namespace kdrt::server
