#include "kdrt/proto/prometheus.h"

#include <charconv>
#include <cmath>

namespace kdrt::proto {
namespace {

/// Values in the shortest round-trip form; `le` bounds in plain decimal ("0.0001", not "1e-04"),
/// the form the Prometheus client libraries write, so bucket series match across exporters.
void append_value(std::string& out, double value, bool plain = false) {
    if (std::isnan(value)) {
        out += "NaN";
    } else if (std::isinf(value)) {
        out += value > 0 ? "+Inf" : "-Inf";
    } else {
        char buf[40];
        const auto r = plain && std::abs(value) >= 1e-9 && std::abs(value) < 1e15
                           ? std::to_chars(buf, buf + sizeof buf, value, std::chars_format::fixed)
                           : std::to_chars(buf, buf + sizeof buf, value);
        out.append(buf, r.ptr);
    }
}

void append_escaped(std::string& out, std::string_view text, bool quote_escapes) {
    for (const char c : text) {
        if (c == '\\')
            out += "\\\\";
        else if (c == '\n')
            out += "\\n";
        else if (c == '"' && quote_escapes)
            out += "\\\"";
        else
            out.push_back(c);
    }
}

void append_labels(std::string& out, const MetricLabels& labels, std::string_view extra_key = {},
                   std::string_view extra_value = {}) {
    if (labels.empty() && extra_key.empty()) return;
    out.push_back('{');
    bool first = true;
    for (const auto& [key, value] : labels) {
        if (!first) out.push_back(',');
        first = false;
        out += key;
        out += "=\"";
        append_escaped(out, value, true);
        out.push_back('"');
    }
    if (!extra_key.empty()) {
        if (!first) out.push_back(',');
        out += extra_key;
        out += "=\"";
        out += extra_value;
        out.push_back('"');
    }
    out.push_back('}');
}

}  // namespace

std::string encode_prometheus(std::span<const MetricFamily> families) {
    std::string out;
    out.reserve(4096);
    for (const MetricFamily& f : families) {
        out += "# HELP ";
        out += f.name;
        out.push_back(' ');
        append_escaped(out, f.help, false);
        out += "\n# TYPE ";
        out += f.name;
        out += f.type == MetricType::kCounter ? " counter\n"
               : f.type == MetricType::kGauge ? " gauge\n"
                                              : " histogram\n";
        if (f.type != MetricType::kHistogram) {
            for (const MetricSample& s : f.samples) {
                out += f.name;
                append_labels(out, s.labels);
                out.push_back(' ');
                append_value(out, s.value);
                out.push_back('\n');
            }
            continue;
        }
        for (const HistogramSample& h : f.histograms) {
            uint64_t cumulative = 0;
            for (size_t i = 0; i < h.bucket_counts.size(); ++i) {
                cumulative += h.bucket_counts[i];
                std::string le;
                append_value(le, i < h.upper_bounds.size() ? h.upper_bounds[i] : INFINITY, true);
                out += f.name;
                out += "_bucket";
                append_labels(out, h.labels, "le", le);
                out.push_back(' ');
                out += std::to_string(cumulative);
                out.push_back('\n');
            }
            out += f.name;
            out += "_sum";
            append_labels(out, h.labels);
            out.push_back(' ');
            append_value(out, h.sum);
            out += '\n';
            out += f.name;
            out += "_count";
            append_labels(out, h.labels);
            out.push_back(' ');
            out += std::to_string(cumulative);
            out.push_back('\n');
        }
    }
    return out;
}

}  // namespace kdrt::proto
