// Distance stage (twin of distance.py): exact point-to-triangle distances near the triangles, by brick.
#pragma once

#include <array>
#include <limits>

#include "common.h"

namespace navi {

struct Triangles {
  std::vector<V3> a, b, c, ab, ac, bc, lo, hi;
  std::vector<V3> unit_normal;  // for the plane-distance pruning test only
  int64_t size() const { return static_cast<int64_t>(a.size()); }
};

// corners: (T, 3, 3) float64 in voxels. Zero-area triangles must already be dropped.
inline Triangles make_triangles(const double* corners, int64_t count) {
  Triangles t;
  for (auto* v : {&t.a, &t.b, &t.c, &t.ab, &t.ac, &t.bc, &t.lo, &t.hi, &t.unit_normal}) v->resize(count);
  for (int64_t i = 0; i < count; ++i) {
    const double* p = corners + 9 * i;
    V3 a{p[0], p[1], p[2]}, b{p[3], p[4], p[5]}, c{p[6], p[7], p[8]};
    t.a[i] = a;
    t.b[i] = b;
    t.c[i] = c;
    t.ab[i] = sub(b, a);
    t.ac[i] = sub(c, a);
    t.bc[i] = sub(c, b);
    t.lo[i] = {std::min(std::min(a.x, b.x), c.x), std::min(std::min(a.y, b.y), c.y), std::min(std::min(a.z, b.z), c.z)};
    t.hi[i] = {std::max(std::max(a.x, b.x), c.x), std::max(std::max(a.y, b.y), c.y), std::max(std::max(a.z, b.z), c.z)};
    const V3 nrm{t.ab[i].y * t.ac[i].z - t.ab[i].z * t.ac[i].y, t.ab[i].z * t.ac[i].x - t.ab[i].x * t.ac[i].z,
                 t.ab[i].x * t.ac[i].y - t.ab[i].y * t.ac[i].x};
    // Only well-conditioned triangles (sin of the corner angle at a >= 1e-3) get a plane test: on
    // slivers the cross product loses too many digits. A zero normal never prunes.
    const double len2 = norm2(nrm);
    const bool sharp = len2 > 1e-6 * norm2(t.ab[i]) * norm2(t.ac[i]);
    t.unit_normal[i] = sharp ? mul(nrm, 1.0 / std::sqrt(len2)) : V3{0.0, 0.0, 0.0};
  }
  return t;
}

inline bool nondegenerate(const double* p) {
  V3 ab{p[3] - p[0], p[4] - p[1], p[5] - p[2]}, ac{p[6] - p[0], p[7] - p[1], p[8] - p[2]};
  double nx = ab.y * ac.z - ab.z * ac.y;
  double ny = ab.z * ac.x - ab.x * ac.z;
  double nz = ab.x * ac.y - ab.y * ac.x;
  return nx != 0.0 || ny != 0.0 || nz != 0.0;
}

// Ericson's closest point on triangle i to p (same regions, order and formulas as distance.py).
inline V3 closest_point(const V3& p, const Triangles& t, int64_t i) {
  const V3 &a = t.a[i], &b = t.b[i], &c = t.c[i], &ab = t.ab[i], &ac = t.ac[i], &bc = t.bc[i];
  V3 ap = sub(p, a), bp = sub(p, b), cp = sub(p, c);
  double d1 = dot(ab, ap), d2 = dot(ac, ap);
  double d3 = dot(ab, bp), d4 = dot(ac, bp);
  double d5 = dot(ab, cp), d6 = dot(ac, cp);
  double vc = d1 * d4 - d3 * d2;
  double vb = d5 * d2 - d1 * d6;
  double va = d3 * d6 - d5 * d4;
  if (d1 <= 0 && d2 <= 0) return a;
  if (d3 >= 0 && d4 <= d3) return b;
  if (vc <= 0 && d1 >= 0 && d3 <= 0) return add(a, mul(ab, d1 / (d1 - d3)));
  if (d6 >= 0 && d5 <= d6) return c;
  if (vb <= 0 && d2 >= 0 && d6 <= 0) return add(a, mul(ac, d2 / (d2 - d6)));
  if (va <= 0 && (d4 - d3) >= 0 && (d5 - d6) >= 0) return add(b, mul(bc, (d4 - d3) / ((d4 - d3) + (d5 - d6))));
  double denom = 1.0 / (va + vb + vc);
  double v = vb * denom, w = vc * denom;
  return add(add(a, mul(ab, v)), mul(ac, w));
}

inline double squared_distance(const V3& p, const Triangles& t, int64_t i) { return norm2(sub(p, closest_point(p, t, i))); }

// Squared distance from p to triangle i's bounding box (a lower bound of its squared distance).
inline double box_squared(const V3& p, const Triangles& t, int64_t i) {
  double gx = std::max(std::max(t.lo[i].x - p.x, p.x - t.hi[i].x), 0.0);
  double gy = std::max(std::max(t.lo[i].y - p.y, p.y - t.hi[i].y), 0.0);
  double gz = std::max(std::max(t.lo[i].z - p.z, p.z - t.hi[i].z), 0.0);
  return gx * gx + gy * gy + gz * gz;
}

// Triangles per brick (CSR, ascending triangle index per brick): those whose box meets the brick's
// box [8b, 8b+8] grown by reach.
struct Buckets {
  int64_t nb = 0;
  std::vector<int64_t> start;  // (nb^3 + 1,)
  std::vector<int32_t> tris;
  int64_t count(int64_t brick) const { return start[brick + 1] - start[brick]; }
};

inline Buckets bucket_triangles(const Triangles& t, int64_t nb, double reach) {
  Buckets out;
  out.nb = nb;
  const int64_t total = nb * nb * nb;
  std::vector<std::array<int64_t, 6>> range(t.size());
  std::vector<char> hit(t.size(), 0);
  auto lo_b = [&](double v) { return std::clamp<int64_t>(static_cast<int64_t>(std::ceil((v - kBrickCells - reach) / kBrickCells)), 0, nb - 1); };
  auto hi_b = [&](double v) { return std::clamp<int64_t>(static_cast<int64_t>(std::floor((v + reach) / kBrickCells)), 0, nb - 1); };
  const double side = static_cast<double>(nb * kBrickCells);
  for (int64_t i = 0; i < t.size(); ++i) {
    const V3 &lo = t.lo[i], &hi = t.hi[i];
    if (hi.x + reach < 0 || hi.y + reach < 0 || hi.z + reach < 0) continue;
    if (lo.x - reach > side || lo.y - reach > side || lo.z - reach > side) continue;
    range[i] = {lo_b(lo.x), hi_b(hi.x), lo_b(lo.y), hi_b(hi.y), lo_b(lo.z), hi_b(hi.z)};
    hit[i] = range[i][0] <= range[i][1] && range[i][2] <= range[i][3] && range[i][4] <= range[i][5];
  }
  out.start.assign(total + 1, 0);
  for (int64_t i = 0; i < t.size(); ++i) {
    if (!hit[i]) continue;
    const auto& r = range[i];
    for (int64_t x = r[0]; x <= r[1]; ++x)
      for (int64_t y = r[2]; y <= r[3]; ++y)
        for (int64_t z = r[4]; z <= r[5]; ++z) ++out.start[(x * nb + y) * nb + z + 1];
  }
  for (int64_t b = 0; b < total; ++b) out.start[b + 1] += out.start[b];
  out.tris.resize(out.start[total]);
  std::vector<int64_t> fill(out.start.begin(), out.start.end() - 1);
  for (int64_t i = 0; i < t.size(); ++i) {
    if (!hit[i]) continue;
    const auto& r = range[i];
    for (int64_t x = r[0]; x <= r[1]; ++x)
      for (int64_t y = r[2]; y <= r[3]; ++y)
        for (int64_t z = r[4]; z <= r[5]; ++z) out.tris[fill[(x * nb + y) * nb + z]++] = static_cast<int32_t>(i);
  }
  return out;
}

constexpr double kPruneMargin = 1e-6;  // squared voxels

// Exact distance (float32 of the float64 distance) and nearest triangle on every lattice point whose
// distance is <= reach; +inf / -1 elsewhere. dist and tri are (R+1)^3, [x, y, z].
inline void nearest_triangles(const Triangles& t, const Buckets& buckets, int64_t resolution, double reach,
                              int threads, float* dist, int32_t* tri) {
  const int64_t n = resolution + 1, nb = buckets.nb;
  const double reach2 = reach * reach;
  std::fill(dist, dist + n * n * n, std::numeric_limits<float>::infinity());
  std::fill(tri, tri + n * n * n, -1);
  parallel_for(nb * nb * nb, threads, [&](int64_t brick) {
    const int64_t count = buckets.count(brick);
    if (count == 0) return;
    const int32_t* cand = buckets.tris.data() + buckets.start[brick];
    const int64_t bx = brick / (nb * nb), by = (brick / nb) % nb, bz = brick % nb;
    const int64_t ex = kBrickCells + (bx == nb - 1), ey = kBrickCells + (by == nb - 1), ez = kBrickCells + (bz == nb - 1);
    for (int64_t i = 0; i < ex; ++i)
      for (int64_t j = 0; j < ey; ++j)
        for (int64_t k = 0; k < ez; ++k) {
          const int64_t x = kBrickCells * bx + i, y = kBrickCells * by + j, z = kBrickCells * bz + k;
          const V3 p{static_cast<double>(x), static_cast<double>(y), static_cast<double>(z)};
          double best = std::numeric_limits<double>::infinity();
          int32_t best_t = -1;
          for (int64_t c = 0; c < count; ++c) {
            // Pruning never changes the result: a candidate is skipped only when a lower bound of its
            // squared distance (box, then plane) exceeds the best so far (or reach) by a margin far
            // above the rounding error of squared_distance.
            const double limit = std::min(best, reach2) + kPruneMargin;
            if (!(box_squared(p, t, cand[c]) <= limit)) continue;
            const double h = dot(sub(p, t.a[cand[c]]), t.unit_normal[cand[c]]);
            if (h * h > limit) continue;
            double d2 = squared_distance(p, t, cand[c]);
            if (d2 < best) {
              best = d2;
              best_t = cand[c];
            }
          }
          if (best <= reach2) {
            dist[lat(n, x, y, z)] = static_cast<float>(std::sqrt(best));
            tri[lat(n, x, y, z)] = best_t;
          }
        }
  });
}

// Class of the nearest drawn triangle within class_reach of each stored brick's centre lattice point
// (ties to the lowest index; 0 when none). Candidates: the 27 neighbouring buckets (built with a
// reach >= 0, they hold every triangle meeting those bricks, hence every one within 12 voxels).
inline void brick_classes(const Triangles& t, const Buckets& buckets, const uint8_t* face_class,
                          const uint8_t* stored, double class_reach, int threads, uint8_t* out) {
  const int64_t nb = buckets.nb;
  const double limit = class_reach * class_reach;
  parallel_for(nb * nb * nb, threads, [&](int64_t brick) {
    out[brick] = 0;
    if (!stored[brick]) return;
    const int64_t bx = brick / (nb * nb), by = (brick / nb) % nb, bz = brick % nb;
    const V3 centre{static_cast<double>(kBrickCells * bx + 4), static_cast<double>(kBrickCells * by + 4),
                    static_cast<double>(kBrickCells * bz + 4)};
    double best = std::numeric_limits<double>::infinity();
    int64_t best_t = -1;
    for (int64_t x = std::max<int64_t>(bx - 1, 0); x <= std::min(bx + 1, nb - 1); ++x)
      for (int64_t y = std::max<int64_t>(by - 1, 0); y <= std::min(by + 1, nb - 1); ++y)
        for (int64_t z = std::max<int64_t>(bz - 1, 0); z <= std::min(bz + 1, nb - 1); ++z) {
          const int64_t nbr = (x * nb + y) * nb + z;
          for (int64_t c = buckets.start[nbr]; c < buckets.start[nbr + 1]; ++c) {
            const int32_t ti = buckets.tris[c];
            double d2 = squared_distance(centre, t, ti);
            if (d2 < best || (d2 == best && ti < best_t)) {
              best = d2;
              best_t = ti;
            }
          }
        }
    if (best_t >= 0 && best <= limit) out[brick] = face_class[best_t];
  });
}

}  // namespace navi
