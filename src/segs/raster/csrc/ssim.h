// Fused SSIM (see ssim.cpp). Images are float32, contiguous [C,H,W]; H and W > taps / 2.
#pragma once

#include <cstddef>

namespace segs_raster {

struct SsimIn {
  const float* render;  // [C,H,W]
  const float* target;  // [C,H,W]
  const float* window;  // [taps], the 1-D Gaussian window (normalised)
  int channels, height, width, taps;
  float c1, c2, eps;
};

// Mean SSIM; writes dS/dmu_x, dS/dE[x^2], dS/dE[xy] into saved [3][C][H][W].
double ssim_forward(const SsimIn& in, float* saved, int threads);

// grad_render [C,H,W] = d(mean SSIM)/d render * grad_mean.
void ssim_backward(const SsimIn& in, const float* saved, float grad_mean, float* grad_render,
                   int threads);

}  // namespace segs_raster
