#pragma once
/// Everything the routes share, free of any HTTP type: configuration, metrics, the compute
/// arena, the mesh store and cache, admission control, the render job queue and the readiness
/// state.

#include <atomic>
#include <memory>
#include <optional>
#include <utility>

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
};

}  // namespace kdrt::server
