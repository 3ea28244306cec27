#include "app.h"

#include <pthread.h>
#include <unistd.h>

#include <atomic>
#include <chrono>
#include <condition_variable>
#include <csignal>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <mutex>
#include <string>
#include <thread>
#include <utility>

#include "core/log.h"
#include "core/systemd_notify.h"
#include "http/http_server.h"
#include "kdrt/proto/mesh_id.h"
#include "kdrt/proto/mesh_io.h"
#include "kdrt/trace.h"
#include "service.h"

namespace kdrt::server {
namespace {

proto::Result<void, std::string> write_port_file(const std::string& path, int port) {
    const std::string tmp = path + ".tmp";
    {
        std::ofstream out(tmp, std::ios::trunc);
        out << port << "\n";
        if (!out) return proto::Err{"cannot write \"" + tmp + "\""};
    }
    std::error_code ec;
    std::filesystem::rename(tmp, path, ec);
    if (ec) return proto::Err{"cannot rename \"" + tmp + "\" to \"" + path + "\": " + ec.message()};
    return {};
}

/// Loads the index and the preloads. Returns false (logged) if the server cannot start.
bool start_up(Service& svc) {
    if (auto opened = svc.cache.open(); !opened) {
        log_event(LogLevel::kCritical, "cannot open the mesh cache", {{"error", opened.error()}});
        return false;
    }
    log_event(LogLevel::kInfo, "mesh index loaded",
              {{"meshes", static_cast<uint64_t>(svc.cache.mesh_count())},
               {"disk_bytes", svc.cache.disk_bytes()}});
    svc.scene_store.set_notice([](const std::string& scene, const std::string& what) {
        log_event(LogLevel::kWarn, "scene store repaired or converted a scene",
                  {{"scene", scene}, {"what", what}});
    });
    svc.scene_store.set_flush_commits(svc.config.scene_sync == "commit");
    if (auto opened = svc.scene_store.open(); !opened) {
        log_event(LogLevel::kCritical, "cannot open the scene store", {{"error", opened.error()}});
        return false;
    }
    log_event(LogLevel::kInfo, "scene store opened",
              {{"scenes", static_cast<uint64_t>(svc.scenes.scene_count())},
               {"form", std::string_view(svc.scene_store.uses_log()
                                             ? "revision logs"
                                             : "revision files (the file system refuses flock)")}});
    if (const size_t files = svc.scene_store.revision_file_scenes();
        files > 0 && svc.scene_store.uses_log())
        log_event(LogLevel::kWarn,
                  "scenes stored as revision files by an earlier kdrt-server: read as they are, "
                  "each moved into a revision log on its next change",
                  {{"scenes", static_cast<uint64_t>(files)}});
    for (const std::string& file : svc.config.preload) {
        if (svc.shutting_down) return true;
        proto::MeshLimits limits;
        limits.max_triangles = svc.config.max_triangles;
        auto mesh = proto::load_mesh_file(file, std::nullopt, limits);
        if (!mesh) {
            log_event(LogLevel::kCritical, "cannot preload mesh",
                      {{"file", file}, {"error", mesh.error().to_string()}});
            return false;
        }
        if (mesh->triangle_count() == 0) {
            log_event(LogLevel::kCritical, "cannot preload mesh",
                      {{"file", file}, {"error", std::string_view("the mesh has no triangles")}});
            return false;
        }
        auto added = svc.cache.add(*mesh);
        if (!added) {
            log_event(LogLevel::kCritical, "cannot preload mesh",
                      {{"file", file}, {"error", added.error().detail}});
            return false;
        }
        log_event(LogLevel::kInfo, "preloaded",
                  {{"file", file},
                   {"mesh", added->summary.id},
                   {"triangles", added->summary.triangles},
                   {"built", added->created},
                   {"build_ms", added->summary.tree.build_ms}});
    }
    return true;
}

/// Blocks the termination signals (and the internal SIGUSR1) in this thread and every thread it
/// starts, so they are collected with sigwait and no handler runs at an arbitrary point of
/// another thread. SIGUSR1: a helper thread finished (start-up failed, or the listener stopped).
sigset_t block_stop_signals() {
    sigset_t signals;
    sigemptyset(&signals);
    sigaddset(&signals, SIGINT);
    sigaddset(&signals, SIGTERM);
    sigaddset(&signals, SIGUSR1);
    pthread_sigmask(SIG_BLOCK, &signals, nullptr);
    ::signal(SIGPIPE, SIG_IGN);
    return signals;
}

/// Binds the listen address and writes the port file. Logs and returns false on failure.
bool bind_and_announce(HttpServer& http, const Service& svc,
                       const std::pair<std::string, int>& listen) {
    const ServerConfig& config = svc.config;
    auto port = http.bind(listen.first, listen.second);
    if (!port) {
        log_event(LogLevel::kCritical, "cannot listen", {{"error", port.error()}});
        return false;
    }
    if (!config.port_file.empty()) {
        if (auto written = write_port_file(config.port_file, *port); !written) {
            log_event(LogLevel::kCritical, "cannot write the port file",
                      {{"error", written.error()}});
            return false;
        }
    }
    log_event(LogLevel::kInfo, "listening",
              {{"address", listen.first + ":" + std::to_string(*port)},
               {"version", std::string_view(KDRT_VERSION)},
               {"engine_threads", static_cast<uint64_t>(svc.compute.threads())},
               {"http_threads", static_cast<uint64_t>(config.http_threads)},
               {"cache_dir", config.cache_dir},
               {"memory_budget", config.memory_budget},
               {"auth", !accepted_tokens(config).empty()}});
    return true;
}

/// What the helper threads report to the main thread (with SIGUSR1).
struct HelperFailures {
    std::atomic<bool> listener{false}, startup{false};
    std::atomic<bool> listener_done{false};  ///< serve() returned
};

/// Serves on a new thread until stopped; a failure is reported to this thread.
std::thread start_listener(HttpServer& http, const Service& svc, HelperFailures& failed) {
    return std::thread([&http, &svc, &failed, main_thread = pthread_self()] {
        if (!http.serve() && !svc.shutting_down) failed.listener = true;
        failed.listener_done = true;
        pthread_kill(main_thread, SIGUSR1);
    });
}

/// notify_systemd, with a failure logged (the server runs on: systemd then times the start out).
void tell_systemd(const std::string& state) {
    if (auto sent = notify_systemd(state); !sent)
        log_event(LogLevel::kError, "cannot notify systemd", {{"error", sent.error()}});
}

/// Loads the mesh index and the preloads on a new thread, then marks the service ready; a
/// failure is reported to this thread.
std::thread start_loading(Service& svc, HelperFailures& failed) {
    return std::thread([&svc, &failed, main_thread = pthread_self()] {
        if (!start_up(svc)) {
            failed.startup = true;
            pthread_kill(main_thread, SIGUSR1);
            return;
        }
        if (svc.shutting_down) return;
        svc.ready = true;
        log_event(LogLevel::kInfo, "ready",
                  {{"meshes", static_cast<uint64_t>(svc.cache.mesh_count())}});
        // systemd's Type=notify (deploy/systemd/kdrt.service): started once /readyz says 200.
        tell_systemd("READY=1\nSTATUS=ready, " + std::to_string(svc.cache.mesh_count()) +
                     " meshes");
    });
}

/// Waits for SIGINT/SIGTERM or a helper's failure; returns the exit code (1 for a failure).
int wait_for_stop(const sigset_t& signals, const HelperFailures& failed, unsigned timeout_s) {
    for (;;) {
        int sig = 0;
        sigwait(&signals, &sig);
        if (sig == SIGUSR1 && !failed.listener && !failed.startup) continue;  // stale wake-up
        if (sig == SIGUSR1) {
            log_event(LogLevel::kCritical,
                      failed.startup ? "start-up failed" : "the listener stopped unexpectedly");
            return 1;
        }
        log_event(LogLevel::kInfo, "shutting down",
                  {{"signal", std::string_view(sig == SIGINT ? "SIGINT" : "SIGTERM")},
                   {"timeout_s", static_cast<uint64_t>(timeout_s)}});
        return 0;
    }
}

/// Requests in flight get `timeout_s` to finish; after that the process logs each request it
/// cuts and exits with status 1 (a shutdown that dropped clients is not a clean exit).
/// disarm() (or the destructor) stops the watchdog.
class ShutdownWatchdog {
public:
    ShutdownWatchdog(unsigned timeout_s, const Service& svc)
        : thread_([this, timeout_s, &svc] {
              std::unique_lock lock(mutex_);
              if (!done_cv_.wait_for(lock, std::chrono::seconds(timeout_s),
                                     [&] { return done_; })) {
                  const std::vector<std::string> cut = svc.requests.describe();
                  log_event(LogLevel::kError,
                            "shutdown timeout: exiting with requests still in flight",
                            {{"timeout_s", static_cast<uint64_t>(timeout_s)},
                             {"requests", static_cast<uint64_t>(cut.size())},
                             {"exit_code", int64_t{1}}});
                  for (const std::string& request : cut)
                      log_event(LogLevel::kError, "shutdown cut request", {{"request", request}});
                  std::fflush(nullptr);
                  ::_exit(1);
              }
          }) {}
    ShutdownWatchdog(const ShutdownWatchdog&) = delete;
    ShutdownWatchdog& operator=(const ShutdownWatchdog&) = delete;
    ~ShutdownWatchdog() { disarm(); }

