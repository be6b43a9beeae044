// The one traversal of a .gmdag scene corpus, compiled for the host (trace_cpu.cpp) and for the
// device (trace_cuda.cu). Every launcher calls trace_item / sample_point per ray / point; nothing
// about the algorithm lives anywhere else. docs/SDFDAG_RUNTIME.md describes it, docs/GMDAG.md the
// file, navi_env/scene.py the runtime layout built from it (leaf grid, corner-word bricks).
//
// Units inside: "voxel space" of the ray's scene, p_vox = (p_world - origin) / voxel_size, so the cube
// is [0, R]^3 and a unit direction stays a unit direction; t is in voxels until it is written out.
// The arithmetic is plain float32. The CPU build has no fused multiply-add (-ffp-contract=off) and
// takes bit-identical steps to trace_ref.py; where the device takes a cheaper route to the same value
// (floor through a rounding add, int8 to float through a byte permute) the result is exact, so that
// changes nothing. The CUDA build contracts a * b + c into fused multiply-adds (--fmad=true, ~3%
// faster), which moves positions and distances by an ulp: CUDA agrees with the CPU to a tolerance
// (docs/SDFDAG_RUNTIME.md, "Determinism"), not bit for bit.
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
constexpr int kBrickWords = 576;        // runtime brick: 8 x 8 x 9 corner words (scene.py)
constexpr int kSceneWords = 16;         // one scene record = 16 x 32-bit words (64 bytes)
constexpr float kFarUnit = 1.0f / 16.0f;  // far-code payload unit, voxels
// Hit epsilon in voxels when the caller passes hit_epsilon <= 0; also the minimum step.
constexpr float kDefaultHitEpsilonVoxels = 0.1f;
constexpr int kRefineIterations = 6;    // bisection halvings after a sign change, then one secant
constexpr float kSecantReach = 16.0f;   // a stop within the threshold reports the secant's zero, at most this many d ahead
constexpr float kBig = 3.0e38f;
// Leaf-grid entries: tag (bits 31-30) | log2 cube edge (bits 29-26) | payload (bits 25-0).
constexpr int kGridShiftBit = 26;
constexpr uint32_t kGridPayloadMask = 0x03FFFFFFu;
// Float tricks, exact for the integers they are used on (0 <= n < 2^23).
constexpr float kTwo23 = 8388608.0f;           // 2^23: float bits 0x4B000000 + n encode 2^23 + n
constexpr int32_t kTwo23Bits = 0x4B000000;
constexpr float kSampleBias = 8388736.0f;      // 2^23 + 128: corner bytes hold sample + 128

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
  kGridOffset = 12,   // u32 first entry of the scene's leaf grid in the corpus grid buffer
  kGridDepth = 13,    // u32 D = min(L, 7): the grid has 2^D cells per axis
};

// Arguments of one trace launch; laid out for C callers (ctypes mirror in navi_env/abi.py).
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

// Arguments of one obstacle sweep launch (navi_env.obstacle_motion.sweep).
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

// ---------------------------------------------------------------------------------------------
// Loads (read-only cache on the device) and exact float helpers.

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

NAVI_HD int32_t float_bits(float f) {
#ifdef __CUDA_ARCH__
  return __float_as_int(f);
#else
  int32_t bits;
  memcpy(&bits, &f, sizeof bits);
  return bits;
#endif
}

NAVI_HD float kNaN() { return bits_float(0x7FC00000); }

NAVI_HD bool finite(float x) { return fabsf(x) <= 3.4028235e38f; }  // false for NaN and +-inf

// A scene record decoded into registers. It keeps only what the walk reads, combined once: the grid
// shift instead of L, and no R - 1 as a float (cell_max, recomputed on the rare clamped path). With L
// and R - 1 held, the device code spilled L and reloaded it from local memory on every leaf change,
// ahead of the grid load; without them the main loop runs in 48 registers with no local memory
// access (stop 36: +1.0-2.1% on all 50 OpenArena maps, bit-identical).
struct Scene {
  uint32_t root, node_offset, brick_offset, grid_offset;
  int resolution;
  int grid_depth;  // D
  int grid_shift;  // log2 of a grid cell's edge in voxels: L + 3 - D
  float ox, oy, oz, voxel, inv_voxel, quant;
};

