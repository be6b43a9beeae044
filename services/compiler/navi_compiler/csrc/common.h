// Shared helpers of the C++ core: 3-vectors in float64, a deterministic parallel loop, lattice indexing.
// Every arithmetic expression mirrors the NumPy reference operation by operation (built with
// -ffp-contract=off, so no fused multiply-add changes a rounding).
#pragma once

#include <algorithm>
#include <atomic>
#include <cmath>
#include <cstdint>
#include <thread>
#include <vector>

namespace navi {

constexpr int kBrickCells = 8;   // cells per brick edge
constexpr int kBrickSide = 9;    // samples per brick edge
constexpr int kBrickSamples = 729;

struct V3 {
  double x, y, z;
};

inline V3 sub(const V3& a, const V3& b) { return {a.x - b.x, a.y - b.y, a.z - b.z}; }
inline V3 add(const V3& a, const V3& b) { return {a.x + b.x, a.y + b.y, a.z + b.z}; }
inline V3 mul(const V3& a, double s) { return {a.x * s, a.y * s, a.z * s}; }
inline double dot(const V3& a, const V3& b) { return a.x * b.x + a.y * b.y + a.z * b.z; }
inline double norm2(const V3& d) { return d.x * d.x + d.y * d.y + d.z * d.z; }

// Runs fn(i) for i in [0, n) on `threads` workers (0: all cores). Work items must write disjoint
// memory, so the result never depends on the thread count or the schedule.
template <class Fn>
void parallel_for(int64_t n, int threads, Fn fn) {
  int workers = threads > 0 ? threads : static_cast<int>(std::max(1u, std::thread::hardware_concurrency()));
  workers = static_cast<int>(std::min<int64_t>(workers, std::max<int64_t>(n, 1)));
  if (workers <= 1) {
    for (int64_t i = 0; i < n; ++i) fn(i);
    return;
  }
  std::atomic<int64_t> next{0};
  auto work = [&]() {
    for (int64_t i = next.fetch_add(1); i < n; i = next.fetch_add(1)) fn(i);
  };
  std::vector<std::thread> pool;
  for (int w = 1; w < workers; ++w) pool.emplace_back(work);
  work();
  for (auto& t : pool) t.join();
}

// Flat index of lattice point (x, y, z) in an (n, n, n) C-order array indexed [x, y, z].
inline int64_t lat(int64_t n, int64_t x, int64_t y, int64_t z) { return (x * n + y) * n + z; }

}  // namespace navi
