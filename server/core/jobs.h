#pragma once
/// Async render jobs (POST /v1/render with `Prefer: respond-async`): a bounded queue served by
/// one worker thread, which renders inside the compute arena (a render already uses every
/// core). Jobs report progress (0..1), can be cancelled while queued or running, and keep their
/// image for job_ttl_s after they finish, within a byte budget (job_result_bytes): when a new
/// image would take the finished jobs' images over it, the oldest finished jobs are forgotten
/// first (their ids then answer 404, as after job_ttl_s). Thread-safe.

#include <atomic>
#include <chrono>
#include <condition_variable>
#include <cstdint>
#include <deque>
#include <memory>
#include <mutex>
#include <optional>
#include <string>
#include <thread>
#include <unordered_map>
#include <vector>

#include "core/compute.h"
#include "core/metrics.h"
#include "core/rendering.h"
#include "kdrt/kdtree.h"
#include "kdrt/proto/image_format.h"
#include "kdrt/proto/json_api.h"
#include "kdrt/proto/result.h"
#include "kdrt/render.h"

namespace kdrt::server {

class JobQueue {
public:
    /// `max_result_bytes`: the finished jobs' images together (an image larger than this fails
    /// its job).
    /// `replica` (may be empty) prefixes every job id as "<replica>.<32 hex digits>", so a
    /// proxy in front of several replicas can send a job's URLs to the one that runs it.
    JobQueue(Compute& compute, Metrics& metrics, unsigned max_jobs, unsigned ttl_s,
             uint64_t max_result_bytes, std::string replica = {});
    ~JobQueue();
    JobQueue(const JobQueue&) = delete;
    JobQueue& operator=(const JobQueue&) = delete;

    /// Queues `input` as a job; fails (with a reason for the 503 detail) when max_jobs are queued
    /// or running, or after shutdown().
    [[nodiscard]] proto::Result<proto::JobStatus, std::string> submit(RenderJob input);

    [[nodiscard]] std::optional<proto::JobStatus> status(const std::string& id);

    struct Output {
        proto::JobStatus status;
        std::shared_ptr<const std::vector<std::byte>> image;  ///< set when status.state == kDone
        proto::ImageFormat format = proto::ImageFormat::kPng;
        proto::ImageEncodeOptions encode;  ///< the job's PNG level (named by a raw answer)
    };
    [[nodiscard]] std::optional<Output> output(const std::string& id);

    enum class CancelOutcome {
        kUnknown,     ///< no such job
        kCancelling,  ///< it was queued (now cancelled) or running (it stops at the next tile)
        kRemoved,     ///< it had finished; it is forgotten now
    };
    CancelOutcome cancel(const std::string& id, proto::JobStatus* status_out = nullptr);

    /// Cancels every job and stops the worker. Idempotent.
    void shutdown();

    [[nodiscard]] unsigned queued() const;
    [[nodiscard]] unsigned running() const;
    /// Bytes of the finished jobs' images held now.
    [[nodiscard]] uint64_t result_bytes() const;

private:
    struct Job {
        proto::JobStatus status;  ///< guarded by mutex_ (progress comes from `progress`)
        RenderJob input;
        std::atomic<bool> cancel{false};
        std::atomic<double> progress{0};
        std::shared_ptr<const std::vector<std::byte>> image;
        std::chrono::steady_clock::time_point finished_at;
    };

    void worker_loop();
    void run(Job& job);
    void purge_expired();                             // mutex_ held
    void evict_over_budget();                         // mutex_ held
    uint64_t held_result_bytes() const;               // mutex_ held
    proto::JobStatus snapshot(const Job& job) const;  // mutex_ held

    Compute& compute_;
    Metrics& metrics_;
    const unsigned max_jobs_;
    const std::chrono::seconds ttl_;
    const uint64_t max_result_bytes_;
    const std::string id_prefix_;  ///< "<replica>." or empty

    mutable std::mutex mutex_;
    std::condition_variable wake_;
    std::unordered_map<std::string, std::shared_ptr<Job>> jobs_;
    std::deque<std::shared_ptr<Job>> queue_;
    unsigned running_ = 0;
    bool stopping_ = false;
    std::atomic<uint64_t> done_{0}, failed_{0}, cancelled_{0}, evicted_{0};
    std::thread worker_;
};

}  // namespace kdrt::server