NAVI_HD Scene load_scene(const int32_t* table, int64_t id) {
  int32_t w[16];
#ifdef __CUDA_ARCH__
  const int4* rec = reinterpret_cast<const int4*>(table + id * kSceneWords);
  const int4 a = __ldg(rec), b = __ldg(rec + 1), c = __ldg(rec + 2), d = __ldg(rec + 3);
  w[0] = a.x; w[1] = a.y; w[2] = a.z; w[3] = a.w;
  w[4] = b.x; w[5] = b.y; w[6] = b.z; w[7] = b.w;
  w[8] = c.x; w[9] = c.y; w[10] = c.z; w[11] = c.w;
  w[12] = d.x; w[13] = d.y; w[14] = d.z; w[15] = d.w;
#else
  for (int k = 0; k < 16; ++k) w[k] = table[id * kSceneWords + k];
#endif
  Scene s;
  s.root = static_cast<uint32_t>(w[kRoot]);
  s.node_offset = static_cast<uint32_t>(w[kNodeOffset]);
  s.brick_offset = static_cast<uint32_t>(w[kBrickOffset]);
  s.grid_offset = static_cast<uint32_t>(w[kGridOffset]);
  s.resolution = w[kResolution];
  s.grid_shift = w[kLevels] + kBrickShift - w[kGridDepth];
  s.grid_depth = w[kGridDepth];
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
// Leaf lookup and the leaf cache.

// The leaf (brick or far cube) holding a lattice cell, decoded: its cube and its child word.
struct Leaf {
  int cx, cy, cz;    // cube min corner, voxels (a multiple of the edge)
  int shift;         // log2 of the cube edge, voxels
  uint32_t tag;      // kTagBrick, kTagFarFree, kTagFarSolid (kTagNode only in an invalid file)
  uint32_t payload;  // relative to the scene's offsets
  uint32_t words;    // brick: its first corner word minus the offset of cell (cx, cy, cz), mod 2^32
};

// Offset of cell (i, j, k)'s corner word in a brick, for local i, j, k, or (mod 2^32) for global
// cells relative to a brick corner at a multiple of 8.
NAVI_HD uint32_t corner_offset(int i, int j, int k) {
  return static_cast<uint32_t>(i) * 72u + static_cast<uint32_t>(j) * 9u + static_cast<uint32_t>(k);
}

// The lattice cell of a voxel-space point: indices and the same indices as floats (exact).
struct Cell {
  int ix, iy, iz;
  float fx, fy, fz;  // float(ix), float(iy), float(iz)
};

// floor(x) clamped to [0, R - 1] (NaN lands on 0), as an int and as a float. The clamp is taken
// before the floor, which gives the same cell; on the device the floor is a round-down add of 2^23,
// exact for 0 <= x < 2^23, whose bits hold the integer and whose value minus 2^23 is its float.
NAVI_HD void cell_axis(float x, float cell_max, int& i, float& f) {
  const float c = fminf(fmaxf(x, 0.0f), cell_max);
#ifdef __CUDA_ARCH__
  const float r = __fadd_rd(c, kTwo23);
  i = __float_as_int(r) - kTwo23Bits;
  f = r - kTwo23;
#else
  f = floorf(c);
  i = static_cast<int>(f);
#endif
}

// R - 1 as a float, the largest cell index (computed where it is needed, on the rare clamped path,
// rather than carried through the walk in a register: see Scene).
NAVI_HD float cell_max(const Scene& s) { return static_cast<float>(s.resolution - 1); }

NAVI_HD Cell cell_of(float px, float py, float pz, float cell_max) {
  Cell c;
  cell_axis(px, cell_max, c.ix, c.fx);
  cell_axis(py, cell_max, c.iy, c.fy);
  cell_axis(pz, cell_max, c.iz, c.fz);
  return c;
}

// floor(x) without the clamp, for 0 <= x < R the same as cell_axis; below 0 a negative index, at or
// past R an index >= R (the host clamps to [-1, R] first so that the conversion stays defined).
NAVI_HD void cell_axis_unclamped(float x, float res, int& i, float& f) {
#ifdef __CUDA_ARCH__
  (void)res;
  const float r = __fadd_rd(x, kTwo23);
  i = __float_as_int(r) - kTwo23Bits;
  f = r - kTwo23;
#else
  f = floorf(fminf(fmaxf(x, -1.0f), res));
  i = static_cast<int>(f);
#endif
}

// Whether a cell index lies in [0, R - 1] on every axis (R is a power of two, so the or of three
// indices in range stays below R, and a negative one sets the sign bit).
NAVI_HD bool cell_in_cube(const Cell& c, int res) {
  return static_cast<uint32_t>(c.ix | c.iy | c.iz) < static_cast<uint32_t>(res);
}

// The leaf holding cell (ix, iy, iz): one leaf-grid load (the descent from the root to depth D,
// done once at load time by scene.py), then, for scenes deeper than the grid, the bounded stackless
// descent through the nodes for the remaining L - D levels.
NAVI_HD Leaf find_leaf(const uint32_t* grid, const uint32_t* nodes, const Scene& s, int ix, int iy, int iz) {
  const int gshift = s.grid_shift;
  const uint32_t gx = static_cast<uint32_t>(ix >> gshift), gy = static_cast<uint32_t>(iy >> gshift);
  const uint32_t gz = static_cast<uint32_t>(iz >> gshift);
  const uint32_t entry = load_ro(grid + s.grid_offset + ((((gz << s.grid_depth) | gy) << s.grid_depth) | gx));
  Leaf leaf;
  leaf.tag = entry >> 30;
  leaf.payload = entry & kGridPayloadMask;
  int shift = static_cast<int>((entry >> kGridShiftBit) & 15u);
  while (leaf.tag == kTagNode && shift > kBrickShift) {
    --shift;
    const uint64_t node = static_cast<uint64_t>(s.node_offset) + leaf.payload;
    const int child = ((ix >> shift) & 1) | (((iy >> shift) & 1) << 1) | (((iz >> shift) & 1) << 2);
    const uint32_t word = load_ro(nodes + node * 8 + child);
    leaf.tag = word >> 30;
    leaf.payload = word & kPayloadMask;
  }
  leaf.shift = shift;
  leaf.cx = (ix >> shift) << shift;
  leaf.cy = (iy >> shift) << shift;
  leaf.cz = (iz >> shift) << shift;
  leaf.words = (s.brick_offset + leaf.payload) * static_cast<uint32_t>(kBrickWords) -
               corner_offset(leaf.cx, leaf.cy, leaf.cz);
  return leaf;
}

// Whether cell (ix, iy, iz), all >= 0, lies in the leaf's cube (its corner is a multiple of the edge).
NAVI_HD bool leaf_contains(const Leaf& leaf, int ix, int iy, int iz) {
  return ((static_cast<uint32_t>((ix ^ leaf.cx) | (iy ^ leaf.cy) | (iz ^ leaf.cz))) >> leaf.shift) == 0;
}

// 2^23 + (corner byte k of a corner word): the byte holds sample + 128, so subtracting kSampleBias
// gives the sample exactly, and the difference of two such values is the difference of the samples.
NAVI_HD float corner(uint32_t word, int k) {
#ifdef __CUDA_ARCH__
  return __int_as_float(static_cast<int>(__byte_perm(word, 0x4B000000u, 0x7440u + static_cast<unsigned>(k))));
#else
  return bits_float(kTwo23Bits | static_cast<int32_t>((word >> (8 * k)) & 0xFFu));
#endif
}

// Trilinear interpolation inside a brick from the cell's corner words w[0], w[1], fractions in
// [0, 1]. Corner word (i, j, k) of a brick (index (8i + j) * 9 + k) holds the samples (i, j, k),
// (i+1, j, k), (i, j+1, k), (i+1, j+1, k) in bytes 0..3, so a cell is two adjacent words.
NAVI_HD float brick_distance(const uint32_t* w, float quant, float fx, float fy, float fz) {
  const uint32_t lo = load_ro(w), hi = load_ro(w + 1);
  const float a0 = corner(lo, 0), a1 = corner(lo, 1), a2 = corner(lo, 2), a3 = corner(lo, 3);
  const float b0 = corner(hi, 0), b1 = corner(hi, 1), b2 = corner(hi, 2), b3 = corner(hi, 3);
  // The same operations as on the samples c000..c111 themselves: c000 + fx * (c100 - c000), ...
  const float x00 = (a0 - kSampleBias) + fx * (a1 - a0);
  const float x10 = (a2 - kSampleBias) + fx * (a3 - a2);
  const float x01 = (b0 - kSampleBias) + fx * (b1 - b0);
  const float x11 = (b2 - kSampleBias) + fx * (b3 - b2);
  const float y0 = x00 + fy * (x10 - x00);
  const float y1 = x01 + fy * (x11 - x01);
  return (y0 + fz * (y1 - y0)) * quant;
}

NAVI_HD float unit_clamp(float x) { return fminf(fmaxf(x, 0.0f), 1.0f); }

// The fraction of p along one axis of its cell (p minus the cell's corner), clamped to [0, 1] for
// points on the cube's faces or just outside them (cell_of clamps the cell into the cube).
NAVI_HD float cell_fraction(float p, float corner) { return unit_clamp(p - corner); }

constexpr uint32_t kNoBrick = 0xFFFFFFFFu;

// Where a launch reads brick samples. The CPU build reads the corner words; the CUDA build reads the
// brick atlas, a 3-d texture of the int8 samples (each brick once, a 9 x 9 x 9 tile) that the texture
// unit interpolates trilinearly in one fetch (scene.py `brick_atlas`).
struct BrickStore {
  const uint32_t* words;  // corner words, or null
  uint64_t atlas;         // cudaTextureObject_t, or 0
  int32_t shift;          // log2 of the bricks per atlas row and per column
};

NAVI_HD BrickStore brick_store(const uint32_t* words, uint64_t atlas, int32_t shift) {
  BrickStore b;
  b.words = words;
  b.atlas = atlas;
  b.shift = shift;
  return b;
}

#ifdef __CUDA_ARCH__
// The field in cell (li, lj, lk) of brick b at fractions ux, uy, uz, from the atlas: brick b's tile
// starts at texel 9 (b mod 2^p, (b >> p) mod 2^p, b >> 2p), and texel (x, y, z) of a tile holds sample
// (x, y, z) as a signed normalised byte (sample / 127). With linear filtering and unnormalised
// coordinates the unit interpolates the 8 texels around (x - 0.5, y - 0.5, z - 0.5), so the sample
// point is the cell's texel plus the fraction plus 0.5. Its weights are 8-bit fixed point (CUDA C++
// Programming Guide, "Linear Filtering"): the field differs from the exact trilinear of the CPU build
// by at most about 1/256 of the samples' spread across the cell (docs/SDFDAG_RUNTIME.md).
__device__ __forceinline__ float atlas_distance(const BrickStore& bs, uint32_t b, int li, int lj, int lk,
                                                float quant, float ux, float uy, float uz) {
  const uint32_t mask = (1u << bs.shift) - 1u;
  const int tx = static_cast<int>((b & mask) * 9u) + li;
  const int ty = static_cast<int>(((b >> bs.shift) & mask) * 9u) + lj;
  const int tz = static_cast<int>((b >> (2 * bs.shift)) * 9u) + lk;
  // small non-negative ints to float exactly without a conversion instruction (bits of 2^23 + n)
  const float x = (__int_as_float(kTwo23Bits + tx) - kTwo23) + (ux + 0.5f);
  const float y = (__int_as_float(kTwo23Bits + ty) - kTwo23) + (uy + 0.5f);
  const float z = (__int_as_float(kTwo23Bits + tz) - kTwo23) + (uz + 0.5f);
  return tex3D<float>(static_cast<cudaTextureObject_t>(bs.atlas), x, y, z) * (127.0f * quant);
}
#endif

// The field at a voxel-space point p inside the cube whose cell (ix, iy, iz) lies in `leaf`.
// Far codes give their lower bound (negative for solid); `solid` marks a far-solid cube.
struct FieldSample {
  float dist;     // voxels
  bool solid;     // inside a far-solid cube
  bool far_free;  // inside a far-free cube (dist is its lower bound)
};

// The field in cell c of `leaf` at fractions ux, uy, uz of the cell (cell_fraction).
NAVI_HD FieldSample leaf_field(const BrickStore& bricks, const Scene& s, const Leaf& leaf, const Cell& c, float ux,
                               float uy, float uz) {
  FieldSample f;
  f.solid = leaf.tag == kTagFarSolid;
  f.far_free = leaf.tag != kTagBrick && leaf.tag != kTagFarSolid;
  if (leaf.tag == kTagBrick) {
    // The cell lies in this brick, so its local index is in [0, 7] and its corner words are
    // leaf.words + corner_offset(ix, iy, iz) (the brick corner's offset cancels mod 2^32).
#ifdef __CUDA_ARCH__
    f.dist = atlas_distance(bricks, s.brick_offset + leaf.payload, c.ix - leaf.cx, c.iy - leaf.cy, c.iz - leaf.cz,
                            s.quant, ux, uy, uz);
#else
    f.dist = brick_distance(bricks.words + (leaf.words + corner_offset(c.ix, c.iy, c.iz)), s.quant, ux, uy, uz);
#endif
  } else if (leaf.tag == kTagFarSolid) {
    f.dist = -(static_cast<float>(leaf.payload) * kFarUnit);
  } else {
    // Far free; an internal node below the brick level cannot occur in a validated file.
    f.dist = leaf.tag == kTagFarFree ? static_cast<float>(leaf.payload) * kFarUnit : 0.0f;
  }
  return f;
}

// A leaf corner that no cell index reaches, in the cube or out of it (walker_init).
constexpr int kNoCorner = 0x40000000;

// Per-ray state for the walk: the cached leaf (the macro-cell void cache) and the last brick sampled.
struct Walker {
  Leaf leaf;            // starts with corner kNoCorner, which contains no cell
  uint32_t last_brick;  // corpus index of the last brick sampled (the class of a hit), or kNoBrick
};

NAVI_HD void walker_init(Walker& w) {
  w.leaf.cx = w.leaf.cy = w.leaf.cz = kNoCorner;
  w.leaf.shift = kBrickShift;
  w.leaf.tag = kTagFarFree;
  w.leaf.payload = 0;
  w.leaf.words = 0;
  w.last_brick = kNoBrick;
}

// Samples the field at voxel-space p, reusing the cached leaf when p's cell lies in it.
NAVI_HD FieldSample walk_sample(const uint32_t* grid, const uint32_t* nodes, const BrickStore& bricks, const Scene& s,
                                Walker& w, float px, float py, float pz) {
  // The cell without the clamp into the cube: the walk's points lie in the cube but for rounding at
  // its faces, and a point outside it cannot lie in the cached leaf, so the clamp waits for the lookup.
  const float res = static_cast<float>(s.resolution);
  Cell c;
  cell_axis_unclamped(px, res, c.ix, c.fx);
  cell_axis_unclamped(py, res, c.iy, c.fy);
  cell_axis_unclamped(pz, res, c.iz, c.fz);
  // The fractions before the leaf lookup: then p need not live across it (on an H100 the device code
  // recomputed p after the lookup instead, and ran 5-10% slower).
  float ux = cell_fraction(px, c.fx), uy = cell_fraction(py, c.fy), uz = cell_fraction(pz, c.fz);
  if (!leaf_contains(w.leaf, c.ix, c.iy, c.iz)) {
    if (!cell_in_cube(c, s.resolution)) {  // on a face or just past it: the nearest cell of the cube
      c = cell_of(px, py, pz, cell_max(s));
      ux = cell_fraction(px, c.fx);
      uy = cell_fraction(py, c.fy);
      uz = cell_fraction(pz, c.fz);
    }
    w.leaf = find_leaf(grid, nodes, s, c.ix, c.iy, c.iz);
    // Samples in the cached leaf are in the same brick, so the last brick sampled changes only here.
    if (w.leaf.tag == kTagBrick) w.last_brick = s.brick_offset + w.leaf.payload;
  }
  return leaf_field(bricks, s, w.leaf, c, ux, uy, uz);
}

// ---------------------------------------------------------------------------------------------
// Dynamic primitives: per-world spheres, capsules and boxes composed with the static field by min.
// A record is 16 float32 words (64 bytes), mirrored in navi_env/obstacles.py; small integers (kind,
// class, owner) are stored as floats (exact below 2^24). Positions are world meters.
enum PrimWord : int {
  kPrimKind = 0,    // 0 none, 1 sphere, 2 capsule, 3 axis-aligned box, 4 oriented box
  kPrimClass = 1,   // class id: a hit reports semantic 1 + class
  kPrimOwner = 2,   // actor index that does not see or collide with it (its own drone), or -1
  kPrimRadius = 3,  // sphere / capsule radius
  kPrimCx = 4,      // centre x, y, z (4, 5, 6)
  kPrimAx = 7,      // capsule: half segment vector; boxes: half extents in the box frame (7, 8, 9)
  kPrimQw = 10,     // oriented box: unit quaternion w, x, y, z (10..13), box frame -> world
};
constexpr int kPrimWords = 16;
constexpr int kPrimNone = 0, kPrimSphere = 1, kPrimCapsule = 2, kPrimBox = 3, kPrimObb = 4;

struct Vec3 {
  float x, y, z;
};

NAVI_HD Vec3 v3(float x, float y, float z) {
  Vec3 v;
  v.x = x;
  v.y = y;
  v.z = z;
  return v;
}
NAVI_HD Vec3 sub(Vec3 a, Vec3 b) { return v3(a.x - b.x, a.y - b.y, a.z - b.z); }
NAVI_HD float dot(Vec3 a, Vec3 b) { return a.x * b.x + a.y * b.y + a.z * b.z; }

// Rotates v by the conjugate of unit quaternion (w, x, y, z): world -> box frame.
NAVI_HD Vec3 rotate_inverse(const float* q, Vec3 v) {
  const float w = load_ro(q), qx = -load_ro(q + 1), qy = -load_ro(q + 2), qz = -load_ro(q + 3);
  // v' = v + 2 w (u x v) + 2 u x (u x v), u = (qx, qy, qz)
  const float cx = qy * v.z - qz * v.y, cy = qz * v.x - qx * v.z, cz = qx * v.y - qy * v.x;
  const float ex = qy * cz - qz * cy, ey = qz * cx - qx * cz, ez = qx * cy - qy * cx;
  return v3(v.x + 2.0f * (w * cx + ex), v.y + 2.0f * (w * cy + ey), v.z + 2.0f * (w * cz + ez));
}

// Exact Euclidean signed distance (meters) from world point p to primitive record r.
NAVI_HD float prim_distance(const float* r, Vec3 p) {
  const int kind = static_cast<int>(load_ro(r + kPrimKind));
  const Vec3 c = v3(load_ro(r + kPrimCx), load_ro(r + kPrimCx + 1), load_ro(r + kPrimCx + 2));
  const float rad = load_ro(r + kPrimRadius);
  Vec3 q = sub(p, c);
  if (kind == kPrimSphere) return sqrtf(dot(q, q)) - rad;
  const Vec3 a = v3(load_ro(r + kPrimAx), load_ro(r + kPrimAx + 1), load_ro(r + kPrimAx + 2));
  if (kind == kPrimCapsule) {
    // Segment c - a .. c + a: the closest point at parameter s in [-1, 1].
    const float aa = dot(a, a);
    const float s = aa > 0.0f ? fminf(fmaxf(dot(q, a) / aa, -1.0f), 1.0f) : 0.0f;
    const Vec3 e = v3(q.x - s * a.x, q.y - s * a.y, q.z - s * a.z);
    return sqrtf(dot(e, e)) - rad;
  }
  if (kind == kPrimBox || kind == kPrimObb) {
    if (kind == kPrimObb) q = rotate_inverse(r + kPrimQw, q);
    const float dx = fabsf(q.x) - a.x, dy = fabsf(q.y) - a.y, dz = fabsf(q.z) - a.z;
    const float ox = fmaxf(dx, 0.0f), oy = fmaxf(dy, 0.0f), oz = fmaxf(dz, 0.0f);
    return sqrtf(ox * ox + oy * oy + oz * oz) + fminf(fmaxf(dx, fmaxf(dy, dz)), 0.0f);
  }
  return kBig;
}

// Entry time (meters) of the ray o + t d, t >= 0, |d| = 1, into a sphere; 0 from inside; kBig if none.
// The half chord comes from the ray's perpendicular offset e = oc - (oc . d) d (rad^2 - |e|^2), not
// from b^2 - (|oc|^2 - rad^2), which cancels catastrophically in float32 for a sphere tens of meters
// away (at 150 m it lost rays passing a millimetre inside the silhouette).
NAVI_HD float sphere_hit(Vec3 o, Vec3 d, Vec3 c, float rad) {
  const Vec3 oc = sub(o, c);
  const float b = dot(oc, d);
  const float cc = dot(oc, oc) - rad * rad;
  if (cc <= 0.0f) return 0.0f;
  const Vec3 e = v3(oc.x - b * d.x, oc.y - b * d.y, oc.z - b * d.z);
  const float disc = rad * rad - dot(e, e);
  if (disc < 0.0f || b > 0.0f) return kBig;  // no root, or both roots behind the origin
  return -b - sqrtf(disc);
}

// Entry time (meters) of a ray into a box |q| <= h of its own frame (o, d in that frame).
NAVI_HD float box_hit(Vec3 o, Vec3 d, Vec3 h) {
  float t0 = 0.0f, t1 = kBig;
  const float os[3] = {o.x, o.y, o.z}, ds[3] = {d.x, d.y, d.z}, hs[3] = {h.x, h.y, h.z};
  for (int k = 0; k < 3; ++k) {
    if (ds[k] != 0.0f) {
      const float inv = 1.0f / ds[k];
      const float ta = (-hs[k] - os[k]) * inv, tb = (hs[k] - os[k]) * inv;
      t0 = fmaxf(t0, fminf(ta, tb));
      t1 = fminf(t1, fmaxf(ta, tb));
    } else if (os[k] < -hs[k] || os[k] > hs[k]) {
      return kBig;
    }
  }
  return t0 <= t1 ? t0 : kBig;
}

// Entry time (meters) of a ray into primitive record r; kBig if the ray misses it.
NAVI_HD float prim_hit(const float* r, Vec3 o, Vec3 d) {
  const int kind = static_cast<int>(load_ro(r + kPrimKind));
  const Vec3 c = v3(load_ro(r + kPrimCx), load_ro(r + kPrimCx + 1), load_ro(r + kPrimCx + 2));
  const float rad = load_ro(r + kPrimRadius);
  if (kind == kPrimSphere) return sphere_hit(o, d, c, rad);
  const Vec3 a = v3(load_ro(r + kPrimAx), load_ro(r + kPrimAx + 1), load_ro(r + kPrimAx + 2));
  if (kind == kPrimCapsule) {
    // The union of the two end spheres and the cylinder between them: the earliest entry of the three
    // (a cylinder entry counts only between the end planes).
    float t = fminf(sphere_hit(o, d, v3(c.x - a.x, c.y - a.y, c.z - a.z), rad),
                    sphere_hit(o, d, v3(c.x + a.x, c.y + a.y, c.z + a.z), rad));
    const Vec3 ba = v3(2.0f * a.x, 2.0f * a.y, 2.0f * a.z);
    const Vec3 oa = v3(o.x - (c.x - a.x), o.y - (c.y - a.y), o.z - (c.z - a.z));
    const float baba = dot(ba, ba), bard = dot(ba, d), baoa = dot(ba, oa);
    const float qa = baba - bard * bard;  // baba * |d_perp|^2
    const float qb = baba * dot(oa, d) - baoa * bard;
    const float qc = baba * dot(oa, oa) - baoa * baoa - rad * rad * baba;
    if (baba > 0.0f && qc <= 0.0f && baoa >= 0.0f && baoa <= baba) return 0.0f;  // inside the cylinder
    if (baba > 0.0f && qa > 0.0f) {
      const float h = qb * qb - qa * qc;
      if (h >= 0.0f) {
        const float tc = (-qb - sqrtf(h)) / qa;
        const float y = baoa + tc * bard;
        if (tc >= 0.0f && y >= 0.0f && y <= baba) t = fminf(t, tc);
      }
    }
    return t;
  }
  if (kind == kPrimBox) return box_hit(sub(o, c), d, a);
  if (kind == kPrimObb) {
    const float* q = r + kPrimQw;
    return box_hit(rotate_inverse(q, sub(o, c)), rotate_inverse(q, d), a);
  }
  return kBig;
}

// A primitive's bounding sphere as seen from one ray origin, for the cull every ray runs before the
// exact intersection: oc = centre - origin and r2 = the squared radius, inflated by 1 um plus 4e-6 of
// |oc| (well above float32 rounding of the test below at any distance), so the cull only rejects rays
// the exact test would also miss and the traced result is unchanged. An empty slot, one the tracing
// actor owns (its own drone), and a bound holding the origin take oc = 0 with r2 = -1 (never hit) or
// r2 = kBig (always tested). The rays of one actor share the origin, so a launch builds every actor's
// table once before its rays (PrimTables below).
struct alignas(16) PrimCull {
  float ocx, ocy, ocz, r2;
};

// Radius of a sphere about the record's centre that holds the whole primitive.
NAVI_HD float prim_bound_radius(const float* r) {
  const int kind = static_cast<int>(load_ro(r + kPrimKind));
  const float rad = load_ro(r + kPrimRadius);
  if (kind == kPrimSphere) return rad;
  const Vec3 a = v3(load_ro(r + kPrimAx), load_ro(r + kPrimAx + 1), load_ro(r + kPrimAx + 2));
  const float half = sqrtf(dot(a, a));  // capsule: half segment; boxes: half diagonal
  return kind == kPrimCapsule ? half + rad : half;
}

// An entry no ray tests (an empty slot).
NAVI_HD PrimCull empty_cull() {
  PrimCull c;
  c.ocx = 0.0f;
  c.ocy = 0.0f;
  c.ocz = 0.0f;
  c.r2 = -1.0f;
  return c;
}

NAVI_HD PrimCull prim_cull(const float* r, int64_t owner, Vec3 o) {
  PrimCull c = empty_cull();
  const float kind = load_ro(r + kPrimKind);
  if (kind == 0.0f || load_ro(r + kPrimOwner) == static_cast<float>(owner)) return c;
  const Vec3 oc = v3(load_ro(r + kPrimCx) - o.x, load_ro(r + kPrimCx + 1) - o.y, load_ro(r + kPrimCx + 2) - o.z);
  const float dist = sqrtf(dot(oc, oc));
  const float bound = prim_bound_radius(r) + 1e-6f + 4e-6f * dist;
  if (!(dist > bound)) {  // the origin is inside the bound (or the record is not finite): test exactly
    c.r2 = kBig;
    return c;
  }
  c.ocx = oc.x;
  c.ocy = oc.y;
  c.ocz = oc.z;
  c.r2 = bound * bound;
  return c;
}

// Whether the ray t >= 0 along unit d may enter the bound: the centre lies ahead and the ray passes
// within the radius (perpendicular offset e = oc - (oc . d) d, well conditioned at any distance).
NAVI_HD bool cull_may_hit(const PrimCull& c, Vec3 d) {
  const float b = c.ocx * d.x + c.ocy * d.y + c.ocz * d.z;
  const float ex = c.ocx - b * d.x, ey = c.ocy - b * d.y, ez = c.ocz - b * d.z;
  return b >= 0.0f && ex * ex + ey * ey + ez * ez <= c.r2;
}

// The cull table entry k of actor b (an empty entry for an actor whose world is outside [0, W)).
NAVI_HD PrimCull actor_prim_cull(const TraceArgs& a, int64_t b, int32_t k) {
  const int64_t wid = a.prim_world != nullptr ? static_cast<int64_t>(load_ro(a.prim_world + b)) : b;
  const Vec3 o = v3(load_ro(a.origins + b * 3), load_ro(a.origins + b * 3 + 1), load_ro(a.origins + b * 3 + 2));
  if (wid < 0 || wid >= a.num_worlds) return empty_cull();  // such an actor sees no primitive
  return prim_cull(a.prims + (wid * a.prims_per_world + k) * kPrimWords, b, o);
}

// ---------------------------------------------------------------------------------------------
// Per-launch primitive tables. Before its rays, a launch with primitives builds (in prim_scratch):
//   cones  (G,)     every group of kRayGroup work items (items [g * kRayGroup, (g + 1) * kRayGroup) of
//                   an actor: one CUDA block) bounds its body-frame directions by a cone: unit axis and
//                   half angle (plus kConeMargin); shared directions only
//   table  (B, K)   each actor's cull entries (actor_prim_cull)
//   masks  (B, G)   bit k set when primitive k's bounding sphere may meet group g's cone (rotated by the
//                   actor's yaw); K <= kMaskPrims with shared directions, else every ray tests all K
// A ray then runs the bounding-sphere test and the exact intersection only for the set bits of its
// group's mask: most groups see no primitive at all and pay one load. Conservative throughout (the
// cone holds every direction of its group with margin, the cone test errs towards "may meet"), so the
// traced result is that of testing every primitive.
constexpr int kRayGroup = 128;      // work items per group; the CUDA kernel's block size
constexpr int kMaskPrims = 64;      // bits of a group mask
constexpr float kConeMargin = 2e-3f;  // radians added to every cone's half angle
constexpr float kWideCone = 1.5f;   // radians: a wider cone (or a degenerate one) bounds nothing

struct alignas(16) RayCone {
  float ax, ay, az;  // unit axis, body frame
  float half;        // half angle in radians with margin; >= kWideCone: every direction
};

struct PrimTables {
  RayCone* cones;   // (G,) or null (no masks)
  PrimCull* table;  // (B, K)
  uint64_t* masks;  // (B, G) or null (no masks)
};

NAVI_HD int64_t ray_groups(int64_t rays) { return (rays + kRayGroup - 1) / kRayGroup; }

NAVI_HD bool uses_masks(const TraceArgs& a) { return a.directions_shared != 0 && a.prims_per_world <= kMaskPrims; }

// Bytes of prim_scratch a launch with primitives needs: cones (16 B each), table (16 B), masks (8 B).
NAVI_HD int64_t prim_scratch_bytes(const TraceArgs& a) {
  const int64_t g = ray_groups(a.num_rays);
  const int64_t table = a.num_actors * a.prims_per_world * static_cast<int64_t>(sizeof(PrimCull));
  if (!uses_masks(a)) return table;
  return g * static_cast<int64_t>(sizeof(RayCone)) + table + a.num_actors * g * 8;
}

NAVI_HD PrimTables prim_tables(const TraceArgs& a) {
  PrimTables t;
  char* base = static_cast<char*>(a.prim_scratch);
  const int64_t g = ray_groups(a.num_rays);
  if (uses_masks(a)) {
    t.cones = reinterpret_cast<RayCone*>(base);
    t.table = reinterpret_cast<PrimCull*>(base + g * static_cast<int64_t>(sizeof(RayCone)));
    t.masks = reinterpret_cast<uint64_t*>(reinterpret_cast<char*>(t.table) +
                                          a.num_actors * a.prims_per_world * static_cast<int64_t>(sizeof(PrimCull)));
  } else {
    t.cones = nullptr;
    t.table = reinterpret_cast<PrimCull*>(base);
    t.masks = nullptr;
  }
  return t;
}

// Work item j's body-frame direction (shared directions); false for an item ray_order skips.
NAVI_HD bool item_direction(const TraceArgs& a, int64_t j, Vec3& d) {
  const int64_t r = a.ray_order != nullptr ? static_cast<int64_t>(load_ro(a.ray_order + j)) : j;
  if (j >= a.num_rays || r < 0 || r >= a.num_rays) return false;
  d = v3(load_ro(a.directions + r * 3), load_ro(a.directions + r * 3 + 1), load_ro(a.directions + r * 3 + 2));
  return finite(d.x) && finite(d.y) && finite(d.z);
}

// Angle in radians between u and d (any lengths; atan2 of |u x d| and u . d, well conditioned).
NAVI_HD float angle_between(Vec3 u, Vec3 d) {
  const float cx = u.y * d.z - u.z * d.y, cy = u.z * d.x - u.x * d.z, cz = u.x * d.y - u.y * d.x;
  return atan2f(sqrtf(cx * cx + cy * cy + cz * cz), dot(u, d));
}

// The cone of an axis (the sum of the group's directions, any length) and the widest angle from it.
NAVI_HD RayCone make_cone(Vec3 sum, float widest) {
  RayCone c;
  const float len = sqrtf(dot(sum, sum));
  const bool ok = len > 1e-6f && widest + kConeMargin < kWideCone;
  c.ax = ok ? sum.x / len : 1.0f;
  c.ay = ok ? sum.y / len : 0.0f;
  c.az = ok ? sum.z / len : 0.0f;
  c.half = ok ? widest + kConeMargin : kWideCone;
  return c;
}

// Group g's cone, serially (the CPU launcher; the CUDA launcher reduces over a block instead).
NAVI_HD RayCone group_cone(const TraceArgs& a, int64_t g) {
  Vec3 sum = v3(0.0f, 0.0f, 0.0f), d;
  for (int64_t j = g * kRayGroup; j < (g + 1) * kRayGroup; ++j) {
    if (item_direction(a, j, d)) {
      const float n = sqrtf(dot(d, d));
      sum = v3(sum.x + d.x / n, sum.y + d.y / n, sum.z + d.z / n);
    }
  }
  float widest = 0.0f;
  for (int64_t j = g * kRayGroup; j < (g + 1) * kRayGroup; ++j) {
    if (item_direction(a, j, d)) widest = fmaxf(widest, angle_between(sum, d));
  }
  return make_cone(sum, widest);
}

// Whether a ray whose direction lies within `half` of unit axis u may enter the bound of entry c
// (origin outside the bound): the angle between u and oc is at most half + asin(r / |oc|), compared as
// u . oc >= cos(half) sqrt(|oc|^2 - r^2) - sin(half) r (both angles below pi / 2), with slack.
NAVI_HD bool cone_may_hit(const PrimCull& c, Vec3 u, float cos_half, float sin_half) {
  if (c.r2 < 0.0f) return false;
  if (c.r2 >= kBig) return true;
  const float l2 = c.ocx * c.ocx + c.ocy * c.ocy + c.ocz * c.ocz;
  const float lhs = u.x * c.ocx + u.y * c.ocy + u.z * c.ocz;
  const float rhs = cos_half * sqrtf(fmaxf(l2 - c.r2, 0.0f)) - sin_half * sqrtf(c.r2);
  return lhs >= rhs - 1e-5f * sqrtf(l2);
}

// The body-frame direction rotated by yaw about +Z (cos/sin as the platform's libm computes them).
NAVI_HD void rotate_yaw(float yaw, float& dx, float& dy) {
  float c, sn;
#ifdef __CUDA_ARCH__
  sincosf(yaw, &sn, &c);
#else
  c = cosf(yaw);
  sn = sinf(yaw);
#endif
  const float rx = c * dx - sn * dy;
  const float ry = sn * dx + c * dy;
  dx = rx;
  dy = ry;
}

// Group g's mask for actor b: bit k when primitive k may be hit by one of the group's rays.
NAVI_HD uint64_t group_mask(const TraceArgs& a, const PrimTables& t, int64_t b, int64_t g) {
  const RayCone cone = t.cones[g];
  const PrimCull* row = t.table + b * a.prims_per_world;
  const bool wide = cone.half >= kWideCone;
  float ux = cone.ax, uy = cone.ay;
  if (a.yaw != nullptr) rotate_yaw(load_ro(a.yaw + b), ux, uy);
  const Vec3 u = v3(ux, uy, cone.az);
  const float cos_half = cosf(cone.half), sin_half = sinf(cone.half);
  uint64_t mask = 0;
  for (int k = 0; k < a.prims_per_world; ++k) {
    const PrimCull c = row[k];
    const bool hit = wide ? c.r2 >= 0.0f : cone_may_hit(c, u, cos_half, sin_half);
    if (hit) mask |= uint64_t{1} << k;
  }
  return mask;
}

NAVI_HD int lowest_bit(uint64_t m) {
#ifdef __CUDA_ARCH__
  return __ffsll(static_cast<long long>(m)) - 1;
#else
  return __builtin_ctzll(m);
#endif
}

// Entry k of a cull table (one 16-byte load on the device).
NAVI_HD PrimCull load_cull(const PrimCull* p) {
#ifdef __CUDA_ARCH__
  const float4 v = __ldg(reinterpret_cast<const float4*>(p));
  PrimCull c;
  c.ocx = v.x;
  c.ocy = v.y;
  c.ocz = v.z;
  c.r2 = v.w;
  return c;
#else
  return *p;
#endif
}

// Primitive k as a candidate first hit: the bounding-sphere test, then the exact entry time.
NAVI_HD void prim_candidate(const float* rec, const PrimCull* row, int k, Vec3 o, Vec3 d, float& best,
                            int32_t& semantic) {
  if (!cull_may_hit(load_cull(row + k), d)) return;
  const float* r = rec + k * kPrimWords;
  const float t = prim_hit(r, o, d);
  if (t < best) {
    best = t;
    semantic = 1 + static_cast<int32_t>(load_ro(r + kPrimClass));
  }
}

// The first primitive hit of a world along a ray (meters, kBig if none) and its semantic, testing the
// primitives of `mask` (bits k < K) in increasing k when `masked`, else all K. rec: the world's K
// records; row: the tracing actor's cull entries (PrimTables).
NAVI_HD float first_prim_hit(const float* rec, const PrimCull* row, int32_t k_count, bool masked, uint64_t mask,
                             Vec3 o, Vec3 d, int32_t& semantic) {
  float best = kBig;
  if (masked) {
    for (uint64_t m = mask; m != 0; m &= m - 1) prim_candidate(rec, row, lowest_bit(m), o, d, best, semantic);
  } else {
    for (int k = 0; k < k_count; ++k) prim_candidate(rec, row, k, o, d, best, semantic);
  }
  return best;
}

// The smallest primitive distance at p in a world, leaving out the owner's own (kBig if none).
NAVI_HD float min_prim_distance(const float* prims, int64_t world, int32_t k_count, int64_t owner, Vec3 p) {
  float best = kBig;
  const float* rec = prims + world * k_count * kPrimWords;
  for (int k = 0; k < k_count; ++k, rec += kPrimWords) {
    const float kind = load_ro(rec + kPrimKind);
    if (kind == 0.0f || load_ro(rec + kPrimOwner) == static_cast<float>(owner)) continue;
    best = fminf(best, prim_distance(rec, p));
  }
  return best;
}

// ---------------------------------------------------------------------------------------------
// The origin sample. Every ray of an actor whose origin lies in its scene's cube starts at t = 0, so
// its first sample is at the origin itself (o + 0 d = o exactly, fused or not): the same field, leaf
// and brick for all R rays. A launch with origin_scratch takes that sample once per actor before the
// rays (one thread per actor), and each ray's first step starts from the record (first_step): one
// sample and leaf lookup less per ray, bit-identical to sampling the origin itself.
constexpr int32_t kOriginValid = 1;     // the record holds the sample (origin finite and in the cube)
constexpr int32_t kOriginSolid = 2;     // FieldSample.solid
constexpr int32_t kOriginFarFree = 4;   // FieldSample.far_free

struct alignas(16) OriginSample {
  Leaf leaf;            // the walker's leaf after the sample
  uint32_t last_brick;  // the walker's last brick after the sample
  float dist;           // FieldSample.dist, voxels
  int32_t flags;        // kOriginValid | kOriginSolid | kOriginFarFree
};

static_assert(sizeof(OriginSample) == 48, "mirrored by navi_env.trace.ORIGIN_SAMPLE_BYTES");

// Actor b's origin sample (flags 0 where its rays cannot use one: bad scene id, non-finite origin, an
// origin outside the cube, whose rays start at their own entry times).
NAVI_HD OriginSample origin_sample(const TraceArgs& a, int64_t b) {
  Walker w;
  walker_init(w);
  OriginSample o;
  o.leaf = w.leaf;
  o.last_brick = w.last_brick;
  o.dist = 0.0f;
  o.flags = 0;
  const int64_t sid = load_scene_id(a.scene_ids, a.scene_id_bytes, b);
  if (sid < 0 || sid >= a.num_scenes) return o;
  const Scene s = load_scene(a.scenes, sid);
  const float ox = (load_ro(a.origins + b * 3) - s.ox) * s.inv_voxel;
  const float oy = (load_ro(a.origins + b * 3 + 1) - s.oy) * s.inv_voxel;
  const float oz = (load_ro(a.origins + b * 3 + 2) - s.oz) * s.inv_voxel;
  const float res = static_cast<float>(s.resolution);
  // inside the closed cube (false for NaN): every ray's slab clip then starts at t = 0
  if (!(ox >= 0.0f && ox <= res && oy >= 0.0f && oy <= res && oz >= 0.0f && oz <= res)) return o;
  const FieldSample f = walk_sample(a.grid, a.nodes, brick_store(a.bricks, a.brick_atlas, a.atlas_shift), s, w,
                                    ox, oy, oz);
  o.leaf = w.leaf;
  o.last_brick = w.last_brick;
  o.dist = f.dist;
  o.flags = kOriginValid | (f.solid ? kOriginSolid : 0) | (f.far_free ? kOriginFarFree : 0);
  return o;
}

// Record b of origin_scratch (16-byte loads on the device).
NAVI_HD OriginSample load_origin(const TraceArgs& a, int64_t b) {
  const OriginSample* p = static_cast<const OriginSample*>(a.origin_scratch) + b;
#ifdef __CUDA_ARCH__
  OriginSample o;
  const int4* src = reinterpret_cast<const int4*>(p);
  int4* dst = reinterpret_cast<int4*>(&o);
  for (int k = 0; k < static_cast<int>(sizeof(OriginSample) / 16); ++k) dst[k] = __ldg(src + k);
  return o;
#else
  return *p;
#endif
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

// Ray time at which the ray leaves the cube [c, c + edge] along one axis (kBig when parallel). The
// face's coordinate, an integer in [0, R] (R <= 2^23), becomes a float through the bits of 2^23 + n on
// the device (exact, no conversion instruction).
NAVI_HD float exit_time(float o, float d, float inv, int c, int edge) {
  if (d == 0.0f) return kBig;
  const int face = d > 0.0f ? c + edge : c;
#ifdef __CUDA_ARCH__
  const float bound = __int_as_float(kTwo23Bits + face) - kTwo23;
#else
  const float bound = static_cast<float>(face);
#endif
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
  float end_d;               // the field at the last sample (the one that ended the walk: kSurface, kCrossing)
  int64_t out;               // output element b * R + r
  Walker w;
  RayResult res;             // semantic < 0 while walking: kOutOfSteps, kPrimStashed, kSurface, kCrossing
  bool done;
};

// res.semantic of a ray that ran out of steps or had no finite input: it reports the distance reached
// (or the horizon), written out with semantic 0, and never a primitive.
constexpr int32_t kOutOfSteps = -1;
// res.semantic of a ray whose first primitive hit lies within the horizon: its depth and semantic are
// already in the outputs (written before the walk, which ends at it), and stay there unless the walk
// hits the static scene first. Nothing about the primitive is carried through the walk.
constexpr int32_t kPrimStashed = -2;
// res.semantic of a ray whose walk ended on the static surface: kSurface at a free sample within the
// hit threshold, kCrossing at a sample inside solid (depth and class set after the walk by settle_hit).
constexpr int32_t kSurface = -3;
constexpr int32_t kCrossing = -4;

// Writes one element of the depth and semantic outputs.
NAVI_HD void write_hit(const TraceArgs& a, int64_t out, float depth, int32_t semantic) {
  a.out_depth[out] = depth;
  if (a.semantic_bytes == 4) {
    static_cast<int32_t*>(a.out_semantic)[out] = semantic;
  } else if (a.semantic_bytes == 1) {
    static_cast<uint8_t*>(a.out_semantic)[out] = static_cast<uint8_t>(semantic < 255 ? semantic : 255);
  }
}

// The mask word of work item j of actor b (PrimTables.masks; null masks: none, every primitive tested).
NAVI_HD uint64_t item_mask(const TraceArgs& a, const PrimTables& t, int64_t b, int64_t j) {
  return t.masks != nullptr ? load_ro(t.masks + b * ray_groups(a.num_rays) + j / kRayGroup) : 0;
}

// The first primitive hit (meters, kBig if none) and its semantic along a ray of actor b from world
// point o in direction d, testing the primitives of `mask` (item_mask) when the launch has masks.
NAVI_HD float actor_prim_hit(const TraceArgs& a, const PrimTables& t, int64_t b, uint64_t mask, Vec3 o, Vec3 d,
                             int32_t& semantic) {
  const int64_t wid = a.prim_world != nullptr ? static_cast<int64_t>(load_ro(a.prim_world + b)) : b;
  if (wid < 0 || wid >= a.num_worlds) return kBig;
  return first_prim_hit(a.prims + wid * a.prims_per_world * kPrimWords, t.table + b * a.prims_per_world,
                        a.prims_per_world, t.masks != nullptr, mask, o, d, semantic);
}

// Sets up work item j (ray r) of actor b (writing to element b * R + r); rays that are decided before
// the first sample (bad scene id, non-finite input, missing the cube) come back done. kPrims: the
// launch has primitives (a separate instantiation, so a launch without them runs the plain walk:
// measured 6-8% slower on an H100 when one kernel served both); `t`: its tables (prim_tables).
template <bool kPrims>
NAVI_HD Ray start_ray(const TraceArgs& a, int64_t b, int64_t j, int64_t r, const PrimTables& t) {
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
  const float* dir = a.directions + (a.directions_shared ? r : b * a.num_rays + r) * 3;
  float dx = load_ro(dir), dy = load_ro(dir + 1);
  const float dz = load_ro(dir + 2);
  if (a.yaw != nullptr) rotate_yaw(load_ro(a.yaw + b), dx, dy);
  const Vec3 world = v3(load_ro(a.origins + b * 3), load_ro(a.origins + b * 3 + 1), load_ro(a.origins + b * 3 + 2));
  if (!(finite(world.x) && finite(world.y) && finite(world.z) && finite(dx) && finite(dy) && finite(dz))) {
    ray.res.semantic = kOutOfSteps;
    return ray;
  }
  // The primitives first, before the scene record is loaded: little is live here, so their code does
  // not crowd the registers the walk keeps (with it after the load, ptxas spilled walk state).
  float reach = a.horizon;  // meters: the horizon, or the first primitive hit before it
  const uint64_t mask = kPrims ? item_mask(a, t, b, j) : 0;
  if (kPrims && (mask != 0 || t.masks == nullptr)) {  // most groups: no primitive near their cone
    int32_t semantic = 0;
    const float prim_t = actor_prim_hit(a, t, b, mask, world, v3(dx, dy, dz), semantic);
    if (prim_t <= a.horizon) {
      reach = prim_t;
      write_hit(a, ray.out, prim_t, semantic);
      ray.res.semantic = kPrimStashed;
    }
  }
  const Scene s = load_scene(a.scenes, sid);
  ray.s = s;
  const float ox = (world.x - s.ox) * s.inv_voxel;
  const float oy = (world.y - s.oy) * s.inv_voxel;
  const float oz = (world.z - s.oz) * s.inv_voxel;
  if (!(finite(ox) && finite(oy) && finite(oz))) {
    ray.res.semantic = kOutOfSteps;
    return ray;
  }
  const float res = static_cast<float>(s.resolution);
  ray.eps = a.hit_epsilon > 0.0f ? a.hit_epsilon * s.inv_voxel : kDefaultHitEpsilonVoxels;

  // Clip the ray to the cube and the horizon (slab test); a ray that misses the cube is a miss.
  ray.inv_x = dx != 0.0f ? 1.0f / dx : kBig;
  ray.inv_y = dy != 0.0f ? 1.0f / dy : kBig;
  ray.inv_z = dz != 0.0f ? 1.0f / dz : kBig;
  float t0 = 0.0f, t1 = reach * s.inv_voxel;
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
  ray.prev_d = -1.0f;  // below any free sample: no surface stop at the first sample
  ray.end_d = 0.0f;
  walker_init(ray.w);
  ray.done = false;
  return ray;
}

// A ray still walking after max_steps samples reports the distance reached (or the horizon) with
// semantic 0.
NAVI_HD void end_out_of_steps(const TraceArgs& a, Ray& ray) {
  ray.res.depth = fminf(ray.t * ray.s.voxel, a.horizon);
  ray.res.semantic = kOutOfSteps;
  ray.done = true;
}

// Where a ray at t whose sample lies in the far-free cube `leaf` (lower bound d) goes next: past the
// whole cube and then d beyond its exit, since every point of the closed cube, the exit point
// included, is at least d from the surface (the far code's promise). A point that rounding leaves in
// the cube (or an exit time that rounds below t) only repeats the skip from t, which still moves the
// ray max(d, eps), so the walk cannot stall. Where the exit face is a face of the scene's cube, the
// exit time is that axis' slab exit, at least t1, so the step passes t1 and the ray ends as a miss (no
// test of the cell across the face is needed).
NAVI_HD float far_step(const Ray& ray, const Leaf& leaf, float t, float d) {
  const int edge = 1 << leaf.shift;
  const float tx = exit_time(ray.ox, ray.dx, ray.inv_x, leaf.cx, edge);
  const float ty = exit_time(ray.oy, ray.dy, ray.inv_y, leaf.cy, edge);
  const float tz = exit_time(ray.oz, ray.dz, ray.inv_z, leaf.cz, edge);
  return fmaxf(fminf(fminf(tx, ty), tz), t) + fmaxf(d, ray.eps);
}

// What one main-loop step does after its sample f (at t, in the walker's leaf w.leaf): the hit tests,
// then the step. Returns true when the ray is done (a miss, kSurface or kCrossing); otherwise t, prev_t
// and prev_d have moved on. first_step calls it; walk_ray's loop spells the same tests out inline (both
// share far_step, which compiles to the same device code as the step written out), because with the
// loop calling this function (and the first step peeled inside walk_ray) the device code ran 0-4%
// slower on the 50 OpenArena maps instead of 2-5% faster (docs/PERFORMANCE.md, stop 34). Tests trace with and without origin samples and demand the same outputs bit for bit,
// which holds the two copies together.
NAVI_HD bool take_step(const TraceArgs& a, Ray& ray, const Walker& w, const FieldSample& f, float& t, float& prev_t,
                       float& prev_d) {
  const float d = f.dist;
  if (f.solid || d < 0.0f) {  // inside: refined after the walk (settle_hit), out of the loop
    ray.res.semantic = kCrossing;
    return true;
  }
  // Within the threshold of a surface while not moving away from it: a ray leaving the surface it
  // starts on is not stopped by it, and none is at its first sample (prev_d starts at -1). The
  // threshold grows with the distance travelled, so that a ray stops once the surface lies within
  // a fixed fraction of its angular footprint.
  if (!f.far_free && d < ray.eps + a.hit_slope * t && d <= prev_d) {
    ray.res.semantic = kSurface;
    return true;
  }
  float next = t + fmaxf(d, ray.eps);
  if (f.far_free) next = far_step(ray, w.leaf, t, d);
  prev_t = t;
  prev_d = d;
  t = next;
  return next > ray.t1;  // past the cube or the horizon: a miss
}

// The first step of a ray that starts at its actor's origin (t = 0), taken from the actor's origin
// sample instead of sampling the field; rays that start elsewhere (an origin outside the cube) and
// launches without origin samples leave it to walk_ray.
NAVI_HD void first_step(const TraceArgs& a, Ray& ray, const OriginSample& origin) {
  if ((origin.flags & kOriginValid) == 0 || ray.t != 0.0f || ray.res.steps != 0 || a.max_steps <= 0) return;
  ray.res.steps = 1;
  ray.w.leaf = origin.leaf;
  ray.w.last_brick = origin.last_brick;
  FieldSample f;
  f.dist = origin.dist;
  f.solid = (origin.flags & kOriginSolid) != 0;
  f.far_free = (origin.flags & kOriginFarFree) != 0;
  ray.end_d = f.dist;
  ray.done = take_step(a, ray, ray.w, f, ray.t, ray.prev_t, ray.prev_d);
}

// The main loop of sphere tracing (see docs/SDFDAG_RUNTIME.md): sample, hit tests, step, for at most
// max_steps samples. A ray that ends here is done (a miss, kSurface or kCrossing); one that runs out of
// samples is not (end_out_of_steps). The loop keeps its state in locals (the last sample's field in
// d, written out once after the loop) and leaves by `break`: the device compiler turns that into fewer
// moves per step than a done flag, and the exits into predicated branches.
NAVI_HD void walk_ray(const TraceArgs& a, Ray& ray) {
  const Scene& s = ray.s;
  Walker& w = ray.w;
  const BrickStore bricks = brick_store(a.bricks, a.brick_atlas, a.atlas_shift);
  float t = ray.t, prev_t = ray.prev_t, prev_d = ray.prev_d, d = ray.end_d;
  int steps = ray.res.steps;
  while (steps < a.max_steps) {
    ++steps;
    const float px = ray.ox + t * ray.dx, py = ray.oy + t * ray.dy, pz = ray.oz + t * ray.dz;
    const FieldSample f = walk_sample(a.grid, a.nodes, bricks, s, w, px, py, pz);
    d = f.dist;
    if (f.solid || d < 0.0f) {  // inside: refined after the walk (settle_hit), out of the loop
      ray.res.semantic = kCrossing;
      ray.done = true;
      break;
    }
    // Within the threshold of a surface while not moving away from it: a ray leaving the surface it
    // starts on is not stopped by it, and none is at its first sample (prev_d starts at -1). The
    // threshold grows with the distance travelled, so that a ray stops once the surface lies within
    // a fixed fraction of its angular footprint.
    if (!f.far_free && d < ray.eps + a.hit_slope * t && d <= prev_d) {
      ray.res.semantic = kSurface;
      ray.done = true;
      break;
    }
    float next = t + fmaxf(d, ray.eps);
    if (f.far_free) next = far_step(ray, w.leaf, t, d);
    prev_t = t;
    prev_d = d;
    t = next;
    if (next > ray.t1) {  // past the cube or the horizon: a miss
      ray.done = true;
      break;
    }
  }
  ray.t = t;
  ray.prev_t = prev_t;
  ray.prev_d = prev_d;
  ray.end_d = d;
  ray.res.steps = steps;
}

// The depth and class of a ray whose walk ended on the static surface (kSurface, kCrossing), after
// the main loop so that the rare refinement and the class lookup stay out of it.
// - kSurface (a free sample within the threshold, approaching): where the line through the last two
//   samples meets zero, t + d (t - t_prev) / (d_prev - d), at most kSecantReach d ahead and not past
//   the walk's end t1; t itself when the field did not fall. On a plane this is the exact crossing,
//   however shallow the ray, so a larger threshold costs little depth accuracy.
// - kCrossing: at the first sample, a hit there (an origin inside solid reports depth 0); later, the
//   surface lies between the previous (free) sample and this one: 6 bisection halvings, then one
//   secant step.
// The class is that of the last brick sampled, refinement samples included.
NAVI_HD void settle_hit(const TraceArgs& a, Ray& ray) {
  const BrickStore bricks = brick_store(a.bricks, a.brick_atlas, a.atlas_shift);
  float hit = ray.t;
  if (ray.res.semantic == kSurface) {
    const float d = ray.end_d;
    if (d < ray.prev_d) hit = ray.t + fminf(d * (ray.t - ray.prev_t) / (ray.prev_d - d), kSecantReach * d);
    hit = fminf(hit, ray.t1);
  } else if (ray.res.steps > 1) {
    float lo = ray.prev_t, hi = ray.t, flo = ray.prev_d, fhi = ray.end_d;
    for (int k = 0; k < kRefineIterations; ++k) {
      const float mid = 0.5f * (lo + hi);
      const FieldSample m = walk_sample(a.grid, a.nodes, bricks, ray.s, ray.w, ray.ox + mid * ray.dx,
                                        ray.oy + mid * ray.dy, ray.oz + mid * ray.dz);
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
  ray.res.depth = hit * ray.s.voxel;
  ray.res.semantic = class_semantic(a.brick_class, ray.w.last_brick);
}

// Writes a finished ray's outputs. A ray whose walk ended without a hit keeps the primitive hit
// written before its walk (kPrimStashed), if any.
template <bool kPrims>
NAVI_HD void finish_ray(const TraceArgs& a, Ray& ray) {
  if (a.out_steps != nullptr) a.out_steps[ray.out] = ray.res.steps;
  if (kPrims && ray.res.semantic == kPrimStashed) return;
  write_hit(a, ray.out, ray.res.depth, ray.res.semantic > 0 ? ray.res.semantic : 0);
}

// Whether a launch traces primitives (picks the trace_item instantiation).
NAVI_HD bool has_prims(const TraceArgs& a) { return a.prims != nullptr && a.prims_per_world > 0; }

// Traces work item j of actor b to the end: ray ray_order[j] (or j). The order only decides which
// rays run side by side in a GPU warp (coherent neighbours take similar step counts); results do
// not depend on it. An out-of-range ray_order entry is skipped (its output is not written). `t`: the
// launch's primitive tables, built before any ray (unused without primitives).
template <bool kPrims>
NAVI_HD void trace_item(const TraceArgs& a, int64_t b, int64_t j, const PrimTables& t) {
  const int64_t r = a.ray_order != nullptr ? static_cast<int64_t>(load_ro(a.ray_order + j)) : j;
  if (r < 0 || r >= a.num_rays) return;
  Ray ray = start_ray<kPrims>(a, b, j, r, t);
  if (!ray.done && a.origin_scratch != nullptr) first_step(a, ray, load_origin(a, b));
  if (!ray.done) walk_ray(a, ray);
  if (!ray.done) {
    end_out_of_steps(a, ray);
  } else if (ray.res.semantic == kSurface || ray.res.semantic == kCrossing) {
    settle_hit(a, ray);
  }
  finish_ray<kPrims>(a, ray);
}

// ---------------------------------------------------------------------------------------------
// One point query: the field in meters (trilinear in bricks, lower bounds in far cubes, the distance
// to the cube outside it), then the min with the point's world's primitives.

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
  float dist;
  if (ex > 0.0f || ey > 0.0f || ez > 0.0f) {
    dist = sqrtf(ex * ex + ey * ey + ez * ez) * s.voxel;
  } else {
    const Cell c = cell_of(px, py, pz, cell_max(s));
    const Leaf leaf = find_leaf(a.grid, a.nodes, s, c.ix, c.iy, c.iz);
    dist = leaf_field(brick_store(a.bricks, a.brick_atlas, a.atlas_shift), s, leaf, c, cell_fraction(px, c.fx), cell_fraction(py, c.fy), cell_fraction(pz, c.fz))
               .dist * s.voxel;
  }
  if (a.prims != nullptr && a.prims_per_world > 0) {
    const int64_t wid = static_cast<int64_t>(load_ro(a.prim_world + i));
    const int64_t owner = a.prim_owner != nullptr ? static_cast<int64_t>(load_ro(a.prim_owner + i)) : -2;
    if (wid >= 0 && wid < a.num_worlds) {
      const Vec3 p = v3(load_ro(a.points + i * 3), load_ro(a.points + i * 3 + 1), load_ro(a.points + i * 3 + 2));
      dist = fminf(dist, min_prim_distance(a.prims, wid, a.prims_per_world, owner, p));
    }
  }
  a.out_distance[i] = dist;
}

// ---------------------------------------------------------------------------------------------
// Obstacle sweep: how far primitive i may translate by delta before it would come within `skin` of
// the drone sphere (the torch twin is navi_env.obstacle_motion.sweep_ref). The drone centre relative
// to the primitive moves along p - t delta; the primitive's distance f is 1-Lipschitz in the point, so
// advancing t by (f - radius - skin) / |delta| never passes the drone however fast or thin the
// primitive, and f is convex in t (every primitive is convex): a primitive not approaching at t = 0
// moves the whole way.

NAVI_HD Vec3 moved_back(Vec3 p, Vec3 d, float t) { return v3(p.x - t * d.x, p.y - t * d.y, p.z - t * d.z); }

NAVI_HD void sweep_item(const SweepArgs& a, int64_t i) {
  const float* rec = a.prims + i * kPrimWords;
  if (load_ro(rec + kPrimKind) == 0.0f) {  // an empty slot moves freely and is infinitely far
    a.out_t[i] = 1.0f;
    a.out_distance[i] = bits_float(0x7F800000);
    return;
  }
  const int64_t b = i / a.prims_per_actor;
  const Vec3 d = v3(load_ro(a.delta + i * 3), load_ro(a.delta + i * 3 + 1), load_ro(a.delta + i * 3 + 2));
  const Vec3 p = v3(load_ro(a.drone + b * 3), load_ro(a.drone + b * 3 + 1), load_ro(a.drone + b * 3 + 2));
  const float length = fmaxf(sqrtf(dot(d, d)), 1e-9f);
  const float probe = fminf(1e-3f / length, 1.0f);  // a millimetre along the path
  float t = 1.0f;
  if (prim_distance(rec, moved_back(p, d, probe)) < prim_distance(rec, p)) {  // approaching
    t = 0.0f;
    for (int it = 0; it < a.iterations; ++it) {
      const float gap = prim_distance(rec, moved_back(p, d, t)) - a.radius - a.skin;
      t = fminf(t + fmaxf(gap, 0.0f) / length, 1.0f);
    }
  }
  a.out_t[i] = t;
  a.out_distance[i] = prim_distance(rec, moved_back(p, d, t));
}

}  // namespace navi
