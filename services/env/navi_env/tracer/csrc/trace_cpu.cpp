// CPU launchers: the traversal of gmdag_trace.h over worker threads. Same C signatures as the CUDA
// launchers in trace_cuda.cu (one argument struct each).
#include <algorithm>
#include <atomic>
#include <cstdint>
#include <exception>
#include <thread>
#include <vector>

#include "gmdag_trace.h"
#include "trace_launch.h"

namespace {

constexpr int64_t kChunk = 1024;  // rays (or points) per unit of work handed to a thread
constexpr int kErrThreads = 1;    // a worker thread could not start
constexpr int kErrScratch = 2;    // prim_scratch missing or smaller than navi::prim_scratch_bytes

// Runs body(i) for i in [0, count) on up to `threads` threads, chunk by chunk.
template <typename Body>
int parallel_for(int64_t count, int32_t threads, const Body& body) {
  const int64_t chunks = (count + kChunk - 1) / kChunk;
  int64_t workers = threads > 0 ? threads : static_cast<int64_t>(std::thread::hardware_concurrency());
  workers = std::max<int64_t>(1, std::min(workers, chunks));
  std::atomic<int64_t> next{0};
  auto run = [&]() {
    for (int64_t c = next.fetch_add(1); c < chunks; c = next.fetch_add(1)) {
      const int64_t end = std::min(count, (c + 1) * kChunk);
      for (int64_t i = c * kChunk; i < end; ++i) body(i);
    }
  };
  try {
    std::vector<std::thread> pool;
    pool.reserve(static_cast<size_t>(workers - 1));
    for (int64_t k = 1; k < workers; ++k) pool.emplace_back(run);
    run();
    for (std::thread& th : pool) th.join();
  } catch (const std::exception&) {
    return kErrThreads;
  }
  return 0;
}

}  // namespace

extern "C" int navi_trace_cpu(const navi::TraceArgs* args) {
  const navi::TraceArgs a = *args;
  const int64_t items = a.num_actors * a.num_rays;
  if (a.origin_scratch != nullptr && items > 0) {
    auto* origins = static_cast<navi::OriginSample*>(a.origin_scratch);
    const int err = parallel_for(a.num_actors, a.cpu_threads, [&](int64_t b) { origins[b] = navi::origin_sample(a, b); });
    if (err != 0) return err;
  }
  if (navi::has_prims(a)) {
    if (a.prim_scratch == nullptr || a.prim_scratch_bytes < navi::prim_scratch_bytes(a)) return kErrScratch;
    const navi::PrimTables t = navi::prim_tables(a);
    const int64_t k = a.prims_per_world, groups = navi::ray_groups(a.num_rays);
    int err = 0;
    if (t.cones != nullptr) {
      err |= parallel_for(groups, a.cpu_threads, [&](int64_t g) { t.cones[g] = navi::group_cone(a, g); });
    }
    err |= parallel_for(a.num_actors * k, a.cpu_threads, [&](int64_t i) {
      t.table[i] = navi::actor_prim_cull(a, i / k, static_cast<int32_t>(i % k));
    });
    if (t.masks != nullptr) {
      err |= parallel_for(a.num_actors * groups, a.cpu_threads,
                          [&](int64_t i) { t.masks[i] = navi::group_mask(a, t, i / groups, i % groups); });
    }
    err |= parallel_for(items, a.cpu_threads, [&](int64_t i) {
      const int64_t b = i / a.num_rays;
      navi::trace_item<true>(a, navi::actor_start<true>(a, b), b, i - b * a.num_rays, t);
    });
    return err;
  }
  const navi::PrimTables none{};
  return parallel_for(items, a.cpu_threads, [&](int64_t i) {
    const int64_t b = i / a.num_rays;
    navi::trace_item<false>(a, navi::actor_start<false>(a, b), b, i - b * a.num_rays, none);
  });
}

extern "C" int navi_sample_cpu(const navi::SampleArgs* args) {
  const navi::SampleArgs a = *args;
  return parallel_for(a.num_points, a.cpu_threads, [&a](int64_t i) { navi::sample_point(a, i); });
}

extern "C" int navi_sweep_cpu(const navi::SweepArgs* args) {
  const navi::SweepArgs a = *args;
  return parallel_for(a.num_items, a.cpu_threads, [&a](int64_t i) { navi::sweep_item(a, i); });
}

extern "C" int navi_trace_args_size() { return static_cast<int>(sizeof(navi::TraceArgs)); }

extern "C" int navi_sample_args_size() { return static_cast<int>(sizeof(navi::SampleArgs)); }

extern "C" int navi_sweep_args_size() { return static_cast<int>(sizeof(navi::SweepArgs)); }

extern "C" int navi_origin_sample_size() { return static_cast<int>(sizeof(navi::OriginSample)); }
