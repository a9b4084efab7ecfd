// Declarations of the metegs `cpu` rasteriser ops (one extension; bindings in bindings.cpp).
#pragma once

#include <torch/extension.h>

#include "pool.h"

#include <algorithm>
#include <cmath>
#include <cstring>
#include <limits>
#include <vector>
// The only place that decides on x86 intrinsics: METEGS_AVX512 / METEGS_FMA where the compiler targets them, never
// with -DMETEGS_PORTABLE (the generic code alone, as on ARM; the test suite builds and checks that variant).
#if !defined(METEGS_PORTABLE) && defined(__AVX512F__)
#define METEGS_AVX512 1
#else
#define METEGS_AVX512 0
#endif
#if !defined(METEGS_PORTABLE) && defined(__FMA__)
#define METEGS_FMA 1
#else
#define METEGS_FMA 0
#endif
#if METEGS_AVX512 || METEGS_FMA
#include <immintrin.h>
#endif

namespace metegs_cpu {

constexpr int TILE = 16;  // tile side (metegs.render.tiles.TILE_SIZE)

// 16 float lanes (a tile row, or 16 Gaussians): one AVX-512 register, two AVX2 ones elsewhere.
typedef float Float16 __attribute__((vector_size(16 * sizeof(float))));

// a * b + c per lane, rounded once where the CPU fuses it (AVX-512, or AVX2 with FMA), else rounded twice (the
// extension is built with -ffp-contract=off: multiply-adds are fused only where this is called).
inline __attribute__((always_inline)) Float16 fmadd16(Float16 a, Float16 b, Float16 c) {
#if METEGS_AVX512
  return (Float16)_mm512_fmadd_ps((__m512)a, (__m512)b, (__m512)c);
#elif METEGS_FMA
  __m256 a2[2], b2[2], c2[2];
  std::memcpy(a2, &a, sizeof(a)), std::memcpy(b2, &b, sizeof(b)), std::memcpy(c2, &c, sizeof(c));
  for (int h = 0; h < 2; ++h) a2[h] = _mm256_fmadd_ps(a2[h], b2[h], c2[h]);
  std::memcpy(&a, a2, sizeof(a));
  return a;
#else
  return a * b + c;
#endif
}

// The first n (0..16) floats at src as a Float16, zeros after them (AVX-512: one masked load).
inline __attribute__((always_inline)) Float16 load_first(const float* src, int64_t n) {
#if METEGS_AVX512
  return (Float16)_mm512_maskz_loadu_ps(static_cast<__mmask16>((1u << n) - 1), src);
#else
  Float16 v{};
  std::memcpy(&v, src, n * sizeof(float));
  return v;
#endif
}

// Stores lanes [0, n) of v at dst (AVX-512: one masked store).
inline __attribute__((always_inline)) void store_first(float* dst, Float16 v, int64_t n) {
#if METEGS_AVX512
  _mm512_mask_storeu_ps(dst, static_cast<__mmask16>((1u << n) - 1), (__m512)v);
#else
  std::memcpy(dst, &v, n * sizeof(float));
#endif
}

// 2 ln(255 o): the bound on the conic's quadratic form where alpha = o exp(-q / 2) reaches 1/255.
template <typename T>
inline double alpha_threshold(T opacity) {
  return 2.0 * std::log(std::max(255.0 * double(opacity), 1.0));
}

// Half-height (in pixels) of the rows where a Gaussian's alpha can reach 1/255: at row offset dy the
// quadratic form is at least dy^2 (ac - b^2) / a, so only rows with |dy| <= sqrt(2 ln(255 o) a / (ac - b^2))
// can contribute (with a small safety margin); +inf when the conic is not positive definite (no culling).
// bin_tiles computes it once per Gaussian (it needs a log and a square root) for the compositing ops.
// `thresh`: alpha_threshold(opacity), when the caller has it already.
template <typename T>
inline double row_half_height_at(double thresh, T a, T b, T c) {
  const double A = a, B = b, Cc = c, det = A * Cc - B * B;
  if (!(A > 0 && det > 0)) return std::numeric_limits<double>::infinity();
  return std::sqrt(thresh * A / det) * (1.0 + 1e-4) + 1e-3;
}
template <typename T>
inline double row_half_height(T a, T b, T c, T opacity) {
  return row_half_height_at(alpha_threshold(opacity), a, b, c);
}

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

// binning.cpp: depth-sorted per-tile lists with an exact ellipse-tile test, and every Gaussian's
// row_half_height ([N] float64) for the compositing ops.
std::vector<at::Tensor> bin_tiles(at::Tensor means2d, at::Tensor conics, at::Tensor opacities, at::Tensor extents,
                                  at::Tensor depths, int64_t width, int64_t height, bool cull);

// composite.cpp: tile compositing and its backward.
std::vector<at::Tensor> composite_forward(at::Tensor means2d, at::Tensor conics, at::Tensor opac, at::Tensor colors,
                                          at::Tensor depths, at::Tensor ids, at::Tensor offsets, int64_t tiles_x,
                                          int64_t tiles_y, int64_t width, int64_t height,
                                          c10::optional<at::Tensor> rows);
// -> per-Gaussian gradients: means2d [N, 2], conics [N, 3], opacities [N], colours [N, D], depths [N].
std::vector<at::Tensor> composite_backward(at::Tensor means2d, at::Tensor conics, at::Tensor opac, at::Tensor colors,
                              at::Tensor depths, at::Tensor ids, at::Tensor offsets, at::Tensor saved_T,
                              at::Tensor saved_last, at::Tensor g_color, at::Tensor g_alpha, at::Tensor g_depth,
                              int64_t tiles_x, int64_t tiles_y, int64_t width, int64_t height,
                              c10::optional<at::Tensor> rows);

// composite.cpp: the render's last step (pipeline.finish_render) on the compositing's outputs:
// color [H, W, 3], alpha [H, W], depth_sum [H, W], background [3] -> rgb = color + (1 - alpha) background [H, W, 3],
// depth = depth_sum / max(alpha, DEPTH_ALPHA_MIN) [H, W].
constexpr double DEPTH_ALPHA_MIN = 1e-10;
std::vector<at::Tensor> finish_forward(at::Tensor color, at::Tensor alpha, at::Tensor depth_sum, at::Tensor background);
// -> gradients of color [H, W, 3] (g_rgb itself), alpha [H, W] (the part through rgb and depth) and depth_sum
// [H, W]; g_depth: none = 0.
std::vector<at::Tensor> finish_backward(at::Tensor alpha, at::Tensor depth_sum, at::Tensor background, at::Tensor g_rgb,
                                        c10::optional<at::Tensor> g_depth);

// ssim.cpp: the SSIM map of the training loss (zero-padded 'same' Gaussian windows) of x against y, both [B, H, W, C]
// -> {map [B, H, W, C], partials [3, B, H, W, C] (for ssim_backward)}; c1, c2: the SSIM constants.
std::vector<at::Tensor> ssim_forward(at::Tensor x, at::Tensor y, at::Tensor window, double c1, double c2);
// -> gradient of x [B, H, W, C] given the map's gradient g_map [B, H, W, C].
at::Tensor ssim_backward(at::Tensor x, at::Tensor y, at::Tensor window, at::Tensor partials, at::Tensor g_map);

}  // namespace metegs_cpu
