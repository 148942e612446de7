// Forward pass: front-to-back alpha compositing per 16x16 tile, in spans of 8 pixels.
//
// Per pixel the transmittance T is kept positive while the pixel accepts Gaussians; it is
// negated (-T) once the pixel is done (next T < 1e-4), and pixels outside the image start at -1.
// A Gaussian only visits the spans where its alpha can reach 1/255 (span_mask) and that still
// have a live pixel, so skipping work never changes the image.
#include <omp.h>

#include <algorithm>
#include <cmath>

#include "pool.h"
#include "raster.h"
#include "simd.h"

namespace segs_raster {
namespace {

struct TileAcc {
  alignas(64) float T[TILE_PIX];
  alignas(64) float r[TILE_PIX];
  alignas(64) float g[TILE_PIX];
  alignas(64) float b[TILE_PIX];
  alignas(64) float d[TILE_PIX];
  alignas(64) int32_t last[TILE_PIX];
};

constexpr int PREFETCH = 8;  // list entries ahead: Packed records are scattered in memory

// Span index bit (16 h + r) <-> pixel offset in the tile arrays.
inline int span_offset(int bit) { return (bit & (TILE - 1)) * TILE + (bit >> 4) * SPAN; }

// Apply Gaussian `p` (list position `k`, 1-based) to one span of 8 pixels at offset `o`.
inline void composite_span(const Packed& p, int32_t k, vf px, float dy, TileAcc& a, int o) {
  const vf s = span_sigma(p, px, dy);
  const vf al = clamp_alpha(p.opacity * vexp(-s));
  const vf t = load(a.T + o);
  const vi ok = (s >= splat<vf>(0.f)) & (al >= splat<vf>(ALPHA_MIN)) & (t > splat<vf>(0.f));
  const vf next = t * (1.f - al);
  const vi take = ok & (next >= splat<vf>(T_MIN));
  const vf w = take ? al * t : splat<vf>(0.f);
  store(a.r + o, load(a.r + o) + w * p.r);
  store(a.g + o, load(a.g + o) + w * p.g);
  store(a.b + o, load(a.b + o) + w * p.bl);
  store(a.d + o, load(a.d + o) + w * p.z);
  store(a.T + o, take ? next : (ok ? -t : t));
  store_i(a.last + o, take ? splat_i(k) : load_i(a.last + o));
}

// Bit (16 h + r) set = that span still has a pixel accepting Gaussians.
inline uint32_t live_spans(const float* T) {
  uint32_t live = 0;
  for (int bit = 0; bit < 2 * TILE; ++bit) {
    const vi on = load(T + span_offset(bit)) > splat<vf>(0.f);
    int any = 0;
    for (int j = 0; j < SPAN; ++j) any |= on[j];
    live |= static_cast<uint32_t>(any != 0) << bit;
  }
  return live;
}

int64_t rasterize_tile(const State& st, int tile, TileAcc& a) {
  const int x0 = (tile % st.tiles_x) * TILE, y0 = (tile / st.tiles_x) * TILE;
  for (int i = 0; i < TILE_PIX; ++i) {
    const bool inside = (x0 + i % TILE < st.width) & (y0 + i / TILE < st.height);
    a.T[i] = inside ? 1.f : -1.f;
    a.r[i] = a.g[i] = a.b[i] = a.d[i] = 0.f;
    a.last[i] = 0;
  }
  uint32_t live = live_spans(a.T);
  const vf px[2] = {LANE + (x0 + 0.5f), LANE + (x0 + SPAN + 0.5f)};  // pixel centres
  const int32_t start = st.tile_start[tile], end = st.tile_start[tile + 1];
  int64_t spans = 0;
  for (int32_t k = start; k < end && live; ++k) {
    if (k + PREFETCH < end) __builtin_prefetch(&st.gs[st.isect[k + PREFETCH]]);
    const Packed& p = st.gs[st.isect[k]];
    for (uint32_t m = span_mask(p, x0, y0) & live; m; m &= m - 1) {
      const int bit = __builtin_ctz(m);
      const float dy = p.v - (static_cast<float>(y0 + (bit & (TILE - 1))) + 0.5f);
      composite_span(p, k - start + 1, px[bit >> 4], dy, a, span_offset(bit));
      ++spans;
    }
    if (((k - start) & 7) == 7) live = live_spans(a.T);
  }
  return spans * SPAN;
}

void write_tile(const State& st, int tile, const TileAcc& a, const ForwardOut& out,
                float* final_T, int32_t* n_contrib, float* depth_acc) {
  const int x0 = (tile % st.tiles_x) * TILE, y0 = (tile / st.tiles_x) * TILE;
  for (int i = 0; i < TILE_PIX; ++i) {
    final_T[i] = std::fabs(a.T[i]);
    n_contrib[i] = a.last[i];
    depth_acc[i] = a.d[i];
    const int x = x0 + i % TILE, y = y0 + i / TILE;
    if (x >= st.width || y >= st.height) continue;
    const size_t pix = static_cast<size_t>(y) * st.width + x;
    const float T = final_T[i];
    out.image[3 * pix] = a.r[i] + T * st.bg[0];
    out.image[3 * pix + 1] = a.g[i] + T * st.bg[1];
    out.image[3 * pix + 2] = a.b[i] + T * st.bg[2];
    const float alpha = 1.f - T;
    out.depth[pix] = a.d[i] / (alpha < ALPHA_EPS ? ALPHA_EPS : alpha);
    out.alpha[pix] = alpha;
  }
}

}  // namespace

State::State()
    : gs(take_vector<Packed>()),
      tile_start(take_vector<int32_t>()),
      isect(take_vector<int32_t>()),
      final_T(take_vector<float>()),
      n_contrib(take_vector<int32_t>()),
      depth_acc(take_vector<float>()) {}

State::~State() {
  give_vector(gs), give_vector(tile_start), give_vector(isect);
  give_vector(final_T), give_vector(n_contrib), give_vector(depth_acc);
}

void forward(const ForwardIn& in, const ForwardOut& out, State& st, int threads) {
  st.n = in.n;
  st.width = in.width;
  st.height = in.height;
  st.tiles_x = (in.width + TILE - 1) / TILE;
  st.tiles_y = (in.height + TILE - 1) / TILE;
  for (int c = 0; c < 3; ++c) st.bg[c] = in.background[c];
  bin_gaussians(in, st, threads);
  const int n_tiles = st.n_tiles();
  st.final_T.assign(static_cast<size_t>(n_tiles) * TILE_PIX, 1.f);
  st.n_contrib.assign(static_cast<size_t>(n_tiles) * TILE_PIX, 0);
  st.depth_acc.assign(static_cast<size_t>(n_tiles) * TILE_PIX, 0.f);
  int64_t evals = 0;
#pragma omp parallel num_threads(threads) reduction(+ : evals)
  {
    TileAcc acc;
#pragma omp for schedule(dynamic, 1)
    for (int tile = 0; tile < n_tiles; ++tile) {
      evals += rasterize_tile(st, tile, acc);
      const size_t o = static_cast<size_t>(tile) * TILE_PIX;
      write_tile(st, tile, acc, out, st.final_T.data() + o, st.n_contrib.data() + o,
                 st.depth_acc.data() + o);
    }
  }
  st.evaluations = evals;
}

}  // namespace segs_raster
