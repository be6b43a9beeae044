// What every tracer header shares: NAVI_HD, which compiles one function for the host (trace_cpu.cpp)
// and the device (trace_cuda.cu), kBig and the exact 2^23 float tricks, loads through the read-only
// cache and exact float helpers. Units and arithmetic of the whole traversal: gmdag_trace.h.
#pragma once

#include <math.h>
#include <stdint.h>
#include <string.h>

#ifdef __CUDACC__
#define NAVI_HD __host__ __device__ __forceinline__
#else
#define NAVI_HD inline
#endif

namespace navi {

constexpr float kBig = 3.0e38f;
// Float tricks, exact for the integers they are used on (0 <= n < 2^23).
constexpr float kTwo23 = 8388608.0f;           // 2^23: float bits 0x4B000000 + n encode 2^23 + n
constexpr int32_t kTwo23Bits = 0x4B000000;

// ---------------------------------------------------------------------------------------------
// Loads (read-only cache on the device) and exact float helpers.

template <typename T>
NAVI_HD T load_ro(const T* p) {
#ifdef __CUDA_ARCH__
  return __ldg(p);
#else
  return *p;
#endif
}

NAVI_HD float bits_float(int32_t bits) {
#ifdef __CUDA_ARCH__
  return __int_as_float(bits);
#else
  float f;
  memcpy(&f, &bits, sizeof f);
  return f;
#endif
}

NAVI_HD int32_t float_bits(float f) {
#ifdef __CUDA_ARCH__
  return __float_as_int(f);
#else
  int32_t bits;
  memcpy(&bits, &f, sizeof bits);
  return bits;
#endif
}

NAVI_HD float kNaN() { return bits_float(0x7FC00000); }

NAVI_HD bool finite(float x) { return fabsf(x) <= 3.4028235e38f; }  // false for NaN and +-inf

}  // namespace navi
