// Dynamic primitives (obstacles) and their culling: the 16-word records (PrimWord), exact distance
// and ray entry per kind, the bounding-sphere cull entries of one ray origin (PrimCull), the
// per-launch tables (RayCone, PrimTables: group cones and masks) and the first hit along a ray.
#pragma once

#include "trace_common.h"
#include "launch_args.h"

namespace navi {

// ---------------------------------------------------------------------------------------------
// Dynamic primitives: per-world spheres, capsules and boxes composed with the static field by min.
// A record is 16 float32 words (64 bytes), mirrored in navi_env/tracer/primitives.py; small integers (kind,
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

// cos and sin of a yaw angle, as the platform's libm computes them.
NAVI_HD void yaw_cos_sin(float yaw, float& c, float& sn) {
#ifdef __CUDA_ARCH__
  sincosf(yaw, &sn, &c);
#else
  c = cosf(yaw);
  sn = sinf(yaw);
#endif
}

// (dx, dy) rotated about +Z by the angle whose cosine and sine are c and sn.
NAVI_HD void rotate_cs(float c, float sn, float& dx, float& dy) {
  const float rx = c * dx - sn * dy;
  const float ry = sn * dx + c * dy;
  dx = rx;
  dy = ry;
}

// The body-frame direction rotated by yaw about +Z.
NAVI_HD void rotate_yaw(float yaw, float& dx, float& dy) {
  float c, sn;
  yaw_cos_sin(yaw, c, sn);
  rotate_cs(c, sn, dx, dy);
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

}  // namespace navi
