// Declarations of the metegs `cpu` rasteriser ops (one extension; bindings in bindings.cpp).
#pragma once

// ATen's tensor and the few factory functions the kernels call, not <torch/extension.h>: that header (the whole
// C++ API and pybind11) takes about 50 s to compile in every source; these take about 8 s.
#include <ATen/Dispatch.h>
#include <ATen/Parallel.h>
#include <ATen/core/Tensor.h>
#include <ATen/ops/empty.h>
#include <ATen/ops/empty_like.h>
#include <ATen/ops/zeros.h>
#include <ATen/ops/zeros_like.h>

#include "pool.h"

#include <algorithm>
#include <cmath>
#include <cstring>
#include <limits>
#include <type_traits>
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

// 16 float lanes as one GCC vector type (project.cpp's Gaussians; the compositing's type where AVX-512 holds it).
typedef float Float16 __attribute__((vector_size(16 * sizeof(float))));

#define METEGS_INLINE inline __attribute__((always_inline))

#if METEGS_AVX512
// N lanes of S: one GCC vector (a 16-lane float row is one AVX-512 register).
template <typename S, int N>
struct VecN {
  typedef S type __attribute__((vector_size(N * sizeof(S))));
};

// m ? a : b per lane (m: a comparison's lanes, all ones or zero).
template <typename M, typename V>
METEGS_INLINE V select(M m, V a, V b) {
  return m ? a : b;
}

// Each lane converted to To's element type.
template <typename To, typename From>
METEGS_INLINE To convert(From v) {
  return __builtin_convertvector(v, To);
}
#else
// Without AVX-512, GCC keeps a 64-byte vector type in memory and moves it through general registers at every
// operation (measured on AVX2, Zen 3: 6 GFLOP/s of multiply-adds on one core against 91 for the same lanes held
// as two 32-byte vectors). Split<S, N> holds N lanes of S as K native vectors of P lanes (32 bytes with AVX, else
// 16) with the operators the kernels use, lane for lane the same arithmetic as the single vector.
#if defined(__AVX__) && !defined(METEGS_PORTABLE)
constexpr int NATIVE_VECTOR_BYTES = 32;
#else
constexpr int NATIVE_VECTOR_BYTES = 16;
#endif
template <typename S>
using MaskOf = std::conditional_t<sizeof(S) == 4, int32_t, int64_t>;

template <typename S, int N>
struct Split {
  static constexpr int P = N < NATIVE_VECTOR_BYTES / int(sizeof(S)) ? N : NATIVE_VECTOR_BYTES / int(sizeof(S));
  static constexpr int K = N / P;
  typedef S Part __attribute__((vector_size(P * sizeof(S))));
  Part p[K];
  // GCC vector types alias their element type
  METEGS_INLINE S& operator[](int i) { return reinterpret_cast<S*>(p)[i]; }
  METEGS_INLINE const S& operator[](int i) const { return reinterpret_cast<const S*>(p)[i]; }
  METEGS_INLINE Split& operator+=(const Split& o) {
    for (int k = 0; k < K; ++k) p[k] += o.p[k];
    return *this;
  }
};

#define METEGS_SPLIT_BINARY(OP)                                                  \
  template <typename S, int N>                                                   \
  METEGS_INLINE Split<S, N> operator OP(const Split<S, N>& a, const Split<S, N>& b) { \
    Split<S, N> r;                                                               \
    for (int k = 0; k < Split<S, N>::K; ++k) r.p[k] = a.p[k] OP b.p[k];          \
    return r;                                                                    \
  }                                                                              \
  template <typename S, int N>                                                   \
  METEGS_INLINE Split<S, N> operator OP(const Split<S, N>& a, S b) {             \
    Split<S, N> r;                                                               \
    for (int k = 0; k < Split<S, N>::K; ++k) r.p[k] = a.p[k] OP b;               \
    return r;                                                                    \
  }                                                                              \
  template <typename S, int N>                                                   \
  METEGS_INLINE Split<S, N> operator OP(S a, const Split<S, N>& b) {             \
    Split<S, N> r;                                                               \
    for (int k = 0; k < Split<S, N>::K; ++k) r.p[k] = a OP b.p[k];               \
    return r;                                                                    \
  }
METEGS_SPLIT_BINARY(+)
METEGS_SPLIT_BINARY(-)
METEGS_SPLIT_BINARY(*)
METEGS_SPLIT_BINARY(/)
METEGS_SPLIT_BINARY(<<)
#undef METEGS_SPLIT_BINARY

#define METEGS_SPLIT_COMPARE(OP)                                                             \
  template <typename S, int N>                                                               \
  METEGS_INLINE Split<MaskOf<S>, N> operator OP(const Split<S, N>& a, const Split<S, N>& b) { \
    Split<MaskOf<S>, N> r;                                                                   \
    for (int k = 0; k < Split<S, N>::K; ++k) r.p[k] = a.p[k] OP b.p[k];                      \
    return r;                                                                                \
  }
