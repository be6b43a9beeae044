// DAG stage (twin of dag.py): bricks, far codes, hash-consed nodes, breadth-first renumbering.
#pragma once

#include <cstring>
#include <limits>
#include <unordered_map>

#include "common.h"
#include "murmur.h"

namespace navi {

constexpr uint32_t kTagNode = 0, kTagBrick = 1, kTagFarFree = 2, kTagFarSolid = 3;
constexpr uint32_t kPayloadMask = (1u << 30) - 1;
constexpr float kHalfDiagonal = 0.866025403784438597f;  // float32(sqrt(3) / 2)

struct DagOut {
  uint32_t root = 0;
  int levels = 0;
  std::vector<uint32_t> nodes;   // (N * 8)
  std::vector<int8_t> bricks;    // (Bn * 729)
  std::vector<uint8_t> classes;  // (Bn)
};

// Interns fixed-width byte rows: MurmurHash3 groups candidates, memcmp decides. Ids count up in order
// of first appearance.
class RowTable {
 public:
  explicit RowTable(size_t width) : width_(width) {}
  uint32_t intern(const uint8_t* row) {
    const uint32_t h = murmur3_32(row, width_);
    auto& bucket = groups_[h];
    for (uint32_t id : bucket)
      if (std::memcmp(rows_.data() + id * width_, row, width_) == 0) return id;
    const uint32_t id = static_cast<uint32_t>(rows_.size() / width_);
    rows_.insert(rows_.end(), row, row + width_);
    bucket.push_back(id);
    return id;
  }
  const uint8_t* row(uint32_t id) const { return rows_.data() + id * width_; }
  size_t size() const { return rows_.size() / width_; }

