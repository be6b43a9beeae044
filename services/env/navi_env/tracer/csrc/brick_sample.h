// The field at a voxel-space point: trilinear in a brick (corner words on the host, the brick atlas
// texture on the device), the lower bound of a far cube (FieldSample), and walk_sample, which samples
// through a ray's cached leaf (Walker) and looks the leaf up only when the point leaves it.
#pragma once

#include "trace_common.h"
#include "scene_record.h"

namespace navi {

constexpr float kSampleBias = 8388736.0f;      // 2^23 + 128: corner bytes hold sample + 128

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

// Where a brick's samples are read on the device: the atlas texel coordinate of point p is
// p + (ax, ay, az), taken once when a walk enters the brick (brick_frame) instead of from p's cell and
// its fractions at every sample. Brick b's tile starts at texel 9 t with t = (b mod 2^s, (b >> s) mod
// 2^s, b >> 2s) for the store's shift s, and texel (x, y, z) of a tile holds sample (x, y, z) as a
// signed normalised byte (sample / 127). With linear filtering and unnormalised coordinates the unit
// interpolates the 8 texels around (x - 0.5, y - 0.5, z - 0.5), so a point at fraction u of the
// brick's local cell l samples at 9 t + l + u + 0.5. With the brick's corner c that is p + a for
// a = 9 t - c + 0.5: both sums are exact until the last addition, so they round to the same float.
// The host build reads the corner words instead and leaves the frame at zero.
struct BrickFrame {
  float ax, ay, az;
};

NAVI_HD BrickFrame no_frame() {
  BrickFrame f;
  f.ax = f.ay = f.az = 0.0f;
  return f;
}

// The frame of brick leaf `leaf` of scene s.
NAVI_HD BrickFrame brick_frame(const BrickStore& bs, const Scene& s, const Leaf& leaf) {
#ifdef __CUDA_ARCH__
  const uint32_t b = s.brick_offset + leaf.payload;  // corpus index
  const int cx = leaf.cx, cy = leaf.cy, cz = leaf.cz;
  // a = 9 t - c + 0.5 as the float 2^22 + (9 t - c + 2^21) + 0.5 minus 2^22 + 2^21, with no
  // conversion and no separate + 0.5: floats in [2^22, 2^23) step by 0.5, so that float's bits are
  // those of 2^22 plus 2 (9 t - c + 2^21) + 1, and both it and the subtraction are exact while
  // |9 t - c| < 2^21 (atlas texels below 2^14, the 3-d texture limit; corners at most 4,096).
  constexpr int kHalfBits = 0x4A800000 + (1 << 22) + 1;  // bits of 2^22, plus 2 * 2^21 + 1
  constexpr float kHalfZero = 6291456.0f;               // 2^22 + 2^21
  const uint32_t mask = (1u << bs.shift) - 1u;
  const uint32_t tx = (b & mask) * 18u, ty = ((b >> bs.shift) & mask) * 18u;
  const uint32_t tz = (b >> (2 * bs.shift)) * 18u;  // 2 * 9 t
  BrickFrame f;
  // c = cx - kCellBias (scene_record.h): 2 kCellBias joins the constant, all mod 2^32.
  constexpr uint32_t kBase = static_cast<uint32_t>(kHalfBits) + 2u * static_cast<uint32_t>(kCellBias);
  f.ax = __int_as_float(static_cast<int>(kBase + tx - 2u * static_cast<uint32_t>(cx))) - kHalfZero;
  f.ay = __int_as_float(static_cast<int>(kBase + ty - 2u * static_cast<uint32_t>(cy))) - kHalfZero;
  f.az = __int_as_float(static_cast<int>(kBase + tz - 2u * static_cast<uint32_t>(cz))) - kHalfZero;
  return f;
#else
  (void)bs;
  (void)s;
  (void)leaf;
  return no_frame();
#endif
}

// The field at a voxel-space point p inside the cube whose cell (ix, iy, iz) lies in `leaf`.
// Far codes give their lower bound (negative for solid); `solid` marks a far-solid cube.
struct FieldSample {
  float dist;     // voxels
  bool solid;     // inside a far-solid cube
  bool far_free;  // inside a far-free cube (dist is its lower bound)
};

// The field at point p, in cell c of `leaf` (c clamped into the cube; p on its faces or inside it).
NAVI_HD FieldSample leaf_field(const BrickStore& bricks, const Scene& s, const Leaf& leaf, const BrickFrame& frame,
                               const Cell& c, float px, float py, float pz) {
  FieldSample f;
  f.solid = leaf.tag == kTagFarSolid;
  f.far_free = leaf.tag != kTagBrick && leaf.tag != kTagFarSolid;
  if (leaf.tag == kTagBrick) {
#ifdef __CUDA_ARCH__
    // The unit's weights are 8-bit fixed point (CUDA C++ Programming Guide, "Linear Filtering"): the
    // field differs from the exact trilinear of the host build by at most about 1/256 of the samples'
    // spread across the cell (docs/SDFDAG_RUNTIME.md). The atlas has one level, so the read names
    // level 0 (a TEX.LZ, with no level operand to set on every step), and the scale 127 quant comes
    // with the scene record rather than from a multiply per sample.
    (void)c;
    f.dist = tex3DLod<float>(static_cast<cudaTextureObject_t>(bricks.atlas), px + frame.ax, py + frame.ay,
                             pz + frame.az, 0.0f) *
             s.atlas_scale;
#else
    // The cell lies in this brick, so its local index is in [0, 7] and its corner words are
    // leaf.words + corner_offset(ix, iy, iz) (the brick corner's offset cancels mod 2^32).
    (void)frame;
    f.dist = brick_distance(bricks.words + (leaf.words + corner_offset(c.ix, c.iy, c.iz)), s.quant,
                            cell_fraction(px, c.fx), cell_fraction(py, c.fy), cell_fraction(pz, c.fz));
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
  BrickFrame frame;     // the brick's frame while the leaf is a brick
  uint32_t last_brick;  // corpus index of the last brick sampled (the class of a hit), or kNoBrick
};

NAVI_HD void walker_init(Walker& w) {
  w.leaf.cx = w.leaf.cy = w.leaf.cz = kNoCorner;
  w.leaf.shift = kBrickShift;
  w.leaf.tag = kTagFarFree;
  w.leaf.payload = 0;
  w.leaf.words = 0;
  w.frame = no_frame();
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
  // A sample in the cached leaf needs only p on the device (the brick frame) and the cell on the host;
  // the lookup below runs on most warp steps in some lane, so it is kept short (docs/PERFORMANCE.md).
  if (!leaf_contains(w.leaf, c.ix, c.iy, c.iz)) {
    if (!cell_in_cube(c, s.resolution)) {  // on a face or just past it: the nearest point of the cube
      px = fminf(fmaxf(px, 0.0f), res);
      py = fminf(fmaxf(py, 0.0f), res);
      pz = fminf(fmaxf(pz, 0.0f), res);
      c = cell_of(px, py, pz, cell_max(s));
    }
    w.leaf = find_leaf(grid, nodes, s, c.ix, c.iy, c.iz);
    // Samples in the cached leaf are in the same brick, so the last brick sampled changes only here.
    if (w.leaf.tag == kTagBrick) {
      w.last_brick = s.brick_offset + w.leaf.payload;
      w.frame = brick_frame(bricks, s, w.leaf);
    }
  }
  return leaf_field(bricks, s, w.leaf, w.frame, c, px, py, pz);
}

}  // namespace navi
