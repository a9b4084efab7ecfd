// Declarations of the metegs `cpu` rasteriser ops (one extension; bindings in bindings.cpp).
#pragma once

#include <torch/extension.h>

#include <vector>

namespace metegs_cpu {

constexpr int TILE = 16;  // tile side (metegs.render.tiles.TILE_SIZE)

// project.cpp: fused EWA projection + SH colours and their backward.
std::vector<at::Tensor> project_forward(at::Tensor means, at::Tensor quats, at::Tensor scales, at::Tensor opacities,
                                        at::Tensor sh, at::Tensor viewmat, at::Tensor K, at::Tensor campos,
                                        int64_t width, int64_t height, double near_plane, double far_plane,
                                        double eps2d, int64_t sh_degree);
std::vector<at::Tensor> project_backward(at::Tensor means, at::Tensor quats, at::Tensor scales,
                                         at::Tensor opacities, at::Tensor sh, at::Tensor viewmat, at::Tensor K,
                                         at::Tensor campos, int64_t width, int64_t height, double near_plane,
                                         double far_plane, double eps2d, int64_t sh_degree, at::Tensor g_means2d,
                                         at::Tensor g_conics, at::Tensor g_depths, at::Tensor g_colors);

// binning.cpp: depth-sorted per-tile lists with an exact ellipse-tile test.
std::vector<at::Tensor> bin_tiles(at::Tensor means2d, at::Tensor conics, at::Tensor opacities, at::Tensor extents,
                                  at::Tensor depths, int64_t width, int64_t height, bool cull);

// composite.cpp: tile compositing and its backward.
std::vector<at::Tensor> composite_forward(at::Tensor means2d, at::Tensor conics, at::Tensor opac, at::Tensor colors,
                                          at::Tensor depths, at::Tensor ids, at::Tensor offsets, int64_t tiles_x,
                                          int64_t tiles_y, int64_t width, int64_t height);
at::Tensor composite_backward(at::Tensor means2d, at::Tensor conics, at::Tensor opac, at::Tensor colors,
                              at::Tensor depths, at::Tensor ids, at::Tensor offsets, at::Tensor saved_T,
                              at::Tensor saved_last, at::Tensor g_color, at::Tensor g_alpha, at::Tensor g_depth,
                              int64_t tiles_x, int64_t tiles_y, int64_t width, int64_t height);

}  // namespace metegs_cpu
