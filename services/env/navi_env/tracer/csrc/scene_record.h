// Scene records and the leaf lookup: the child-word tags and the leaf-grid entry layout, the 16-word
// scene record (SceneWord) and its decoded form (Scene), lattice cells of voxel-space points, and
// find_leaf, the leaf (brick or far cube) holding a cell, with leaf_contains, the test that lets a
// ray keep its cached leaf (brick_sample.h, Walker).
#pragma once

#include "trace_common.h"

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
// Leaf-grid entries: tag (bits 31-30) | log2 cube edge (bits 29-26) | payload (bits 25-0).
constexpr int kGridShiftBit = 26;
constexpr uint32_t kGridPayloadMask = 0x03FFFFFFu;

// Cell indices, and the leaf corners made from them, carry a bias on the device: kCellBias plus the
// index, which is the bits of the float 2^23 + index, the bits the floor's rounding add leaves
// (cell_axis). The walk's containment test XORs such bits straight from the add, and the far step's
// face coordinates are floats by the same bits, with no subtraction on either side; the bias has no
// bits below 2^23, so shifts by up to 23 and the XOR of two biased indices see the plain index. The
// leaf grid's index is linear in the cells, so the bias comes off with the scene's grid offset
// (load_scene). The host keeps plain indices (kCellBias 0).
#ifdef __CUDA_ARCH__
constexpr int32_t kCellBias = kTwo23Bits;
#else
constexpr int32_t kCellBias = 0;
#endif

// Scene record layout (int32 words; float fields hold float32 bits). Mirrored in navi_env/tracer/scene.py.
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

// A scene record decoded into registers. It keeps only what the walk reads, combined once: the grid
// shift instead of L, and no R - 1 as a float (cell_max, recomputed on the rare clamped path), so the
// main loop does not spill L and reload it from local memory on every leaf change, ahead of the grid
// load. Taken once per actor before a block's rays (actor_start), the record's fields sit in uniform
// registers.
struct Scene {
  uint32_t root, node_offset, brick_offset, grid_offset;
  int resolution;
  int grid_depth;  // D
  int grid_shift;  // log2 of a grid cell's edge in voxels: L + 3 - D
  float ox, oy, oz, voxel, inv_voxel, quant;
  float atlas_scale;  // 127 quant: voxels per unit of the brick atlas' normalised reads (device)
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
  // The grid index ((gz 2^D) + gy) 2^D + gx of biased cells exceeds the plain one by b (4^D + 2^D + 1),
  // b = kCellBias >> grid_shift (mod 2^32; the host's b is 0).
  const uint32_t gb = static_cast<uint32_t>(kCellBias) >> s.grid_shift;
  s.grid_offset -= (((gb << s.grid_depth) + gb) << s.grid_depth) + gb;
  s.ox = bits_float(w[kOriginX]);
  s.oy = bits_float(w[kOriginY]);
  s.oz = bits_float(w[kOriginZ]);
  s.voxel = bits_float(w[kVoxelSize]);
  s.inv_voxel = bits_float(w[kInvVoxelSize]);
  s.quant = bits_float(w[kQuantStep]);
  s.atlas_scale = 127.0f * s.quant;
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

// The lattice cell of a voxel-space point: indices (plus kCellBias) and the indices as floats (exact).
struct Cell {
  int ix, iy, iz;
  float fx, fy, fz;  // float(ix), float(iy), float(iz)
};

// floor(x) clamped to [0, R - 1] (NaN lands on 0), as an int (plus kCellBias) and as a float. The
// clamp is taken before the floor, which gives the same cell; on the device the floor is a round-down
// add of 2^23, exact for 0 <= x < 2^23, whose bits are the biased index and whose value minus 2^23 is
// its float.
NAVI_HD void cell_axis(float x, float cell_max, int& i, float& f) {
  const float c = fminf(fmaxf(x, 0.0f), cell_max);
#ifdef __CUDA_ARCH__
  const float r = __fadd_rd(c, kTwo23);
  i = __float_as_int(r);  // kCellBias + floor
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

// floor(x) without the clamp, for 0 <= x < R the same as cell_axis; below 0 an index below the range,
// at or past R one above it (cell_in_cube; the host clamps to [-1, R] first so that the conversion
// stays defined).
NAVI_HD void cell_axis_unclamped(float x, float res, int& i, float& f) {
#ifdef __CUDA_ARCH__
  (void)res;
  const float r = __fadd_rd(x, kTwo23);
  i = __float_as_int(r);  // kCellBias + floor
  f = r - kTwo23;
#else
  f = floorf(fminf(fmaxf(x, -1.0f), res));
  i = static_cast<int>(f);
#endif
}

// Whether a cell index lies in [0, R - 1] on every axis (R is a power of two, so the or of three
// indices in range stays below R, and a negative one sets the sign bit). On the device the or of three
// biased indices in range is the bias plus the or of the indices; a point below 0 rounds to the bits of
// a float in [2^22, 2^23), below the bias, whose or with biased indices leaves a difference of at least
// 2^23, and alone a negative one.
NAVI_HD bool cell_in_cube(const Cell& c, int res) {
  return static_cast<uint32_t>(c.ix | c.iy | c.iz) - static_cast<uint32_t>(kCellBias) < static_cast<uint32_t>(res);
}

// The leaf holding cell (ix, iy, iz): one leaf-grid load (the descent from the root to depth D,
// done once at load time by scene.py), then, for scenes deeper than the grid, the bounded stackless
// descent through the nodes for the remaining L - D levels.
NAVI_HD Leaf find_leaf(const uint32_t* grid, const uint32_t* nodes, const Scene& s, int ix, int iy, int iz) {
  const int gshift = s.grid_shift;
  const uint32_t gx = static_cast<uint32_t>(ix >> gshift), gy = static_cast<uint32_t>(iy >> gshift);
  const uint32_t gz = static_cast<uint32_t>(iz >> gshift);  // plus kCellBias >> gshift on the device
  // The entry's index in 32 bits (a corpus grid holds fewer than 2^32 entries: scene.py MAX_OFFSET), so
  // the address is one wide multiply-add rather than two 64-bit additions.
  const uint32_t entry = load_ro(grid + (s.grid_offset + ((((gz << s.grid_depth) + gy) << s.grid_depth) + gx)));
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

}  // namespace navi
