// EWA projection (forward and hand-written backward), the same arithmetic as
// segs/raster/_projection.py (which is the reference; tests compare the two).
#include <omp.h>

#include <algorithm>
#include <cmath>

#include "projection.h"

namespace segs_raster {
namespace {

constexpr float FOV_MARGIN = 0.3f;

struct M3 {
  float m[3][3];
};

// Rotation from a normalised wxyz quaternion.
M3 rotmat(float w, float x, float y, float z) {
  return {{{1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)},
           {2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)},
           {2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)}}};
}

// Everything one Gaussian's forward computes that the backward reuses.
struct Proj {
  float q[4], qnorm;         // normalised quaternion and the norm used
  M3 Rq, M, cov_c;           // rotation, R S, camera covariance
  float p[3], zs, inv_z;     // camera point, z used for division (1 if culled by depth), 1/zs
  float cx_, cy_;            // clamped x/z, y/z used in the Jacobian
  bool clamp_x, clamp_y, in_depth;
  float J[2][3];
  float a, b, c, det;        // dilated 2D covariance
};

void compute(const ProjectIn& in, int i, Proj& s) {
  const float* qi = in.quats + 4 * i;
  const float nrm = std::sqrt(qi[0] * qi[0] + qi[1] * qi[1] + qi[2] * qi[2] + qi[3] * qi[3]);
  s.qnorm = std::max(nrm, 1e-12f);
  const float inv_n = 1.f / s.qnorm;
  for (int k = 0; k < 4; ++k) s.q[k] = qi[k] * inv_n;
  s.Rq = rotmat(s.q[0], s.q[1], s.q[2], s.q[3]);
  const float* sc = in.scales + 3 * i;
  for (int r = 0; r < 3; ++r)
    for (int k = 0; k < 3; ++k) s.M.m[r][k] = s.Rq.m[r][k] * sc[k];
  const float* V = in.viewmat;  // row-major 4x4
  float VM[3][3];               // Rv M
  for (int r = 0; r < 3; ++r) {
    s.p[r] = V[4 * r] * in.means[3 * i] + V[4 * r + 1] * in.means[3 * i + 1] +
             V[4 * r + 2] * in.means[3 * i + 2] + V[4 * r + 3];
    for (int k = 0; k < 3; ++k)
      VM[r][k] = V[4 * r] * s.M.m[0][k] + V[4 * r + 1] * s.M.m[1][k] + V[4 * r + 2] * s.M.m[2][k];
  }
  for (int r = 0; r < 3; ++r)
    for (int k = 0; k < 3; ++k)
      s.cov_c.m[r][k] = VM[r][0] * VM[k][0] + VM[r][1] * VM[k][1] + VM[r][2] * VM[k][2];
  s.in_depth = s.p[2] >= in.near && s.p[2] <= in.far;
  s.zs = s.in_depth ? s.p[2] : 1.f;
  const float fx = in.K[0], fy = in.K[4];
  const float lxp = in.lim[0], lxn = in.lim[1], lyp = in.lim[2], lyn = in.lim[3];
  s.inv_z = 1.f / s.zs;
  const float xz = s.p[0] * s.inv_z, yz = s.p[1] * s.inv_z;
  s.cx_ = std::min(std::max(xz, -lxn), lxp);
  s.cy_ = std::min(std::max(yz, -lyn), lyp);
  s.clamp_x = s.cx_ != xz;
  s.clamp_y = s.cy_ != yz;
  const float iz = s.inv_z;
  s.J[0][0] = fx * iz, s.J[0][1] = 0.f, s.J[0][2] = -fx * s.cx_ * iz;
  s.J[1][0] = 0.f, s.J[1][1] = fy * iz, s.J[1][2] = -fy * s.cy_ * iz;
  float JC[2][3];
  for (int r = 0; r < 2; ++r)
    for (int k = 0; k < 3; ++k)
      JC[r][k] = s.J[r][0] * s.cov_c.m[0][k] + s.J[r][1] * s.cov_c.m[1][k] +
                 s.J[r][2] * s.cov_c.m[2][k];
  auto jcj = [&](int r, int k) { return JC[r][0] * s.J[k][0] + JC[r][1] * s.J[k][1] + JC[r][2] * s.J[k][2]; };
  s.a = jcj(0, 0) + in.eps2d;
  s.b = 0.5f * (jcj(0, 1) + jcj(1, 0));
  s.c = jcj(1, 1) + in.eps2d;
  s.det = s.a * s.c - s.b * s.b;
}

