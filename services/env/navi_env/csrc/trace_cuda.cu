// CUDA launchers: the traversal of gmdag_trace.h on the caller's stream, with the same C signatures
// as the CPU launchers in trace_cpu.cpp. No synchronisation: errors of the launch itself are
// returned; errors of the kernel surface at the caller's next synchronisation.
//
// One thread per work item (ray), 128 threads per block: small blocks free their slot on the SM as
// soon as their slowest ray ends (measured faster than 64, 256 or 512 on an H100, and faster than
// persistent warps refilling lanes from a work counter). At least 9 blocks per SM (ptxas fits the
// kernel in 56 registers, no spills): 4% faster on an H100 than the 64 registers / 8 blocks it picks
// alone; 10 blocks (48 registers) spill and gain less. The grid is 2-d: x walks an actor's rays in
// blocks of 128, y the actors (strided beyond 65,535), so no thread divides to find its actor.
#include <cuda_runtime.h>

#include <cstdint>

#include "gmdag_trace.h"
#include "trace_launch.h"

namespace {

constexpr int kThreads = 128;
constexpr int kMinBlocksPerSm = 9;
// The primitive kernel at 9 blocks too (56 registers, no spill): on an H100 faster than at 8 blocks
// (62 registers): aggressor 512^3, 8,192 agents x 8 primitives, one job: 9.44 against 10.04 ms per
// launch (docs/PERFORMANCE.md, 2026-11-24).
constexpr int kMinBlocksPerSmPrims = 9;
constexpr int kSharedPrims = 64;  // cull-table entries a block holds (1 KiB)

constexpr int64_t kMaxGridY = 65535;

// Plain walk (no primitives in the launch).
__global__ void __launch_bounds__(kThreads, kMinBlocksPerSm) trace_kernel(const navi::TraceArgs a) {
  const int64_t j = static_cast<int64_t>(blockIdx.x) * kThreads + threadIdx.x;
  if (j >= a.num_rays) return;
  for (int64_t b = blockIdx.y; b < a.num_actors; b += gridDim.y) navi::trace_item<false>(a, b, j);
}

// With primitives: every block's rays belong to one actor at a time, so the block builds that actor's
// cull table (navi::actor_prim_cull, one entry per primitive) in shared memory once and each ray tests
// its bounding spheres from there before any exact intersection. Worlds of more than kSharedPrims
// primitives build the table per ray instead. Every thread reaches the barriers (no early return).
__global__ void __launch_bounds__(kThreads, kMinBlocksPerSmPrims) trace_prims_kernel(const navi::TraceArgs a) {
  __shared__ navi::PrimCull cull[kSharedPrims];
  const int64_t j = static_cast<int64_t>(blockIdx.x) * kThreads + threadIdx.x;
  const bool staged = a.prims_per_world <= kSharedPrims;
  for (int64_t b = blockIdx.y; b < a.num_actors; b += gridDim.y) {
    if (staged) {
      __syncthreads();  // the previous actor's rays are done with the table
      for (int k = threadIdx.x; k < a.prims_per_world; k += kThreads) cull[k] = navi::actor_prim_cull(a, b, k);
      __syncthreads();
    }
    if (j < a.num_rays) navi::trace_item<true>(a, b, j, staged ? cull : nullptr);
  }
}

__global__ void __launch_bounds__(kThreads) sample_kernel(const navi::SampleArgs a) {
  const int64_t i = static_cast<int64_t>(blockIdx.x) * kThreads + threadIdx.x;
  if (i < a.num_points) navi::sample_point(a, i);
}

__global__ void __launch_bounds__(kThreads) sweep_kernel(const navi::SweepArgs a) {
  const int64_t i = static_cast<int64_t>(blockIdx.x) * kThreads + threadIdx.x;
  if (i < a.num_items) navi::sweep_item(a, i);
}

int select_device(int device) {
  int current = -1;
  cudaError_t err = cudaGetDevice(&current);
  if (err == cudaSuccess && current != device) err = cudaSetDevice(device);
  return static_cast<int>(err);
}

}  // namespace

extern "C" int navi_trace_cuda(const navi::TraceArgs* args) {
  const int64_t count = args->num_actors * args->num_rays;
  if (count == 0) return 0;
  const int err = select_device(args->device);
  if (err != 0) return err;
  const dim3 grid(static_cast<unsigned>((args->num_rays + kThreads - 1) / kThreads),
                  static_cast<unsigned>(args->num_actors < kMaxGridY ? args->num_actors : kMaxGridY));
  const cudaStream_t stream = static_cast<cudaStream_t>(args->stream);
  if (navi::has_prims(*args)) {
    trace_prims_kernel<<<grid, kThreads, 0, stream>>>(*args);
  } else {
    trace_kernel<<<grid, kThreads, 0, stream>>>(*args);
  }
  return static_cast<int>(cudaGetLastError());
}

extern "C" int navi_sample_cuda(const navi::SampleArgs* args) {
  if (args->num_points == 0) return 0;
  const int err = select_device(args->device);
  if (err != 0) return err;
  const int64_t blocks = (args->num_points + kThreads - 1) / kThreads;
  sample_kernel<<<static_cast<unsigned>(blocks), kThreads, 0, static_cast<cudaStream_t>(args->stream)>>>(*args);
  return static_cast<int>(cudaGetLastError());
}

extern "C" int navi_sweep_cuda(const navi::SweepArgs* args) {
  if (args->num_items == 0) return 0;
  const int err = select_device(args->device);
  if (err != 0) return err;
  const int64_t blocks = (args->num_items + kThreads - 1) / kThreads;
  sweep_kernel<<<static_cast<unsigned>(blocks), kThreads, 0, static_cast<cudaStream_t>(args->stream)>>>(*args);
  return static_cast<int>(cudaGetLastError());
}

extern "C" int navi_trace_args_size() { return static_cast<int>(sizeof(navi::TraceArgs)); }

extern "C" int navi_sample_args_size() { return static_cast<int>(sizeof(navi::SampleArgs)); }

extern "C" int navi_sweep_args_size() { return static_cast<int>(sizeof(navi::SweepArgs)); }

extern "C" const char* navi_cuda_error_string(int code) {
  return cudaGetErrorString(static_cast<cudaError_t>(code));
}
