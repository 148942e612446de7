// SIMD helpers (GCC/Clang vector extensions, no intrinsics): the compiler maps them to AVX-512,
// AVX2 or SSE registers. Pixels are processed in spans of 8 (half a tile row); the 16 rows of
// a tile are handled together when deciding which spans a Gaussian can reach.
//
// Forward and backward share these helpers so that they recompute bit-identical alphas.
#pragma once

#include <cstdint>
#if defined(__AVX__)
#include <immintrin.h>
#endif

#include "raster.h"

namespace segs_raster {

constexpr int SPAN = 8;  // pixels per SIMD span (half a tile row)

typedef float vf __attribute__((vector_size(4 * SPAN)));    // one span
typedef int32_t vi __attribute__((vector_size(4 * SPAN)));
typedef float vf16 __attribute__((vector_size(4 * TILE)));  // one value per tile row
typedef int32_t vi16 __attribute__((vector_size(4 * TILE)));

template <class V>
static inline V splat(float s) { return V{} + s; }
static inline vi splat_i(int32_t s) { return vi{} + s; }
static inline vf load(const float* p) { return *reinterpret_cast<const vf*>(p); }  // 32-B aligned
static inline vi load_i(const int32_t* p) { return *reinterpret_cast<const vi*>(p); }
static inline void store(float* p, vf v) { *reinterpret_cast<vf*>(p) = v; }
static inline void store_i(int32_t* p, vi v) { *reinterpret_cast<vi*>(p) = v; }

static const vf LANE = {0.f, 1.f, 2.f, 3.f, 4.f, 5.f, 6.f, 7.f};
static const vf16 ROW = {0.f, 1.f, 2.f, 3.f, 4.f, 5.f, 6.f, 7.f,
                         8.f, 9.f, 10.f, 11.f, 12.f, 13.f, 14.f, 15.f};

typedef float vf4 __attribute__((vector_size(16)));

// Sum of the 8 lanes (pairwise: 4 + 2 + 1 adds).
static inline float hsum(vf v) {
  const vf4 s = __builtin_shufflevector(v, v, 0, 1, 2, 3) + __builtin_shufflevector(v, v, 4, 5, 6, 7);
  return (s[0] + s[2]) + (s[1] + s[3]);
}

// exp(x) for x <= 0: Cephes range reduction and degree-5 polynomial, relative error ~1e-7
// (like libm's expf); inputs below -87 are clamped (the result is far below 1/255 anyway).
static inline vf vexp(vf x) {
  x = x < splat<vf>(-87.f) ? splat<vf>(-87.f) : x;
  const vf t = x * 1.44269504088896341f + 0.5f;
  vi n = __builtin_convertvector(t, vi);  // truncates toward zero
  const vf tn = __builtin_convertvector(n, vf);
  n = n + (tn > t);  // floor: minus 1 where truncation rounded up
  const vf nf = __builtin_convertvector(n, vf);
  vf r = x - nf * 0.693359375f;
  r = r - nf * -2.12194440e-4f;
  vf p = splat<vf>(1.9875691500e-4f);
  p = p * r + 1.3981999507e-3f;
  p = p * r + 8.3334519073e-3f;
  p = p * r + 4.1665795894e-2f;
  p = p * r + 1.6666665459e-1f;
  p = p * r + 5.0000001201e-1f;
  p = p * r * r + r + 1.0f;
  const vi bits = (n + 127) << 23;
  return p * (vf)bits;  // vector cast = bit reinterpretation
}

// Falloff exponent of a span: sigma = ha dx^2 + b dx dy + hc dy^2 (dx = u - px, dy = v - py).
static inline vf span_sigma(const Packed& p, vf px, float dy) {
  const vf dx = p.u - px;
  return dx * (dx * p.ha + p.b * dy) + p.hc * dy * dy;
}

// min(x, 0.99): 3D-GS alpha clamp.
static inline vf clamp_alpha(vf x) { return x < splat<vf>(ALPHA_MAX) ? x : splat<vf>(ALPHA_MAX); }

// Lane j of a comparison result (0 or -1) -> bit j. The only intrinsics in this code: the
// generic loop compiles to 16 extractions.
static inline uint32_t bits16(vi16 m) {
#if defined(__AVX512F__)
  const __m512i v = reinterpret_cast<__m512i&>(m);
  return _mm512_test_epi32_mask(v, v);
#elif defined(__AVX2__)
  const __m256i* h = reinterpret_cast<const __m256i*>(&m);
  return static_cast<uint32_t>(_mm256_movemask_ps(_mm256_castsi256_ps(h[0]))) |
         static_cast<uint32_t>(_mm256_movemask_ps(_mm256_castsi256_ps(h[1]))) << 8;
#else
  uint32_t b = 0;
  for (int j = 0; j < TILE; ++j) b |= static_cast<uint32_t>(m[j] & 1) << j;
  return b;
#endif
}

// Whether any lane is > 0.
static inline bool any_positive(vf v) {
#if defined(__AVX__)
  return _mm256_movemask_ps(_mm256_cmp_ps(reinterpret_cast<__m256&>(v), _mm256_setzero_ps(),
                                          _CMP_GT_OQ)) != 0;
#else
  const vi on = v > splat<vf>(0.f);
  int any = 0;
  for (int j = 0; j < SPAN; ++j) any |= on[j];
  return any != 0;
#endif
}

// Spans of the tile at (x0, y0) where Gaussian p can reach alpha >= 1/255: bit 16 h + r is
// row r, half h (pixels 8h .. 8h + 7). Exact test per span: the smallest sigma over the span's pixel centres (sigma is a
// convex parabola along a row, minimal at px*) against the level ln(255 opacity) + margin.
static inline uint32_t span_mask(const Packed& p, int x0, int y0) {
  if (!(p.level >= 0.f)) return 0xffffffffu;  // degenerate conic: no culling
  const vf16 dy = p.v - (ROW + (static_cast<float>(y0) + 0.5f));
  const vf16 px_star = p.u + p.b * p.inv_2ha * dy;  // where d sigma / d px = 0
  uint32_t out = 0;
  for (int h = 0; h < 2; ++h) {
    const float lo = static_cast<float>(x0 + SPAN * h) + 0.5f, hi = lo + (SPAN - 1);
    vf16 pc = px_star < lo ? splat<vf16>(lo) : px_star;
    pc = pc > hi ? splat<vf16>(hi) : pc;
    const vf16 dx = p.u - pc;
    const vf16 s = dx * (dx * p.ha + p.b * dy) + p.hc * dy * dy;
    out |= bits16(s <= p.level) << (TILE * h);
  }
  return out;
}

}  // namespace segs_raster
