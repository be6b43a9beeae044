// The one traversal of a .gmdag scene corpus, compiled for the host (trace_cpu.cpp) and for the
// device (trace_cuda.cu). Every launcher calls trace_ray / sample_point per ray / point; nothing
// about the algorithm lives anywhere else. docs/SDFDAG_RUNTIME.md describes it, docs/GMDAG.md the data.
//
// Units inside: "voxel space" of the ray's scene, p_vox = (p_world - origin) / voxel_size, so the cube
// is [0, R]^3 and a unit direction stays a unit direction; t is in voxels until it is written out.
// The arithmetic is plain float32 with no fused multiply-add (CPU: -ffp-contract=off, CUDA:
// --fmad=false) so that the CPU, the CUDA build and trace_ref.py take bit-identical steps.
#pragma once

#include <math.h>
#include <stdint.h>
#include <string.h>

#ifdef __CUDACC__
#define NAVI_HD __host__ __device__ __forceinline__
#else
#define NAVI_HD inline
#endif

namespace navi {

constexpr uint32_t kTagNode = 0;
constexpr uint32_t kTagBrick = 1;
constexpr uint32_t kTagFarFree = 2;
constexpr uint32_t kTagFarSolid = 3;
constexpr uint32_t kPayloadMask = 0x3FFFFFFFu;
constexpr int kBrickShift = 3;          // bricks are 8 = 1 << 3 cells per axis
constexpr int kBrickSamples = 729;      // 9^3 corner samples per brick
constexpr int kSceneWords = 16;         // one scene record = 16 x 32-bit words (64 bytes)
constexpr float kFarUnit = 1.0f / 16.0f;  // far-code payload unit, voxels
// Hit epsilon in voxels when the caller passes hit_epsilon <= 0; also the minimum step.
constexpr float kDefaultHitEpsilonVoxels = 0.1f;
constexpr int kRefineIterations = 6;    // bisection halvings after a sign change, then one secant
constexpr float kBig = 3.0e38f;

// Scene record layout (int32 words; float fields hold float32 bits). Mirrored in navi_env/scene.py.
enum SceneWord : int {
  kRoot = 0,          // u32 child word of the root (payload relative to the scene's node offset)
  kNodeOffset = 1,    // u32 first node of the scene in the corpus node buffer
  kBrickOffset = 2,   // u32 first brick of the scene in the corpus brick buffer
  kResolution = 3,    // u32 R
  kLevels = 4,        // u32 L = log2(R / 8)
  kOriginX = 5,       // f32 cube min corner, meters
  kOriginY = 6,
  kOriginZ = 7,
  kVoxelSize = 8,     // f32 h, meters
  kInvVoxelSize = 9,  // f32 1 / h (rounded once from float64)
  kQuantStep = 10,    // f32 voxels per i8 unit
  kBand = 11,         // f32 clamp band, voxels
};

// Arguments of one trace launch; laid out for C callers (ctypes mirror in navi_env/abi.py).
struct TraceArgs {
  const uint32_t* nodes;        // (sum node_count * 8,) child words of every scene
  const int8_t* bricks;         // (sum brick_count * 729,) samples of every scene
  const uint8_t* brick_class;   // (sum brick_count,) class id per brick
  const int32_t* scenes;        // (S, 16) scene records
  const void* scene_ids;        // (B,) int32 or int64
  const float* origins;         // (B, 3) world meters
  const float* directions;      // (R, 3) shared or (B, R, 3) per actor, unit vectors
  const float* yaw;             // (B,) radians about +Z, or null
  const int32_t* ray_order;     // (R,) permutation, or null: thread j of an actor traces ray ray_order[j]
  float* out_depth;             // (B, R) meters
  void* out_semantic;           // (B, R) int32 or uint8, or null
  int32_t* out_steps;           // (B, R) steps taken, or null
  void* stream;                 // cudaStream_t for the CUDA launcher; ignored on the CPU
  int64_t num_actors;           // B
  int64_t num_rays;             // R
  int32_t num_scenes;           // S
  int32_t scene_id_bytes;       // 4 or 8
  int32_t semantic_bytes;       // 0 (no output), 1 or 4
  int32_t directions_shared;    // 1: (R, 3), 0: (B, R, 3)
  int32_t max_steps;            // bound on main-loop samples per ray
  int32_t cpu_threads;          // CPU worker threads (<= 0: hardware concurrency); ignored by CUDA
  int32_t device;               // CUDA device index; ignored on the CPU
  float horizon;                // meters; a miss reports this depth
  float hit_epsilon;            // meters; <= 0 selects kDefaultHitEpsilonVoxels in each scene
  int32_t reserved;             // zero
};

// Arguments of one point-query launch (sample_distance).
struct SampleArgs {
  const uint32_t* nodes;
  const int8_t* bricks;
  const int32_t* scenes;
  const void* scene_ids;        // (N,) int32 or int64
  const float* points;          // (N, 3) world meters
  float* out_distance;          // (N,) meters
  void* stream;
  int64_t num_points;
  int32_t num_scenes;
  int32_t scene_id_bytes;
  int32_t cpu_threads;
  int32_t device;
};

// ---------------------------------------------------------------------------------------------
// Loads (read-only cache on the device).

template <typename T>
NAVI_HD T load_ro(const T* p) {
#ifdef __CUDA_ARCH__
  return __ldg(p);
#else
  return *p;
#endif
}

NAVI_HD float bits_float(int32_t bits) {
#ifdef __CUDA_ARCH__
  return __int_as_float(bits);
#else
  float f;
  memcpy(&f, &bits, sizeof f);
  return f;
#endif
}

NAVI_HD float kNaN() { return bits_float(0x7FC00000); }

NAVI_HD bool finite(float x) { return fabsf(x) <= 3.4028235e38f; }  // false for NaN and +-inf

// A scene record decoded into registers.
struct Scene {
  uint32_t root, node_offset, brick_offset;
  int resolution, levels;
  float ox, oy, oz, voxel, inv_voxel, quant;
};

NAVI_HD Scene load_scene(const int32_t* table, int64_t id) {
  int32_t w[12];
#ifdef __CUDA_ARCH__
  const int4* rec = reinterpret_cast<const int4*>(table + id * kSceneWords);
  const int4 a = __ldg(rec), b = __ldg(rec + 1), c = __ldg(rec + 2);
  w[0] = a.x; w[1] = a.y; w[2] = a.z; w[3] = a.w;
  w[4] = b.x; w[5] = b.y; w[6] = b.z; w[7] = b.w;
  w[8] = c.x; w[9] = c.y; w[10] = c.z; w[11] = c.w;
#else
  for (int k = 0; k < 12; ++k) w[k] = table[id * kSceneWords + k];
#endif
  Scene s;
  s.root = static_cast<uint32_t>(w[kRoot]);
  s.node_offset = static_cast<uint32_t>(w[kNodeOffset]);
  s.brick_offset = static_cast<uint32_t>(w[kBrickOffset]);
  s.resolution = w[kResolution];
  s.levels = w[kLevels];
  s.ox = bits_float(w[kOriginX]);
  s.oy = bits_float(w[kOriginY]);
  s.oz = bits_float(w[kOriginZ]);
  s.voxel = bits_float(w[kVoxelSize]);
  s.inv_voxel = bits_float(w[kInvVoxelSize]);
  s.quant = bits_float(w[kQuantStep]);
  return s;
}

NAVI_HD int64_t load_scene_id(const void* ids, int bytes, int64_t i) {
  if (bytes == 8) return load_ro(static_cast<const int64_t*>(ids) + i);
  return load_ro(static_cast<const int32_t*>(ids) + i);
}

// ---------------------------------------------------------------------------------------------
// Descent and the leaf cache.

// The leaf (brick or far cube) holding a lattice cell: its child word and its cube.
struct Leaf {
  int cx, cy, cz;  // cube min corner, voxels
  int shift;       // log2 of the cube edge, voxels
  uint32_t word;   // child word (tag << 30 | payload), payload relative to the scene offsets
};

// Cell index of a coordinate, clamped to [0, R - 1] in float first (NaN lands on 0).
NAVI_HD int cell_of(float x, int resolution) {
  return static_cast<int>(fminf(fmaxf(floorf(x), 0.0f), static_cast<float>(resolution - 1)));
}

// Bounded stackless descent from the root to the leaf holding cell (ix, iy, iz): at most L loads.
NAVI_HD Leaf descend(const uint32_t* nodes, const Scene& s, int ix, int iy, int iz) {
  uint32_t word = s.root;
  int shift = s.levels + kBrickShift;  // log2 R: the root's cube edge
  while ((word >> 30) == kTagNode && shift > kBrickShift) {
    --shift;
    const uint64_t node = static_cast<uint64_t>(s.node_offset) + (word & kPayloadMask);
    const int child = ((ix >> shift) & 1) | (((iy >> shift) & 1) << 1) | (((iz >> shift) & 1) << 2);
    word = load_ro(nodes + node * 8 + child);
  }
  Leaf leaf;
  leaf.shift = shift;
  leaf.cx = (ix >> shift) << shift;
  leaf.cy = (iy >> shift) << shift;
  leaf.cz = (iz >> shift) << shift;
  leaf.word = word;
  return leaf;
}

NAVI_HD bool leaf_contains(const Leaf& leaf, int ix, int iy, int iz) {
  return ((ix - leaf.cx) >> leaf.shift) == 0 && ((iy - leaf.cy) >> leaf.shift) == 0 &&
         ((iz - leaf.cz) >> leaf.shift) == 0;
}

// Trilinear interpolation inside a brick: cell (i, j, k) in [0, 7]^3 of the brick, fractions in [0, 1].
NAVI_HD float brick_distance(const int8_t* brick, float quant, int i, int j, int k, float fx, float fy, float fz) {
  const int8_t* c = brick + i + 9 * j + 81 * k;
  const float c000 = load_ro(c), c100 = load_ro(c + 1), c010 = load_ro(c + 9), c110 = load_ro(c + 10);
  const float c001 = load_ro(c + 81), c101 = load_ro(c + 82), c011 = load_ro(c + 90), c111 = load_ro(c + 91);
  const float x00 = c000 + fx * (c100 - c000);
  const float x10 = c010 + fx * (c110 - c010);
  const float x01 = c001 + fx * (c101 - c001);
  const float x11 = c011 + fx * (c111 - c011);
  const float y0 = x00 + fy * (x10 - x00);
  const float y1 = x01 + fy * (x11 - x01);
  return (y0 + fz * (y1 - y0)) * quant;
}

NAVI_HD float unit_clamp(float x) { return fminf(fmaxf(x, 0.0f), 1.0f); }

constexpr uint32_t kNoBrick = 0xFFFFFFFFu;

// The field at a voxel-space point p inside the cube whose cell (ix, iy, iz) lies in `leaf`.
// Far codes give their lower bound (negative for solid); `solid` marks a far-solid cube.
struct FieldSample {
  float dist;      // voxels
  bool solid;      // inside a far-solid cube
  bool far_free;   // inside a far-free cube (dist is its lower bound)
  uint32_t brick;  // corpus brick index, or kNoBrick
};

NAVI_HD FieldSample leaf_field(const int8_t* bricks, const Scene& s, const Leaf& leaf, float px, float py, float pz,
                               int ix, int iy, int iz) {
  FieldSample f;
  const uint32_t tag = leaf.word >> 30;
  const uint32_t payload = leaf.word & kPayloadMask;
  f.solid = tag == kTagFarSolid;
  f.far_free = tag != kTagBrick && tag != kTagFarSolid;
  f.brick = kNoBrick;
  if (tag == kTagBrick) {
    f.brick = s.brick_offset + payload;
    const int8_t* brick = bricks + static_cast<uint64_t>(f.brick) * kBrickSamples;
    // The cell lies in this brick, so its local index is in [0, 7]; the fraction is clamped for
    // points on (or, after a forced exit, just outside) the cell's faces.
    f.dist = brick_distance(brick, s.quant, ix - leaf.cx, iy - leaf.cy, iz - leaf.cz,
                            unit_clamp(px - static_cast<float>(ix)), unit_clamp(py - static_cast<float>(iy)),
                            unit_clamp(pz - static_cast<float>(iz)));
  } else if (tag == kTagFarSolid) {
    f.dist = -(static_cast<float>(payload) * kFarUnit);
  } else {
    // Far free; an internal node below the brick level cannot occur in a validated file.
    f.dist = tag == kTagFarFree ? static_cast<float>(payload) * kFarUnit : 0.0f;
  }
  return f;
}

// Per-ray state for the walk: the cached leaf (the macro-cell void cache) and a forced exit cell.
struct Walker {
  Leaf leaf;
  bool cached;
  int force_axis;   // -1, or the axis whose cell index must reach force_cell (after a far skip)
  int force_cell;
  int force_sign;   // +1 or -1: direction along force_axis
};

// Samples the field at voxel-space p, reusing the cached leaf when p's cell lies in it.
NAVI_HD FieldSample walk_sample(const uint32_t* nodes, const int8_t* bricks, const Scene& s, Walker& w, float px,
                                float py, float pz) {
  int ix = cell_of(px, s.resolution), iy = cell_of(py, s.resolution), iz = cell_of(pz, s.resolution);
  if (w.force_axis >= 0) {
    const int c = w.force_axis == 0 ? ix : (w.force_axis == 1 ? iy : iz);
    const int forced = w.force_sign > 0 ? (c > w.force_cell ? c : w.force_cell) : (c < w.force_cell ? c : w.force_cell);
    if (w.force_axis == 0) ix = forced;
    if (w.force_axis == 1) iy = forced;
    if (w.force_axis == 2) iz = forced;
  }
  if (!(w.cached && leaf_contains(w.leaf, ix, iy, iz))) {
    w.leaf = descend(nodes, s, ix, iy, iz);
    w.cached = true;
  }
  return leaf_field(bricks, s, w.leaf, px, py, pz, ix, iy, iz);
}

// ---------------------------------------------------------------------------------------------
// One ray.

// Narrows [t0, t1] to the ray's part inside the slab [0, res] along one axis (inv = 1 / d).
NAVI_HD void clip_slab(float o, float d, float inv, float res, float& t0, float& t1) {
  if (d != 0.0f) {
    const float ta = (0.0f - o) * inv;
    const float tb = (res - o) * inv;
    t0 = fmaxf(t0, fminf(ta, tb));
    t1 = fminf(t1, fmaxf(ta, tb));
  } else if (o < 0.0f || o > res) {
    t1 = -1.0f;
  }
}

// Ray time at which the ray leaves the cube [c, c + edge] along one axis (kBig when parallel).
NAVI_HD float exit_time(float o, float d, float inv, int c, int edge) {
  if (d == 0.0f) return kBig;
  const float bound = static_cast<float>(d > 0.0f ? c + edge : c);
  return (bound - o) * inv;
}

struct RayResult {
  float depth;   // meters
  int32_t semantic;  // 0 miss, 1 + class id on a hit
  int32_t steps;
};

NAVI_HD int32_t class_semantic(const uint8_t* brick_class, uint32_t brick) {
  return brick != kNoBrick ? 1 + static_cast<int32_t>(load_ro(brick_class + brick)) : 1;
}

// One ray in flight: everything the main loop carries from one step to the next.
struct Ray {
  Scene s;
  float ox, oy, oz;          // origin, voxel space
  float dx, dy, dz;          // unit direction
  float inv_x, inv_y, inv_z; // 1 / direction (kBig where 0)
  float eps;                 // hit epsilon, voxels
  float t, t1;               // current time and the clip end (cube exit or horizon), voxels
  float prev_t, prev_d;      // previous sample
  uint32_t last_brick;       // last brick sampled (class of a hit), or kNoBrick
  int64_t out;               // output element b * R + r
  Walker w;
  RayResult res;
  bool done;
};

// Sets up ray r of actor b (writing to element b * R + r); rays that are decided before the first
// sample (bad scene id, non-finite input, missing the cube) come back done.
NAVI_HD Ray start_ray(const TraceArgs& a, int64_t b, int64_t r) {
  Ray ray;
  ray.out = b * a.num_rays + r;
  ray.res.depth = a.horizon;
  ray.res.semantic = 0;
  ray.res.steps = 0;
  ray.done = true;
  const int64_t sid = load_scene_id(a.scene_ids, a.scene_id_bytes, b);
  if (sid < 0 || sid >= a.num_scenes) {
    ray.res.depth = kNaN();
    return ray;
  }
  const Scene s = load_scene(a.scenes, sid);
  ray.s = s;
  const float* dir = a.directions + (a.directions_shared ? r : b * a.num_rays + r) * 3;
  float dx = load_ro(dir), dy = load_ro(dir + 1);
  const float dz = load_ro(dir + 2);
  if (a.yaw != nullptr) {
    const float yaw = load_ro(a.yaw + b);
    const float c = cosf(yaw), sn = sinf(yaw);
    const float rx = c * dx - sn * dy;
    const float ry = sn * dx + c * dy;
    dx = rx;
    dy = ry;
  }
  const float ox = (load_ro(a.origins + b * 3) - s.ox) * s.inv_voxel;
  const float oy = (load_ro(a.origins + b * 3 + 1) - s.oy) * s.inv_voxel;
  const float oz = (load_ro(a.origins + b * 3 + 2) - s.oz) * s.inv_voxel;
  if (!(finite(ox) && finite(oy) && finite(oz) && finite(dx) && finite(dy) && finite(dz))) return ray;
  const float res = static_cast<float>(s.resolution);
  ray.eps = a.hit_epsilon > 0.0f ? a.hit_epsilon * s.inv_voxel : kDefaultHitEpsilonVoxels;

  // Clip the ray to the cube and the horizon (slab test); a ray that misses the cube is a miss.
  ray.inv_x = dx != 0.0f ? 1.0f / dx : kBig;
  ray.inv_y = dy != 0.0f ? 1.0f / dy : kBig;
  ray.inv_z = dz != 0.0f ? 1.0f / dz : kBig;
  float t0 = 0.0f, t1 = a.horizon * s.inv_voxel;
  clip_slab(ox, dx, ray.inv_x, res, t0, t1);
  clip_slab(oy, dy, ray.inv_y, res, t0, t1);
  clip_slab(oz, dz, ray.inv_z, res, t0, t1);
  if (t0 > t1) return ray;
  ray.ox = ox;
  ray.oy = oy;
  ray.oz = oz;
  ray.dx = dx;
  ray.dy = dy;
  ray.dz = dz;
  ray.t = t0;
  ray.t1 = t1;
  ray.prev_t = t0;
  ray.prev_d = 0.0f;
  ray.last_brick = kNoBrick;
  ray.w.cached = false;
  ray.w.force_axis = -1;
  ray.w.force_cell = 0;
  ray.w.force_sign = 1;
  ray.done = false;
  return ray;
}

// One main-loop iteration of sphere tracing (see docs/SDFDAG_RUNTIME.md): sample, hit tests, step.
NAVI_HD void step_ray(const TraceArgs& a, Ray& ray) {
  const Scene& s = ray.s;
  Walker& w = ray.w;
  if (ray.res.steps >= a.max_steps) {
    ray.res.depth = fminf(ray.t * s.voxel, a.horizon);  // out of steps: the distance reached, semantic 0
    ray.done = true;
    return;
  }
  const int step = ray.res.steps;
  ray.res.steps = step + 1;
  const float t = ray.t;
  const float px = ray.ox + t * ray.dx, py = ray.oy + t * ray.dy, pz = ray.oz + t * ray.dz;
  const FieldSample f = walk_sample(a.nodes, a.bricks, s, w, px, py, pz);
  w.force_axis = -1;
  if (f.brick != kNoBrick) ray.last_brick = f.brick;
  if (f.solid || f.dist < 0.0f) {
    float hit = t;
    if (step > 0) {
      // Sign change between prev_t (free) and t (solid): bisect, then one secant step.
      float lo = ray.prev_t, hi = t, flo = ray.prev_d, fhi = f.dist;
      for (int k = 0; k < kRefineIterations; ++k) {
        const float mid = 0.5f * (lo + hi);
        const FieldSample m =
            walk_sample(a.nodes, a.bricks, s, w, ray.ox + mid * ray.dx, ray.oy + mid * ray.dy, ray.oz + mid * ray.dz);
        if (m.brick != kNoBrick) ray.last_brick = m.brick;
        if (m.solid || m.dist < 0.0f) {
          hi = mid;
          fhi = m.dist;
        } else {
          lo = mid;
          flo = m.dist;
        }
      }
      const float denom = flo - fhi;
      hit = denom > 0.0f ? lo + (hi - lo) * (flo / denom) : lo;
    }
    ray.res.depth = hit * s.voxel;
    ray.res.semantic = class_semantic(a.brick_class, ray.last_brick);
    ray.done = true;
    return;
  }
  // Within epsilon of a surface while not moving away from it (a ray leaving the surface it
  // starts on is not stopped by it).
  if (step > 0 && !f.far_free && f.dist < ray.eps && f.dist <= ray.prev_d) {
    ray.res.depth = t * s.voxel;
    ray.res.semantic = class_semantic(a.brick_class, ray.last_brick);
    ray.done = true;
    return;
  }
  float next = t + fmaxf(f.dist, ray.eps);
  if (f.far_free) {
    // Skip the whole far cube: to its exit, or by its lower bound when that is farther. The next
    // sample is forced into the neighbouring cube across the exit face, so rounding cannot stall.
    const int edge = 1 << w.leaf.shift;
    const float tx = exit_time(ray.ox, ray.dx, ray.inv_x, w.leaf.cx, edge);
    const float ty = exit_time(ray.oy, ray.dy, ray.inv_y, w.leaf.cy, edge);
    const float tz = exit_time(ray.oz, ray.dz, ray.inv_z, w.leaf.cz, edge);
    const int axis = (tx <= ty && tx <= tz) ? 0 : (ty <= tz ? 1 : 2);
    const float t_exit = axis == 0 ? tx : (axis == 1 ? ty : tz);
    const float d_axis = axis == 0 ? ray.dx : (axis == 1 ? ray.dy : ray.dz);
    const int cube_min = axis == 0 ? w.leaf.cx : (axis == 1 ? w.leaf.cy : w.leaf.cz);
    next = fmaxf(t + f.dist, t_exit);
    w.force_axis = axis;
    w.force_sign = d_axis > 0.0f ? 1 : -1;
    w.force_cell = d_axis > 0.0f ? cube_min + edge : cube_min - 1;
    if (w.force_cell < 0 || w.force_cell >= s.resolution) {  // left the cube: a miss
      ray.done = true;
      return;
    }
  }
  ray.prev_t = t;
  ray.prev_d = f.dist;
  ray.t = next;
  if (next > ray.t1) ray.done = true;  // past the cube or the horizon: a miss
}

// Writes a finished ray's outputs.
NAVI_HD void finish_ray(const TraceArgs& a, const Ray& ray) {
  a.out_depth[ray.out] = ray.res.depth;
  if (a.semantic_bytes == 4) {
    static_cast<int32_t*>(a.out_semantic)[ray.out] = ray.res.semantic;
  } else if (a.semantic_bytes == 1) {
    static_cast<uint8_t*>(a.out_semantic)[ray.out] =
        static_cast<uint8_t>(ray.res.semantic < 255 ? ray.res.semantic : 255);
  }
  if (a.out_steps != nullptr) a.out_steps[ray.out] = ray.res.steps;
}

// Work item i = b * R + j is ray ray_order[j] (or j) of actor b. The order only decides which rays
// run side by side in a GPU warp (coherent neighbours take similar step counts); results do not
// depend on it.
// Returns false for an out-of-range ray_order entry (the item is skipped).
NAVI_HD bool item_ray(const TraceArgs& a, int64_t i, int64_t& b, int64_t& r) {
  b = i / a.num_rays;
  const int64_t j = i - b * a.num_rays;
  r = a.ray_order != nullptr ? static_cast<int64_t>(load_ro(a.ray_order + j)) : j;
  return r >= 0 && r < a.num_rays;
}

// Traces work item i to the end.
NAVI_HD void trace_ray(const TraceArgs& a, int64_t i) {
  int64_t b, r;
  if (!item_ray(a, i, b, r)) return;
  Ray ray = start_ray(a, b, r);
  while (!ray.done) step_ray(a, ray);
  finish_ray(a, ray);
}

// ---------------------------------------------------------------------------------------------
// One point query: the field in meters (trilinear in bricks, lower bounds in far cubes, the distance
// to the cube outside it).

NAVI_HD void sample_point(const SampleArgs& a, int64_t i) {
  const int64_t sid = load_scene_id(a.scene_ids, a.scene_id_bytes, i);
  if (sid < 0 || sid >= a.num_scenes) {
    a.out_distance[i] = kNaN();
    return;
  }
  const Scene s = load_scene(a.scenes, sid);
  const float px = (load_ro(a.points + i * 3) - s.ox) * s.inv_voxel;
  const float py = (load_ro(a.points + i * 3 + 1) - s.oy) * s.inv_voxel;
  const float pz = (load_ro(a.points + i * 3 + 2) - s.oz) * s.inv_voxel;
  const float res = static_cast<float>(s.resolution);
  const float ex = fmaxf(fmaxf(0.0f - px, px - res), 0.0f);
  const float ey = fmaxf(fmaxf(0.0f - py, py - res), 0.0f);
  const float ez = fmaxf(fmaxf(0.0f - pz, pz - res), 0.0f);
  if (!(finite(px) && finite(py) && finite(pz))) {
    a.out_distance[i] = kNaN();
    return;
  }
  if (ex > 0.0f || ey > 0.0f || ez > 0.0f) {
    a.out_distance[i] = sqrtf(ex * ex + ey * ey + ez * ez) * s.voxel;
    return;
  }
  const int ix = cell_of(px, s.resolution), iy = cell_of(py, s.resolution), iz = cell_of(pz, s.resolution);
  const Leaf leaf = descend(a.nodes, s, ix, iy, iz);
  a.out_distance[i] = leaf_field(a.bricks, s, leaf, px, py, pz, ix, iy, iz).dist * s.voxel;
}

}  // namespace navi
