// One ray through the static scene: the actor's origin sample (OriginSample), start_ray (primitives
// first, then the slab clip to the cube and horizon), the walk loop with its far step (walk_ray,
// take_step, far_step), settle_hit (the secant and bisection refinement of a hit) and finish_ray.
#pragma once

#include "trace_common.h"
#include "launch_args.h"
#include "scene_record.h"
#include "brick_sample.h"
#include "primitives.h"

namespace navi {

// Hit epsilon in voxels when the caller passes hit_epsilon <= 0; also the minimum step.
constexpr float kDefaultHitEpsilonVoxels = 0.1f;
constexpr int kRefineIterations = 6;    // bisection halvings after a sign change, then one secant
constexpr float kSecantReach = 16.0f;   // a stop within the threshold reports the secant's zero, at most this many d ahead

// ---------------------------------------------------------------------------------------------
// The origin sample and the actor's frame. Every ray of an actor whose origin lies in its scene's cube
// starts at t = 0, so its first sample is at the origin itself (o + 0 d = o exactly, fused or not): the
// same field, leaf and brick for all R rays. A launch with origin_scratch takes that sample once per
// actor before the rays (one thread per actor), together with what every ray of the actor would
// otherwise derive again: the scene id, the origin in voxel space and the cosine and sine of the yaw.
// Each ray then starts from the record (start_ray) and takes its first step from it (first_step):
// bit-identical to each ray loading, converting and sampling for itself, and on short rays a per-ray
// set-up costs as many instructions as the walk (docs/PERFORMANCE.md).
constexpr int32_t kOriginValid = 1;     // the record holds the frame and the sample (origin finite, in the cube)
constexpr int32_t kOriginSolid = 2;     // FieldSample.solid
constexpr int32_t kOriginFarFree = 4;   // FieldSample.far_free

// What a ray of the actor starts from (the first 32 bytes of the record: two 16-byte loads).
struct alignas(16) ActorFrame {
  float ox, oy, oz;        // origin, voxel space of the actor's scene
  int32_t flags;           // kOriginValid | kOriginSolid | kOriginFarFree; 0: the rays start on their own
  float cos_yaw, sin_yaw;  // yaw_cos_sin of the actor's yaw (1, 0 without yaw)
  int32_t scene;           // scene id
  float dist;              // FieldSample.dist at the origin, voxels
};

// The walker after the origin sample (read by first_step only).
struct alignas(16) OriginWalker {
  Leaf leaf;            // the walker's leaf after the sample
  BrickFrame frame;     // its brick frame
  uint32_t last_brick;  // the walker's last brick after the sample
};

struct alignas(16) OriginSample {
  ActorFrame actor;
  OriginWalker walker;
};

static_assert(sizeof(ActorFrame) == 32 && sizeof(OriginSample) == 80,
              "mirrored by navi_env.tracer.abi.ORIGIN_SAMPLE_BYTES");

// A frame no ray starts from (launches without origin samples).
NAVI_HD ActorFrame no_actor_frame() {
  ActorFrame f;
  f.ox = f.oy = f.oz = 0.0f;
  f.flags = 0;
  f.cos_yaw = 1.0f;
  f.sin_yaw = 0.0f;
  f.scene = -1;
  f.dist = 0.0f;
  return f;
}

// Actor b's record (flags 0 where its rays cannot use one: bad scene id, non-finite origin, an origin
// outside the cube, whose rays start at their own entry times).
NAVI_HD OriginSample origin_sample(const TraceArgs& a, int64_t b) {
  Walker w;
  walker_init(w);
  OriginSample o;
  o.actor = no_actor_frame();
  o.walker.leaf = w.leaf;
  o.walker.frame = w.frame;
  o.walker.last_brick = w.last_brick;
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
  o.actor.ox = ox;
  o.actor.oy = oy;
  o.actor.oz = oz;
  if (a.yaw != nullptr) yaw_cos_sin(load_ro(a.yaw + b), o.actor.cos_yaw, o.actor.sin_yaw);
  o.actor.scene = static_cast<int32_t>(sid);
  o.actor.dist = f.dist;
  o.actor.flags = kOriginValid | (f.solid ? kOriginSolid : 0) | (f.far_free ? kOriginFarFree : 0);
  o.walker.leaf = w.leaf;
  o.walker.frame = w.frame;
  o.walker.last_brick = w.last_brick;
  return o;
}

// A record in origin_scratch (16-byte read-only loads on the device).
template <typename T>
NAVI_HD T load_record(const T* p) {
#ifdef __CUDA_ARCH__
  static_assert(sizeof(T) % 16 == 0, "whole 16-byte words");
  T v;
  const int4* src = reinterpret_cast<const int4*>(p);
  int4* dst = reinterpret_cast<int4*>(&v);
  for (int k = 0; k < static_cast<int>(sizeof(T) / 16); ++k) dst[k] = __ldg(src + k);
  return v;
#else
  return *p;
#endif
}

// Actor b's frame (a frame with flags 0 for a launch without origin samples).
NAVI_HD ActorFrame load_frame(const TraceArgs& a, int64_t b) {
  if (a.origin_scratch == nullptr) return no_actor_frame();
  return load_record(&(static_cast<const OriginSample*>(a.origin_scratch) + b)->actor);
}

// What every ray of actor b starts from, taken once per actor where a launch traces several of its
// rays in a row (a CUDA block's strip of ray groups): the frame, whether the scene id is in range, the
// scene record, and the world origin where a ray needs it (no origin sample, or primitives).
struct ActorStart {
  ActorFrame frame;  // load_frame
  bool valid;        // the scene id lies in [0, num_scenes)
  Scene s;           // its record (valid actors)
  Vec3 world;        // the origin, meters (without kOriginValid, or with primitives; else 0)
};

template <bool kPrims>
NAVI_HD ActorStart actor_start(const TraceArgs& a, int64_t b) {
  ActorStart st;
  st.frame = load_frame(a, b);
  const bool framed = (st.frame.flags & kOriginValid) != 0;
  const int64_t sid = framed ? static_cast<int64_t>(st.frame.scene) : load_scene_id(a.scene_ids, a.scene_id_bytes, b);
  st.valid = sid >= 0 && sid < a.num_scenes;
  st.s = st.valid ? load_scene(a.scenes, sid) : Scene{};  // nothing read past the table
  // A framed actor's origin is finite (it lies in the cube); the world point is needed for primitives.
  st.world = v3(0.0f, 0.0f, 0.0f);
  if (!framed || kPrims) {
    st.world = v3(load_ro(a.origins + b * 3), load_ro(a.origins + b * 3 + 1), load_ro(a.origins + b * 3 + 2));
  }
  return st;
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
// the device (exact, no conversion instruction). The time is computed on every axis and the parallel
// one replaced after, with no branch: the far step of the three axes compiled to 30 SASS instructions
// with this select, 38 with an early return.
NAVI_HD float exit_time(float o, float d, float inv, int c, int edge) {
  const int face = d > 0.0f ? c + edge : c;
#ifdef __CUDA_ARCH__
  const float bound = __int_as_float(face) - kTwo23;  // face: kCellBias + coordinate
#else
  const float bound = static_cast<float>(face);
#endif
  const float time = (bound - o) * inv;  // finite or infinite, never NaN, also where d = 0 (inv = kBig)
  return d != 0.0f ? time : kBig;
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
  float end_d;               // the field at the sample that stopped the walk (kSurface, kCrossing)
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

// Where a ray from a point inside the closed slab [0, res] leaves it along one axis: t1 narrowed to the
// face ahead. The same time as clip_slab's for such a point (the time to the face behind is <= 0).
NAVI_HD float slab_exit(float o, float d, float inv, float res, float t1) {
  return d != 0.0f ? fminf(t1, ((d > 0.0f ? res : 0.0f) - o) * inv) : t1;
}

// Sets up work item j (ray r) of actor b (writing to element b * R + r); rays that are decided before
// the first sample (bad scene id, non-finite input, missing the cube) come back done. `st`: the actor's
// start (actor_start); with kOriginValid in its frame the voxel-space origin and the yaw come from the
// frame and the origin lies in the cube (the clip starts at t = 0), else the ray derives them itself.
// kPrims: the launch has primitives (a separate instantiation, so a launch without them runs the plain
// walk: one kernel serving both is slower, docs/PERFORMANCE.md); `t`: its tables (prim_tables).
template <bool kPrims>
NAVI_HD Ray start_ray(const TraceArgs& a, int64_t b, int64_t j, int64_t r, const PrimTables& t,
                      const ActorStart& st) {
  const ActorFrame& f = st.frame;
  const bool framed = (f.flags & kOriginValid) != 0;
  Ray ray;
  ray.out = b * a.num_rays + r;
  ray.res.depth = a.horizon;
  ray.res.semantic = 0;
  ray.res.steps = 0;
  ray.done = true;
  if (!st.valid) {
    ray.res.depth = kNaN();
    return ray;
  }
  const float* dir = a.directions + (a.directions_shared ? r : b * a.num_rays + r) * 3;
  float dx = load_ro(dir), dy = load_ro(dir + 1);
  const float dz = load_ro(dir + 2);
  if (a.yaw != nullptr) {
    if (framed) {
      rotate_cs(f.cos_yaw, f.sin_yaw, dx, dy);
    } else {
      rotate_yaw(load_ro(a.yaw + b), dx, dy);
    }
  }
  const Vec3 world = st.world;
  if (!(finite(world.x) && finite(world.y) && finite(world.z) && finite(dx) && finite(dy) && finite(dz))) {
    ray.res.semantic = kOutOfSteps;
    return ray;
  }
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
  const Scene& s = st.s;
  ray.s = s;
  float ox = f.ox, oy = f.oy, oz = f.oz;
  if (!framed) {
    ox = (world.x - s.ox) * s.inv_voxel;
    oy = (world.y - s.oy) * s.inv_voxel;
    oz = (world.z - s.oz) * s.inv_voxel;
    if (!(finite(ox) && finite(oy) && finite(oz))) {
      ray.res.semantic = kOutOfSteps;
      return ray;
    }
  }
  const float res = static_cast<float>(s.resolution);
  ray.eps = a.hit_epsilon > 0.0f ? a.hit_epsilon * s.inv_voxel : kDefaultHitEpsilonVoxels;

  // Clip the ray to the cube and the horizon (slab test); a ray that misses the cube is a miss.
  ray.inv_x = dx != 0.0f ? 1.0f / dx : kBig;
  ray.inv_y = dy != 0.0f ? 1.0f / dy : kBig;
  ray.inv_z = dz != 0.0f ? 1.0f / dz : kBig;
  float t0 = 0.0f, t1 = reach * s.inv_voxel;
  if (framed) {  // from inside the cube: only the faces ahead
    t1 = slab_exit(ox, dx, ray.inv_x, res, t1);
    t1 = slab_exit(oy, dy, ray.inv_y, res, t1);
    t1 = slab_exit(oz, dz, ray.inv_z, res, t1);
  } else {
    clip_slab(ox, dx, ray.inv_x, res, t0, t1);
    clip_slab(oy, dy, ray.inv_y, res, t0, t1);
    clip_slab(oz, dz, ray.inv_z, res, t0, t1);
  }
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
// share far_step, which compiles to the same device code as the step written out), because a loop
// calling this function (with the first step peeled inside walk_ray) compiles to slower device code
// (docs/PERFORMANCE.md). Tests trace with and without origin samples and demand the same outputs bit
// for bit, which holds the two copies together.
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
NAVI_HD void first_step(const TraceArgs& a, Ray& ray, int64_t b, const ActorFrame& origin) {
  if ((origin.flags & kOriginValid) == 0 || ray.t != 0.0f || ray.res.steps != 0 || a.max_steps <= 0) return;
  const OriginWalker w = load_record(&(static_cast<const OriginSample*>(a.origin_scratch) + b)->walker);
  ray.res.steps = 1;
  ray.w.leaf = w.leaf;
  ray.w.frame = w.frame;
  ray.w.last_brick = w.last_brick;
  FieldSample f;
  f.dist = origin.dist;
  f.solid = (origin.flags & kOriginSolid) != 0;
  f.far_free = (origin.flags & kOriginFarFree) != 0;
  ray.end_d = f.dist;
  ray.done = take_step(a, ray, ray.w, f, ray.t, ray.prev_t, ray.prev_d);
}

// The main loop of sphere tracing (see docs/SDFDAG_RUNTIME.md): sample, hit tests, step, for at most
// max_steps samples. A ray that ends here is done (a miss, kSurface or kCrossing); one that runs out of
// samples is not (end_out_of_steps). The loop keeps its state in locals and has one exit for both hit
// tests: which of them stopped the ray is read after the loop from what the stop leaves behind (the
// last sample's field, written to end_d at the stop, and the walker's leaf), and a miss from t past
// t1, where no stop can leave it. An exit per outcome makes the device compiler set the outcome's
// codes in registers on every step; one exit keeps the common brick step short (docs/PERFORMANCE.md,
// "Design lessons").
NAVI_HD void walk_ray(const TraceArgs& a, Ray& ray) {
  const Scene& s = ray.s;
  Walker& w = ray.w;
  const BrickStore bricks = brick_store(a.bricks, a.brick_atlas, a.atlas_shift);
  float t = ray.t, prev_t = ray.prev_t, prev_d = ray.prev_d;
  int steps = ray.res.steps;
  bool stop = false;
  while (steps < a.max_steps) {
    ++steps;
    const float px = ray.ox + t * ray.dx, py = ray.oy + t * ray.dy, pz = ray.oz + t * ray.dz;
    const FieldSample f = walk_sample(a.grid, a.nodes, bricks, s, w, px, py, pz);
    const float d = f.dist;
    // Inside (kCrossing: refined after the walk by settle_hit), or within the threshold of a surface
    // while not moving away from it (kSurface): a ray leaving the surface it starts on is not stopped
    // by it, and none is at its first sample (prev_d starts at -1). The threshold grows with the
    // distance travelled, so that a ray stops once the surface lies within a fixed fraction of its
    // angular footprint.
    if (f.solid || d < 0.0f || (!f.far_free && d < ray.eps + a.hit_slope * t && d <= prev_d)) {
      ray.end_d = d;
      stop = true;
      break;
    }
    float next = t + fmaxf(d, ray.eps);
    if (f.far_free) next = far_step(ray, w.leaf, t, d);
    prev_t = t;
    prev_d = d;
    t = next;
    if (next > ray.t1) break;  // past the cube or the horizon: a miss
  }
  if (stop) {  // the sample that stopped the ray is still the walker's: its leaf and end_d tell which test
    ray.res.semantic = (w.leaf.tag == kTagFarSolid || ray.end_d < 0.0f) ? kCrossing : kSurface;
    ray.done = true;
  } else if (t > ray.t1) {  // a stop leaves t at its sample, at most t1; running out of steps too
    ray.done = true;
  }
  ray.t = t;
  ray.prev_t = prev_t;
  ray.prev_d = prev_d;
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

}  // namespace navi
