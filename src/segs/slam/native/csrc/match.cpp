// The ORB frontend's matching kernels in C++ (projection search, descriptor kNN; the pose solver: pose.cpp).
//
// 1. Projection search: grid radius query, octave / free / right-coordinate filters, Hamming
//    distances and the best / second-best candidate per query, in one pass.
//    It replaces, result for result, the numpy pipeline of segs.slam.estimation.matching.search_projection up
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
#include <stdexcept>
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
// passes (segs.slam.backend.local_mapping's fusion). Returns (queries [Q] ascending, best keypoint [Q], best distance [Q] int64,
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

// Vocabulary.words: the greedy descent of a k-ary tree of ORB centres (levels[l]: [k^(l+1),32],
// the children of node n in rows n*k .. n*k+k-1); at each level the child of least Hamming
// distance, the first on ties (numpy's argmin) -> word id per descriptor of desc [N,32].
py::array_t<i64> tree_words(const Arr<std::uint8_t>& desc, const py::list& levels, i64 k) {
  const i64 n = desc.ndim() == 2 ? desc.shape(0) : 0;
  if (desc.ndim() != 2 || desc.shape(1) != 32) throw std::invalid_argument("desc: [N,32] uint8 expected");
  std::vector<Arr<std::uint8_t>> lv;
  i64 rows = 1;
  for (auto c : levels) {
    lv.push_back(c.cast<Arr<std::uint8_t>>());
    rows *= k;
    if (lv.back().ndim() != 2 || lv.back().shape(0) != rows || lv.back().shape(1) != 32)
      throw std::invalid_argument("levels: [k^l,32] uint8 centres expected");
  }
  py::array_t<i64> out(n);
  i64* o = out.mutable_data();
  const std::uint8_t* d = desc.data();
  std::vector<const std::uint8_t*> c;
  for (const auto& a : lv) c.push_back(a.data());
  py::gil_scoped_release release;
  for (i64 i = 0; i < n; ++i) {
    i64 node = 0;
    for (const std::uint8_t* centres : c) {
      const std::uint8_t* child = centres + node * k * 32;
      int best = std::numeric_limits<int>::max();
      i64 arg = 0;
      for (i64 j = 0; j < k; ++j) {
        const int h = hamming32(d + 32 * i, child + 32 * j);
        if (h < best) best = h, arg = j;
      }
      node = node * k + arg;
    }
    o[i] = node;
  }
  return out;
}

}  // namespace

void register_map_kernels(py::module_& m);   // map.cpp
void register_pose_kernels(py::module_& m);  // pose.cpp

PYBIND11_MODULE(SEGS_EXTENSION_NAME, m) {
  m.doc() = "segs SLAM kernels: projection search, kNN, motion-only optimisation, map bookkeeping";
  m.def("best_two_in_radius", &best_two_in_radius);
  m.def("knn_hamming", &knn_hamming);
  m.def("tree_words", &tree_words);
  register_map_kernels(m);
  register_pose_kernels(m);
}
