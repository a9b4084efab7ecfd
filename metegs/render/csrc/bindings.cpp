// Python bindings of the metegs `cpu` rasteriser extension.
#include "metegs_cpu.h"

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
  m.def("project_forward", &metegs_cpu::project_forward, "fused EWA projection + SH colours (CPU)");
  m.def("project_backward", &metegs_cpu::project_backward, "backward of project_forward (CPU)");
  m.def("bin_tiles", &metegs_cpu::bin_tiles, "depth-sorted per-tile Gaussian lists (CPU)");
  m.def("forward", &metegs_cpu::composite_forward, "metegs tile compositing forward (CPU)");
  m.def("backward", &metegs_cpu::composite_backward, "metegs tile compositing backward (CPU), per-Gaussian gradients");
}
