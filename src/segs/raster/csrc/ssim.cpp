// Fused SSIM loss on the CPU: mean SSIM of two [C,H,W] float32 images and its gradient with
// respect to the first (the render). Same definition as kornia.metrics.ssim with
// padding='same': a separable window w (K taps, odd) applied with 'reflect' borders (index -1
// reads 1) to x, y, x^2, y^2, xy; S = (2 mu_x mu_y + C1)(2 cov + C2) /
// ((mu_x^2 + mu_y^2 + C1)(var_x + var_y + C2) + eps).
//
// The forward pass also stores, per pixel, dS/dmu_x, dS/dE[x^2] and dS/dE[xy] (3 maps); the
// backward pass blurs them with the transposed window operator and combines:
//   dL/dx = B^T a + 2 x B^T b + y B^T c   with a, b, c the stored maps times dL/dS.
// One pass is horizontal then vertical; its transpose is vertical (a gather of rows) then
// horizontal (a scatter within a row), so rows run in parallel without write conflicts.
#include "ssim.h"

#include <omp.h>

#include <algorithm>
#include <utility>
#include <vector>

#include "pool.h"

namespace segs_raster {
namespace {

inline int reflect(int i, int n) {
  if (i < 0) i = -i;
  if (i >= n) i = 2 * (n - 1) - i;
  return i;
}

// Horizontal pass of one row: out[j] = sum_t w[t] in[reflect(j + t - r)], via a padded copy.
void blur_row(const float* in, float* out, float* pad, int width, const float* w, int taps) {
  const int r = taps / 2;
  for (int j = 0; j < width + 2 * r; ++j) pad[j] = in[reflect(j - r, width)];
  for (int j = 0; j < width; ++j) out[j] = 0.f;
  for (int t = 0; t < taps; ++t) {
    const float wt = w[t];
    const float* src = pad + t;
    for (int j = 0; j < width; ++j) out[j] += wt * src[j];
  }
}

// Transpose of blur_row: out[reflect(j + t - r)] += w[t] in[j].
void blur_row_t(const float* in, float* out, int width, const float* w, int taps) {
  const int r = taps / 2;
  for (int j = 0; j < width; ++j) out[j] = 0.f;
  for (int t = 0; t < taps; ++t) {
    const float wt = w[t];
    const int shift = t - r;
    const int lo = std::max(0, -shift), hi = std::min(width, width - shift);
    for (int j = lo; j < hi; ++j) out[j + shift] += wt * in[j];
    for (int j = 0; j < lo; ++j) out[reflect(j + shift, width)] += wt * in[j];
    for (int j = std::max(hi, 0); j < width; ++j) out[reflect(j + shift, width)] += wt * in[j];
  }
}

// Rows that the vertical pass reads for output row i, with their weights (duplicates merged).
std::vector<std::vector<std::pair<int, float>>> vertical_taps(int height, const float* w, int taps,
                                                              bool transpose) {
  const int r = taps / 2;
  std::vector<std::vector<std::pair<int, float>>> rows(height);
  for (int i = 0; i < height; ++i) {
    for (int t = 0; t < taps; ++t) {
      const int src = reflect(i + t - r, height);
      const int out = transpose ? src : i, in = transpose ? i : src;
      auto& list = rows[out];
      auto it = std::find_if(list.begin(), list.end(), [&](auto& p) { return p.first == in; });
      if (it == list.end()) list.emplace_back(in, w[t]);
      else it->second += w[t];
    }
  }
  return rows;
}

}  // namespace

double ssim_forward(const SsimIn& in, float* saved, int threads) {
  const int C = in.channels, H = in.height, W = in.width, K = in.taps;
  const size_t plane = size_t(H) * W, n = plane * C;
  Scratch<float> rows_buf;  // 5 horizontally blurred moment maps [5][C][H][W]
  rows_buf.v.resize(5 * n);
  float* hb = rows_buf.v.data();
  const auto vtaps = vertical_taps(H, in.window, K, false);
  std::vector<double> partial(std::max(threads, 1), 0.0);  // per-thread sums, added in order
#pragma omp parallel num_threads(threads)
  {
    std::vector<float> pad(W + K), prod(W);
#pragma omp for schedule(static)
    for (int cr = 0; cr < C * H; ++cr) {
      const size_t off = size_t(cr) * W;
      const float* x = in.render + off;
      const float* y = in.target + off;
      blur_row(x, hb + off, pad.data(), W, in.window, K);
      blur_row(y, hb + n + off, pad.data(), W, in.window, K);
      for (int j = 0; j < W; ++j) prod[j] = x[j] * x[j];
      blur_row(prod.data(), hb + 2 * n + off, pad.data(), W, in.window, K);
      for (int j = 0; j < W; ++j) prod[j] = y[j] * y[j];
      blur_row(prod.data(), hb + 3 * n + off, pad.data(), W, in.window, K);
      for (int j = 0; j < W; ++j) prod[j] = x[j] * y[j];
      blur_row(prod.data(), hb + 4 * n + off, pad.data(), W, in.window, K);
    }
    std::vector<float> m(5 * size_t(W));
#pragma omp for schedule(static)
    for (int cr = 0; cr < C * H; ++cr) {
      const int c = cr / H, i = cr % H;
      std::fill(m.begin(), m.end(), 0.f);
      for (const auto& [src, wt] : vtaps[i]) {
        const size_t base = size_t(c) * plane + size_t(src) * W;
        for (int q = 0; q < 5; ++q) {
          const float* s = hb + q * n + base;
          float* d = m.data() + size_t(q) * W;
          for (int j = 0; j < W; ++j) d[j] += wt * s[j];
        }
      }
      const float *mx = m.data(), *my = mx + W, *exx = my + W, *eyy = exx + W, *exy = eyy + W;
      const size_t off = size_t(cr) * W;
      float *d_mu = saved + off, *d_xx = saved + n + off, *d_xy = saved + 2 * n + off;
      double row_sum = 0.0;
      for (int j = 0; j < W; ++j) {
        const float mxy = mx[j] * my[j], mxx = mx[j] * mx[j], myy = my[j] * my[j];
        const float a1 = 2.f * mxy + in.c1, a2 = 2.f * (exy[j] - mxy) + in.c2;
        const float b1 = mxx + myy + in.c1, b2 = (exx[j] - mxx) + (eyy[j] - myy) + in.c2;
        const float den = b1 * b2 + in.eps;
        const float s = a1 * a2 / den;
        row_sum += s;
        d_xy[j] = 2.f * a1 / den;
        d_xx[j] = -s * b1 / den;
        d_mu[j] = 2.f * my[j] * (a2 - a1) / den - 2.f * mx[j] * s * (b2 - b1) / den;
      }
      partial[omp_get_thread_num()] += row_sum;
    }
  }
  double total = 0.0;
  for (double p : partial) total += p;
  return total / double(n);
}

void ssim_backward(const SsimIn& in, const float* saved, float grad_mean, float* grad_render,
                   int threads) {
  const int C = in.channels, H = in.height, W = in.width, K = in.taps;
  const size_t plane = size_t(H) * W, n = plane * C;
  const float scale = grad_mean / float(n);
  const auto vtaps = vertical_taps(H, in.window, K, true);
#pragma omp parallel num_threads(threads)
  {
    std::vector<float> v(3 * size_t(W)), h(3 * size_t(W));
#pragma omp for schedule(static)
    for (int cr = 0; cr < C * H; ++cr) {
      const int c = cr / H, i = cr % H;
      std::fill(v.begin(), v.end(), 0.f);
      for (const auto& [src, wt] : vtaps[i]) {  // transpose of the vertical pass: gather rows
        const size_t base = size_t(c) * plane + size_t(src) * W;
        for (int q = 0; q < 3; ++q) {
          const float* s = saved + q * n + base;
          float* d = v.data() + size_t(q) * W;
          const float k = wt * scale;
          for (int j = 0; j < W; ++j) d[j] += k * s[j];
        }
      }
      for (int q = 0; q < 3; ++q)  // transpose of the horizontal pass
        blur_row_t(v.data() + size_t(q) * W, h.data() + size_t(q) * W, W, in.window, K);
      const size_t off = size_t(cr) * W;
      const float *x = in.render + off, *y = in.target + off;
      const float *ha = h.data(), *hb = ha + W, *hc = hb + W;
      float* g = grad_render + off;
      for (int j = 0; j < W; ++j) g[j] = ha[j] + 2.f * x[j] * hb[j] + y[j] * hc[j];
    }
  }
}

}  // namespace segs_raster
