// Backward pass: back-to-front recomputation per tile, from the final transmittance.
//
// For the Gaussians i accepted by a pixel (T_1 = 1, T_{i+1} = T_i (1 - alpha_i)):
//   image = sum c_i alpha_i T_i + T_final bg,  depth = sum z_i alpha_i T_i,  alpha = 1 - T_final
//   d image / d alpha_i = T_i (c_i - Y_i) - T_final / (1 - alpha_i) bg
//   d alpha / d alpha_i = T_final / (1 - alpha_i)
// with Y_i the (normalised) colour behind i: Y_n = 0, Y_{i-1} = alpha_i c_i + (1 - alpha_i) Y_i.
// Only g . Y_i is needed (g = d loss / d (image, depth) of the pixel), so a pixel keeps the
// scalar Q_i = g . Y_i with the same recursion instead of Y_i itself.
// Each thread sums per-Gaussian gradients in its own buffer; buffers are reduced at the end.
#include <omp.h>

#include <algorithm>
#include <cmath>

#include "pool.h"
#include "raster.h"
#include "simd.h"

namespace segs_raster {
namespace {

struct TileGrad {
  alignas(64) float T[TILE_PIX];   // transmittance behind the current Gaussian
  alignas(64) float q[TILE_PIX];   // g . (colour, depth) behind it (normalised)
  alignas(64) float gr[TILE_PIX];  // d loss / d image, depth, and the T_final term
  alignas(64) float gg[TILE_PIX];
  alignas(64) float gb[TILE_PIX];
  alignas(64) float gd[TILE_PIX];
  alignas(64) float gt[TILE_PIX];  // T_final (g_alpha - g_image . bg)
  alignas(64) int32_t last[TILE_PIX];
  int32_t span_last[2 * TILE];  // per span (bit 16 h + r): largest n_contrib of its pixels
  int32_t order[2 * TILE];      // span bits by decreasing span_last
};

constexpr int PREFETCH = 8;  // list entries ahead: Packed records are scattered in memory

inline int span_offset(int bit) { return (bit & (TILE - 1)) * TILE + (bit >> 4) * SPAN; }

// Load the tile's pixel state; returns the background gradient contribution in bg[3].
void load_tile(const State& st, const BackwardIn& in, int tile, TileGrad& s, double bg[3]) {
  const int x0 = (tile % st.tiles_x) * TILE, y0 = (tile / st.tiles_x) * TILE;
  const size_t o = static_cast<size_t>(tile) * TILE_PIX;
  for (int i = 0; i < TILE_PIX; ++i) {
    const int x = x0 + i % TILE, y = y0 + i / TILE;
    const bool inside = x < st.width && y < st.height;
    const size_t pix = inside ? static_cast<size_t>(y) * st.width + x : 0;
    const float T = st.final_T[o + i];
    s.T[i] = T;
    s.q[i] = 0.f;
    s.gr[i] = inside ? in.g_image[3 * pix] : 0.f;
    s.gg[i] = inside ? in.g_image[3 * pix + 1] : 0.f;
    s.gb[i] = inside ? in.g_image[3 * pix + 2] : 0.f;
    // expected depth = depth_acc / max(alpha, eps): chain rule into depth_acc and alpha
    const float alpha = 1.f - T, gz = inside ? in.g_depth[pix] : 0.f;
    const float denom = alpha < ALPHA_EPS ? ALPHA_EPS : alpha;
    s.gd[i] = gz / denom;
    float ga = inside ? in.g_alpha[pix] : 0.f;
    if (alpha >= ALPHA_EPS) ga -= gz * st.depth_acc[o + i] / (denom * denom);
    s.gt[i] = T * (ga - (s.gr[i] * st.bg[0] + s.gg[i] * st.bg[1] + s.gb[i] * st.bg[2]));
    s.last[i] = inside ? st.n_contrib[o + i] : 0;
    bg[0] += T * s.gr[i];
    bg[1] += T * s.gg[i];
    bg[2] += T * s.gb[i];
  }
  for (int bit = 0; bit < 2 * TILE; ++bit) {
    const int32_t* l = s.last + span_offset(bit);
    s.span_last[bit] = *std::max_element(l, l + SPAN);
    s.order[bit] = bit;
  }
  std::sort(s.order, s.order + 2 * TILE,
            [&s](int a, int b) { return s.span_last[a] > s.span_last[b]; });
}

// One Gaussian's lane sums over the spans of a tile (a local, so it stays in registers).
// Screen-space terms are kept as moments of gsig = d loss / d sigma, combined in finish():
// d sigma / d u = 2 ha dx + b dy, d v = b dx + 2 hc dy, d a = dx^2 / 2, d b = dx dy, d c = dy^2 / 2.
struct Acc {
  vf sdx, sdx2, sdy, sdxdy, sdy2;  // sums of gsig dx, gsig dx^2, gsig dy, gsig dx dy, gsig dy^2
  vf op, r, g, b, z;               // d opacity, d colour, d depth
};

// Per-thread gradient buffer stride: one cache line per Gaussian.
constexpr int GRAD_STRIDE = 16;
static_assert(GRAD_STRIDE >= N_GRAD, "gradient record too small");

// Undo Gaussian `p` (list position kk, 1-based) on the span at offset o; add its gradients.
inline void backprop_span(const Packed& p, int32_t kk, vf px, float dy, TileGrad& s, int o,
                          Acc& a) {
  const vf dx = p.u - px;
  const vf sg = span_sigma(p, px, dy);
  const vf e = vexp(-sg);
  const vf raw = p.opacity * e;
  const vf al = clamp_alpha(raw);
  const vf zero = splat<vf>(0.f);
  const vi valid = (splat_i(kk) <= load_i(s.last + o)) & (sg >= zero) &
                   (al >= splat<vf>(ALPHA_MIN));
  const vf om = 1.f - al, inv = 1.f / om;
  const vf T = load(s.T + o), q = load(s.q + o);
  const vf Ti = valid ? T * inv : T;
  const vf w = valid ? al * Ti : zero;
  const vf gr = load(s.gr + o), gg = load(s.gg + o), gb = load(s.gb + o), gd = load(s.gd + o);
  const vf cg = gr * p.r + gg * p.g + gb * p.bl + gd * p.z;  // g . (colour, depth) of p
  const vf ga = Ti * (cg - q) + load(s.gt + o) * inv;
  const vi free = valid & (raw <= splat<vf>(ALPHA_MAX));
  const vf gsig = free ? -al * ga : zero;
  const vf gdx = gsig * dx;
  a.sdx += gdx;
  a.sdx2 += gdx * dx;
  a.sdy += gsig * dy;
  a.sdxdy += gdx * dy;
  a.sdy2 += gsig * (dy * dy);
  a.op += free ? e * ga : zero;
  a.r += w * gr;
  a.g += w * gg;
  a.b += w * gb;
  a.z += w * gd;
  store(s.q + o, valid ? al * cg + om * q : q);
  store(s.T + o, Ti);
}

// Add one Gaussian's gradients (u, v, conic a, b, c, opacity, r, g, b, z) to its record.
inline void finish(const Packed& p, const Acc& a, float* dst) {
  const float sdx = hsum(a.sdx), sdy = hsum(a.sdy);
  dst[0] += 2.f * p.ha * sdx + p.b * sdy;
  dst[1] += p.b * sdx + 2.f * p.hc * sdy;
  dst[2] += 0.5f * hsum(a.sdx2);
  dst[3] += hsum(a.sdxdy);
  dst[4] += 0.5f * hsum(a.sdy2);
  dst[5] += hsum(a.op);
  dst[6] += hsum(a.r);
  dst[7] += hsum(a.g);
  dst[8] += hsum(a.b);
  dst[9] += hsum(a.z);
}

void backprop_tile(const State& st, int tile, TileGrad& s, float* grad) {
  const int x0 = (tile % st.tiles_x) * TILE, y0 = (tile / st.tiles_x) * TILE;
  const vf px[2] = {LANE + (x0 + 0.5f), LANE + (x0 + SPAN + 0.5f)};
  const int32_t start = st.tile_start[tile];
  uint32_t active = 0;  // spans with a pixel whose n_contrib >= kk
  int next = 0;
  for (int32_t kk = s.span_last[s.order[0]]; kk >= 1; --kk) {
    while (next < 2 * TILE && s.span_last[s.order[next]] >= kk) active |= 1u << s.order[next++];
    if (kk > PREFETCH) {
      const int32_t ahead = st.isect[start + kk - 1 - PREFETCH];
      __builtin_prefetch(&st.gs[ahead]);
      __builtin_prefetch(grad + static_cast<size_t>(ahead) * GRAD_STRIDE, 1);
    }
    const int32_t pos = st.isect[start + kk - 1];
    const Packed& p = st.gs[pos];
    uint32_t m = span_mask(p, x0, y0) & active;
    if (!m) continue;
    Acc a = {};
    for (; m; m &= m - 1) {
      const int bit = __builtin_ctz(m);
      const float dy = p.v - (static_cast<float>(y0 + (bit & (TILE - 1))) + 0.5f);
      backprop_span(p, kk, px[bit >> 4], dy, s, span_offset(bit), a);
    }
    finish(p, a, grad + static_cast<size_t>(pos) * GRAD_STRIDE);
  }
}

// Zero the caller's per-Gaussian gradient arrays, then add the per-thread buffers into them.
void scatter(const State& st, const std::vector<float>& bufs, int nt, const BackwardOut& out,
             int threads) {
  const int m = static_cast<int>(st.gs.size());
  const size_t stride = static_cast<size_t>(m) * GRAD_STRIDE;
#pragma omp parallel num_threads(threads)
  {
#pragma omp for schedule(static)
  for (int i = 0; i < st.n; ++i) {
    out.means2d[2 * i] = out.means2d[2 * i + 1] = out.opacities[i] = out.depths[i] = 0.f;
    for (int q = 0; q < 3; ++q) out.conics[3 * i + q] = out.colors[3 * i + q] = 0.f;
  }
#pragma omp for schedule(static)
  for (int pos = 0; pos < m; ++pos) {
    float g[N_GRAD] = {0.f};
    for (int t = 0; t < nt; ++t)
      for (int q = 0; q < N_GRAD; ++q) g[q] += bufs[t * stride + pos * GRAD_STRIDE + q];
    const int id = st.gs[pos].id;
    out.means2d[2 * id] = g[0];
    out.means2d[2 * id + 1] = g[1];
    for (int q = 0; q < 3; ++q) out.conics[3 * id + q] = g[2 + q];
    out.opacities[id] = g[5];
    for (int q = 0; q < 3; ++q) out.colors[3 * id + q] = g[6 + q];
    out.depths[id] = g[9];
  }
  }
}

}  // namespace

void backward(const State& st, const BackwardIn& in, const BackwardOut& out, int threads) {
  const int n_tiles = st.n_tiles();
  const size_t stride = st.gs.size() * GRAD_STRIDE;
  threads = std::max(1, std::min(threads, n_tiles));
  Scratch<float> scratch;
  std::vector<float>& bufs = scratch.v;
  bufs.assign(stride * threads, 0.f);
  std::vector<double> bg_parts(3 * static_cast<size_t>(threads), 0.0);
  int used = 1;
  // Deterministic: tile i always goes to thread i % used (static round robin, which balances
  // about as well as a dynamic schedule here), and the per-thread sums are added in thread order
  // in scatter(), so the same inputs give bit-identical gradients from run to run.
#pragma omp parallel num_threads(threads)
  {
    TileGrad* s = new TileGrad;
    double bg_local[3] = {0.0, 0.0, 0.0};
    const int t = omp_get_thread_num();
#pragma omp single
    used = omp_get_num_threads();
#pragma omp for schedule(static, 1)
    for (int tile = 0; tile < n_tiles; ++tile) {
      load_tile(st, in, tile, *s, bg_local);
      backprop_tile(st, tile, *s, bufs.data() + stride * t);
    }
    for (int c = 0; c < 3; ++c) bg_parts[3 * t + c] = bg_local[c];
    delete s;
  }
  for (int c = 0; c < 3; ++c) {
    double bg = 0.0;
    for (int t = 0; t < used; ++t) bg += bg_parts[3 * t + c];
    out.background[c] = static_cast<float>(bg);
  }
  scatter(st, bufs, used, out, threads);
}

}  // namespace segs_raster
