#pragma once
/// kdrt-server's life cycle: bind, write the port file, load the mesh index, preload meshes,
/// mark ready, serve; on SIGTERM/SIGINT stop accepting, let in-flight requests finish (bounded
/// by shutdown_timeout_s) and return 0.

#include "core/config.h"

namespace kdrt::server {

/// Runs the server until a termination signal. Returns the process exit code (0 after a
/// signal, 1 if start-up failed). Must be called from the main thread before any other thread
/// is started (it blocks the termination signals for all threads and waits for them itself).
int run_server(const ServerConfig& config);

/// `kdrt-server --mesh-id FILE...`: prints "<id>  <file>" per file. Returns the exit code.
int print_mesh_ids(const std::vector<std::string>& files);

}  // namespace kdrt::server
