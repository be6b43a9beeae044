// CUDA launchers: the traversal of gmdag_trace.h on the caller's stream, with the same C signatures
// as the CPU launchers in trace_cpu.cpp. No synchronisation: errors of the launch itself are
// returned; errors of the kernel surface at the caller's next synchronisation.
//
// The launch, and why (the measurements are in docs/PERFORMANCE.md, "Design lessons"):
// - One thread per work item (ray), 128 threads per block: a small block frees its slot on the SM as
//   soon as its slowest ray ends.
// - No lane refill (persistent warps, work counters, chunks of an actor's rays): refilled lanes stop
//   taking the same branches (brick, far cube, leaf lookup) together.
// - At least 12 blocks per SM (40 registers, an 8-byte spill, none of it in the main loop): the walk
//   needs the warps to hide the latency of its texture and leaf-grid reads.
// - A block takes the actor's start (actor_start: frame, scene record) once before its rays, so the
//   compiler keeps the scene's fields, the hit epsilon and the atlas scale in uniform registers; that
//   is what lets 12 blocks fit.
// - The grid is 2-d: x walks an actor's rays in chunks of ray groups, y the actors, so no thread
//   divides to find its actor.
// - Where the launch is large enough (launch_shape), a block traces kGroupsPerBlock consecutive ray
//   groups of one actor: 768 rays, one strip of 16 azimuths by all 48 elevations of the 256 x 48
//   pattern in the tiled order (and in the azimuth-major order). Its warps walk neighbouring directions
//   from one origin in turn and find the strip's bricks and leaf-grid entries in the SM's L1.
// - Smaller launches keep a block per ray group and, above 2,048 actors, trace it for several actors
//   strided by the grid's height (grid_rows): each warp goes on to its next actor without waiting for
//   the block's slowest warp.
#include <cuda_runtime.h>

#include <cstdint>

#include "gmdag_trace.h"
#include "trace_launch.h"

