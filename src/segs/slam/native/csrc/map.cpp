// Map bookkeeping of local mapping in C++: loops over the map's observation dictionaries
// (point -> {keyframe id: keypoint index}) that cost tens of milliseconds per keyframe as Python
// bytecode. Each function reads the dictionaries through the CPython API under the GIL and
// returns what the Python loop it replaces computed (segs.slam.backend.local_mapping / segs.slam.map.map).
#include <pybind11/numpy.h>
#include <pybind11/pybind11.h>

#include "common.h"

#include <algorithm>
#include <cstdint>
#include <stdexcept>
#include <unordered_map>
#include <vector>

namespace py = pybind11;

namespace {

using segs_slam::Arr;
using segs_slam::hamming32;
using segs_slam::i64;

i64 as_int(PyObject* o) {
  const long long v = PyLong_AsLongLong(o);
  if (v == -1 && PyErr_Occurred()) throw py::error_already_set();
  return v;
}

// The observation dicts of points pids[j] in the map's list obs (Map.obs: point id -> {kf id:
// keypoint index}), read in place: callers pass the whole list and the ids instead of a list
// gathered in Python for each call (borrowed references, valid while the list is).
class PointObs {
 public:
  PointObs(const py::list& obs, const Arr<i64>& pids) : list_(obs.ptr()), ids_(pids.data()), n_(pids.size()) {
    const py::ssize_t size = PyList_GET_SIZE(list_);
    for (py::ssize_t j = 0; j < n_; ++j)
      if (ids_[j] < 0 || ids_[j] >= size) throw std::out_of_range("pids: a point id outside the map");
  }
  py::ssize_t size() const { return n_; }
  PyObject* operator[](py::ssize_t j) const {
    PyObject* d = PyList_GET_ITEM(list_, ids_[j]);
    if (!PyDict_Check(d)) throw std::invalid_argument("obs: dicts expected");
    return d;
  }

 private:
  PyObject* list_;
  const i64* ids_;
  py::ssize_t n_;
};

// A dict {kf id: array} read by keyframe id, each array converted when first asked for (a call
// touches the few keyframes that observe its points, not every keyframe of the map). `cols`: the
// row length the arrays must have (0: one-dimensional). The arrays stay referenced by the dict.
template <typename T>
class KeyframeArrays {
 public:
  KeyframeArrays(const py::dict& d, py::ssize_t cols, const char* what) : dict_(d.ptr()), cols_(cols), what_(what) {}
  // the array of keyframe `key` (a Python int), or nullptr where the dict has none
  const T* find(PyObject* key) {
    const i64 k = as_int(key);
    auto it = cache_.find(k);
    if (it != cache_.end()) return it->second;
    PyObject* v = PyDict_GetItemWithError(dict_, key);
    if (v == nullptr && PyErr_Occurred()) throw py::error_already_set();
    const T* p = nullptr;
    if (v != nullptr) {
      auto a = Arr<T>::ensure(py::reinterpret_borrow<py::object>(v));
      if (!a || (cols_ ? (a.ndim() != 2 || a.shape(1) != cols_) : a.ndim() != 1))
        throw std::invalid_argument(what_);
      p = a.data();
      keep_.push_back(std::move(a));
    }
    cache_.emplace(k, p);
    return p;
  }

