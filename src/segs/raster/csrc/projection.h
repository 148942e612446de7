// EWA projection of 3D Gaussians, forward and backward (see projection.cpp).
#pragma once

#include <cstdint>

namespace segs_raster {

struct ProjectIn {
  const float* means;    // [N,3] world
  const float* quats;    // [N,4] wxyz, any norm
  const float* scales;   // [N,3]
  const float* viewmat;  // [4,4] world-to-camera, row-major
  const float* K;        // [3,3] row-major
  int n, width, height;
  float near, far;
  float eps2d;     // low-pass added to the 2D covariance's diagonal (pixels^2)
  float lim[4];  // filled by set_limits()
};

struct ProjectOut {
  float* means2d;   // [N,2]
  float* conics;    // [N,3]
  float* depths;    // [N]
  int32_t* radii;   // [N]
};

struct ProjectGradIn {
  const float* means2d;  // [N,2]
  const float* conics;   // [N,3]
  const float* depths;   // [N]
};

struct ProjectGradOut {
  float* means;   // [N,3]
  float* quats;   // [N,4]
  float* scales;  // [N,3]
};

void set_limits(ProjectIn& in);
void project_forward(const ProjectIn& in, const ProjectOut& out, int threads);
void project_backward(const ProjectIn& in, const ProjectGradIn& g, const ProjectGradOut& out,
                      int threads);

}  // namespace segs_raster
