// Sign stage (twin of sign.py): walls, the flood fill from seeds or the border, leak fallback, and
// the sign of wall points from probes on both sides of the nearest surface.
#pragma once

#include <numeric>

#include "distance.h"

namespace navi {

constexpr float kWall = 0.5f;
constexpr double kProbe = 1.5;

struct FillResult {
  bool inside_seeded = false;
  bool leaked = false;
  int64_t seeds_used = 0;
};

inline bool on_border(int64_t n, int64_t x, int64_t y, int64_t z) {
  return x == 0 || y == 0 || z == 0 || x == n - 1 || y == n - 1 || z == n - 1;
}

// 6-connected BFS over non-wall points from the points already marked in `reached`.
inline void flood(int64_t n, const uint8_t* wall, uint8_t* reached) {
  std::vector<int64_t> queue;
  for (int64_t i = 0; i < n * n * n; ++i)
    if (reached[i]) queue.push_back(i);
  const int64_t step[3] = {n * n, n, 1};
  for (size_t head = 0; head < queue.size(); ++head) {
    const int64_t i = queue[head];
    const int64_t coord[3] = {i / (n * n), (i / n) % n, i % n};
    for (int axis = 0; axis < 3; ++axis) {
      if (coord[axis] > 0) {
        const int64_t j = i - step[axis];
        if (!reached[j] && !wall[j]) {
          reached[j] = 1;
          queue.push_back(j);
        }
      }
      if (coord[axis] < n - 1) {
        const int64_t j = i + step[axis];
        if (!reached[j] && !wall[j]) {
          reached[j] = 1;
          queue.push_back(j);
        }
      }
    }
  }
}

inline void seed_border(int64_t n, const uint8_t* wall, uint8_t* reached) {
  std::fill(reached, reached + n * n * n, 0);
  for (int64_t x = 0; x < n; ++x)
    for (int64_t y = 0; y < n; ++y)
      for (int64_t z = 0; z < n; ++z)
        if (on_border(n, x, y, z) && !wall[lat(n, x, y, z)]) reached[lat(n, x, y, z)] = 1;
}

// seeds: (S, 3) float64 voxels. reached: (R+1)^3 output.
inline FillResult fill(int64_t resolution, const uint8_t* wall, const double* seeds, int64_t seed_count,
                       uint8_t* reached) {
  const int64_t n = resolution + 1;
  FillResult out;
  std::fill(reached, reached + n * n * n, 0);
  for (int64_t s = 0; s < seed_count; ++s) {
    const double* p = seeds + 3 * s;
    bool inside = true;
    for (int a = 0; a < 3; ++a) inside = inside && p[a] >= 0.0 && p[a] <= static_cast<double>(resolution);
    if (!inside) continue;
    int64_t base[3];
    for (int a = 0; a < 3; ++a) base[a] = std::min(static_cast<int64_t>(std::floor(p[a])), resolution - 1);
    double d2[8];
    int64_t pts[8][3];
    for (int c = 0; c < 8; ++c) {
      pts[c][0] = base[0] + (c & 1);
      pts[c][1] = base[1] + ((c >> 1) & 1);
      pts[c][2] = base[2] + ((c >> 2) & 1);
      const double dx = static_cast<double>(pts[c][0]) - p[0], dy = static_cast<double>(pts[c][1]) - p[1],
                   dz = static_cast<double>(pts[c][2]) - p[2];
      d2[c] = dx * dx + dy * dy + dz * dz;
    }
    int order[8];
    std::iota(order, order + 8, 0);
    std::stable_sort(order, order + 8, [&](int u, int v) { return d2[u] < d2[v]; });
    for (int c : order) {
      const int64_t i = lat(n, pts[c][0], pts[c][1], pts[c][2]);
      if (!wall[i]) {
        reached[i] = 1;
        ++out.seeds_used;
        break;
      }
    }
  }
  if (out.seeds_used > 0) {
    flood(n, wall, reached);
    bool touched = false;
    for (int64_t x = 0; x < n && !touched; ++x)
      for (int64_t y = 0; y < n && !touched; ++y)
        for (int64_t z = 0; z < n && !touched; ++z)
          touched = on_border(n, x, y, z) && reached[lat(n, x, y, z)];
    if (!touched) {
      out.inside_seeded = true;
      return out;
    }
    out.leaked = true;
  }
  seed_border(n, wall, reached);
  flood(n, wall, reached);
  return out;
}

inline bool probe_reached(const V3& p, int64_t resolution, const uint8_t* reached) {
  const int64_t n = resolution + 1;
  auto idx = [&](double v) {
    return static_cast<int64_t>(std::clamp(std::floor(v + 0.5), 0.0, static_cast<double>(resolution)));
  };
  return reached[lat(n, idx(p.x), idx(p.y), idx(p.z))] != 0;
}

// (mine, other, off) for wall point p whose nearest triangle is ti.
inline void probes(const V3& p, const Triangles& t, int32_t ti, int64_t resolution, const uint8_t* reached,
                   bool* mine, bool* other, bool* off) {
  const V3 q = closest_point(p, t, ti);
  const V3 d = sub(p, q);
  const double u = std::sqrt(d.x * d.x + d.y * d.y + d.z * d.z);
  *off = u > 0.0;
  V3 step{0.0, 0.0, 0.0};
  if (*off) step = mul(d, kProbe / u);
  *mine = probe_reached(add(q, step), resolution, reached);
  *other = probe_reached(sub(q, step), resolution, reached);
}

// +1 / -1 per lattice point (see sign.py).
inline void signs(int64_t resolution, const float* drawn_dist, const int32_t* drawn_tri, const float* bar_dist,
                  const int32_t* bar_tri, const Triangles& drawn, const Triangles& bar, const uint8_t* reached,
                  int threads, int8_t* out) {
  const int64_t n = resolution + 1;
  parallel_for(n, threads, [&](int64_t x) {
    for (int64_t y = 0; y < n; ++y)
      for (int64_t z = 0; z < n; ++z) {
        const int64_t i = lat(n, x, y, z);
        const V3 p{static_cast<double>(x), static_cast<double>(y), static_cast<double>(z)};
        bool mine = false, other = false, off = false;
        if (drawn_dist[i] <= kWall) {
          probes(p, drawn, drawn_tri[i], resolution, reached, &mine, &other, &off);
          out[i] = (mine && !other && off) ? 1 : -1;
        } else if (bar_dist[i] <= kWall) {
          probes(p, bar, bar_tri[i], resolution, reached, &mine, &other, &off);
          out[i] = (mine && !other && off) ? 1 : -1;
        } else {
          out[i] = reached[i] ? 1 : -1;
        }
      }
  });
}

}  // namespace navi
