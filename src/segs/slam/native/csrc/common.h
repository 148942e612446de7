// Shared by the SLAM kernels (match.cpp, map.cpp): array aliases and the ORB Hamming distance.
#pragma once

#include <pybind11/numpy.h>

#include <cstdint>

namespace segs_slam {

using i64 = std::int64_t;
template <typename T>
using Arr = pybind11::array_t<T, pybind11::array::c_style | pybind11::array::forcecast>;

// Hamming distance of two 256-bit ORB descriptors (32 bytes each).
inline int hamming32(const std::uint8_t* a, const std::uint8_t* b) {
  const auto* x = reinterpret_cast<const std::uint64_t*>(a);
  const auto* y = reinterpret_cast<const std::uint64_t*>(b);
  return __builtin_popcountll(x[0] ^ y[0]) + __builtin_popcountll(x[1] ^ y[1]) +
         __builtin_popcountll(x[2] ^ y[2]) + __builtin_popcountll(x[3] ^ y[3]);
}

}  // namespace segs_slam