METEGS_SPLIT_COMPARE(<)
METEGS_SPLIT_COMPARE(<=)
METEGS_SPLIT_COMPARE(>)
METEGS_SPLIT_COMPARE(>=)
#undef METEGS_SPLIT_COMPARE

template <typename S, int N>
METEGS_INLINE Split<S, N> operator-(const Split<S, N>& a) {
  Split<S, N> r;
  for (int k = 0; k < Split<S, N>::K; ++k) r.p[k] = -a.p[k];
  return r;
}

template <typename S, int N>
struct VecN {
  using type = Split<S, N>;
};

// m ? a : b per lane (m: a comparison's lanes, all ones or zero).
template <typename MS, typename S, int N>
METEGS_INLINE Split<S, N> select(const Split<MS, N>& m, const Split<S, N>& a, const Split<S, N>& b) {
  static_assert(Split<MS, N>::P == Split<S, N>::P, "a mask selects lanes of its own width");
  Split<S, N> r;
  for (int k = 0; k < Split<S, N>::K; ++k) r.p[k] = m.p[k] ? a.p[k] : b.p[k];
  return r;
}

// Each lane converted to To's element type (as __builtin_convertvector).
template <typename To, typename S, int N>
METEGS_INLINE To convert(const Split<S, N>& v) {
  To r;
  if constexpr (To::P == Split<S, N>::P) {
    for (int k = 0; k < To::K; ++k) r.p[k] = __builtin_convertvector(v.p[k], typename To::Part);
  } else {
    for (int l = 0; l < N; ++l) r[l] = v[l];
  }
  return r;
}
#endif

// The bits of v as a To of the same size.
template <typename To, typename From>
METEGS_INLINE To bitcast(const From& v) {
  static_assert(sizeof(To) == sizeof(From), "bitcast keeps the size");
  To r;
  std::memcpy(&r, &v, sizeof(r));
  return r;
}

// 16 float lanes of a tile row: one AVX-512 register, else two AVX2 (or four SSE / NEON) ones.
using Lanes16 = VecN<float, 16>::type;

// a * b + c per lane, rounded once where the CPU fuses it (AVX-512, or AVX2 with FMA), else rounded twice (the
// extension is built with -ffp-contract=off: multiply-adds are fused only where this is called).
METEGS_INLINE Lanes16 fmadd16(const Lanes16& a, const Lanes16& b, const Lanes16& c) {
#if METEGS_AVX512
  return (Lanes16)_mm512_fmadd_ps((__m512)a, (__m512)b, (__m512)c);
#else
  Lanes16 r;
#if METEGS_FMA
  static_assert(Lanes16::P == 8, "FMA parts are 8 floats");
  for (int k = 0; k < Lanes16::K; ++k)
    r.p[k] = (Lanes16::Part)_mm256_fmadd_ps((__m256)a.p[k], (__m256)b.p[k], (__m256)c.p[k]);
#else
  for (int k = 0; k < Lanes16::K; ++k) r.p[k] = a.p[k] * b.p[k] + c.p[k];
#endif
  return r;
#endif
}

// The first n (0..16) floats at src as 16 lanes, zeros after them (AVX-512: one masked load).
template <typename V = Float16>
METEGS_INLINE V load_first(const float* src, int64_t n) {
#if METEGS_AVX512
  return (V)_mm512_maskz_loadu_ps(static_cast<__mmask16>((1u << n) - 1), src);
#else
  V v{};
  std::memcpy(&v, src, n * sizeof(float));
  return v;
#endif
}

// Stores lanes [0, n) of v at dst (AVX-512: one masked store).
template <typename V>
METEGS_INLINE void store_first(float* dst, const V& v, int64_t n) {
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

// opening.cpp: grey-scale opening of x [B, H, W, C] (each channel) by a k x k square (k odd), windows clipped at the
// borders -> {opened [B, H, W, C], index [B, H, W, C] int32: the flat index in x each value was picked from, or an
// empty tensor unless with_index}.
std::vector<at::Tensor> opening_forward(at::Tensor x, int64_t k, bool with_index);
// opening.cpp: render and photo [B, H, W, C] with the pixels where either holds a bright stroke narrower than k
// (the mean over channels of image - opening > min_excess) replaced by both openings -> {render out, photo out,
// the render's opening index (empty unless with_index), stroke [B, H, W] bool}.
std::vector<at::Tensor> strokes_out_forward(at::Tensor render, at::Tensor photo, int64_t k, double min_excess,
                                            bool with_index);
// -> gradient of render given g_out [B, H, W, C], strokes_out_forward's index and stroke.
at::Tensor strokes_out_backward(at::Tensor index, at::Tensor stroke, at::Tensor g_out);

}  // namespace metegs_cpu