int radius_of(const ProjectIn& in, const Proj& s, float u, float v) {
  if (!s.in_depth || !(s.det > 0.f)) return 0;
  const float mid = 0.5f * (s.a + s.c);
  const float lam = mid + std::sqrt(std::max(mid * mid - s.det, 0.1f));
  const float r = std::ceil(3.f * std::sqrt(lam));
  const bool inside = u + r > 0 && u - r < in.width && v + r > 0 && v - r < in.height;
  return inside ? static_cast<int>(r) : 0;
}

}  // namespace

// Jacobian clamp limits on x/z, y/z: the image plus FOV_MARGIN of the half field of view.
void set_limits(ProjectIn& in) {
  const float fx = in.K[0], fy = in.K[4], cx = in.K[2], cy = in.K[5];
  in.lim[0] = (in.width - cx) / fx + FOV_MARGIN * 0.5f * in.width / fx;
  in.lim[1] = cx / fx + FOV_MARGIN * 0.5f * in.width / fx;
  in.lim[2] = (in.height - cy) / fy + FOV_MARGIN * 0.5f * in.height / fy;
  in.lim[3] = cy / fy + FOV_MARGIN * 0.5f * in.height / fy;
}

void project_forward(const ProjectIn& in, const ProjectOut& out, int threads) {
#pragma omp parallel for schedule(static) num_threads(threads)
  for (int i = 0; i < in.n; ++i) {
    Proj s;
    compute(in, i, s);
    const float u = in.K[0] * s.p[0] * s.inv_z + in.K[2];
    const float v = in.K[4] * s.p[1] * s.inv_z + in.K[5];
    const float inv_det = 1.f / (s.det > 0.f ? s.det : 1.f);
    out.means2d[2 * i] = u;
    out.means2d[2 * i + 1] = v;
    out.conics[3 * i] = s.c * inv_det;
    out.conics[3 * i + 1] = -s.b * inv_det;
    out.conics[3 * i + 2] = s.a * inv_det;
    out.depths[i] = s.p[2];
    out.radii[i] = radius_of(in, s, u, v);
  }
}

