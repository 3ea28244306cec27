#include "kdrt/proto/prometheus.h"

#include <gtest/gtest.h>

#include <cmath>

namespace kdrt::proto {
namespace {

TEST(Prometheus, CountersGaugesAndEscaping) {
    std::vector<MetricFamily> families(2);
    families[0].name = "x_total";
    families[0].help = "Help with \\ and\nnewline.";
    families[0].type = MetricType::kCounter;
    families[0].samples = {{{{"route", "/a\"b\\c\n"}, {"status", "200"}}, 3}, {{}, 1.5}};
    families[1].name = "g";
    families[1].help = "A gauge.";
    families[1].type = MetricType::kGauge;
    families[1].samples = {{{}, INFINITY}, {{{"k", "v"}}, NAN}};
    EXPECT_EQ(encode_prometheus(families),
              "# HELP x_total Help with \\\\ and\\nnewline.\n"
              "# TYPE x_total counter\n"
              "x_total{route=\"/a\\\"b\\\\c\\n\",status=\"200\"} 3\n"
              "x_total 1.5\n"
              "# HELP g A gauge.\n"
              "# TYPE g gauge\n"
              "g +Inf\n"
              "g{k=\"v\"} NaN\n");
}

TEST(Prometheus, HistogramBucketsAreCumulative) {
    MetricFamily f;
    f.name = "d_seconds";
    f.help = "Durations.";
    f.type = MetricType::kHistogram;
    f.histograms = {{{{"route", "/r"}}, {0.1, 1}, {2, 0, 5}, 7.25}};
    EXPECT_EQ(encode_prometheus({&f, 1}),
              "# HELP d_seconds Durations.\n"
              "# TYPE d_seconds histogram\n"
              "d_seconds_bucket{route=\"/r\",le=\"0.1\"} 2\n"
              "d_seconds_bucket{route=\"/r\",le=\"1\"} 2\n"
              "d_seconds_bucket{route=\"/r\",le=\"+Inf\"} 7\n"
              "d_seconds_sum{route=\"/r\"} 7.25\n"
              "d_seconds_count{route=\"/r\"} 7\n");
}

}  // namespace
}  // namespace kdrt::proto
