// Python bindings (pybind11 only, no torch headers: builds in seconds).
//
// Tensors cross as data pointers (int). The Python wrapper (segs/raster/_cpu_backend.py)
// guarantees float32/int32, contiguous, CPU, and the shapes documented in raster.h.
#include <pybind11/pybind11.h>

#include <cstdint>
#include <memory>

#include "projection.h"
#include "raster.h"
#include "ssim.h"

namespace py = pybind11;
using segs_raster::State;

namespace {

template <typename T>
T* ptr(std::uintptr_t p) {
  return reinterpret_cast<T*>(p);
}

std::unique_ptr<State> forward(std::uintptr_t means2d, std::uintptr_t conics,
                               std::uintptr_t colors, std::uintptr_t opacities,
                               std::uintptr_t depths, std::uintptr_t radii,
                               std::uintptr_t background, int n, int width, int height,
                               std::uintptr_t image, std::uintptr_t depth, std::uintptr_t alpha,
                               int threads) {
  segs_raster::ForwardIn in{ptr<const float>(means2d), ptr<const float>(conics),
                            ptr<const float>(colors),  ptr<const float>(opacities),
                            ptr<const float>(depths),  ptr<const int32_t>(radii),
                            ptr<const float>(background), n, width, height};
  segs_raster::ForwardOut out{ptr<float>(image), ptr<float>(depth), ptr<float>(alpha)};
  auto st = std::make_unique<State>();
  segs_raster::forward(in, out, *st, threads);
  return st;
}

void backward(const State& st, std::uintptr_t g_image, std::uintptr_t g_depth,
              std::uintptr_t g_alpha, std::uintptr_t means2d, std::uintptr_t conics,
              std::uintptr_t colors, std::uintptr_t opacities, std::uintptr_t depths,
              std::uintptr_t background, int threads) {
  segs_raster::BackwardIn in{ptr<const float>(g_image), ptr<const float>(g_depth),
                             ptr<const float>(g_alpha)};
  segs_raster::BackwardOut out{ptr<float>(means2d),   ptr<float>(conics), ptr<float>(colors),
                               ptr<float>(opacities), ptr<float>(depths),
                               ptr<float>(background)};
  segs_raster::backward(st, in, out, threads);
}

void project_forward(std::uintptr_t means, std::uintptr_t quats, std::uintptr_t scales,
                     std::uintptr_t viewmat, std::uintptr_t K, int n, int width, int height,
                     float near, float far, float eps2d, std::uintptr_t means2d, std::uintptr_t conics,
                     std::uintptr_t depths, std::uintptr_t radii, int threads) {
  segs_raster::ProjectIn in{ptr<const float>(means),   ptr<const float>(quats),
                            ptr<const float>(scales),  ptr<const float>(viewmat),
                            ptr<const float>(K), n, width, height, near, far, eps2d, {}};
  segs_raster::set_limits(in);
  segs_raster::ProjectOut out{ptr<float>(means2d), ptr<float>(conics), ptr<float>(depths),
                              ptr<int32_t>(radii)};
  segs_raster::project_forward(in, out, threads);
}

void project_backward(std::uintptr_t means, std::uintptr_t quats, std::uintptr_t scales,
                      std::uintptr_t viewmat, std::uintptr_t K, int n, int width, int height,
                      float near, float far, float eps2d, std::uintptr_t g_means2d, std::uintptr_t g_conics,
                      std::uintptr_t g_depths, std::uintptr_t out_means, std::uintptr_t out_quats,
                      std::uintptr_t out_scales, int threads) {
  segs_raster::ProjectIn in{ptr<const float>(means),   ptr<const float>(quats),
                            ptr<const float>(scales),  ptr<const float>(viewmat),
                            ptr<const float>(K), n, width, height, near, far, eps2d, {}};
  segs_raster::set_limits(in);
  segs_raster::ProjectGradIn g{ptr<const float>(g_means2d), ptr<const float>(g_conics),
                               ptr<const float>(g_depths)};
  segs_raster::ProjectGradOut out{ptr<float>(out_means), ptr<float>(out_quats),
                                  ptr<float>(out_scales)};
  segs_raster::project_backward(in, g, out, threads);
}

segs_raster::SsimIn ssim_in(std::uintptr_t render, std::uintptr_t target, std::uintptr_t window,
                           int channels, int height, int width, int taps, float c1, float c2,
                           float eps) {
  return {ptr<const float>(render), ptr<const float>(target), ptr<const float>(window),
          channels, height, width, taps, c1, c2, eps};
}

double ssim_forward(std::uintptr_t render, std::uintptr_t target, std::uintptr_t window,
                    int channels, int height, int width, int taps, float c1, float c2, float eps,
                    std::uintptr_t saved, int threads) {
  auto in = ssim_in(render, target, window, channels, height, width, taps, c1, c2, eps);
  return segs_raster::ssim_forward(in, ptr<float>(saved), threads);
}

void ssim_backward(std::uintptr_t render, std::uintptr_t target, std::uintptr_t window,
                   int channels, int height, int width, int taps, float c1, float c2, float eps,
                   std::uintptr_t saved, float grad_mean, std::uintptr_t grad_render,
                   int threads) {
  auto in = ssim_in(render, target, window, channels, height, width, taps, c1, c2, eps);
  segs_raster::ssim_backward(in, ptr<const float>(saved), grad_mean, ptr<float>(grad_render),
                             threads);
}

}  // namespace

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
  m.doc() = "segs.raster CPU kernels (see csrc/raster.h, csrc/ssim.h)";
  py::class_<State>(m, "State")
      .def_readonly("n_gaussians", &State::n)
      .def_property_readonly("n_listed", [](const State& s) { return s.gs.size(); })
      .def_property_readonly("n_intersections", [](const State& s) { return s.isect.size(); })
      .def_readonly("evaluations", &State::evaluations);
  m.def("forward", &forward, py::call_guard<py::gil_scoped_release>());
  m.def("backward", &backward, py::call_guard<py::gil_scoped_release>());
  m.def("project_forward", &project_forward, py::call_guard<py::gil_scoped_release>());
  m.def("project_backward", &project_backward, py::call_guard<py::gil_scoped_release>());
  m.def("ssim_forward", &ssim_forward, py::call_guard<py::gil_scoped_release>());
  m.def("ssim_backward", &ssim_backward, py::call_guard<py::gil_scoped_release>());
}
