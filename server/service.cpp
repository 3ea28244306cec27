#include "service.h"

namespace kdrt::server {

Service::Service(ServerConfig cfg)
    : config(std::move(cfg)),
      // Every HTTP thread, the job thread and the start-up loader may call into the arena.
      compute(config.threads, config.http_threads + 2),
      store(config.cache_dir),
      cache(store, compute, metrics, config.memory_budget),
      scene_store(config.cache_dir, store.tmp_dir(), config.scene_revisions_kept),
      scenes(
          scene_store, cache, compute, metrics,
          SceneCacheOptions{config.max_instances, config.max_scenes, config.scene_memory_budget}),
      gate(config.max_inflight),
      batch_budget(config.batch_memory_budget),
      renders(config.max_renders, config.max_queued),
      builds(config.max_builds, config.max_queued),
      jobs(compute, metrics, config.max_jobs, config.job_ttl_s, config.job_result_bytes,
           config.replica),
      batch_buffers(config.buffer_pool_bytes) {
    metrics.add_collector([this](std::vector<proto::MetricFamily>& out) {
        using proto::MetricType;
        const auto gauge = [&](const char* name, const char* help, proto::MetricLabels labels,
                               double value) {
            if (out.empty() || out.back().name != name) {
                proto::MetricFamily f;
                f.name = name;
                f.help = help;
                f.type = MetricType::kGauge;
                out.push_back(std::move(f));
            }
            out.back().samples.push_back({std::move(labels), value});
        };
        const char* bytes_help =
            "Bytes of the mesh cache, in memory (resident trees, the surface indexes of "
            "distance queries and the hit clearances of scene scans) and on disk (meshes, trees, "
            "summaries).";
        gauge("kdrt_cache_bytes", bytes_help, {{"where", "memory"}},
              static_cast<double>(cache.memory_bytes()));
        gauge("kdrt_cache_bytes", bytes_help, {{"where", "disk"}},
              static_cast<double>(cache.disk_bytes()));
        gauge("kdrt_cache_budget_bytes",
              "Configured memory budget for trees and their surface indexes and clearances.", {},
              static_cast<double>(config.memory_budget));
        gauge("kdrt_cache_meshes", "Stored meshes, and how many have their tree in memory.",
              {{"state", "stored"}}, static_cast<double>(cache.mesh_count()));
        gauge("kdrt_cache_meshes", "Stored meshes, and how many have their tree in memory.",
              {{"state", "resident"}}, static_cast<double>(cache.resident_count()));
        gauge("kdrt_store_damaged_meshes",
              "Acknowledged meshes whose mesh file and tree are both damaged (not served until "
              "uploaded again).",
              {}, static_cast<double>(cache.damaged_count()));
        gauge("kdrt_scenes", "Stored scenes, and how many built revisions are in memory.",
              {{"state", "stored"}}, static_cast<double>(scenes.scene_count()));
        gauge("kdrt_scenes", "Stored scenes, and how many built revisions are in memory.",
              {{"state", "resident"}}, static_cast<double>(scenes.resident_count()));
        gauge("kdrt_scene_bytes",
              "Bytes of built scenes in memory (at most scene_memory_budget; their meshes' trees "
              "are in kdrt_cache_bytes).",
              {}, static_cast<double>(scenes.memory_bytes()));
        gauge("kdrt_inflight_requests", "Uploads, traces and renders in flight.", {},
              static_cast<double>(gate.in_flight()));
        gauge("kdrt_batch_bytes", "Bytes of ray batches in flight (at most batch_memory_budget).",
              {}, static_cast<double>(batch_budget.held()));
        gauge("kdrt_work_slots", "Renders and builds running and waiting for a slot.",
              {{"work", "render"}, {"state", "running"}}, static_cast<double>(renders.running()));
        gauge("kdrt_work_slots", "Renders and builds running and waiting for a slot.",
              {{"work", "render"}, {"state", "waiting"}}, static_cast<double>(renders.waiting()));
        gauge("kdrt_work_slots", "Renders and builds running and waiting for a slot.",
              {{"work", "build"}, {"state", "running"}}, static_cast<double>(builds.running()));
        gauge("kdrt_work_slots", "Renders and builds running and waiting for a slot.",
              {{"work", "build"}, {"state", "waiting"}}, static_cast<double>(builds.waiting()));
        gauge("kdrt_buffer_pool_bytes",
              "Idle batch buffers kept for reuse (at most buffer_pool_bytes).", {},
              static_cast<double>(batch_buffers.idle_bytes()));
        gauge("kdrt_engine_threads", "Threads of the tracing/build arena.", {},
              static_cast<double>(compute.threads()));
        gauge("kdrt_ready", "1 when /readyz answers 200.", {}, ready && !shutting_down ? 1.0 : 0.0);
    });
}

}  // namespace kdrt::server
