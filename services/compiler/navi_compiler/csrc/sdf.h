// Signed-field pipeline of the C++ engine (twin of sdf.py): distance -> sign -> far field -> lattice.
#pragma once

#include <chrono>
#include <string>
#include <utility>

#include "dag.h"
#include "distance.h"
#include "farfield.h"
#include "sign.h"

namespace navi {

constexpr double kReachMargin = 1.0;
constexpr double kClassReach = 12.0;

struct SdfStats {
  std::vector<std::pair<std::string, double>> seconds;  // wall time per stage, in order
  int flags = 0;
  int64_t seeds_used = 0;
  int64_t wall_points = 0;
  int64_t free_points = 0;
};

// Keeps the non-degenerate triangles of corners (T, 3, 3) (and their classes when given).
inline std::vector<double> keep_nondegenerate(const double* corners, int64_t count, const uint8_t* classes,
                                              std::vector<uint8_t>* kept_classes) {
  std::vector<double> out;
  for (int64_t i = 0; i < count; ++i) {
    if (!nondegenerate(corners + 9 * i)) continue;
    out.insert(out.end(), corners + 9 * i, corners + 9 * i + 9);
    if (classes != nullptr) kept_classes->push_back(classes[i]);
  }
  return out;
}

// lattice: (R+1)^3 float32 output; brick_class: (nb^3) uint8 output.
inline SdfStats signed_field(const double* drawn_corners, int64_t drawn_count, const uint8_t* face_class,
                             const double* barrier_corners, int64_t barrier_count, const double* seeds,
                             int64_t seed_count, int64_t resolution, float band, int threads, float* lattice,
                             uint8_t* brick_class) {
  const int64_t n = resolution + 1, n3 = n * n * n, nb = resolution / kBrickCells;
  SdfStats stats;
  auto clock = std::chrono::steady_clock::now();
  auto lap = [&](const char* stage) {
    const auto now = std::chrono::steady_clock::now();
    stats.seconds.emplace_back(stage, std::chrono::duration<double>(now - clock).count());
    clock = now;
  };
  std::vector<uint8_t> classes;
  const std::vector<double> drawn_kept = keep_nondegenerate(drawn_corners, drawn_count, face_class, &classes);
  const std::vector<double> barrier_kept = keep_nondegenerate(barrier_corners, barrier_count, nullptr, nullptr);
  const Triangles drawn = make_triangles(drawn_kept.data(), static_cast<int64_t>(drawn_kept.size() / 9));
  const Triangles bar = make_triangles(barrier_kept.data(), static_cast<int64_t>(barrier_kept.size() / 9));
  const double reach = static_cast<double>(band) + kReachMargin;
  const Buckets drawn_buckets = bucket_triangles(drawn, nb, reach);

  std::vector<float> dist(n3);
  std::vector<int32_t> tri(n3);
  nearest_triangles(drawn, drawn_buckets, resolution, reach, threads, dist.data(), tri.data());
  lap("distance");
  std::vector<float> bar_dist(n3);
  std::vector<int32_t> bar_tri(n3);
  {
    const Buckets bar_buckets = bucket_triangles(bar, nb, reach);
    nearest_triangles(bar, bar_buckets, resolution, reach, threads, bar_dist.data(), bar_tri.data());
  }
  lap("barrier");
  std::vector<uint8_t> wall(n3);
  for (int64_t i = 0; i < n3; ++i) {
    wall[i] = dist[i] <= kWall || bar_dist[i] <= kWall;
    stats.wall_points += wall[i];
  }
  std::vector<uint8_t> reached(n3);
  const FillResult filled = fill(resolution, wall.data(), seeds, seed_count, reached.data());
  stats.seeds_used = filled.seeds_used;
  stats.flags = (filled.inside_seeded ? 1 : 0) | (filled.leaked ? 2 : 0);
  std::vector<uint8_t>().swap(wall);
  lap("fill");
  std::vector<int8_t> sign(n3);
  signs(resolution, dist.data(), tri.data(), bar_dist.data(), bar_tri.data(), drawn, bar, reached.data(), threads,
        sign.data());
  // Distances are measured to drawn and barrier surfaces alike (sdf.py): the field reaches zero at a
  // barrier, so it stays 1-Lipschitz across a Quake 3 sky or an open scene's lid.
  for (int64_t i = 0; i < n3; ++i) dist[i] = std::min(dist[i], bar_dist[i]);
  std::vector<float>().swap(bar_dist);
  std::vector<int32_t>().swap(bar_tri);
  std::vector<int32_t>().swap(tri);
  std::vector<uint8_t>().swap(reached);
  lap("sign");

  std::vector<int32_t> d2(n3);
  {
    std::vector<uint8_t> sites(n3);
    surface_corners(resolution, dist.data(), threads, sites.data());
    lap("surface cells");
    squared_edt(resolution, sites.data(), threads, d2.data());
  }
  lap("edt");
  const float cap = static_cast<float>(2 * resolution);
  const float reach32 = static_cast<float>(reach);
  std::vector<int64_t> free_per_x(n, 0);
  parallel_for(n, threads, [&](int64_t x) {
    for (int64_t i = x * n * n; i < (x + 1) * n * n; ++i) {
      const float value = std::isfinite(dist[i]) ? dist[i] : std::max(std::min(lower_bound(d2[i]), cap), reach32);
      lattice[i] = value * static_cast<float>(sign[i]);
      free_per_x[x] += sign[i] > 0;
    }
  });
  for (int64_t x = 0; x < n; ++x) stats.free_points += free_per_x[x];
  lap("assemble");

  std::vector<uint8_t> stored(nb * nb * nb);
  parallel_for(nb * nb * nb, threads, [&](int64_t b) {
    const int64_t bx = b / (nb * nb), by = (b / nb) % nb, bz = b % nb;
    float lo = std::numeric_limits<float>::infinity(), hi = -std::numeric_limits<float>::infinity();
    for (int i = 0; i < kBrickSide; ++i)
      for (int j = 0; j < kBrickSide; ++j)
        for (int k = 0; k < kBrickSide; ++k) {
          const float s = lattice[lat(n, 8 * bx + i, 8 * by + j, 8 * bz + k)];
          lo = std::min(lo, s);
          hi = std::max(hi, s);
        }
    stored[b] = !(lo >= band || hi <= -band);
  });
  brick_classes(drawn, drawn_buckets, classes.data(), stored.data(), kClassReach, threads, brick_class);
  lap("classes");
  return stats;
}

}  // namespace navi
