// CUDA launchers: the traversal of gmdag_trace.h on the caller's stream, with the same C signatures
// as the CPU launchers in trace_cpu.cpp. No synchronisation: errors of the launch itself are
// returned; errors of the kernel surface at the caller's next synchronisation.
//
// One thread per work item (ray), 128 threads per block: small blocks free their slot on the SM as
// soon as their slowest ray ends (measured faster than 256 or 512 on an H100, and faster than
// persistent warps refilling lanes from a work counter).
#include <cuda_runtime.h>

#include <cstdint>

#include "gmdag_trace.h"
#include "trace_launch.h"

namespace {

constexpr int kThreads = 128;

__global__ void __launch_bounds__(kThreads) trace_kernel(const navi::TraceArgs a) {
  const int64_t i = static_cast<int64_t>(blockIdx.x) * kThreads + threadIdx.x;
  if (i < a.num_actors * a.num_rays) navi::trace_ray(a, i);
}

__global__ void __launch_bounds__(kThreads) sample_kernel(const navi::SampleArgs a) {
  const int64_t i = static_cast<int64_t>(blockIdx.x) * kThreads + threadIdx.x;
  if (i < a.num_points) navi::sample_point(a, i);
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
  const int64_t blocks = (count + kThreads - 1) / kThreads;
  trace_kernel<<<static_cast<unsigned>(blocks), kThreads, 0, static_cast<cudaStream_t>(args->stream)>>>(*args);
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

extern "C" int navi_trace_args_size() { return static_cast<int>(sizeof(navi::TraceArgs)); }

extern "C" int navi_sample_args_size() { return static_cast<int>(sizeof(navi::SampleArgs)); }

extern "C" const char* navi_cuda_error_string(int code) {
  return cudaGetErrorString(static_cast<cudaError_t>(code));
}
