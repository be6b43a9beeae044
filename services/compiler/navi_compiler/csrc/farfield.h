// Far-field stage (twin of farfield.py): exact squared EDT to the corners of the surface cells, and
// its square root rounded down to float32 as a lower bound of the distance.
#pragma once

#include <limits>

#include "common.h"

namespace navi {

constexpr int32_t kNoSite = 1 << 30;
constexpr float kSurfaceCell = 0.866025403784438597f;  // float32(sqrt(3) / 2)

// sites: (R+1)^3, 1 at every corner of a cell with a corner whose distance is <= sqrt(3)/2. The
// corners of the cells around a lattice point p are p + {-1, 0, 1}^3, so this is the 3x3x3 box
// dilation of the "close" points, done as three separable passes (farfield.py builds the cells).
inline void surface_corners(int64_t resolution, const float* dist, int threads, uint8_t* sites) {
  const int64_t n = resolution + 1;
  std::vector<uint8_t> tmp(static_cast<size_t>(n * n * n));
  parallel_for(n, threads, [&](int64_t x) {  // close points, dilated along z
    for (int64_t y = 0; y < n; ++y) {
      const float* row = dist + lat(n, x, y, 0);
      uint8_t* out = tmp.data() + lat(n, x, y, 0);
      for (int64_t z = 0; z < n; ++z) {
        bool any = row[z] <= kSurfaceCell;
        if (z > 0) any = any || row[z - 1] <= kSurfaceCell;
        if (z + 1 < n) any = any || row[z + 1] <= kSurfaceCell;
        out[z] = any;
      }
    }
  });
  parallel_for(n, threads, [&](int64_t x) {  // along y
    for (int64_t y = 0; y < n; ++y) {
      uint8_t* out = sites + lat(n, x, y, 0);
      const uint8_t* mid = tmp.data() + lat(n, x, y, 0);
      const uint8_t* lo = y > 0 ? mid - n : mid;
      const uint8_t* hi = y + 1 < n ? mid + n : mid;
      for (int64_t z = 0; z < n; ++z) out[z] = mid[z] | lo[z] | hi[z];
    }
  });
  parallel_for(n, threads, [&](int64_t x) {  // along x
    for (int64_t y = 0; y < n; ++y) {
      uint8_t* out = tmp.data() + lat(n, x, y, 0);
      const uint8_t* mid = sites + lat(n, x, y, 0);
      const uint8_t* lo = x > 0 ? mid - n * n : mid;
      const uint8_t* hi = x + 1 < n ? mid + n * n : mid;
      for (int64_t z = 0; z < n; ++z) out[z] = mid[z] | lo[z] | hi[z];
    }
  });
  std::copy(tmp.begin(), tmp.end(), sites);
}

// One line of the exact 1-D squared distance transform (lower envelope of parabolas, Felzenszwalb &
// Huttenlocher); f has kNoSite where there is no site. Exact in integers.
inline void edt_line(int64_t n, const int64_t* f, int64_t* out, int64_t* v, double* z) {
  int64_t k = -1;
  for (int64_t q = 0; q < n; ++q) {
    if (f[q] >= kNoSite) continue;
    while (k >= 0) {
      const double s = static_cast<double>((f[q] + q * q) - (f[v[k]] + v[k] * v[k])) / static_cast<double>(2 * q - 2 * v[k]);
      if (s <= z[k]) {
        --k;
      } else {
        break;
      }
    }
    ++k;
    v[k] = q;
    z[k] = k == 0 ? -1e300 : static_cast<double>((f[q] + q * q) - (f[v[k - 1]] + v[k - 1] * v[k - 1])) /
                                   static_cast<double>(2 * q - 2 * v[k - 1]);
  }
  if (k < 0) {
    for (int64_t q = 0; q < n; ++q) out[q] = kNoSite;
    return;
  }
  int64_t j = 0;
  for (int64_t q = 0; q < n; ++q) {
    while (j < k && z[j + 1] < static_cast<double>(q)) ++j;
    const int64_t d = q - v[j];
    out[q] = std::min<int64_t>(d * d + f[v[j]], kNoSite);
  }
}

// Squared EDT of `sites` into d2 ((R+1)^3 int32, kNoSite where there is no site): exact 1-D passes
// along z, y and x. The y and x passes gather a plane's lines into a contiguous block first, so every
// pass streams memory.
inline void squared_edt(int64_t resolution, const uint8_t* sites, int threads, int32_t* d2) {
  const int64_t n = resolution + 1;
  for (int64_t i = 0; i < n * n * n; ++i) d2[i] = sites[i] ? 0 : kNoSite;
  auto run_lines = [&](int64_t lines, int64_t* block, int64_t* g, int64_t* v, double* z) {
    for (int64_t l = 0; l < lines; ++l) {
      edt_line(n, block + l * n, g, v, z);
      std::copy(g, g + n, block + l * n);
    }
  };
  parallel_for(n, threads, [&](int64_t x) {  // z pass: lines are contiguous rows
    std::vector<int64_t> block(n * n), g(n), v(n);
    std::vector<double> z(n + 1);
    int32_t* plane = d2 + lat(n, x, 0, 0);
    for (int64_t i = 0; i < n * n; ++i) block[i] = plane[i];
    run_lines(n, block.data(), g.data(), v.data(), z.data());
    for (int64_t i = 0; i < n * n; ++i) plane[i] = static_cast<int32_t>(block[i]);
  });
  parallel_for(n, threads, [&](int64_t x) {  // y pass: in the x plane, line z holds d2[x, :, z]
    std::vector<int64_t> block(n * n), g(n), v(n);
    std::vector<double> z(n + 1);
    int32_t* plane = d2 + lat(n, x, 0, 0);
    for (int64_t y = 0; y < n; ++y)
      for (int64_t k = 0; k < n; ++k) block[k * n + y] = plane[y * n + k];
    run_lines(n, block.data(), g.data(), v.data(), z.data());
    for (int64_t y = 0; y < n; ++y)
      for (int64_t k = 0; k < n; ++k) plane[y * n + k] = static_cast<int32_t>(block[k * n + y]);
  });
  parallel_for(n, threads, [&](int64_t y) {  // x pass: in the y slice, line z holds d2[:, y, z]
    std::vector<int64_t> block(n * n), g(n), v(n);
    std::vector<double> z(n + 1);
    for (int64_t x = 0; x < n; ++x) {
      const int32_t* row = d2 + lat(n, x, y, 0);
      for (int64_t k = 0; k < n; ++k) block[k * n + x] = row[k];
    }
    run_lines(n, block.data(), g.data(), v.data(), z.data());
    for (int64_t x = 0; x < n; ++x) {
      int32_t* row = d2 + lat(n, x, y, 0);
      for (int64_t k = 0; k < n; ++k) row[k] = static_cast<int32_t>(block[k * n + x]);
    }
  });
}

inline float lower_bound(int32_t d2) {
  if (d2 >= kNoSite) return std::numeric_limits<float>::infinity();
  const double exact = std::sqrt(static_cast<double>(d2));
  float low = static_cast<float>(exact);
  if (static_cast<double>(low) > exact) low = std::nextafter(low, 0.0f);
  return low;
}

}  // namespace navi
