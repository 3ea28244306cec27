// kdrt-server: the kdrt HTTP service. See server/core/config.h for the settings, app.h for the life
// cycle and proto/openapi.yaml for the API.

#include <malloc.h>

#include <csignal>
#include <cstdio>
#include <exception>
#include <string>
#include <vector>

#include "app.h"
#include "core/config.h"
#include "core/log.h"
#include "store/store_check.h"

extern char** environ;

namespace {

int run(int argc, char** argv) {
    std::vector<std::string> args(argv + 1, argv + argc);
    std::vector<std::string> env;
    for (char** e = environ; *e; ++e) env.emplace_back(*e);
    auto invocation = kdrt::server::parse_invocation(args, env);
    if (!invocation) {
        std::fprintf(stderr, "kdrt-server: %s\n", invocation.error().c_str());
        return 2;
    }
    using Mode = kdrt::server::Invocation::Mode;
    switch (invocation->mode) {
        case Mode::kHelp:
            std::fputs(kdrt::server::help_text().c_str(), stdout);
            return 0;
        case Mode::kVersion:
            std::printf("kdrt-server %s\n", KDRT_VERSION);
            return 0;
        case Mode::kMeshId:
            return kdrt::server::print_mesh_ids(invocation->mesh_files);
        case Mode::kCheckStore:
            return kdrt::server::check_store(invocation->config, stdout);
        case Mode::kServe:
            break;
    }
    // A file size limit (RLIMIT_FSIZE) must fail the write (EFBIG, answered 507), not kill the
    // process with SIGXFSZ.
    std::signal(SIGXFSZ, SIG_IGN);
#ifdef __GLIBC__
    // A request's working blocks (a 64 x 2048 scan: 4 MiB of rays, its hits, the cloud) come
    // from the heaps and stay there for the next request. With glibc's adaptive thresholds a
    // thread's heap was shrunk (MADV_DONTNEED) once its free top passed twice the largest block
    // freed so far, and the next scan faulted every page back in: ~1,600 faults a frame of
    // scene_latency.py, at ~10 us each on a virtual machine. Blocks above 32 MiB (trees,
    // uploads) are still mapped and unmapped; a heap keeps what its thread's largest request
    // used.
    mallopt(M_MMAP_THRESHOLD, 32 << 20);
    mallopt(M_TRIM_THRESHOLD, 256 << 20);
#endif
    kdrt::server::setup_logging(invocation->config.log_level, invocation->config.log_format);
    for (const std::string& warning : invocation->warnings)
        kdrt::server::log_event(kdrt::server::LogLevel::kWarn, warning);
    return kdrt::server::run_server(invocation->config);
}

}  // namespace

/// An exception that escapes (std::bad_alloc, std::system_error) is reported on stderr; exit 1.
int main(int argc, char** argv) {
    try {
        return run(argc, argv);
    } catch (const std::exception& e) {
        std::fprintf(stderr, "kdrt-server: %s\n", e.what());
    } catch (...) {
        std::fputs("kdrt-server: unknown exception\n", stderr);
    }
    return 1;
}
