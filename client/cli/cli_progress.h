#pragma once
/// Render progress on stderr: a redrawn bar on a terminal, plain lines (every 10 %) otherwise.

#include <chrono>
#include <ostream>
#include <string>

namespace kdrt::cli {

class ProgressReporter {
public:
    /// `tty`: draw a bar redrawn in place with '\r'; else print "LABEL: N%" lines at each 10 %
    /// step. `quiet`: print nothing.
    ProgressReporter(std::ostream& err, bool tty, bool quiet, std::string label);

    /// Reports a state ("queued", "running", ...) and a share done in [0, 1]. Repeated values
    /// print nothing new.
    void update(std::string_view state, double progress);
    /// Ends the bar (a newline on a terminal) and prints "LABEL: <message>".
    void finish(std::string_view message);

    /// The bar line for `progress` without the leading '\r' (for tests): "[#####-----]  50%
    /// running".
    [[nodiscard]] static std::string bar(std::string_view state, double progress, int width = 30);

private:
    std::ostream& err_;
    bool tty_;
    bool quiet_;
    std::string label_;
    std::string last_state_;
    int last_percent_ = -1;
    int last_decile_ = -1;
    bool drawn_ = false;
};

}  // namespace kdrt::cli
