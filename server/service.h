#pragma once
/// Everything the routes share, free of any HTTP type: configuration, metrics, the compute
/// arena, the mesh store and cache, admission control, the render job queue and the readiness
/// state.

#include <atomic>
#include <chrono>
#include <map>
#include <memory>
#include <mutex>
#include <optional>
#include <string>
#include <thread>
#include <utility>
#include <vector>

#include "buffer_pool.h"
#include "compute.h"
#include "config.h"
#include "jobs.h"
#include "mesh_cache.h"
#include "mesh_store.h"
#include "metrics.h"

namespace kdrt::server {

/// Counts heavy requests (uploads, traces, renders) in flight; beyond the limit they get 503.
class AdmissionGate {
public:
    explicit AdmissionGate(unsigned limit) : limit_(limit) {}

    /// A held slot; released on destruction.
    class Slot {
    public:
        explicit Slot(std::atomic<unsigned>& count) : count_(&count) {}
        Slot(Slot&& other) noexcept : count_(std::exchange(other.count_, nullptr)) {}
        Slot(const Slot&) = delete;
        Slot& operator=(const Slot&) = delete;
        Slot& operator=(Slot&& other) noexcept {
            if (this != &other) {
                if (count_) count_->fetch_sub(1);
                count_ = std::exchange(other.count_, nullptr);
            }
            return *this;
        }
        ~Slot() {
            if (count_) count_->fetch_sub(1);
        }

    private:
        std::atomic<unsigned>* count_;
    };

    /// A slot, or nullopt when `limit` requests already hold one.
    [[nodiscard]] std::optional<Slot> try_enter() {
        if (in_flight_.fetch_add(1) >= limit_) {
            in_flight_.fetch_sub(1);
            return std::nullopt;
        }
        return Slot(in_flight_);
    }
    [[nodiscard]] unsigned in_flight() const noexcept { return in_flight_.load(); }
    [[nodiscard]] unsigned limit() const noexcept { return limit_; }

private:
    const unsigned limit_;
    std::atomic<unsigned> in_flight_{0};
};

/// The request each HTTP thread is serving now, so a shutdown that times out can say which
/// requests it cut. Keyed by thread: a thread's next request replaces its entry.
class RequestRegistry {
public:
    void begin(std::string id, std::string method, std::string path) {
        std::lock_guard lock(mutex_);
        current_[std::this_thread::get_id()] = {std::move(id), std::move(method), std::move(path),
                                                std::chrono::steady_clock::now()};
    }
    void end() {
        std::lock_guard lock(mutex_);
        current_.erase(std::this_thread::get_id());
    }
    /// "id METHOD path (N ms)" per request still being served.
    [[nodiscard]] std::vector<std::string> describe() const {
        std::lock_guard lock(mutex_);
        std::vector<std::string> out;
        const auto now = std::chrono::steady_clock::now();
        for (const auto& [thread, r] : current_) {
            const auto ms =
                std::chrono::duration_cast<std::chrono::milliseconds>(now - r.start).count();
            out.push_back(r.id + " " + r.method + " " + r.path + " (" + std::to_string(ms) +
                          " ms)");
        }
        return out;
    }

private:
    struct Current {
        std::string id, method, path;
        std::chrono::steady_clock::time_point start;
    };
    mutable std::mutex mutex_;
    std::map<std::thread::id, Current> current_;
};

struct Service {
    explicit Service(ServerConfig cfg);

    const ServerConfig config;
    Metrics metrics;
    Compute compute;
    MeshStore store;
    MeshCache cache;
    AdmissionGate gate;
    JobQueue jobs;
    BufferPool batch_buffers;                ///< rays and encoded answers of KDRR batches
    std::atomic<bool> ready{false};          ///< index loaded and preloads done
    std::atomic<bool> shutting_down{false};  ///< SIGTERM/SIGINT received
    RequestRegistry requests;                ///< what each HTTP thread serves now
};

}  // namespace kdrt::server