namespace {

// d loss / d (a, b, c) of the dilated covariance from d loss / d conic (c, -b, a) / det.
void conic_vjp(const Proj& s, const float* g, float G[2][2]) {
  float ga, gb, gc;
  if (s.det > 0.f) {
    const float i2 = 1.f / (s.det * s.det), a = s.a, b = s.b, c = s.c;
    ga = (-c * c * g[0] + b * c * g[1] - b * b * g[2]) * i2;
    gb = (2.f * b * c * g[0] - (s.det + 2.f * b * b) * g[1] + 2.f * a * b * g[2]) * i2;
    gc = (-b * b * g[0] + a * b * g[1] - a * a * g[2]) * i2;
  } else {  // reference divides by 1 there
    ga = g[2], gb = -g[1], gc = g[0];
  }
  G[0][0] = ga, G[0][1] = G[1][0] = 0.5f * gb, G[1][1] = gc;
}

// d loss / d camera point p from the Jacobian and means2d gradients (z only if not culled).
void point_vjp(const ProjectIn& in, const Proj& s, const float GJ[2][3], const float* gm,
               float gdepth, float gp[3]) {
  const float fx = in.K[0], fy = in.K[4], x = s.p[0], y = s.p[1];
  const float iz = s.inv_z, iz2 = iz * iz, iz3 = iz2 * iz;
  const float dx = s.clamp_x ? 0.f : 1.f, dy = s.clamp_y ? 0.f : 1.f;
  gp[0] = gm[0] * fx * iz - GJ[0][2] * fx * dx * iz2;
  gp[1] = gm[1] * fy * iz - GJ[1][2] * fy * dy * iz2;
  float gz = 0.f;
  if (s.in_depth) {
    gz -= (gm[0] * fx * x + gm[1] * fy * y) * iz2;
    gz -= (GJ[0][0] * fx + GJ[1][1] * fy) * iz2;
    gz += GJ[0][2] * (fx * s.cx_ * iz2 + dx * fx * x * iz3);
    gz += GJ[1][2] * (fy * s.cy_ * iz2 + dy * fy * y * iz3);
  }
  gp[2] = gz + gdepth;
}

// d loss / d quaternion (raw, before normalisation) from d loss / d rotation matrix.
void quat_vjp(const Proj& s, const float G[3][3], float* gq) {
  const float w = s.q[0], x = s.q[1], y = s.q[2], z = s.q[3];
  const float g[4] = {
      2.f * (-z * G[0][1] + y * G[0][2] + z * G[1][0] - x * G[1][2] - y * G[2][0] + x * G[2][1]),
      2.f * (y * G[0][1] + z * G[0][2] + y * G[1][0] - 2.f * x * G[1][1] - w * G[1][2] +
             z * G[2][0] + w * G[2][1] - 2.f * x * G[2][2]),
      2.f * (-2.f * y * G[0][0] + x * G[0][1] + w * G[0][2] + x * G[1][0] + z * G[1][2] -
             w * G[2][0] + z * G[2][1] - 2.f * y * G[2][2]),
      2.f * (-2.f * z * G[0][0] - w * G[0][1] + x * G[0][2] + w * G[1][0] - 2.f * z * G[1][1] +
             y * G[1][2] + x * G[2][0] + y * G[2][1])};
  const float dot = w * g[0] + x * g[1] + y * g[2] + z * g[3];
  const bool normed = s.qnorm > 1e-12f;
  const float inv_n = 1.f / s.qnorm;
  for (int k = 0; k < 4; ++k) gq[k] = (normed ? g[k] - s.q[k] * dot : g[k]) * inv_n;
}

void backward_one(const ProjectIn& in, const ProjectGradIn& g, const ProjectGradOut& out, int i) {
  Proj s;
  compute(in, i, s);
  float G2[2][2];
  conic_vjp(s, g.conics + 3 * i, G2);
  float GJ[2][3], GC[3][3], tmp[2][3];  // d/dJ = 2 G J C, d/dC = J^T G J
  for (int r = 0; r < 2; ++r)
    for (int k = 0; k < 3; ++k) tmp[r][k] = G2[r][0] * s.J[0][k] + G2[r][1] * s.J[1][k];
  for (int r = 0; r < 2; ++r)
    for (int k = 0; k < 3; ++k)
      GJ[r][k] = 2.f * (tmp[r][0] * s.cov_c.m[0][k] + tmp[r][1] * s.cov_c.m[1][k] +
                        tmp[r][2] * s.cov_c.m[2][k]);
  for (int r = 0; r < 3; ++r)
    for (int k = 0; k < 3; ++k) GC[r][k] = s.J[0][r] * tmp[0][k] + s.J[1][r] * tmp[1][k];
  float gp[3];
  point_vjp(in, s, GJ, g.means2d + 2 * i, g.depths[i], gp);
  const float* V = in.viewmat;
  float GS[3][3], VG[3][3];  // GS = Rv^T GC Rv
  for (int r = 0; r < 3; ++r)
    for (int k = 0; k < 3; ++k)
      VG[r][k] = V[r] * GC[0][k] + V[4 + r] * GC[1][k] + V[8 + r] * GC[2][k];
  for (int r = 0; r < 3; ++r)
    for (int k = 0; k < 3; ++k)
      GS[r][k] = VG[r][0] * V[k] + VG[r][1] * V[4 + k] + VG[r][2] * V[8 + k];
  for (int r = 0; r < 3; ++r)
    out.means[3 * i + r] = V[r] * gp[0] + V[4 + r] * gp[1] + V[8 + r] * gp[2];
  float GR[3][3];
  const float* sc = in.scales + 3 * i;
  for (int k = 0; k < 3; ++k) out.scales[3 * i + k] = 0.f;
  for (int r = 0; r < 3; ++r)
    for (int k = 0; k < 3; ++k) {
      const float gm = 2.f * (GS[r][0] * s.M.m[0][k] + GS[r][1] * s.M.m[1][k] +
                              GS[r][2] * s.M.m[2][k]);
      GR[r][k] = gm * sc[k];
      out.scales[3 * i + k] += gm * s.Rq.m[r][k];
    }
  quat_vjp(s, GR, out.quats + 4 * i);
}

}  // namespace

void project_backward(const ProjectIn& in, const ProjectGradIn& g, const ProjectGradOut& out,
                      int threads) {
#pragma omp parallel for schedule(static) num_threads(threads)
  for (int i = 0; i < in.n; ++i) backward_one(in, g, out, i);
}

}  // namespace segs_raster