 private:
  PyObject* dict_;
  py::ssize_t cols_;
  const char* what_;
  std::unordered_map<i64, const T*> cache_;
  std::vector<py::object> keep_;
};

// ORB-SLAM's keyframe redundancy count (LocalMapping::KeyFrameCulling): of the points pids[i]
// (observations in obs_all, dicts {kf id: keypoint index}), how many are seen by at least `th_obs` keyframes other
// than `exclude` that are in `octaves` (the map's keyframes) at an octave <= level[i].
i64 redundant_points(const py::list& obs_all, Arr<i64> pids, Arr<i64> level, i64 exclude, const py::dict& octaves,
                     i64 th_obs) {
  KeyframeArrays<i64> oct(octaves, 0, "octaves: int64 arrays expected");
  const i64* lvl = level.data();
  const PointObs obs(obs_all, pids);
  const py::ssize_t n = obs.size();
  if (level.size() != n) throw std::invalid_argument("level: one entry per point expected");
  i64 redundant = 0;
  for (py::ssize_t i = 0; i < n; ++i) {
    PyObject* d = obs[i];
    PyObject *key, *value;
    Py_ssize_t pos = 0;
    i64 cnt = 0;
    while (PyDict_Next(d, &pos, &key, &value)) {
      if (as_int(key) == exclude) continue;
      const i64* o = oct.find(key);
      if (o == nullptr) continue;
      if (o[as_int(value)] <= lvl[i] && ++cnt >= th_obs) {
        ++redundant;
        break;
      }
    }
  }
  return redundant;
}

// Flattens observations for Map.update_geometry: for point row j (point pids[j]) every observer k that is
// a key of `alive` -> (owner [O] = j, kf [O] = k), in dict order; and per row the octave of its
// observation by ref[j] (-1 where ref[j] is not alive or does not observe the point).
py::tuple gather_observers(const py::list& obs_all, Arr<i64> pids, const py::dict& octaves, Arr<i64> ref) {
  KeyframeArrays<i64> oct(octaves, 0, "octaves: int64 arrays expected");
  const PointObs obs(obs_all, pids);
  const py::ssize_t n = obs.size();
  if (ref.size() != n) throw std::invalid_argument("ref: one entry per point expected");
  const i64* r = ref.data();
  std::vector<i64> owner, kf;
  py::array_t<i64> ref_oct(n);
  i64* ro = ref_oct.mutable_data();
  for (py::ssize_t j = 0; j < n; ++j) {
    PyObject* d = obs[j];
    PyObject *key, *value;
    Py_ssize_t pos = 0;
    ro[j] = -1;
    while (PyDict_Next(d, &pos, &key, &value)) {
      const i64* o = oct.find(key);
      if (o == nullptr) continue;
      const i64 k = as_int(key);
      owner.push_back(j);
      kf.push_back(k);
      if (k == r[j]) ro[j] = o[as_int(value)];
    }
  }
  py::array_t<i64> a(static_cast<py::ssize_t>(owner.size())), b(static_cast<py::ssize_t>(kf.size()));
  std::copy(owner.begin(), owner.end(), a.mutable_data());
  std::copy(kf.begin(), kf.end(), b.mutable_data());
  return py::make_tuple(a, b, ref_oct);
}

// Map.update_descriptors: per point pids[j], the descriptors of its observations by keyframes in
// `descs` ({kf id: keypoint descriptors [N,32] uint8}) in dict order; for points with at least two,
// the one with the least median Hamming distance to the others (ORB-SLAM's
// ComputeDistinctiveDescriptors; median of an even count = mean of the middle two; the first on
// ties). -> (rows [R] of the points that have one, descriptors [R,32]).
py::tuple distinctive_descriptors(const py::list& obs_all, Arr<i64> pids, const py::dict& descs) {
  KeyframeArrays<std::uint8_t> table(descs, 32, "descs: uint8 [N,32] arrays expected");
  const PointObs obs(obs_all, pids);
  const py::ssize_t n = obs.size();
  std::vector<i64> rows;
  std::vector<std::uint8_t> out;
  std::vector<const std::uint8_t*> d;
  std::vector<int> dist, row;
  for (py::ssize_t j = 0; j < n; ++j) {
    PyObject* o = obs[j];
    PyObject *key, *value;
    Py_ssize_t pos = 0;
    d.clear();
    while (PyDict_Next(o, &pos, &key, &value)) {
      const std::uint8_t* a = table.find(key);
      if (a != nullptr) d.push_back(a + 32 * as_int(value));
    }
    const std::size_t m = d.size();
    if (m < 2) continue;
    dist.assign(m * m, 0);
    for (std::size_t a = 0; a < m; ++a)
      for (std::size_t b = a + 1; b < m; ++b) dist[a * m + b] = dist[b * m + a] = hamming32(d[a], d[b]);
    int best_med = 0;
    std::size_t best = 0;
    for (std::size_t a = 0; a < m; ++a) {
      row.assign(dist.begin() + a * m, dist.begin() + (a + 1) * m);
      std::sort(row.begin(), row.end());
      const int med = row[(m - 1) / 2] + row[m / 2];
      if (a == 0 || med < best_med) {
        best_med = med;
        best = a;
      }
    }
    rows.push_back(j);
    out.insert(out.end(), d[best], d[best] + 32);
  }
  py::array_t<i64> r(static_cast<py::ssize_t>(rows.size()));
  std::copy(rows.begin(), rows.end(), r.mutable_data());
  py::array_t<std::uint8_t> desc({static_cast<py::ssize_t>(rows.size()), static_cast<py::ssize_t>(32)});
  std::copy(out.begin(), out.end(), desc.mutable_data());
  return py::make_tuple(r, desc);
}

}  // namespace

// Local mapping's fusion candidates: which points pids[j] (observations in obs_all, dicts {kf id:
// keypoint index}) keyframe `kf` does not observe -> [N] bool.
py::array_t<bool> unobserved_by(const py::list& obs_all, Arr<i64> pids, i64 kf) {
  const PointObs obs(obs_all, pids);
  const py::ssize_t n = obs.size();
  py::array_t<bool> out(n);
  bool* o = out.mutable_data();
  const py::int_ key(kf);
  for (py::ssize_t j = 0; j < n; ++j) {
    const int has = PyDict_Contains(obs[j], key.ptr());
    if (has < 0) throw py::error_already_set();
    o[j] = has == 0;
  }
  return out;
}

