#pragma once
/// Everything the routes share, free of any HTTP type: configuration, metrics, the compute
/// arena, the mesh store and cache, admission control, the render job queue and the readiness
/// state.

#include <atomic>
#include <chrono>
#include <condition_variable>
#include <cstdint>
#include <map>
#include <memory>
#include <mutex>
#include <optional>
#include <string>
#include <thread>
#include <utility>
#include <vector>

#include "core/buffer_pool.h"
#include "core/compute.h"
#include "core/config.h"
#include "core/jobs.h"
#include "core/metrics.h"
#include "store/mesh_cache.h"
#include "store/mesh_store.h"
#include "store/scene_cache.h"
#include "store/scene_store.h"

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

/// Bytes of a shared budget held by work in flight (ray batches: their rays and answers); work
/// that does not fit gets 503 before it starts.
class ByteBudget {
public:
    explicit ByteBudget(uint64_t limit) : limit_(limit) {}

    /// Held bytes; given back on destruction.
    class Hold {
    public:
        Hold(ByteBudget& budget, uint64_t bytes) : budget_(&budget), bytes_(bytes) {}
        Hold(Hold&& other) noexcept
            : budget_(std::exchange(other.budget_, nullptr)), bytes_(other.bytes_) {}
        Hold(const Hold&) = delete;
        Hold& operator=(const Hold&) = delete;
        Hold& operator=(Hold&&) = delete;
        ~Hold() {
            if (budget_) budget_->held_.fetch_sub(bytes_);
        }

        /// Holds `more` bytes besides, when they fit next to what is held now (a body whose
        /// size is learnt as it arrives). False, holding what it held, when they do not.
        [[nodiscard]] bool grow(uint64_t more) {
            if (budget_ == nullptr || !budget_->take(more)) return false;
            bytes_ += more;
            return true;
        }
        [[nodiscard]] uint64_t bytes() const noexcept { return bytes_; }

    private:
        ByteBudget* budget_;
        uint64_t bytes_;
    };

    /// `bytes` of the budget, or nullopt when they do not fit next to what is held.
    [[nodiscard]] std::optional<Hold> try_take(uint64_t bytes) {
        if (!take(bytes)) return std::nullopt;
        return Hold(*this, bytes);
    }
    [[nodiscard]] uint64_t held() const noexcept { return held_.load(); }
    [[nodiscard]] uint64_t limit() const noexcept { return limit_; }

private:
    bool take(uint64_t bytes) {
        uint64_t held = held_.load();
        do {
            if (bytes > limit_ || held > limit_ - bytes) return false;
        } while (!held_.compare_exchange_weak(held, held + bytes));
        return true;
    }

    const uint64_t limit_;
    std::atomic<uint64_t> held_{0};
};

/// Admits at most `running` of one kind of expensive work (renders, tree builds) at once; up to
/// `queued` more wait for a slot in arrival order, and the rest are refused at once (503 +
/// Retry-After), so a burst is shed early instead of sharing the cores ever more thinly.
class WorkGate {
public:
    WorkGate(unsigned running, unsigned queued) : running_limit_(running), queue_limit_(queued) {}

    class Slot {
    public:
        explicit Slot(WorkGate& gate) : gate_(&gate) {}
        Slot(Slot&& other) noexcept : gate_(std::exchange(other.gate_, nullptr)) {}
        Slot(const Slot&) = delete;
        Slot& operator=(const Slot&) = delete;
        Slot& operator=(Slot&&) = delete;
        ~Slot() {
            if (gate_) gate_->leave();
        }

    private:
        WorkGate* gate_;
    };

    /// A slot, after waiting in the queue when every slot is taken; nullopt when the queue is
    /// full too, or once `stop` is set (checked while waiting).
    [[nodiscard]] std::optional<Slot> enter(const std::atomic<bool>& stop) {
        std::unique_lock lock(mutex_);
        if (running_ >= running_limit_ || waiting_ > 0) {
            if (waiting_ >= queue_limit_) return std::nullopt;
            ++waiting_;
            const uint64_t ticket = next_ticket_++;
            while (!stop && (running_ >= running_limit_ || ticket != serving_))
                cv_.wait_for(lock, std::chrono::milliseconds(100));
            --waiting_;
            if (stop) return std::nullopt;  // shutting down: every waiter leaves
            ++serving_;
            cv_.notify_all();  // the next ticket may take a slot too
        }
        ++running_;
        return Slot(*this);
    }
    [[nodiscard]] unsigned running() const {
        std::lock_guard lock(mutex_);
        return running_;
    }
    [[nodiscard]] unsigned waiting() const {
        std::lock_guard lock(mutex_);
        return waiting_;
    }
    [[nodiscard]] unsigned running_limit() const noexcept { return running_limit_; }
    [[nodiscard]] unsigned queue_limit() const noexcept { return queue_limit_; }

private:
    void leave() {
        {
            std::lock_guard lock(mutex_);
            --running_;
        }
        cv_.notify_all();
    }

    const unsigned running_limit_, queue_limit_;
    mutable std::mutex mutex_;
    std::condition_variable cv_;
    unsigned running_ = 0, waiting_ = 0;
    uint64_t next_ticket_ = 0, serving_ = 0;  ///< FIFO order of the waiters
};

struct Service {
    explicit Service(ServerConfig cfg);

    const ServerConfig config;
    Metrics metrics;
    Compute compute;
    MeshStore store;
    MeshCache cache;
    SceneStore scene_store;  ///< scenes/ under cache_dir (revision files)
    SceneCache scenes;       ///< built scenes, limits, pose updates
    AdmissionGate gate;
    ByteBudget batch_budget;  ///< bytes of ray batches in flight (batch_memory_budget)
    WorkGate renders;         ///< synchronous renders (max_renders, max_queued)
    WorkGate builds;          ///< mesh uploads: parse and tree build (max_builds, max_queued)
    JobQueue jobs;
    BufferPool batch_buffers;                ///< rays and encoded answers of KDRR batches
    std::atomic<bool> ready{false};          ///< index loaded and preloads done
    std::atomic<bool> shutting_down{false};  ///< SIGTERM/SIGINT received
    RequestRegistry requests;                ///< what each HTTP thread serves now
};

}  // namespace kdrt::server
