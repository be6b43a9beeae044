// The launchers' argument structs (TraceArgs, SampleArgs, SweepArgs): the C ABI of every launcher,
// CPU and CUDA. The ctypes mirrors in abi.py repeat them field by field; a build's sizes are checked
// against them at load (navi_*_args_size), their field order is not, so it changes in both or neither.
#pragma once

#include <stdint.h>

namespace navi {

// Arguments of one trace launch; laid out for C callers (ctypes mirror in navi_env/tracer/abi.py).
struct TraceArgs {
  const uint32_t* nodes;        // (sum node_count * 8,) child words of every scene
  const uint32_t* grid;         // (sum 8^D,) leaf-grid entries of every scene
  const uint32_t* bricks;       // (sum brick_count * 576,) corner words of every scene (CPU build)
  const uint8_t* brick_class;   // (sum brick_count,) class id per brick
  const int32_t* scenes;        // (S, 16) scene records
  const void* scene_ids;        // (B,) int32 or int64
  const float* origins;         // (B, 3) world meters
  const float* directions;      // (R, 3) shared or (B, R, 3) per actor, unit vectors
  const float* yaw;             // (B,) radians about +Z, or null
  const int32_t* ray_order;     // (R,) permutation, or null: item j of an actor traces ray ray_order[j]
  float* out_depth;             // (B, R) meters
  void* out_semantic;           // (B, R) int32 or uint8, or null
  int32_t* out_steps;           // (B, R) steps taken, or null
  void* stream;                 // cudaStream_t for the CUDA launcher; ignored on the CPU
  const float* prims;           // (W, K, 16) dynamic primitive records (see PrimWord), or null
  const int32_t* prim_world;    // (B,) world of each actor's primitives, or null: actor b uses world b
  void* prim_scratch;           // prim_scratch_bytes() of device memory the launch may overwrite (with prims)
  uint64_t brick_atlas;         // cudaTextureObject_t of the brick atlas (CUDA build; scene.py BrickAtlas)
  int64_t num_actors;           // B
  int64_t num_rays;             // R
  int64_t prim_scratch_bytes;   // size of prim_scratch
  int32_t num_scenes;           // S
  int32_t scene_id_bytes;       // 4 or 8
  int32_t semantic_bytes;       // 0 (no output), 1 or 4
  int32_t directions_shared;    // 1: (R, 3), 0: (B, R, 3)
  int32_t max_steps;            // bound on main-loop samples per ray
  int32_t cpu_threads;          // CPU worker threads (<= 0: hardware concurrency); ignored by CUDA
  int32_t device;               // CUDA device index; ignored on the CPU
  float horizon;                // meters; a miss reports this depth
  float hit_epsilon;            // meters; <= 0 selects kDefaultHitEpsilonVoxels in each scene
  int32_t prims_per_world;      // K (0: no primitives)
  int32_t num_worlds;           // W; an actor whose world is outside [0, W) sees no primitive
  float hit_slope;              // >= 0: the hit threshold at distance t is epsilon + hit_slope * t
  int32_t atlas_shift;          // log2 of the bricks per atlas row and per atlas column (CUDA build)
  void* origin_scratch;         // (B,) OriginSample the launch fills before its rays, or null (each ray
                                // takes its first sample itself; same results)
};

// Arguments of one point-query launch (sample_distance).
struct SampleArgs {
  const uint32_t* nodes;
  const uint32_t* grid;
  const uint32_t* bricks;
  const int32_t* scenes;
  const void* scene_ids;        // (N,) int32 or int64
  const float* points;          // (N, 3) world meters
  float* out_distance;          // (N,) meters
  void* stream;
  const float* prims;           // (W, K, 16) primitive records, or null
  const int32_t* prim_world;    // (N,) world of each point (required with prims)
  const int32_t* prim_owner;    // (N,) primitive owner to leave out at each point (a drone itself), or null
  uint64_t brick_atlas;         // as in TraceArgs
  int64_t num_points;
  int32_t num_scenes;
  int32_t scene_id_bytes;
  int32_t cpu_threads;
  int32_t device;
  int32_t prims_per_world;      // K
  int32_t num_worlds;           // W
  int32_t atlas_shift;          // as in TraceArgs
};

// Arguments of one obstacle sweep launch (navi_env.sim.obstacles.sweep).
struct SweepArgs {
  const float* prims;           // (N, K, 16) primitive records at the start of the step
  const float* delta;           // (N, K, 3) each primitive's translation this step, meters
  const float* drone;           // (N, 3) drone centres, meters
  float* out_t;                 // (N, K) fraction of delta the primitive may move, in [0, 1]
  float* out_distance;          // (N, K) its distance from the drone centre there (+inf: empty slot)
  void* stream;                 // cudaStream_t for the CUDA launcher; ignored on the CPU
  int64_t num_items;            // N * K
  int32_t prims_per_actor;      // K
  int32_t iterations;           // march steps
  int32_t cpu_threads;          // CPU worker threads (<= 0: hardware concurrency); ignored by CUDA
  int32_t device;               // CUDA device index; ignored on the CPU
  float radius;                 // drone radius, meters
  float skin;                   // meters the march keeps between a primitive and the drone sphere
};

}  // namespace navi