 private:
  size_t width_;
  std::vector<uint8_t> rows_;
  std::unordered_map<uint32_t, std::vector<uint32_t>> groups_;
};

inline uint32_t far_payload(float lower) {
  float scaled = std::floor(std::max(lower, 0.0f) * 16.0f);
  scaled = std::min(scaled, 536870912.0f);  // 2^29, exact in float32
  return static_cast<uint32_t>(scaled);
}

inline int8_t quantise(float s, float step) {
  float q = std::trunc(s / step);
  q = std::min(std::max(q, -127.0f), 127.0f);
  if (std::fabs(q * step) > std::fabs(s)) q = q - (q > 0.0f ? 1.0f : (q < 0.0f ? -1.0f : 0.0f));
  return static_cast<int8_t>(q);
}

// lattice: (R+1)^3 float32 [x, y, z]; brick_class: (nb^3) uint8; quant_step = float32(band / 127).
inline DagOut build_dag(int64_t resolution, const float* lattice, const uint8_t* brick_class, float band,
                        float quant_step, int threads) {
  const int64_t n = resolution + 1, nb = resolution / kBrickCells, total = nb * nb * nb;
  DagOut out;
  while ((int64_t{kBrickCells} << out.levels) < resolution) ++out.levels;
  const int levels = out.levels;

  // Brick level: far codes or stored bricks (quantised in parallel, interned in scan order).
  std::vector<uint32_t> words(total);
  std::vector<uint8_t> near(total, 0);
  std::vector<int64_t> slot(total, -1);
  parallel_for(total, threads, [&](int64_t b) {
    const int64_t bx = b / (nb * nb), by = (b / nb) % nb, bz = b % nb;
    float lo = std::numeric_limits<float>::infinity(), hi = -std::numeric_limits<float>::infinity();
    for (int k = 0; k < kBrickSide; ++k)
      for (int j = 0; j < kBrickSide; ++j)
        for (int i = 0; i < kBrickSide; ++i) {
          const float s = lattice[lat(n, 8 * bx + i, 8 * by + j, 8 * bz + k)];
          lo = std::min(lo, s);
          hi = std::max(hi, s);
        }
    if (lo >= band) {
      words[b] = (kTagFarFree << 30) | far_payload(lo - kHalfDiagonal);
    } else if (hi <= -band) {
      words[b] = (kTagFarSolid << 30) | far_payload(-hi - kHalfDiagonal);
    } else {
      near[b] = 1;
    }
  });
  int64_t stored = 0;
  for (int64_t b = 0; b < total; ++b)
    if (near[b]) slot[b] = stored++;
  std::vector<uint8_t> keys(static_cast<size_t>(stored) * (kBrickSamples + 1));
  parallel_for(total, threads, [&](int64_t b) {
    if (!near[b]) return;
    const int64_t bx = b / (nb * nb), by = (b / nb) % nb, bz = b % nb;
    uint8_t* key = keys.data() + slot[b] * (kBrickSamples + 1);
    for (int k = 0; k < kBrickSide; ++k)
      for (int j = 0; j < kBrickSide; ++j)
        for (int i = 0; i < kBrickSide; ++i) {
          const int8_t q = quantise(lattice[lat(n, 8 * bx + i, 8 * by + j, 8 * bz + k)], quant_step);
          key[i + 9 * j + 81 * k] = static_cast<uint8_t>(q);
        }
    key[kBrickSamples] = brick_class[b];
  });
  RowTable brick_table(kBrickSamples + 1);
  for (int64_t b = 0; b < total; ++b)
    if (near[b]) words[b] = (kTagBrick << 30) | brick_table.intern(keys.data() + slot[b] * (kBrickSamples + 1));

  // Internal levels, bottom-up: merge uniform far children, intern the rest per depth.
  std::vector<RowTable> tables;
  tables.reserve(levels);
  for (int d = 0; d < levels; ++d) tables.emplace_back(32);
  for (int d = levels - 1; d >= 0; --d) {
    const int64_t m = int64_t{1} << d, child_n = 2 * m;
    std::vector<uint32_t> parent(m * m * m);
    for (int64_t p = 0; p < m * m * m; ++p) {
      const int64_t i = p / (m * m), j = (p / m) % m, k = p % m;
      uint32_t ch[8];
      for (int c = 0; c < 8; ++c)
        ch[c] = words[((2 * i + (c & 1)) * child_n + (2 * j + ((c >> 1) & 1))) * child_n + (2 * k + ((c >> 2) & 1))];
      const uint32_t tag = ch[0] >> 30;
      bool same_far = tag >= kTagFarFree;
      uint32_t payload = ch[0] & kPayloadMask;
      for (int c = 1; c < 8; ++c) {
        same_far = same_far && (ch[c] >> 30) == tag;
        payload = std::min(payload, ch[c] & kPayloadMask);
      }
      if (same_far) {
        parent[p] = (tag << 30) | payload;
      } else {
        uint8_t row[32];
        for (int c = 0; c < 8; ++c)
          for (int byte = 0; byte < 4; ++byte) row[4 * c + byte] = static_cast<uint8_t>(ch[c] >> (8 * byte));
        parent[p] = (kTagNode << 30) | tables[d].intern(row);
      }
    }
    words.swap(parent);
  }

  // Renumber breadth-first: by depth, in order of first reference.
  const uint32_t root = words[0];
  if ((root >> 30) != kTagNode) {
    if ((root >> 30) == kTagBrick) {
      out.root = kTagBrick << 30;
      const uint8_t* key = brick_table.row(root & kPayloadMask);
      out.bricks.assign(reinterpret_cast<const int8_t*>(key), reinterpret_cast<const int8_t*>(key) + kBrickSamples);
      out.classes.push_back(key[kBrickSamples]);
    } else {
      out.root = root;
    }
    return out;
  }
  out.root = kTagNode << 30;
  std::vector<uint32_t> order{root & kPayloadMask};
  int64_t base = 0;
  for (int d = 0; d < levels; ++d) {
    const uint32_t child_tag = d + 1 < levels ? kTagNode : kTagBrick;
    const size_t provisional = child_tag == kTagNode ? tables[d + 1].size() : brick_table.size();
    std::vector<int64_t> rank(provisional, -1);
    std::vector<uint32_t> next;
    const int64_t child_base = child_tag == kTagNode ? base + static_cast<int64_t>(order.size()) : 0;
    for (uint32_t id : order) {
      const uint8_t* row = tables[d].row(id);
      for (int c = 0; c < 8; ++c) {
        uint32_t w = 0;
        for (int byte = 0; byte < 4; ++byte) w |= static_cast<uint32_t>(row[4 * c + byte]) << (8 * byte);
        if ((w >> 30) == child_tag) {
          const uint32_t cid = w & kPayloadMask;
          if (rank[cid] < 0) {
            rank[cid] = static_cast<int64_t>(next.size());
            next.push_back(cid);
          }
          w = (child_tag << 30) | static_cast<uint32_t>(rank[cid] + child_base);
        }
        out.nodes.push_back(w);
      }
    }
    base += static_cast<int64_t>(order.size());
    if (child_tag == kTagNode) {
      order.swap(next);
    } else {
      for (uint32_t bid : next) {
        const uint8_t* key = brick_table.row(bid);
        out.bricks.insert(out.bricks.end(), reinterpret_cast<const int8_t*>(key),
                          reinterpret_cast<const int8_t*>(key) + kBrickSamples);
        out.classes.push_back(key[kBrickSamples]);
      }
    }
  }
  return out;
}

}  // namespace navi
