#include "cli_progress.h"

#include <algorithm>
#include <cmath>

namespace kdrt::cli {

ProgressReporter::ProgressReporter(std::ostream& err, bool tty, bool quiet, std::string label)
    : err_(err), tty_(tty), quiet_(quiet), label_(std::move(label)) {}

std::string ProgressReporter::bar(std::string_view state, double progress, int width) {
    const double p = std::isfinite(progress) ? std::clamp(progress, 0.0, 1.0) : 0.0;
    const int filled = static_cast<int>(p * width);
    const int percent = static_cast<int>(p * 100.0);
    std::string line = "[";  // appended: GCC 12 warns falsely (-Wrestrict) on "[" + std::string
    line.append(static_cast<size_t>(filled), '#');
    line.append(static_cast<size_t>(width - filled), '-');
    line += "] ";
    const std::string number = std::to_string(percent);
    line.append(3 - std::min<size_t>(3, number.size()), ' ');
    line += number;
    line += "% ";
    line += state;
    return line;
}

void ProgressReporter::update(std::string_view state, double progress) {
    if (quiet_) return;
    const double p = std::isfinite(progress) ? std::clamp(progress, 0.0, 1.0) : 0.0;
    const int percent = static_cast<int>(p * 100.0);
    if (tty_) {
        if (percent == last_percent_ && state == last_state_) return;
        // Pad to clear a longer previous state name.
        err_ << '\r' << label_ << ": " << bar(state, p) << "   " << std::flush;
        drawn_ = true;
    } else {
        // finish() reports the end: no line for the final states here.
        const int decile = percent / 10;
        const bool final_state = state == "done" || state == "failed" || state == "cancelled";
        if (final_state) {
        } else if (state != last_state_ && state != "running") {
            err_ << label_ << ": " << state << "\n" << std::flush;
        } else if (decile != last_decile_ && state == "running") {
            err_ << label_ << ": " << decile * 10 << "%\n" << std::flush;
            last_decile_ = decile;
        }
    }
    last_percent_ = percent;
    last_state_ = std::string(state);
}

void ProgressReporter::finish(std::string_view message) {
    if (quiet_) return;
    if (tty_ && drawn_) err_ << "\n";
    err_ << label_ << ": " << message << "\n" << std::flush;
}

}  // namespace kdrt::cli