    void disarm() {
        {
            std::lock_guard lock(mutex_);
            done_ = true;
        }
        done_cv_.notify_one();
        if (thread_.joinable()) thread_.join();
    }

private:
    std::mutex mutex_;
    std::condition_variable done_cv_;
    bool done_ = false;
    std::thread thread_;  ///< last: starts once the members it uses exist
};

/// New /v1 requests now get 503; uploads, traces and renders already admitted run to the end
/// before the listener stops (httplib cuts streamed responses short once it is stopped).
void drain_and_stop(Service& svc, HttpServer& http, const HelperFailures& helpers) {
    tell_systemd("STOPPING=1\nSTATUS=draining requests in flight");
    svc.shutting_down = true;
    svc.ready = false;
    svc.jobs.shutdown();  // cancels queued and running render jobs
    while (svc.gate.in_flight() > 0) std::this_thread::sleep_for(std::chrono::milliseconds(2));
    // httplib's stop() does nothing until the listener runs: a stop right after start-up (a
    // failed preload) used to leave it listening until the shutdown watchdog fired. Repeat it.
    while (!helpers.listener_done) {
        http.stop();
        std::this_thread::sleep_for(std::chrono::milliseconds(2));
    }
}

}  // namespace

int run_server(const ServerConfig& config) {
    const sigset_t signals = block_stop_signals();
    auto listen = split_listen(config.listen);
    if (!listen) {
        log_event(LogLevel::kCritical, "bad listen address", {{"error", listen.error()}});
        return 1;
    }
    Service svc(config);
    svc.metrics.set_build_info({{"version", KDRT_VERSION},
                                {"httplib", httplib_version()},
                                {"compiler", __VERSION__},
                                {"isa", std::string(isa_name(default_isa()))}});
    HttpServer http(svc);
    if (!bind_and_announce(http, svc, *listen)) return 1;

    HelperFailures failed;
    std::thread listener = start_listener(http, svc, failed);
    std::thread startup = start_loading(svc, failed);
    const int exit_code = wait_for_stop(signals, failed, config.shutdown_timeout_s);
    ShutdownWatchdog watchdog(config.shutdown_timeout_s, svc);
    drain_and_stop(svc, http, failed);
    listener.join();
    startup.join();
    watchdog.disarm();
    log_event(LogLevel::kInfo, "stopped", {{"exit_code", static_cast<int64_t>(exit_code)}});
    return exit_code;
}

int print_mesh_ids(const std::vector<std::string>& files) {
    int status = 0;
    for (const std::string& file : files) {
        auto mesh = proto::load_mesh_file(file);
        if (!mesh) {
            std::fprintf(stderr, "kdrt-server: %s\n", mesh.error().to_string().c_str());
            status = 1;
            continue;
        }
        std::printf("%s  %s\n", proto::mesh_id(*mesh).c_str(), file.c_str());
    }
    return status;
}

}  // namespace kdrt::server
