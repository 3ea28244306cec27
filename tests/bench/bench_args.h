#pragma once
/// Command-line parsing for kdrt-bench: positional arguments plus `--name value` /
/// `--name=value` options, with usage errors kept apart from runtime failures (exit 2 vs 1).

#include <cstdint>
#include <map>
#include <optional>
#include <set>
#include <span>
#include <stdexcept>
#include <string>
#include <string_view>
#include <vector>

namespace kdrt::bench {

/// A malformed command line (unknown option, missing or bad value). kdrt-bench exits with 2.
class UsageError : public std::runtime_error {
public:
    using std::runtime_error::runtime_error;
};

/// A well-formed request that failed (unreadable file, parse error, unavailable mode).
/// kdrt-bench exits with 1.
class BenchError : public std::runtime_error {
public:
    using std::runtime_error::runtime_error;
};

/// The arguments after the subcommand name.
class Args {
public:
    /// Splits `args` into positionals and options. `value_options` are the option names (without
    /// "--") the subcommand accepts; each takes exactly one value. `--help` / `-h` set help().
    /// Throws UsageError for an unknown option, a missing value or an option given twice.
    /// `flag_options` take no value (`--stats`); flag() tells whether one was given.
    Args(std::span<char* const> args, std::span<const std::string_view> value_options,
         std::span<const std::string_view> flag_options = {});

    [[nodiscard]] bool help() const noexcept { return help_; }
    [[nodiscard]] const std::vector<std::string>& positional() const noexcept {
        return positional_;
    }

    /// Throws UsageError unless there are exactly `names.size()` positionals; the message names
    /// the first missing one, or the first extra value.
    void expect_positional(std::span<const std::string_view> names) const;

    /// Whether the flag option was given.
    [[nodiscard]] bool flag(std::string_view name) const { return flags_.contains(name); }
    /// The option's value, if given.
    [[nodiscard]] std::optional<std::string> get(std::string_view name) const;
    /// The option's value; UsageError naming the option if absent.
    [[nodiscard]] std::string require(std::string_view name) const;
    /// An integer option in [min_value, max_value], or `fallback` if absent. UsageError otherwise.
    [[nodiscard]] uint64_t get_uint(std::string_view name, uint64_t fallback, uint64_t min_value,
                                    uint64_t max_value) const;
    /// A finite number option in [min_value, max_value], or `fallback` if absent. UsageError
    /// otherwise.
    [[nodiscard]] float get_float(std::string_view name, float fallback, float min_value,
                                  float max_value) const;

private:
    std::vector<std::string> positional_;
    std::map<std::string, std::string, std::less<>> options_;
    std::set<std::string, std::less<>> flags_;
    bool help_ = false;
};

}  // namespace kdrt::bench
