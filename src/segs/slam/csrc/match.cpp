// The ORB frontend's matching kernels in C++ (projection search, motion-only pose, descriptor kNN).
//
// 1. Projection search: grid radius query, octave / free / right-coordinate filters, Hamming
//    distances and the best / second-best candidate per query, in one pass.
//    It replaces, result for result, the numpy pipeline of segs.slam.matching.search_projection up
// to its ratio test: KeypointGrid.query -> filters -> hamming_pairs -> best_two. Candidates are
// visited in the order the numpy query lists them (cell rows top to bottom, within a row the grid
// order: cells left to right, keypoints by index), and a candidate replaces the best only when
// strictly nearer, so ties resolve as numpy's stable lexsort resolves them.
#include <pybind11/numpy.h>
#include <pybind11/pybind11.h>

#include "common.h"

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <limits>
#include <vector>

namespace py = pybind11;

namespace {

using segs_slam::Arr;
using segs_slam::hamming32;
using segs_slam::i64;

// numpy's floor division of two doubles (npymath's npy_divmod), so that cell ranges match the
// Python query to the bit.
double floor_div(double a, double b) {
  double mod = std::fmod(a, b);
  double div = (a - mod) / b;
  if (mod != 0.0 && ((b < 0) != (mod < 0))) div -= 1.0;
  if (div != 0.0) {
    double fl = std::floor(div);
    if (div - fl > 0.5) fl += 1.0;
    return fl;
  }
  return std::copysign(0.0, a / b);
}

i64 cell_of(double v, double cell, i64 n) {
  i64 c = static_cast<i64>(floor_div(v, cell));
  return c < 0 ? 0 : (c > n - 1 ? n - 1 : c);
}

// Best and second-best keypoint per query within its radius. Shapes: start [nx*ny+1], order [N],
// kp_uv [N,2], kp_oct [N], kp_desc [N,32], kp_points [N] (only_free: -1 = free) or empty,
// kp_ur [N] (-1 = none) or empty, q [M,2], radius [M], lo / hi [M], q_ur [M] or empty,
// q_desc [M,32]; gate_z [M] (empty: no gate) with sigma2 [levels], inv_ur_sigma2 (<= 0: the
// octave's), bf and the chi-square thresholds: keep only candidates whose reprojection error
// passes (segs.slam.local_mapping's fusion). Returns (queries [Q] ascending, best keypoint [Q], best distance [Q] int64,
// second distance [Q] float64, inf when the query had one candidate).
py::tuple best_two_in_radius(Arr<i64> start, Arr<i64> order, Arr<double> kp_uv, Arr<i64> kp_oct,
                             Arr<std::uint8_t> kp_desc, Arr<i64> kp_points, Arr<double> kp_ur,
                             double cell, i64 nx, i64 ny, Arr<double> q, Arr<double> radius,
                             Arr<i64> lo, Arr<i64> hi, Arr<double> q_ur, Arr<std::uint8_t> q_desc,
                             Arr<double> gate_z, Arr<double> sigma2, double inv_ur_sigma2, double bf,
                             double chi2_mono, double chi2_stereo) {
  const i64 m = q.shape(0);
  const double* gz = gate_z.size() ? gate_z.data() : nullptr;
  const double* sig2 = sigma2.data();
  const i64* st = start.data();
  const i64* ord = order.data();
  const double* uv = kp_uv.data();
  const i64* oct = kp_oct.data();
  const std::uint8_t* kd = kp_desc.data();
  const i64* pts = kp_points.size() ? kp_points.data() : nullptr;
  const double* kur = kp_ur.size() ? kp_ur.data() : nullptr;
  const double* qq = q.data();
  const double* rad = radius.data();
  const i64* lo_ = lo.data();
  const i64* hi_ = hi.data();
  const double* qur = q_ur.size() ? q_ur.data() : nullptr;
  const std::uint8_t* qd = q_desc.data();
  std::vector<i64> out_q, out_k, out_d1;
  std::vector<double> out_d2;
  const double inf = std::numeric_limits<double>::infinity();
  {
    py::gil_scoped_release release;
    for (i64 i = 0; i < m; ++i) {
      const double qx = qq[2 * i], qy = qq[2 * i + 1], r = rad[i];
      const i64 x0 = cell_of(qx - r, cell, nx), x1 = cell_of(qx + r, cell, nx);
      const i64 y0 = cell_of(qy - r, cell, ny), y1 = cell_of(qy + r, cell, ny);
      int best = std::numeric_limits<int>::max();
      double second = inf;
      i64 best_k = -1;
      for (i64 row = y0; row <= y1; ++row) {
        const i64 a = st[row * nx + x0], b = st[row * nx + x1 + 1];
        for (i64 p = a; p < b; ++p) {
          const i64 k = ord[p];
          const double dx = uv[2 * k] - qx, dy = uv[2 * k + 1] - qy;
          if (!(dx * dx + dy * dy <= r * r)) continue;
          if (oct[k] < lo_[i] || oct[k] > hi_[i]) continue;
          if (pts && pts[k] >= 0) continue;
          if (qur && kur && !(kur[k] < 0 || std::abs(qur[i] - kur[k]) <= r)) continue;
          if (gz) {  // reprojection chi-square gate of local mapping's fusion (project_match)
            double e2 = (dx * dx + dy * dy) / sig2[oct[k]];
            const bool st = kur[k] >= 0;
            if (st) {
              const double w = inv_ur_sigma2 > 0 ? inv_ur_sigma2 : 1.0 / sig2[oct[k]];
              const double e = bf / std::max(gz[i], 1e-9) - (uv[2 * k] - kur[k]);
              e2 = e2 + (e * e) * w;
            }
            if (!(e2 < (st ? chi2_stereo : chi2_mono))) continue;
          }
          const int d = hamming32(qd + 32 * i, kd + 32 * k);
          if (d < best) {
            if (best_k >= 0) second = best;
            best = d;
            best_k = k;
          } else if (d < second) {
            second = d;
          }
        }
      }
      if (best_k >= 0) {
        out_q.push_back(i);
        out_k.push_back(best_k);
        out_d1.push_back(best);
        out_d2.push_back(second);
      }
    }
  }
  auto to_np = [](const auto& v) {
    using T = typename std::decay_t<decltype(v)>::value_type;
    py::array_t<T> a(static_cast<py::ssize_t>(v.size()));
    std::copy(v.begin(), v.end(), a.mutable_data());
    return a;
  };
  return py::make_tuple(to_np(out_q), to_np(out_k), to_np(out_d1), to_np(out_d2));
}

// Whitened residuals and J^T J, J^T r of the pose-only reprojection edges at pose (R, t), as in
// segs.slam.optimize._pose_system. Returns the cost r . r.
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

// T <- exp(dx) T, exp as segs.slam.optimize._se3_exp: Rodrigues rotation, first-order translation.
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

// Levenberg-Marquardt as segs.slam.optimize._solve_pose: w2c [4,4], P [M,3], uv [M,2], ur [M] or
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
  return result;
}

