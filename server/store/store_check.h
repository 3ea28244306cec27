#pragma once
/// `kdrt-server --check-store`: a read-only scrub of the cache directory.

#include <cstdio>

#include "core/config.h"

namespace kdrt::server {

/// Checks every mesh under config.cache_dir: the mesh file against its id (SHA-256 of its
/// triangles), the tree file (its container names this mesh, the engine blob validates), the
/// summary against both. Prints one line per mesh ("ok ID" or "damaged ID: what, per file" with
/// whether a running server can repair it from what remains) and a total to `out`. Never
/// writes. Returns 0 when every mesh is intact, 1 when any is damaged, 2 when the store cannot
/// be read.
int check_store(const ServerConfig& config, std::FILE* out);

}  // namespace kdrt::server