// Local mapping's new keyframe (LocalMapper._process_new): keyframe `kf` observes point pids[j] at
// keypoint idx[j], in order. Per entry -> 0: it already does at that keypoint; 1: it already does
// at another keypoint (the entry is dropped); 2: the observation is added to obs_all[pids[j]].
py::array_t<std::int8_t> observe_points(const py::list& obs_all, Arr<i64> pids, Arr<i64> idx, i64 kf) {
  const PointObs obs(obs_all, pids);
  const py::ssize_t n = obs.size();
  if (idx.size() != n) throw std::invalid_argument("idx: one keypoint per point expected");
  const i64* ki = idx.data();
  py::array_t<std::int8_t> out(n);
  std::int8_t* o = out.mutable_data();
  const py::int_ key(kf);
  for (py::ssize_t j = 0; j < n; ++j) {
    PyObject* d = obs[j];
    PyObject* have = PyDict_GetItemWithError(d, key.ptr());
    if (have != nullptr) {
      o[j] = as_int(have) == ki[j] ? 0 : 1;
      continue;
    }
    if (PyErr_Occurred()) throw py::error_already_set();
    const py::int_ value(ki[j]);
    if (PyDict_SetItem(d, key.ptr(), value.ptr()) < 0) throw py::error_already_set();
    o[j] = 2;
  }
  return out;
}

// Counts per keyframe id in first-seen order (the order of the Python dict the callers build).
class FirstSeenCounter {
 public:
  void add(i64 k) {
    auto it = at_.find(k);
    if (it == at_.end()) {
      at_.emplace(k, keys_.size());
      keys_.push_back(k);
      counts_.push_back(1);
    } else {
      ++counts_[it->second];
    }
  }
  // -> (ids [K], counts [K]) as int64 arrays
  py::tuple arrays() const {
    py::array_t<i64> a(static_cast<py::ssize_t>(keys_.size())), b(static_cast<py::ssize_t>(counts_.size()));
    std::copy(keys_.begin(), keys_.end(), a.mutable_data());
    std::copy(counts_.begin(), counts_.end(), b.mutable_data());
    return py::make_tuple(a, b);
  }

 private:
  std::vector<i64> keys_, counts_;
  std::unordered_map<i64, std::size_t> at_;
};

// Map.update_connections: how many of the points pids[j] (observations in obs_all, dicts {kf id:
// keypoint index}) each keyframe other than `exclude` observes -> (keyframe ids [K] in first-seen
// order, counts [K]).
py::tuple count_observers(const py::list& obs_all, Arr<i64> pids, i64 exclude) {
  const PointObs obs(obs_all, pids);
  const py::ssize_t n = obs.size();
  FirstSeenCounter counter;
  for (py::ssize_t j = 0; j < n; ++j) {
    PyObject* d = obs[j];
    PyObject *key, *value;
    Py_ssize_t pos = 0;
    while (PyDict_Next(d, &pos, &key, &value)) {
      const i64 k = as_int(key);
      if (k != exclude) counter.add(k);
    }
  }
  return counter.arrays();
}

// KeyFrameDatabase.common_words: through the inverted index {word: set of keyframe ids}, how many
// of `words` each keyframe not in `exclude` shares -> (keyframe ids [K] in first-seen order, counts [K]).
py::tuple common_words(const Arr<i64>& words, const py::dict& index, const py::object& exclude) {
  if (!PyAnySet_Check(exclude.ptr())) throw std::invalid_argument("exclude: a set or frozenset expected");
  FirstSeenCounter counter;
  const i64* w = words.data();
  for (py::ssize_t i = 0; i < words.size(); ++i) {
    const py::int_ word(w[i]);
    PyObject* kfs = PyDict_GetItemWithError(index.ptr(), word.ptr());  // borrowed
    if (kfs == nullptr) {
      if (PyErr_Occurred()) throw py::error_already_set();
      continue;
    }
    py::iterator it = py::reinterpret_borrow<py::iterable>(kfs).begin();
    for (; it != py::iterator::sentinel(); ++it) {
      PyObject* item = (*it).ptr();
      const int skip = PySet_Contains(exclude.ptr(), item);
      if (skip < 0) throw py::error_already_set();
      if (!skip) counter.add(as_int(item));
    }
  }
  return counter.arrays();
}

void register_map_kernels(py::module_& m) {
  m.def("common_words", &common_words);
  m.def("count_observers", &count_observers);
  m.def("unobserved_by", &unobserved_by);
  m.def("observe_points", &observe_points);
  m.def("redundant_points", &redundant_points);
  m.def("gather_observers", &gather_observers);
  m.def("distinctive_descriptors", &distinctive_descriptors);
}
