// Python bindings of the metegs `cpu` rasteriser extension.
#include "metegs_cpu.h"

#include <torch/csrc/utils/pybind.h>  // pybind11 with at::Tensor's casters, without the whole C++ API

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
  // The ops release the GIL while they run, as torch's own ops do: other Python threads (the live viewer's
  // server, a benchmark's memory sampler) go on meanwhile.
  const auto nogil = py::call_guard<py::gil_scoped_release>();
  m.def("project_forward", &metegs_cpu::project_forward, "fused EWA projection + SH colours (CPU)", nogil);
  m.def("project_backward", &metegs_cpu::project_backward, "backward of project_forward (CPU)", nogil);
  m.def("bin_tiles", &metegs_cpu::bin_tiles, "depth-sorted per-tile Gaussian lists (CPU)", nogil);
  m.def("forward", &metegs_cpu::composite_forward, "metegs tile compositing forward (CPU)", nogil, py::arg("means2d"),
        py::arg("conics"), py::arg("opacities"), py::arg("colors"), py::arg("depths"), py::arg("ids"),
        py::arg("offsets"), py::arg("tiles_x"), py::arg("tiles_y"), py::arg("width"), py::arg("height"),
        py::arg("rows") = py::none());
  m.def("backward", &metegs_cpu::composite_backward, "metegs tile compositing backward (CPU), per-Gaussian gradients", nogil,
        py::arg("means2d"), py::arg("conics"), py::arg("opacities"), py::arg("colors"), py::arg("depths"),
        py::arg("ids"), py::arg("offsets"), py::arg("saved_T"), py::arg("saved_last"), py::arg("g_color"),
        py::arg("g_alpha"), py::arg("g_depth"), py::arg("tiles_x"), py::arg("tiles_y"), py::arg("width"),
        py::arg("height"), py::arg("rows") = py::none());
  m.def("finish_forward", &metegs_cpu::finish_forward, "background and expected depth of a render (CPU)", nogil);
  m.def("finish_backward", &metegs_cpu::finish_backward, "backward of finish_forward (CPU)", nogil, py::arg("alpha"),
        py::arg("depth_sum"), py::arg("background"), py::arg("g_rgb"), py::arg("g_depth") = py::none());
  m.def("ssim_forward", &metegs_cpu::ssim_forward, "SSIM map of the training loss and its partials (CPU)", nogil,
        py::arg("x"), py::arg("y"), py::arg("window"), py::arg("c1"), py::arg("c2"));
  m.def("ssim_backward", &metegs_cpu::ssim_backward, "backward of ssim_forward with respect to x (CPU)", nogil,
        py::arg("x"), py::arg("y"), py::arg("window"), py::arg("partials"), py::arg("g_map"));
  m.def("opening_forward", &metegs_cpu::opening_forward, "grey-scale opening by a square and its source pixels (CPU)",
        nogil, py::arg("x"), py::arg("k"), py::arg("with_index") = true);
  m.def("strokes_out_forward", &metegs_cpu::strokes_out_forward,
        "render and photo with their thin bright strokes opened (CPU)", nogil, py::arg("render"), py::arg("photo"),
        py::arg("k"), py::arg("min_excess"), py::arg("with_index") = true);
  m.def("strokes_out_backward", &metegs_cpu::strokes_out_backward, "backward of strokes_out_forward (CPU)", nogil,
        py::arg("index"), py::arg("stroke"), py::arg("g_out"));
  m.def("set_num_threads", [](int64_t n) { metegs::thread_override() = std::max<int64_t>(n, 0); },
        "threads of the metegs kernels called from this thread (0: torch's intra-op count)", py::arg("n"));
  m.def("get_num_threads", &metegs::num_threads, "threads of the metegs kernels called from this thread");
  m.def("uses_openmp_team", &metegs::uses_openmp_team,
        "whether the kernels called from this thread run on torch's OpenMP team (else on metegs' pool)");
}
