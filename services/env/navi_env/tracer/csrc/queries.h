// The per-item entry points of the three launches: trace_item (one ray to the end, through ray_walk.h),
// sample_point (the field and the primitives at one point) and sweep_item (how far one primitive may
// move before it comes within the skin of the drone sphere). What a trace launch prepares before its
// rays lives beside what it serves: origin_sample in ray_walk.h, the primitive tables in primitives.h.
#pragma once

#include "trace_common.h"
#include "launch_args.h"
#include "scene_record.h"
#include "brick_sample.h"
#include "primitives.h"
#include "ray_walk.h"

namespace navi {

// Whether a launch traces primitives (picks the trace_item instantiation).
NAVI_HD bool has_prims(const TraceArgs& a) { return a.prims != nullptr && a.prims_per_world > 0; }

// Traces work item j of actor b to the end: ray ray_order[j] (or j). The order only decides which
// rays run side by side in a GPU warp (coherent neighbours take similar step counts); results do
// not depend on it. An out-of-range ray_order entry is skipped (its output is not written). `st`: the
// actor's start (actor_start<kPrims>(a, b)); `t`: the launch's primitive tables, built before any ray
// (unused without primitives).
template <bool kPrims>
NAVI_HD void trace_item(const TraceArgs& a, const ActorStart& st, int64_t b, int64_t j, const PrimTables& t) {
  const int64_t r = a.ray_order != nullptr ? static_cast<int64_t>(load_ro(a.ray_order + j)) : j;
  if (r < 0 || r >= a.num_rays) return;
  Ray ray = start_ray<kPrims>(a, b, j, r, t, st);
  if (!ray.done) first_step(a, ray, b, st.frame);
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
    const BrickStore bricks = brick_store(a.bricks, a.brick_atlas, a.atlas_shift);
    const Cell c = cell_of(px, py, pz, cell_max(s));
    const Leaf leaf = find_leaf(a.grid, a.nodes, s, c.ix, c.iy, c.iz);
    const BrickFrame frame = leaf.tag == kTagBrick ? brick_frame(bricks, s, leaf) : no_frame();
    dist = leaf_field(bricks, s, leaf, frame, c, px, py, pz).dist * s.voxel;
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
// the drone sphere (the torch twin is navi_env.sim.obstacles.sweep_ref). The drone centre relative
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
