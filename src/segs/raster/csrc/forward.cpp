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
constexpr int CHUNK = 32;    // Gaussians whose span masks are computed before compositing

// Span index bit (16 h + r) <-> pixel offset in the tile arrays.
inline int span_offset(int bit) { return (bit & (TILE - 1)) * TILE + (bit >> 4) * SPAN; }

// The compositing state of one span, held in registers while a chunk of Gaussians is applied.
struct Span {
  vf T, r, g, b, d;
  vi last;
};

// Apply Gaussian `p` (list position `k`, 1-based) to a span with pixel centres px, row offset dy.
inline void composite(const Packed& p, int32_t k, vf px, float dy, Span& s) {
  const vf sg = span_sigma(p, px, dy);
  const vf al = clamp_alpha(p.opacity * vexp(-sg));
  const vi ok = (sg >= splat<vf>(0.f)) & (al >= splat<vf>(ALPHA_MIN)) & (s.T > splat<vf>(0.f));
  const vf next = s.T * (1.f - al);
  const vi take = ok & (next >= splat<vf>(T_MIN));
  const vf w = take ? al * s.T : splat<vf>(0.f);
  s.r += w * p.r;
  s.g += w * p.g;
  s.b += w * p.bl;
  s.d += w * p.z;
  s.T = take ? next : (ok ? -s.T : s.T);
  s.last = take ? splat_i(k) : s.last;
}

// Bit (16 h + r) set = that span still has a pixel accepting Gaussians.
inline uint32_t live_spans(const float* T) {
  uint32_t live = 0;
  for (int bit = 0; bit < 2 * TILE; ++bit)
    live |= static_cast<uint32_t>(any_positive(load(T + span_offset(bit)))) << bit;
  return live;
}

// One chunk of the tile's list: span masks first, then span by span with the state in
// registers (the list position order is kept within each span). Returns the spans evaluated.
int64_t composite_chunk(const State& st, int32_t c0, int32_t c1, int32_t start, int x0, int y0,
                        uint32_t& live, TileAcc& a) {
  const Packed* ptr[CHUNK];
  uint32_t mask[CHUNK], any = 0;
  uint8_t list[2 * TILE][CHUNK];
  int count[2 * TILE] = {0};
  const int n = c1 - c0;
  for (int j = 0; j < n; ++j) {
    if (c0 + j + PREFETCH < st.tile_start.back())
      __builtin_prefetch(&st.gs[st.isect[c0 + j + PREFETCH]]);
    ptr[j] = &st.gs[st.isect[c0 + j]];
    mask[j] = span_mask(*ptr[j], x0, y0) & live;
    any |= mask[j];
  }
  for (int j = 0; j < n; ++j)
    for (uint32_t m = mask[j]; m; m &= m - 1) {
      const int bit = __builtin_ctz(m);
      list[bit][count[bit]++] = static_cast<uint8_t>(j);
    }
  const vf px[2] = {LANE + (x0 + 0.5f), LANE + (x0 + SPAN + 0.5f)};
  int64_t spans = 0;
  for (uint32_t m = any; m; m &= m - 1) {
    const int bit = __builtin_ctz(m), o = span_offset(bit);
    const float yc = static_cast<float>(y0 + (bit & (TILE - 1))) + 0.5f;
    Span s{load(a.T + o), load(a.r + o), load(a.g + o), load(a.b + o), load(a.d + o),
           load_i(a.last + o)};
    for (int i = 0; i < count[bit]; ++i) {
      const int j = list[bit][i];
      composite(*ptr[j], c0 + j - start + 1, px[bit >> 4], ptr[j]->v - yc, s);
      ++spans;
      if (!any_positive(s.T)) {
        live &= ~(1u << bit);
        break;
      }
    }
    store(a.T + o, s.T), store(a.r + o, s.r), store(a.g + o, s.g), store(a.b + o, s.b);
    store(a.d + o, s.d), store_i(a.last + o, s.last);
  }
  return spans;
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
  const int32_t start = st.tile_start[tile], end = st.tile_start[tile + 1];
  int64_t spans = 0;
  for (int32_t c0 = start; c0 < end && live; c0 += CHUNK)
    spans += composite_chunk(st, c0, std::min(c0 + CHUNK, end), start, x0, y0, live, a);
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
