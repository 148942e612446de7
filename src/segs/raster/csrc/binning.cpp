// Visibility, front-to-back sort and per-tile Gaussian lists.
//
// A Gaussian touches the tiles of its 3-sigma square (gsplat's isect_tiles arithmetic). Tiles
// outside the ellipse where alpha can reach 1/255 are dropped too: no pixel there could pass
// the alpha test, so the image is unchanged and less work is listed.
#include <omp.h>

#include <algorithm>
#include <cmath>
#include <cstring>

#include "pool.h"
#include "raster.h"

namespace segs_raster {
namespace {

struct Rect {
  int32_t x0, x1, y0, y1;  // tiles, exclusive ends
};

inline int clampi(float v, int hi) {
  v = std::fmin(std::fmax(v, 0.f), static_cast<float>(hi));
  return static_cast<int>(v);
}

// Level such that alpha >= 1/255 implies sigma <= level (a little generous against rounding).
float cull_level(float op) { return std::log(255.f * op) * 1.0001f + 1e-3f; }

bool regular(float a, float b, float c) { return a > 0.f && c > 0.f && a * c - b * b > 0.f; }

// Pixel columns/rows (inclusive) whose centre can have alpha >= 1/255; false if degenerate.
bool alpha_box(float u, float v, float a, float b, float c, float op, int32_t box[4]) {
  if (!regular(a, b, c)) return false;
  const float det = a * c - b * b, level = 2.f * cull_level(op);
  const float hx = std::sqrt(level * c / det) * 1.0001f + 0.01f;
  const float hy = std::sqrt(level * a / det) * 1.0001f + 0.01f;
  const float big = 1e9f;
  box[0] = static_cast<int32_t>(std::fmax(std::ceil(u - hx - 0.5f), -big));
  box[1] = static_cast<int32_t>(std::fmin(std::floor(u + hx - 0.5f), big));
  box[2] = static_cast<int32_t>(std::fmax(std::ceil(v - hy - 0.5f), -big));
  box[3] = static_cast<int32_t>(std::fmin(std::floor(v + hy - 0.5f), big));
  return true;
}

int floordiv(int32_t a, int b) { return a >= 0 ? a / b : -((-a + b - 1) / b); }

// Per Gaussian: tile rectangle (empty if invisible); returns visibility.
bool prepare_one(const ForwardIn& in, int i, int tw, int th, Rect& rect) {
  const float op = in.opacities[i];
  if (in.radii[i] <= 0 || !(op >= ALPHA_MIN)) return false;
  const float u = in.means2d[2 * i], v = in.means2d[2 * i + 1];
  const float r = static_cast<float>(in.radii[i]);
  rect = {clampi(std::floor((u - r) / TILE), tw), clampi(std::ceil((u + r) / TILE), tw),
          clampi(std::floor((v - r) / TILE), th), clampi(std::ceil((v + r) / TILE), th)};
  const float* cn = in.conics + 3 * i;
  int32_t box[4];
  if (alpha_box(u, v, cn[0], cn[1], cn[2], op, box)) {
    rect.x0 = std::max(rect.x0, std::min(floordiv(box[0], TILE), tw));
    rect.x1 = std::min(rect.x1, std::max(floordiv(box[1], TILE) + 1, 0));
    rect.y0 = std::max(rect.y0, std::min(floordiv(box[2], TILE), th));
    rect.y1 = std::min(rect.y1, std::max(floordiv(box[3], TILE) + 1, 0));
  }
  return rect.x1 > rect.x0 && rect.y1 > rect.y0;
}

// Stable LSD radix sort of (key, value) by key, 8 bits per pass; skips constant digits.
void radix_sort(std::vector<uint32_t>& keys, std::vector<int32_t>& vals) {
  const size_t n = keys.size();
  Scratch<uint32_t> k2_;
  Scratch<int32_t> v2_;
  std::vector<uint32_t>& k2 = k2_.v;
  std::vector<int32_t>& v2 = v2_.v;
  k2.resize(n);
  v2.resize(n);
  for (int shift = 0; shift < 32; shift += 8) {
    size_t count[257] = {0};
    for (size_t i = 0; i < n; ++i) ++count[((keys[i] >> shift) & 255u) + 1];
    if (std::any_of(count + 1, count + 257, [n](size_t c) { return c == n; })) continue;
    for (int d = 0; d < 256; ++d) count[d + 1] += count[d];
    for (size_t i = 0; i < n; ++i) {
      const size_t dst = count[(keys[i] >> shift) & 255u]++;
      k2[dst] = keys[i];
      v2[dst] = vals[i];
    }
    keys.swap(k2);
    vals.swap(v2);
  }
}

Packed pack(const ForwardIn& in, int i) {
  Packed p;
  p.u = in.means2d[2 * i];
  p.v = in.means2d[2 * i + 1];
  p.ha = 0.5f * in.conics[3 * i];
  p.b = in.conics[3 * i + 1];
  p.hc = 0.5f * in.conics[3 * i + 2];
  p.opacity = in.opacities[i];
  p.r = in.colors[3 * i];
  p.g = in.colors[3 * i + 1];
  p.bl = in.colors[3 * i + 2];
  p.z = in.depths[i];
  p.level = regular(in.conics[3 * i], p.b, in.conics[3 * i + 2]) ? cull_level(p.opacity) : -1.f;
  p.id = i;
  p.inv_2ha = p.level >= 0.f ? 1.f / (2.f * p.ha) : 0.f;
  p.pad[0] = p.pad[1] = p.pad[2] = 0.f;
  return p;
}

// Fill per-tile lists in depth order; each thread owns a band of tile rows (no atomics).
void fill_tiles(State& st, const std::vector<Rect>& rects, int threads) {
  const int tw = st.tiles_x, th = st.tiles_y, m = static_cast<int>(rects.size());
  std::vector<int32_t> count(static_cast<size_t>(tw) * th + 1, 0);
#pragma omp parallel num_threads(threads)
  {
    const int t = omp_get_thread_num(), nt = omp_get_num_threads();
    const int r0 = th * t / nt, r1 = th * (t + 1) / nt;
    for (int g = 0; g < m; ++g) {
      const Rect& q = rects[g];
      for (int y = std::max(q.y0, r0); y < std::min(q.y1, r1); ++y)
        for (int x = q.x0; x < q.x1; ++x) ++count[y * tw + x + 1];
    }
#pragma omp barrier
#pragma omp single
    for (int i = 0; i < tw * th; ++i) count[i + 1] += count[i];
    // implicit barrier after single
    std::vector<int32_t> cursor(count.begin(), count.end() - 1);
#pragma omp single
    st.isect.assign(count.back(), 0);
    for (int g = 0; g < m; ++g) {
      const Rect& q = rects[g];
      for (int y = std::max(q.y0, r0); y < std::min(q.y1, r1); ++y)
        for (int x = q.x0; x < q.x1; ++x) st.isect[cursor[y * tw + x]++] = g;
    }
  }
  st.tile_start.assign(count.begin(), count.end());
}

}  // namespace

void bin_gaussians(const ForwardIn& in, State& st, int threads) {
  const int n = in.n, tw = st.tiles_x, th = st.tiles_y;
  Scratch<Rect> rect_all_, rects_;
  Scratch<uint8_t> visible_;
  Scratch<uint32_t> keys_;
  Scratch<int32_t> ids_;
  std::vector<Rect>& rect_all = rect_all_.v;
  std::vector<uint8_t>& visible = visible_.v;
  rect_all.resize(n);
  visible.resize(n);
#pragma omp parallel for schedule(static) num_threads(threads)
  for (int i = 0; i < n; ++i)
    visible[i] = prepare_one(in, i, tw, th, rect_all[i]);
  std::vector<uint32_t>& keys = keys_.v;
  std::vector<int32_t>& ids = ids_.v;
  for (int i = 0; i < n; ++i) {
    if (!visible[i]) continue;
    uint32_t k;
    std::memcpy(&k, in.depths + i, sizeof(k));  // z > 0: float bits sort like the floats
    keys.push_back(k);
    ids.push_back(i);
  }
  radix_sort(keys, ids);
  const int m = static_cast<int>(ids.size());
  st.gs.resize(m);
  std::vector<Rect>& rects = rects_.v;
  rects.resize(m);
#pragma omp parallel for schedule(static) num_threads(threads)
  for (int j = 0; j < m; ++j) {
    st.gs[j] = pack(in, ids[j]);
    rects[j] = rect_all[ids[j]];
  }
  fill_tiles(st, rects, threads);
}

}  // namespace segs_raster
