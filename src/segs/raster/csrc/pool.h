// Recycled std::vector storage. Each call allocates tens of MB of per-Gaussian and per-pixel
// buffers; handing freed vectors back to the next call (capacity kept) avoids the page faults
// and kernel zeroing of fresh allocations. At most KEEP vectors per element type are kept (a few MB each).
#pragma once

#include <mutex>
#include <utility>
#include <vector>

namespace segs_raster {

template <class T>
struct VectorPool {
  static constexpr size_t KEEP = 8;
  std::mutex mu;
  std::vector<std::vector<T>> spare;

  static VectorPool& get() {
    static VectorPool pool;
    return pool;
  }
};

// An empty vector, with the capacity of a recycled one when available.
template <class T>
std::vector<T> take_vector() {
  VectorPool<T>& p = VectorPool<T>::get();
  std::lock_guard<std::mutex> lock(p.mu);
  if (p.spare.empty()) return {};
  std::vector<T> v = std::move(p.spare.back());
  p.spare.pop_back();
  v.clear();
  return v;
}

template <class T>
void give_vector(std::vector<T>& v) {
  if (v.capacity() == 0) return;
  VectorPool<T>& p = VectorPool<T>::get();
  std::lock_guard<std::mutex> lock(p.mu);
  if (p.spare.size() < VectorPool<T>::KEEP) p.spare.push_back(std::move(v));
}

// A scratch vector for one call, recycled when it goes out of scope.
template <class T>
struct Scratch {
  std::vector<T> v = take_vector<T>();
  Scratch() = default;
  Scratch(const Scratch&) = delete;
  Scratch& operator=(const Scratch&) = delete;
  ~Scratch() { give_vector(v); }
};

}  // namespace segs_raster
