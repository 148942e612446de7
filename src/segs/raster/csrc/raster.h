// CPU Gaussian rasterizer (3D-GS semantics), forward and hand-written backward.
//
// Pure C++17 + OpenMP, no torch headers: the Python side passes raw float32 pointers.
// Work is split over 16x16 tiles (OpenMP, dynamic schedule); inside a tile a Gaussian is applied
// row by row to 16 pixels at a time (one SIMD vector per row, see simd.h).
#pragma once

#include <cstdint>
#include <vector>

namespace segs_raster {

constexpr int TILE = 16;
constexpr int TILE_PIX = TILE * TILE;
constexpr float ALPHA_MIN = 1.0f / 255.0f;
constexpr float ALPHA_MAX = 0.99f;
constexpr float T_MIN = 1e-4f;
constexpr float ALPHA_EPS = 1e-10f;  // expected depth divides by max(alpha, ALPHA_EPS)
constexpr int N_GRAD = 10;  // per Gaussian: d u, v, conic a, b, c, opacity, r, g, b, z

// One visible Gaussian, stored in front-to-back order (one cache line).
struct alignas(64) Packed {
  float u, v;         // projected mean, pixels
  float ha, b, hc;    // conic: sigma = ha dx^2 + b dx dy + hc dy^2 (ha = a/2, hc = c/2)
  float opacity;
  float r, g, bl, z;  // colour and camera depth
  float level;        // alpha >= 1/255 needs sigma <= level (ln(255 opacity) + margin); -1: unknown
  int32_t id;         // index in the caller's arrays
  float inv_2ha;      // 1 / (2 ha), for span_mask
  float pad[3];
};

// Everything the backward pass needs; owned by the Python autograd context.
struct State {
  int n = 0, width = 0, height = 0, tiles_x = 0, tiles_y = 0;
  float bg[3] = {0.f, 0.f, 0.f};
  std::vector<Packed> gs;           // [M] visible Gaussians, depth order
  std::vector<int32_t> tile_start;  // [n_tiles + 1] offsets into isect
  std::vector<int32_t> isect;       // [I] positions into gs, per tile front to back
  std::vector<float> final_T;       // [n_tiles * 256] transmittance left per pixel
  std::vector<int32_t> n_contrib;   // [n_tiles * 256] list length up to the last contributor
  std::vector<float> depth_acc;     // [n_tiles * 256] sum of w_i z_i (before normalising)
  int64_t evaluations = 0;          // pixel-Gaussian evaluations of the forward pass

  int n_tiles() const { return tiles_x * tiles_y; }
  State();
  ~State();  // hands the buffers back to the pool (pool.h)
  State(const State&) = delete;
  State& operator=(const State&) = delete;
};

struct ForwardIn {
  const float* means2d;    // [N,2]
  const float* conics;     // [N,3] a, b, c
  const float* colors;     // [N,3]
  const float* opacities;  // [N]
  const float* depths;     // [N]
  const int32_t* radii;    // [N] 0 = culled
  const float* background; // [3]
  int n, width, height;
};

struct ForwardOut {
  float* image;  // [H,W,3]
  float* depth;  // [H,W] expected z: sum w_i z_i / max(alpha, 1e-10)
  float* alpha;  // [H,W] 1 - final transmittance
};

struct BackwardIn {
  const float* g_image;  // [H,W,3]
  const float* g_depth;  // [H,W]
  const float* g_alpha;  // [H,W]
};

struct BackwardOut {  // every entry is written (zero for Gaussians not drawn)
  float* means2d;     // [N,2]
  float* conics;      // [N,3]
  float* colors;      // [N,3]
  float* opacities;   // [N]
  float* depths;      // [N]
  float* background;  // [3]
};

// binning.cpp: visibility, depth sort, per-tile lists.
void bin_gaussians(const ForwardIn& in, State& st, int threads);
// forward.cpp / backward.cpp
void forward(const ForwardIn& in, const ForwardOut& out, State& st, int threads);
void backward(const State& st, const BackwardIn& in, const BackwardOut& out, int threads);

}  // namespace segs_raster
