#include "core/jobs.h"

#include <random>

#include "core/log.h"
#include "core/rendering.h"

namespace kdrt::server {
namespace {

double unix_now() {
    return std::chrono::duration<double>(std::chrono::system_clock::now().time_since_epoch())
        .count();
}

/// 128 random bits as 32 hex digits: job ids are not guessable.
std::string random_id() {
    static thread_local std::mt19937_64 rng{std::random_device{}() ^
                                            (uint64_t{std::random_device{}()} << 32)};
    static constexpr char kHex[] = "0123456789abcdef";
    std::string id;
    for (int word = 0; word < 2; ++word) {
        uint64_t bits = rng();
        for (int i = 0; i < 16; ++i, bits >>= 4) id.push_back(kHex[bits & 15]);
    }
    return id;
}

}  // namespace

JobQueue::JobQueue(Compute& compute, Metrics& metrics, unsigned max_jobs, unsigned ttl_s,
                   uint64_t max_result_bytes, std::string replica)
    : compute_(compute),
      metrics_(metrics),
      max_jobs_(max_jobs),
      ttl_(ttl_s),
      max_result_bytes_(max_result_bytes),
      id_prefix_(replica.empty() ? std::string() : replica + "."),
      worker_([this] { worker_loop(); }) {
    metrics_.add_collector([this](std::vector<proto::MetricFamily>& out) {
        proto::MetricFamily jobs;
        jobs.name = "kdrt_jobs";
        jobs.help = "Async render jobs waiting in the queue or rendering.";
        jobs.type = proto::MetricType::kGauge;
        jobs.samples = {{{{"state", "queued"}}, static_cast<double>(queued())},
                        {{{"state", "running"}}, static_cast<double>(running())}};
        out.push_back(std::move(jobs));
        proto::MetricFamily finished;
        finished.name = "kdrt_jobs_finished_total";
        finished.help = "Async render jobs finished, by outcome.";
        finished.type = proto::MetricType::kCounter;
        finished.samples = {{{{"outcome", "done"}}, static_cast<double>(done_.load())},
                            {{{"outcome", "failed"}}, static_cast<double>(failed_.load())},
                            {{{"outcome", "cancelled"}}, static_cast<double>(cancelled_.load())}};
        out.push_back(std::move(finished));
        proto::MetricFamily held;
        held.name = "kdrt_job_result_bytes";
        held.help = "Bytes of finished async jobs' images held (at most job_result_bytes).";
        held.type = proto::MetricType::kGauge;
        held.samples = {{{}, static_cast<double>(result_bytes())}};
        out.push_back(std::move(held));
        proto::MetricFamily evicted;
        evicted.name = "kdrt_jobs_evicted_total";
        evicted.help =
            "Finished async jobs forgotten before job_ttl_s to stay within job_result_bytes.";
        evicted.type = proto::MetricType::kCounter;
        evicted.samples = {{{}, static_cast<double>(evicted_.load())}};
        out.push_back(std::move(evicted));
    });
}

JobQueue::~JobQueue() { shutdown(); }

proto::Result<proto::JobStatus, std::string> JobQueue::submit(RenderJob input) {
    std::lock_guard lock(mutex_);
    purge_expired();
    if (stopping_) return proto::Err{std::string("the server is shutting down")};
    if (queue_.size() + running_ >= max_jobs_)
        return proto::Err{std::to_string(max_jobs_) +
                          " render jobs are queued or running (max_jobs)"};
    auto job = std::make_shared<Job>();
    job->status.id = id_prefix_ + random_id();
    job->status.mesh = input.mesh;
    job->status.format = std::string(proto::image_format_name(input.format));
    job->status.created = unix_now();
    job->input = std::move(input);
    jobs_[job->status.id] = job;
    queue_.push_back(job);
    wake_.notify_one();
    return snapshot(*job);
}

std::optional<proto::JobStatus> JobQueue::status(const std::string& id) {
    std::lock_guard lock(mutex_);
    purge_expired();
    const auto it = jobs_.find(id);
    if (it == jobs_.end()) return std::nullopt;
    return snapshot(*it->second);
}

std::optional<JobQueue::Output> JobQueue::output(const std::string& id) {
    std::lock_guard lock(mutex_);
    purge_expired();
    const auto it = jobs_.find(id);
    if (it == jobs_.end()) return std::nullopt;
    const Job& job = *it->second;
    return Output{snapshot(job), job.image, job.input.format, job.input.encode};
}

JobQueue::CancelOutcome JobQueue::cancel(const std::string& id, proto::JobStatus* status_out) {
    std::lock_guard lock(mutex_);
    purge_expired();
    const auto it = jobs_.find(id);
    if (it == jobs_.end()) return CancelOutcome::kUnknown;
    const std::shared_ptr<Job> job = it->second;
    switch (job->status.state) {
        case proto::JobState::kQueued:
            std::erase(queue_, job);
            job->status.state = proto::JobState::kCancelled;
            job->status.cancel_requested = true;
            job->finished_at = std::chrono::steady_clock::now();
            cancelled_.fetch_add(1);
            break;
        case proto::JobState::kRunning:
            job->cancel = true;
            job->status.cancel_requested = true;
            break;
        default:
            jobs_.erase(it);
            return CancelOutcome::kRemoved;
    }
    if (status_out) *status_out = snapshot(*job);
    return CancelOutcome::kCancelling;
}

void JobQueue::shutdown() {
    {
        std::lock_guard lock(mutex_);
        if (stopping_ && !worker_.joinable()) return;
        stopping_ = true;
        for (const auto& [id, job] : jobs_) {
            job->cancel = true;
            if (job->status.state == proto::JobState::kQueued) {
                job->status.state = proto::JobState::kCancelled;
                cancelled_.fetch_add(1);
            }
        }
        queue_.clear();
    }
    wake_.notify_all();
    if (worker_.joinable()) worker_.join();
}

unsigned JobQueue::queued() const {
    std::lock_guard lock(mutex_);
    return static_cast<unsigned>(queue_.size());
}

unsigned JobQueue::running() const {
    std::lock_guard lock(mutex_);
    return running_;
}

uint64_t JobQueue::result_bytes() const {
    std::lock_guard lock(mutex_);
    return held_result_bytes();
}

uint64_t JobQueue::held_result_bytes() const {
    uint64_t bytes = 0;
    for (const auto& [id, job] : jobs_)
        if (job->image) bytes += job->image->size();
    return bytes;
}

void JobQueue::evict_over_budget() {
    uint64_t held = held_result_bytes();
    while (held > max_result_bytes_) {
        auto oldest = jobs_.end();
        for (auto it = jobs_.begin(); it != jobs_.end(); ++it)
            if (it->second->image &&
                (oldest == jobs_.end() || it->second->finished_at < oldest->second->finished_at))
                oldest = it;
        if (oldest == jobs_.end()) return;
        held -= oldest->second->image->size();
        log_event(LogLevel::kInfo, "job evicted",
                  {{"job", oldest->first},
                   {"result_bytes", static_cast<uint64_t>(oldest->second->image->size())},
                   {"reason", std::string_view("job_result_bytes")}});
        jobs_.erase(oldest);
        evicted_.fetch_add(1);
    }
}

void JobQueue::worker_loop() {
    for (;;) {
        std::shared_ptr<Job> job;
        {
            std::unique_lock lock(mutex_);
            wake_.wait(lock, [&] { return stopping_ || !queue_.empty(); });
            if (stopping_) return;
            job = queue_.front();
            queue_.pop_front();
            job->status.state = proto::JobState::kRunning;
            ++running_;
        }
        run(*job);
    }
}

void JobQueue::run(Job& job) {
    const double queued_seconds = unix_now() - job.status.created;
    RenderControl control;
    control.cancel = &job.cancel;
    control.progress = [&job](double share) {
        job.progress.store(share, std::memory_order_relaxed);
    };
    proto::JobState state = proto::JobState::kDone;
    std::string error;
    std::shared_ptr<const std::vector<std::byte>> image;
    std::optional<double> render_ms;
    try {
        auto rendered = render_and_encode(compute_, *job.input.tree, job.input.settings,
                                          job.input.format, job.input.encode, control);
        if (rendered && rendered->bytes.size() > max_result_bytes_) {
            state = proto::JobState::kFailed;
            error = "the image (" + std::to_string(rendered->bytes.size()) +
                    " bytes) is larger than job_result_bytes (" +
                    std::to_string(max_result_bytes_) + ")";
        } else if (rendered) {
            render_ms = rendered->stats.seconds * 1e3;
            metrics_.record_render(rendered->stats.rays, rendered->stats.seconds, queued_seconds);
            image = std::make_shared<const std::vector<std::byte>>(std::move(rendered->bytes));
        } else {
            state = proto::JobState::kFailed;
            error = rendered.error();
        }
    } catch (const RenderCancelled&) {
        state = proto::JobState::kCancelled;
    } catch (const std::exception& e) {
        state = proto::JobState::kFailed;
        error = e.what();
    }
    log_event(state == proto::JobState::kFailed ? LogLevel::kError : LogLevel::kInfo,
              "job finished",
              {{"job", job.status.id},
               {"state", job_state_name(state)},
               {"render_ms", render_ms.value_or(0.0)},
               {"error", error}});
    std::lock_guard lock(mutex_);
    --running_;
    job.status.state = state;
    job.status.error = std::move(error);
    job.status.render_ms = render_ms;
    job.image = std::move(image);
    job.status.result_bytes = job.image ? job.image->size() : 0;
    job.input.tree.reset();  // the job no longer pins the tree
    job.finished_at = std::chrono::steady_clock::now();
    evict_over_budget();
    (state == proto::JobState::kDone     ? done_
     : state == proto::JobState::kFailed ? failed_
                                         : cancelled_)
        .fetch_add(1);
}

void JobQueue::purge_expired() {
    const auto now = std::chrono::steady_clock::now();
    std::erase_if(jobs_, [&](const auto& item) {
        const Job& job = *item.second;
        const bool finished = job.status.state == proto::JobState::kDone ||
                              job.status.state == proto::JobState::kFailed ||
                              job.status.state == proto::JobState::kCancelled;
        return finished && now - job.finished_at > ttl_;
    });
}

proto::JobStatus JobQueue::snapshot(const Job& job) const {
    proto::JobStatus s = job.status;
    s.progress =
        s.state == proto::JobState::kDone ? 1.0 : job.progress.load(std::memory_order_relaxed);
    return s;
}

}  // namespace kdrt::server