// One query's running k' nearest (d ascending, n their indices): cv2.batchDistance's insertion.
inline void knn_insert(std::int32_t* d, std::int32_t* n, i64 kk, int h, i64 j) {
  if (h >= d[kk - 1]) return;
  i64 s = kk - 2;
  for (; s >= 0 && d[s] > h; --s) {
    d[s + 1] = d[s];
    n[s + 1] = n[s];
  }
  d[s + 1] = h;
  n[s + 1] = static_cast<std::int32_t>(j);
}

// k nearest descriptors of db [B,32] for each of da [A,32] (Hamming) -> (distances [A,k'] int32,
// indices [A,k'] int32), k' = min(k, B). cv2.batchDistance's selection, entry for entry: targets in
// index order, one enters when strictly nearer than the current k'-th and goes after those at
// the same distance, so ties keep the lower index first.
py::tuple knn_hamming(const Arr<std::uint8_t>& da, const Arr<std::uint8_t>& db, int k) {
  const i64 A = da.shape(0), B = db.shape(0);
  const i64 kk = std::max<i64>(0, std::min<i64>(k, B));
  Arr<std::int32_t> dist({A, kk}), idx({A, kk});
  const auto* a = reinterpret_cast<const std::uint64_t*>(da.data());
  const auto* b = reinterpret_cast<const std::uint64_t*>(db.data());
  std::int32_t* dp = dist.mutable_data();
  std::int32_t* ip = idx.mutable_data();
  if (kk == 0) return py::make_tuple(dist, idx);
  {
    py::gil_scoped_release release;
    std::fill(dp, dp + A * kk, std::numeric_limits<std::int32_t>::max());
    std::fill(ip, ip + A * kk, -1);
    constexpr i64 Q = 4;  // queries per pass over db: each target's 4 words are loaded once
    for (i64 i0 = 0; i0 < A; i0 += Q) {
      const i64 nq = std::min(Q, A - i0);
      std::uint64_t q[Q][4] = {};
      for (i64 t = 0; t < nq; ++t)
        for (int w = 0; w < 4; ++w) q[t][w] = a[4 * (i0 + t) + w];
      for (i64 j = 0; j < B; ++j) {
        const std::uint64_t* y = b + 4 * j;
        int h[Q];
        for (i64 t = 0; t < Q; ++t)
          h[t] = __builtin_popcountll(q[t][0] ^ y[0]) + __builtin_popcountll(q[t][1] ^ y[1]) +
                 __builtin_popcountll(q[t][2] ^ y[2]) + __builtin_popcountll(q[t][3] ^ y[3]);
        for (i64 t = 0; t < nq; ++t)
          knn_insert(dp + (i0 + t) * kk, ip + (i0 + t) * kk, kk, h[t], j);
      }
    }
  }
  return py::make_tuple(dist, idx);
}

}  // namespace

void register_map_kernels(py::module_& m);  // map.cpp

PYBIND11_MODULE(SEGS_EXTENSION_NAME, m) {
  m.doc() = "segs SLAM kernels: projection search, kNN, motion-only optimisation, map bookkeeping";
  m.def("best_two_in_radius", &best_two_in_radius);
  m.def("solve_pose", &solve_pose);
  m.def("knn_hamming", &knn_hamming);
  register_map_kernels(m);
}