namespace {

constexpr int kThreads = 128;
constexpr int kMinBlocksPerSm = 12;
// The primitive kernel runs 10 blocks per SM (48 registers, no spill in the walk's loop): at K = 8
// primitives it traces faster than at 9 blocks (56 registers).
constexpr int kMinBlocksPerSmPrims = 10;
static_assert(kThreads == navi::kRayGroup, "a CUDA block is one ray group");

constexpr int64_t kMaxGridY = 65535;
// Ray groups per block where the launch has at least kMinStripBlocks blocks with them (about six
// waves of resident blocks on an H100), so that its last wave stays short.
constexpr int64_t kGroupsPerBlock = 6;
constexpr int64_t kMinStripBlocks = 8192;
// Grid rows (grid_rows) where a block traces one ray group: each block traces kActorsPerBlock actors
// where that leaves at least kMinGridRows rows; smaller launches keep one actor per block, so their
// grids stay many waves deep.
constexpr int64_t kActorsPerBlock = 4;
constexpr int64_t kMinGridRows = 2048;

// The grid's height for B actors: min(B, max(kMinGridRows, ceil(B / kActorsPerBlock)), kMaxGridY).
int64_t grid_rows(int64_t actors) {
  const int64_t packed = (actors + kActorsPerBlock - 1) / kActorsPerBlock;
  const int64_t rows = packed > kMinGridRows ? packed : kMinGridRows;
  const int64_t capped = rows < kMaxGridY ? rows : kMaxGridY;
  return actors < capped ? actors : capped;
}

// A trace launch's grid and the ray groups each block traces per actor (`groups`): block (x, y)
// traces groups [x groups, (x + 1) groups) of actors y, y + gridDim.y, ...
struct LaunchShape {
  dim3 grid;
  int groups;
};

LaunchShape launch_shape(int64_t actors, int64_t rays) {
  const int64_t groups = navi::ray_groups(rays);
  const int64_t per_block = groups < kGroupsPerBlock ? groups : kGroupsPerBlock;
  const int64_t columns = (groups + per_block - 1) / per_block;
  const int64_t rows = actors < kMaxGridY ? actors : kMaxGridY;
  if (per_block > 1 && columns * rows >= kMinStripBlocks) {
    return {dim3(static_cast<unsigned>(columns), static_cast<unsigned>(rows)), static_cast<int>(per_block)};
  }
  return {dim3(static_cast<unsigned>(groups), static_cast<unsigned>(grid_rows(actors))), 1};
}

// Block (x, y)'s work items (launch_shape): ray groups [x groups, (x + 1) groups) of actors y,
// y + gridDim.y, ..., each actor's start taken once before its rays.
template <bool kPrims>
__device__ void trace_block(const navi::TraceArgs& a, const navi::PrimTables& t, int groups) {
  for (int64_t b = blockIdx.y; b < a.num_actors; b += gridDim.y) {
    const navi::ActorStart st = navi::actor_start<kPrims>(a, b);
    for (int g = 0; g < groups; ++g) {
      const int64_t j = (static_cast<int64_t>(blockIdx.x) * groups + g) * kThreads + threadIdx.x;
      if (j < a.num_rays) navi::trace_item<kPrims>(a, st, b, j, t);
    }
  }
}

// Plain walk (no primitives in the launch); launch_shape gives the grid and `groups`.
__global__ void __launch_bounds__(kThreads, kMinBlocksPerSm) trace_kernel(const navi::TraceArgs a, int groups) {
  trace_block<false>(a, navi::PrimTables{}, groups);
}

// The launch's primitive tables (primitives.h, "Per-launch primitive tables"), then the rays.
// Group g's cone: one block of kRayGroup threads, one item each; a block reduction of the directions'
// sum (the axis), then of the widest angle from it.
__global__ void __launch_bounds__(kThreads) cone_kernel(const navi::TraceArgs a, const navi::PrimTables t) {
  __shared__ float part[4][kThreads / 32];
  const int64_t j = static_cast<int64_t>(blockIdx.x) * kThreads + threadIdx.x;
  const int lane = threadIdx.x % 32, warp = threadIdx.x / 32;
  navi::Vec3 d = navi::v3(0.0f, 0.0f, 0.0f);
  const bool ok = navi::item_direction(a, j, d);
  const float n = ok ? sqrtf(navi::dot(d, d)) : 1.0f;
  float v[3] = {ok ? d.x / n : 0.0f, ok ? d.y / n : 0.0f, ok ? d.z / n : 0.0f};
  for (int c = 0; c < 3; ++c) {
    for (int off = 16; off > 0; off /= 2) v[c] += __shfl_xor_sync(0xffffffffu, v[c], off);
    if (lane == 0) part[c][warp] = v[c];
  }
  __syncthreads();
  navi::Vec3 sum = navi::v3(0.0f, 0.0f, 0.0f);
  for (int w = 0; w < kThreads / 32; ++w) sum = navi::v3(sum.x + part[0][w], sum.y + part[1][w], sum.z + part[2][w]);
  float widest = ok ? navi::angle_between(sum, d) : 0.0f;
  for (int off = 16; off > 0; off /= 2) widest = fmaxf(widest, __shfl_xor_sync(0xffffffffu, widest, off));
  if (lane == 0) part[3][warp] = widest;
  __syncthreads();
  if (threadIdx.x == 0) {
    for (int w = 0; w < kThreads / 32; ++w) widest = fmaxf(widest, part[3][w]);
    t.cones[blockIdx.x] = navi::make_cone(sum, widest);
  }
}

__global__ void __launch_bounds__(kThreads) cull_table_kernel(const navi::TraceArgs a, const navi::PrimTables t) {
  const int64_t i = static_cast<int64_t>(blockIdx.x) * kThreads + threadIdx.x;
  const int64_t k = a.prims_per_world;
  if (i < a.num_actors * k) t.table[i] = navi::actor_prim_cull(a, i / k, static_cast<int32_t>(i % k));
}

__global__ void __launch_bounds__(kThreads) mask_kernel(const navi::TraceArgs a, const navi::PrimTables t) {
  const int64_t i = static_cast<int64_t>(blockIdx.x) * kThreads + threadIdx.x;
  const int64_t groups = navi::ray_groups(a.num_rays);
  if (i < a.num_actors * groups) t.masks[i] = navi::group_mask(a, t, i / groups, i % groups);
}

// With primitives, the same schedule: a block traces whole ray groups, so the rays of each share one
// mask word.
__global__ void __launch_bounds__(kThreads, kMinBlocksPerSmPrims)
    trace_prims_kernel(const navi::TraceArgs a, const navi::PrimTables t, int groups) {
  trace_block<true>(a, t, groups);
}

// Each actor's origin sample (ray_walk.h, "The origin sample"), before the rays.
__global__ void __launch_bounds__(kThreads) origin_kernel(const navi::TraceArgs a) {
  const int64_t b = static_cast<int64_t>(blockIdx.x) * kThreads + threadIdx.x;
  if (b < a.num_actors) static_cast<navi::OriginSample*>(a.origin_scratch)[b] = navi::origin_sample(a, b);
}

__global__ void __launch_bounds__(kThreads) sample_kernel(const navi::SampleArgs a) {
  const int64_t i = static_cast<int64_t>(blockIdx.x) * kThreads + threadIdx.x;
  if (i < a.num_points) navi::sample_point(a, i);
}

__global__ void __launch_bounds__(kThreads) sweep_kernel(const navi::SweepArgs a) {
  const int64_t i = static_cast<int64_t>(blockIdx.x) * kThreads + threadIdx.x;
  if (i < a.num_items) navi::sweep_item(a, i);
}

unsigned blocks_for(int64_t items) { return static_cast<unsigned>((items + kThreads - 1) / kThreads); }

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
  const LaunchShape shape = launch_shape(args->num_actors, args->num_rays);
  const cudaStream_t stream = static_cast<cudaStream_t>(args->stream);
  if (args->origin_scratch != nullptr) origin_kernel<<<blocks_for(args->num_actors), kThreads, 0, stream>>>(*args);
  if (navi::has_prims(*args)) {
    const navi::TraceArgs& a = *args;
    if (a.prim_scratch == nullptr || a.prim_scratch_bytes < navi::prim_scratch_bytes(a)) {
      return static_cast<int>(cudaErrorInvalidValue);
    }
    const navi::PrimTables t = navi::prim_tables(a);
    const int64_t groups = navi::ray_groups(a.num_rays);
    if (t.cones != nullptr) cone_kernel<<<static_cast<unsigned>(groups), kThreads, 0, stream>>>(a, t);
    cull_table_kernel<<<blocks_for(a.num_actors * a.prims_per_world), kThreads, 0, stream>>>(a, t);
    if (t.masks != nullptr) mask_kernel<<<blocks_for(a.num_actors * groups), kThreads, 0, stream>>>(a, t);
    trace_prims_kernel<<<shape.grid, kThreads, 0, stream>>>(a, t, shape.groups);
  } else {
    trace_kernel<<<shape.grid, kThreads, 0, stream>>>(*args, shape.groups);
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

// The brick atlas of a corpus (scene.py `brick_atlas`): a w x h x d texel 3-d array of signed bytes,
// copied from host memory laid out [z][y][x], read through a texture object with linear filtering,
// clamped addressing, unnormalised coordinates and normalised float reads (sample / 127). Writes the
// texture object and the array handle (both needed by navi_atlas_destroy_cuda); synchronous.
extern "C" int navi_atlas_create_cuda(const int8_t* host, int64_t w, int64_t h, int64_t d, int device,
                                      uint64_t* tex_out, void** array_out) {
  *tex_out = 0;
  *array_out = nullptr;
  int err = select_device(device);
  if (err != 0) return err;
  const cudaChannelFormatDesc desc = cudaCreateChannelDesc<signed char>();
  cudaArray_t array = nullptr;
  cudaError_t e = cudaMalloc3DArray(&array, &desc, make_cudaExtent(w, h, d));
  if (e != cudaSuccess) return static_cast<int>(e);
  cudaMemcpy3DParms copy = {};
  copy.srcPtr = make_cudaPitchedPtr(const_cast<int8_t*>(host), w, w, h);
  copy.dstArray = array;
  copy.extent = make_cudaExtent(w, h, d);
  copy.kind = cudaMemcpyHostToDevice;
  e = cudaMemcpy3D(&copy);
  cudaResourceDesc res = {};
  res.resType = cudaResourceTypeArray;
  res.res.array.array = array;
  cudaTextureDesc td = {};
  for (int axis = 0; axis < 3; ++axis) td.addressMode[axis] = cudaAddressModeClamp;
  td.filterMode = cudaFilterModeLinear;
  td.readMode = cudaReadModeNormalizedFloat;
  td.normalizedCoords = 0;
  cudaTextureObject_t tex = 0;
  if (e == cudaSuccess) e = cudaCreateTextureObject(&tex, &res, &td, nullptr);
  if (e != cudaSuccess) {
    cudaFreeArray(array);
    return static_cast<int>(e);
  }
  *tex_out = static_cast<uint64_t>(tex);
  *array_out = array;
  return 0;
}

// Frees what navi_atlas_create_cuda made (after the device's pending work that may read it).
extern "C" int navi_atlas_destroy_cuda(uint64_t tex, void* array, int device) {
  int err = select_device(device);
  if (err != 0) return err;
  cudaError_t e = cudaDeviceSynchronize();
  if (tex != 0) {
    const cudaError_t e2 = cudaDestroyTextureObject(static_cast<cudaTextureObject_t>(tex));
    if (e == cudaSuccess) e = e2;
  }
  if (array != nullptr) {
    const cudaError_t e3 = cudaFreeArray(static_cast<cudaArray_t>(array));
    if (e == cudaSuccess) e = e3;
  }
  return static_cast<int>(e);
}

extern "C" int navi_trace_args_size() { return static_cast<int>(sizeof(navi::TraceArgs)); }

extern "C" int navi_sample_args_size() { return static_cast<int>(sizeof(navi::SampleArgs)); }

extern "C" int navi_sweep_args_size() { return static_cast<int>(sizeof(navi::SweepArgs)); }

extern "C" int navi_origin_sample_size() { return static_cast<int>(sizeof(navi::OriginSample)); }

extern "C" const char* navi_cuda_error_string(int code) {
  return cudaGetErrorString(static_cast<cudaError_t>(code));
}
