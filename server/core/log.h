#pragma once
/// Logging through spdlog (the only spdlog user is server/). Two formats: text
/// (`2025-01-01 12:00:00.123 info  request method=GET route=/healthz status=200 ...`) and json
/// (one object per line: {"time": ..., "level": ..., "msg": ..., fields...}).

#include <initializer_list>
#include <string>
#include <string_view>

#include "kdrt/proto/json_api.h"
#include "kdrt/proto/result.h"

namespace kdrt::server {

enum class LogLevel { kTrace, kDebug, kInfo, kWarn, kError, kCritical, kOff };

/// Sets up the process logger (stderr). `level` and `format` were validated by the config.
void setup_logging(std::string_view level, std::string_view format);

/// True when events at `level` are written.
[[nodiscard]] bool log_enabled(LogLevel level) noexcept;

/// Writes one event: a message plus key/value fields.
void log_event(LogLevel level, std::string_view message,
               std::initializer_list<proto::JsonField> fields = {});

}  // namespace kdrt::server
