// The motion-only pose kernels of the ORB frontend in C++.
//
// solve_pose: segs.slam.estimation.optimize._solve_pose (Levenberg-Marquardt on a w2c from pose-only
// reprojection edges). refine_pose: segs.slam.estimation.optimize.refine_pose around it (ORB-SLAM's
// PoseOptimization: rounds of Huber-reweighted LM with the chi-square inlier classification
// between rounds), so that a frame's pose refinement is one call without the interpreter.
// Both follow the Python code operation for operation; results agree to rounding (the rotation's
// re-orthonormalisation is the polar factor by Newton's iteration here, an SVD there).
#include <pybind11/numpy.h>
#include <pybind11/pybind11.h>

#include "common.h"

#include <algorithm>
#include <cmath>
#include <limits>
#include <vector>

namespace py = pybind11;

namespace {

using segs_slam::Arr;
using segs_slam::i64;

constexpr double kChi2Mono = 5.991, kChi2Stereo = 7.815;  // segs.slam.estimation.optimize.CHI2_MONO / _STEREO

// Whitened residuals and J^T J, J^T r of the pose-only reprojection edges at pose (R, t), as in
// segs.slam.estimation.optimize._pose_system. Returns the cost r . r.
struct PoseProblem {
  const double *P, *uv, *ur, *w, *w_ur;
  const bool* stereo;
  i64 n;
  double fx, fy, cx, cy, bf;

  double system(const double* T, double* H, double* g) const {
    for (int i = 0; i < 36; ++i) H[i] = 0.0;
    for (int i = 0; i < 6; ++i) g[i] = 0.0;
    double cost = 0.0;
    auto add = [&](const double* J, double r) {
      for (int a = 0; a < 6; ++a) {
        g[a] += J[a] * r;
        for (int b = 0; b < 6; ++b) H[6 * a + b] += J[a] * J[b];
      }
      cost += r * r;
    };
    for (i64 i = 0; i < n; ++i) {
      const double* p = P + 3 * i;
      const double x = T[0] * p[0] + T[1] * p[1] + T[2] * p[2] + T[3];
      const double y = T[4] * p[0] + T[5] * p[1] + T[6] * p[2] + T[7];
      const double z = T[8] * p[0] + T[9] * p[1] + T[10] * p[2] + T[11];
      const double iz = 1.0 / std::max(z, 1e-6);
      const double X = x * iz, Y = y * iz, XY = X * Y;
      const double fw = fx * w[i], gw = fy * w[i];
      const double Ju[6] = {-fw * XY, fw * (1.0 + X * X), -fw * Y, fw * iz, 0.0, -fw * X * iz};
      add(Ju, (fx * X + cx - uv[2 * i]) * w[i]);
      const double Jv[6] = {-gw * (1.0 + Y * Y), gw * XY, gw * X, 0.0, gw * iz, -gw * Y * iz};
      add(Jv, (fy * Y + cy - uv[2 * i + 1]) * w[i]);
      if (stereo && stereo[i]) {
        const double b = bf * iz * w_ur[i];
        const double Js[6] = {-b * Y, b * X, 0.0, 0.0, 0.0, -b * iz};
        add(Js, (bf * iz - (uv[2 * i] - ur[i])) * w_ur[i]);
      }
    }
    return cost;
  }
};

// Solves A x = b (6x6, partial pivoting); false when a pivot is exactly zero (numpy's LinAlgError).
bool solve6(double* A, double* b, double* x) {
  int piv[6] = {0, 1, 2, 3, 4, 5};
  for (int c = 0; c < 6; ++c) {
    int best = c;
    for (int r = c + 1; r < 6; ++r)
      if (std::abs(A[6 * piv[r] + c]) > std::abs(A[6 * piv[best] + c])) best = r;
    std::swap(piv[c], piv[best]);
    const double d = A[6 * piv[c] + c];
    if (d == 0.0) return false;
    for (int r = c + 1; r < 6; ++r) {
      const double f = A[6 * piv[r] + c] / d;
      for (int k = c; k < 6; ++k) A[6 * piv[r] + k] -= f * A[6 * piv[c] + k];
      b[piv[r]] -= f * b[piv[c]];
    }
  }
  for (int c = 5; c >= 0; --c) {
    double v = b[piv[c]];
    for (int k = c + 1; k < 6; ++k) v -= A[6 * piv[c] + k] * x[k];
    x[c] = v / A[6 * piv[c] + c];
  }
  return true;
}

// T <- exp(dx) T, exp as segs.slam.estimation.optimize._se3_exp: Rodrigues rotation, first-order translation.
void left_update(const double* dx, const double* T, double* out) {
  const double th = std::sqrt(dx[0] * dx[0] + dx[1] * dx[1] + dx[2] * dx[2]);
  double R[9] = {1, 0, 0, 0, 1, 0, 0, 0, 1};
  if (th >= std::numeric_limits<double>::epsilon()) {
    const double c = std::cos(th), s = std::sin(th), c1 = 1.0 - c;
    const double kx = dx[0] / th, ky = dx[1] / th, kz = dx[2] / th;
    R[0] = c + c1 * kx * kx;      R[1] = c1 * kx * ky - s * kz; R[2] = c1 * kx * kz + s * ky;
    R[3] = c1 * kx * ky + s * kz; R[4] = c + c1 * ky * ky;      R[5] = c1 * ky * kz - s * kx;
    R[6] = c1 * kx * kz - s * ky; R[7] = c1 * ky * kz + s * kx; R[8] = c + c1 * kz * kz;
  }
  for (int r = 0; r < 3; ++r) {
    for (int c = 0; c < 4; ++c)
      out[4 * r + c] = R[3 * r] * T[c] + R[3 * r + 1] * T[4 + c] + R[3 * r + 2] * T[8 + c];
    out[4 * r + 3] += dx[3 + r];
  }
  for (int c = 0; c < 4; ++c) out[12 + c] = T[12 + c];
}


// Levenberg-Marquardt as segs.slam.estimation.optimize._solve_pose on T [4,4] (in place).
void lm_pose(const PoseProblem& pr, double* T, int evaluations) {
  double H[36], g[6], H2[36], g2[6], A[36], b[6], dx[6], T2[16];
  double cost = pr.system(T, H, g), lam = 1e-4;
  for (int it = 0; it < evaluations - 1; ++it) {
    for (int i = 0; i < 36; ++i) A[i] = H[i];
    for (int i = 0; i < 6; ++i) {
      A[7 * i] += lam * (H[7 * i] + 1e-12);
      b[i] = -g[i];
    }
    if (!solve6(A, b, dx)) break;
    left_update(dx, T, T2);
    const double cost2 = pr.system(T2, H2, g2);
    if (cost2 < cost) {
      double dd = 0.0;
      for (int i = 0; i < 6; ++i) dd += dx[i] * dx[i];
      const bool stalled = cost - cost2 <= 1e-8 * cost || dd < 1e-20;
      std::copy(T2, T2 + 16, T);
      std::copy(H2, H2 + 36, H);
      std::copy(g2, g2 + 6, g);
      cost = cost2;
      lam = std::max(lam * 0.1, 1e-10);
      if (stalled) break;
    } else {
      lam *= 10.0;
      if (lam > 1e6) break;
    }
  }
}

// The rotation of T [4,4] replaced by its nearest rotation (the polar factor U V^T of its SVD,
// segs.slam.geometry.orthonormalize), by Newton's iteration R <- (R + R^-T) / 2, which converges
// quadratically from the near-rotations an LM step leaves.
void orthonormalize(double* T) {
  double R[9] = {T[0], T[1], T[2], T[4], T[5], T[6], T[8], T[9], T[10]};
  for (int it = 0; it < 3; ++it) {
    const double c[9] = {R[4] * R[8] - R[5] * R[7], R[5] * R[6] - R[3] * R[8], R[3] * R[7] - R[4] * R[6],
                         R[2] * R[7] - R[1] * R[8], R[0] * R[8] - R[2] * R[6], R[1] * R[6] - R[0] * R[7],
                         R[1] * R[5] - R[2] * R[4], R[2] * R[3] - R[0] * R[5], R[0] * R[4] - R[1] * R[3]};
    const double det = R[0] * c[0] + R[1] * c[1] + R[2] * c[2];  // c: cofactors, R^-T = c / det
    if (!(std::abs(det) > 1e-12)) return;
    double diff = 0.0;
    for (int i = 0; i < 9; ++i) {
      const double r = 0.5 * (R[i] + c[i] / det);
      diff = std::max(diff, std::abs(r - R[i]));
      R[i] = r;
    }
    if (diff < 1e-15) break;
  }
  for (int r = 0; r < 3; ++r)
    for (int c = 0; c < 3; ++c) T[4 * r + c] = R[3 * r + c];
  T[12] = T[13] = T[14] = 0.0;
  T[15] = 1.0;
}

// segs.slam.estimation.optimize.reproj_chi2 of one observation i at pose T -> chi2; z and the stereo flag out.
inline double chi2_at(const double* T, const double* P, const double* uv, const double* ur, const double* inv_s2,
                      double fx, double fy, double cx, double cy, double bf, double inv_ur_sigma2, i64 i, double& z,
                      bool& st) {
  const double* p = P + 3 * i;
  const double x = T[0] * p[0] + T[1] * p[1] + T[2] * p[2] + T[3];
  const double y = T[4] * p[0] + T[5] * p[1] + T[6] * p[2] + T[7];
  z = T[8] * p[0] + T[9] * p[1] + T[10] * p[2] + T[11];
  const double zs = std::abs(z) < 1e-9 ? 1e-9 : z;
  const double du = fx * x / zs + cx - uv[2 * i], dv = fy * y / zs + cy - uv[2 * i + 1];
  double chi2 = (du * du + dv * dv) * inv_s2[i];
  st = ur != nullptr && ur[i] >= 0;
  if (st) {
    const double e = bf / zs - (uv[2 * i] - ur[i]);
    chi2 = chi2 + (e * e) * (inv_ur_sigma2 > 0 ? inv_ur_sigma2 : inv_s2[i]);
  }
  return chi2;
}

// Levenberg-Marquardt as segs.slam.estimation.optimize._solve_pose: w2c [4,4], P [M,3], uv [M,2], ur [M] or
// empty, w [M], K [3,3], stereo [M] bool or empty, w_ur [M] or empty -> w2c [4,4].
py::array_t<double> solve_pose(Arr<double> w2c, Arr<double> P, Arr<double> uv, Arr<double> ur,
                               Arr<double> w, Arr<double> K, double bf, Arr<bool> stereo,
                               Arr<double> w_ur, int evaluations) {
  const double* k = K.data();
  PoseProblem pr{P.data(), uv.data(), ur.size() ? ur.data() : nullptr, w.data(),
                 w_ur.size() ? w_ur.data() : nullptr, stereo.size() ? stereo.data() : nullptr,
                 P.shape(0), k[0], k[4], k[2], k[5], bf};
  py::array_t<double> result({4, 4});
  double* T = result.mutable_data();
  std::copy(w2c.data(), w2c.data() + 16, T);
  {
    py::gil_scoped_release release;
    lm_pose(pr, T, evaluations);
  }
  return result;
}

// segs.slam.estimation.optimize.refine_pose: w2c0 [4,4], P [M,3], uv [M,2], ur [M] or empty (monocular),
// inv_sigma2 [M], K [3,3], bf, rounds, min_inliers, iterations (LM evaluations per solve),
// ur_sigma (0: None, the octave's sigma), warm -> (w2c [4,4], inliers [M] bool).
py::tuple refine_pose(Arr<double> w2c0, Arr<double> P, Arr<double> uv, Arr<double> ur, Arr<double> inv_sigma2,
                      Arr<double> K, double bf, int rounds, int min_inliers, int iterations, double ur_sigma,
                      bool warm) {
  const i64 n = P.shape(0);
  if (uv.shape(0) != n || inv_sigma2.size() != n || (ur.size() && ur.size() != n))
    throw std::invalid_argument("refine_pose: P, uv, ur and inv_sigma2 need one row per match");
  const double* k = K.data();
  const double fx = k[0], fy = k[4], cx = k[2], cy = k[5];
  const double inv_ur_sigma2 = ur_sigma > 0 ? 1.0 / (ur_sigma * ur_sigma) : 0.0;
  const double w_ur_fixed = ur_sigma > 0 ? 1.0 / ur_sigma : 0.0;
  const double *p = P.data(), *m = uv.data(), *r = ur.size() ? ur.data() : nullptr, *s2 = inv_sigma2.data();
  py::array_t<double> result({4, 4});
  py::array_t<bool> inliers(n);
  double* T = result.mutable_data();
  bool* inl = inliers.mutable_data();
  std::copy(w2c0.data(), w2c0.data() + 16, T);
  std::fill(inl, inl + n, n >= min_inliers ? true : false);
  if (n < min_inliers) return py::make_tuple(result, inliers);
  {
    py::gil_scoped_release release;
    const double huber = std::sqrt(kChi2Mono);
    // the inliers' rows gathered for the solver
    std::vector<double> sp, suv, sur, sw, swur;
    std::vector<char> sst;
    std::vector<bool> fresh(n);
    for (int round = 0; round < rounds; ++round) {
      i64 count = 0;
      for (i64 i = 0; i < n; ++i) count += inl[i];
      if (count < min_inliers) break;
      // Huber by reweighting: round one widens the kernel (10, 3, 1 x) unless warm; the last round
      // is plain least squares (scale 0 here, None in Python)
      double scales[3] = {1.0, 0.0, 0.0};
      int n_scales = 1;
      if (round == 0 && !warm) {
        scales[0] = 10.0, scales[1] = 3.0, scales[2] = 1.0;
        n_scales = 3;
      } else if (round > 0 && round == rounds - 1) {
        scales[0] = 0.0;
      }
      for (int si = 0; si < n_scales; ++si) {
        const double sc = scales[si];
        sp.clear(), suv.clear(), sur.clear(), sw.clear(), swur.clear(), sst.clear();
        for (i64 i = 0; i < n; ++i) {
          if (!inl[i]) continue;
          double hw = 1.0, z;
          bool st;
          if (sc > 0) {
            const double e = std::sqrt(chi2_at(T, p, m, r, s2, fx, fy, cx, cy, bf, inv_ur_sigma2, i, z, st));
            hw = std::sqrt(e > sc * huber ? sc * huber / std::max(e, 1e-12) : 1.0);
          }
          const double w = std::sqrt(s2[i]);
          sp.insert(sp.end(), p + 3 * i, p + 3 * i + 3);
          suv.insert(suv.end(), m + 2 * i, m + 2 * i + 2);
          sw.push_back(w * hw);
          if (r) {
            sur.push_back(r[i]);
            sst.push_back(r[i] >= 0);
            swur.push_back((ur_sigma > 0 ? w_ur_fixed : w) * hw);
          }
        }
        PoseProblem pr{sp.data(), suv.data(), r ? sur.data() : nullptr, sw.data(), r ? swur.data() : nullptr,
                       r ? reinterpret_cast<const bool*>(sst.data()) : nullptr, static_cast<i64>(sw.size()),
                       fx, fy, cx, cy, bf};
        lm_pose(pr, T, iterations);
        orthonormalize(T);
      }
      bool same = true;
      for (i64 i = 0; i < n; ++i) {
        double z;
        bool st;
        const double chi2 = chi2_at(T, p, m, r, s2, fx, fy, cx, cy, bf, inv_ur_sigma2, i, z, st);
        fresh[i] = chi2 < (st ? kChi2Stereo : kChi2Mono) && z > 0;
        same = same && fresh[i] == inl[i];
      }
      for (i64 i = 0; i < n; ++i) inl[i] = fresh[i];
      if (round > 0 && same) break;
    }
  }
  return py::make_tuple(result, inliers);
}

}  // namespace

void register_pose_kernels(py::module_& m) {
  m.def("solve_pose", &solve_pose);
  m.def("refine_pose", &refine_pose);
}
