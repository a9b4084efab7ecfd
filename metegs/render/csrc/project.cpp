// Fused EWA projection + spherical-harmonics shading for the metegs `cpu` rasteriser, forward and
// hand-written backward.
//
// Same semantics as metegs.render.projection.project_gaussians followed by
// metegs.render.pipeline.gaussian_colors (the torch reference): the same culling rules (near/far,
// non-finite input, non-positive 2D determinant, box off screen), the same clamp of the
// linearisation point to 1.3x the field of view, opacity-aware binning extents, colours clamped at 0.
// Culled Gaussians get finite placeholders (zeros, depth 1) and zero gradients. The backward
// recomputes the forward quantities of each Gaussian instead of saving them.
//
// The maths is written once, branch-free, for a "lane" type L: a vector of 16 Gaussians (float32: GCC vector
// extensions, AVX-512 here) or one Gaussian (float64 for the gradient checks, and the float32 remainder of a
// block). Every decision is a lane mask and a select, so the 16 lanes and the scalar path compute the same
// operations in the same order (built with -ffp-contract=off: no fused multiply-adds).

#include "metegs_cpu.h"

#include <algorithm>
#include <cmath>
#include <cstring>
#include <limits>
#include <type_traits>

namespace metegs_cpu {
namespace {

constexpr double SH_C0 = 0.28209479177387814;
constexpr double SH_C1 = 0.4886025119029199;
constexpr double SH_C2[5] = {1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792,
                             0.5462742152960396};
constexpr double SH_C3[7] = {-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154,
                             -0.4570457994644658, 1.445305721320277, -0.5900435899266435};

constexpr int LANES = 16;  // Gaussians per vector
typedef float VF __attribute__((vector_size(LANES * sizeof(float))));
typedef int32_t VI __attribute__((vector_size(LANES * sizeof(int32_t))));
typedef double VD __attribute__((vector_size(LANES * sizeof(double))));

// Lane traits: S the scalar type, B the mask type (bool, or int32 lanes of -1 / 0), W the wider type in which
// the conic gradient is computed.
template <typename L>
struct Lane {
  using S = L;
  using B = bool;
  using W = double;
  static constexpr int N = 1;
};
template <>
struct Lane<VF> {
  using S = float;
  using B = VI;
  using W = VD;
  static constexpr int N = LANES;
};

template <typename L>
using S_ = typename Lane<L>::S;
template <typename L>
using B_ = typename Lane<L>::B;

template <typename L>
inline __attribute__((always_inline)) L cst(double v) {  // a constant in every lane
  return L{} + static_cast<S_<L>>(v);
}
template <typename L, typename M>
inline __attribute__((always_inline)) L sel(M m, L a, L b) {
  return m ? a : b;
}
inline __attribute__((always_inline)) bool mnot(bool m) { return !m; }
inline __attribute__((always_inline)) VI mnot(VI m) { return ~m; }
// std::min / std::max, NaN handling included: min(a, b) = b < a ? b : a, max(a, b) = a < b ? b : a.
template <typename L>
inline __attribute__((always_inline)) L vmin(L a, L b) { return sel(b < a, b, a); }
template <typename L>
inline __attribute__((always_inline)) L vmax(L a, L b) { return sel(a < b, b, a); }
// Finite (neither infinite nor NaN): x - x is 0 exactly then, NaN otherwise.
template <typename L>
inline __attribute__((always_inline)) B_<L> finite(L x) { return (x - x) == cst<L>(0); }

inline __attribute__((always_inline)) float vsqrt(float x) { return std::sqrt(x); }
inline __attribute__((always_inline)) double vsqrt(double x) { return std::sqrt(x); }
inline __attribute__((always_inline)) VF vsqrt(VF x) {
#if METEGS_AVX512
  return (VF)_mm512_sqrt_ps((__m512)x);
#else
  for (int i = 0; i < LANES; ++i) x[i] = std::sqrt(x[i]);
  return x;
#endif
}
inline __attribute__((always_inline)) float vceil(float x) { return std::ceil(x); }
inline __attribute__((always_inline)) double vceil(double x) { return std::ceil(x); }
inline __attribute__((always_inline)) VF vceil(VF x) {
#if METEGS_AVX512
  return (VF)_mm512_roundscale_ps((__m512)x, _MM_FROUND_TO_POS_INF | _MM_FROUND_NO_EXC);
#else
  for (int i = 0; i < LANES; ++i) x[i] = std::ceil(x[i]);
  return x;
#endif
}
inline __attribute__((always_inline)) float vlog(float x) { return std::log(x); }
inline __attribute__((always_inline)) double vlog(double x) { return std::log(x); }
inline VF vlog(VF x) {
  for (int i = 0; i < LANES; ++i) x[i] = std::log(x[i]);
  return x;
}
inline __attribute__((always_inline)) double widen(float x) { return x; }
inline __attribute__((always_inline)) double widen(double x) { return x; }
inline __attribute__((always_inline)) VD widen(VF x) { return __builtin_convertvector(x, VD); }
template <typename L>
inline __attribute__((always_inline)) L narrow(typename Lane<L>::W x) {
  if constexpr (Lane<L>::N == 1) return static_cast<L>(x);
  else return __builtin_convertvector(x, L);
}
// A float in [0, 1e7] (integral) as int32, per lane.
inline __attribute__((always_inline)) int32_t to_i32(float x) { return static_cast<int32_t>(x); }
inline __attribute__((always_inline)) int32_t to_i32(double x) { return static_cast<int32_t>(x); }
inline __attribute__((always_inline)) VI to_i32(VF x) { return __builtin_convertvector(x, VI); }

#if METEGS_AVX512
// l * stride in lane l: the offsets of a gather or scatter over the 16 Gaussians of a block.
inline __attribute__((always_inline)) __m512i lane_offsets(int64_t stride) {
  return _mm512_mullo_epi32(_mm512_set_epi32(15, 14, 13, 12, 11, 10, 9, 8, 7, 6, 5, 4, 3, 2, 1, 0),
                            _mm512_set1_epi32(static_cast<int32_t>(stride)));
}
#endif

// Lanes l of base[l * stride] (the N Gaussians of a block, one field each), and the reverse.
template <typename L>
inline __attribute__((always_inline)) L load(const S_<L>* base, int64_t stride) {
  if constexpr (Lane<L>::N == 1) {
    return base[0];
  } else {
#if METEGS_AVX512
    return (L)_mm512_i32gather_ps(lane_offsets(stride), base, 4);
#else
    L v;
    for (int i = 0; i < LANES; ++i) v[i] = base[i * stride];
    return v;
#endif
  }
}
template <typename L>
inline __attribute__((always_inline)) void store(S_<L>* base, int64_t stride, L v) {
  if constexpr (Lane<L>::N == 1) {
    base[0] = v;
  } else {
#if METEGS_AVX512
    _mm512_i32scatter_ps(base, lane_offsets(stride), (__m512)v, 4);
#else
    for (int i = 0; i < LANES; ++i) base[i * stride] = v[i];
#endif
  }
}
inline __attribute__((always_inline)) void store_i32(int32_t* base, int32_t v) { base[0] = v; }
inline __attribute__((always_inline)) void store_i32(int32_t* base, VI v) { std::memcpy(base, &v, sizeof(v)); }

// In-place transpose of a 16 x 16 float block held as 16 vectors: four butterfly stages, each swapping the
// off-diagonal S x S blocks of every 2S x 2S block with 16 two-vector shuffles (64 in all).
template <int S>
inline __attribute__((always_inline)) void transpose_stage(VF (&r)[LANES]) {
  VI lo, hi;
  for (int l = 0; l < LANES; ++l) {
    lo[l] = (l & S) ? LANES + l - S : l;
    hi[l] = (l & S) ? LANES + l : l + S;
  }
  for (int i = 0; i < LANES; ++i)
    if (!(i & S)) {
      const VF a = r[i], b = r[i + S];
      r[i] = __builtin_shuffle(a, b, lo);
      r[i + S] = __builtin_shuffle(a, b, hi);
    }
}
inline __attribute__((always_inline)) void transpose16(VF (&r)[LANES]) {
  transpose_stage<8>(r);
  transpose_stage<4>(r);
  transpose_stage<2>(r);
  transpose_stage<1>(r);
}

// The SH coefficients q = 3 k + channel, q < nq, of the lane group whose first Gaussian's row (row floats per
// Gaussian) starts at c: coef[q] holds coefficient q of every lane. Vectors: 16 rows of 16 floats loaded and
// transposed per 16 coefficients (a gather per coefficient and a scatter per gradient cost several times more).
template <typename L>
inline void load_sh(const S_<L>* c, int64_t row, int nq, L* coef) {
  if constexpr (Lane<L>::N == 1) {
    for (int q = 0; q < nq; ++q) coef[q] = c[q];
  } else {
    for (int q0 = 0; q0 < nq; q0 += LANES) {
      const int64_t n = std::min<int64_t>(LANES, row - q0);  // floats of a row from q0 on
      VF r[LANES];
      for (int l = 0; l < LANES; ++l) r[l] = load_first(c + l * row + q0, n);
      transpose16(r);
      for (int j = 0; j < LANES && q0 + j < nq; ++j) coef[q0 + j] = r[j];
    }
  }
}

// The inverse of load_sh for gradients: grad[q], q < nq, into each Gaussian's row; zeros at q in [nq, row).
template <typename L>
inline void store_sh(S_<L>* c, int64_t row, int nq, const L* grad) {
  if constexpr (Lane<L>::N == 1) {
    for (int q = 0; q < nq; ++q) c[q] = grad[q];
    std::fill(c + nq, c + row, S_<L>(0));
  } else {
    for (int64_t q0 = 0; q0 < row; q0 += LANES) {
      const int64_t n = std::min<int64_t>(LANES, row - q0);
      VF r[LANES];
      for (int j = 0; j < LANES; ++j) r[j] = q0 + j < nq ? grad[q0 + j] : VF{};
      transpose16(r);
      for (int l = 0; l < LANES; ++l) store_first(c + l * row + q0, r[l], n);
    }
  }
}

template <typename T>
struct Camera {
  T R[9], t[3], fx, fy, cx, cy, campos[3];
  T lim_x_pos, lim_x_neg, lim_y_pos, lim_y_neg;
  int64_t width, height;
  T near_plane, far_plane, eps2d;
};

// The inputs of one lane group (a block of N Gaussians starting at g).
template <typename L>
struct Inputs {
  L mean[3], quat[4], scale[3], opacity;
};

template <typename L>
inline __attribute__((always_inline)) Inputs<L> load_inputs(const S_<L>* mp, const S_<L>* qp, const S_<L>* sp,
                                                             const S_<L>* op, int64_t g) {
  Inputs<L> in;
  for (int i = 0; i < 3; ++i) in.mean[i] = load<L>(mp + 3 * g + i, 3);
  for (int i = 0; i < 4; ++i) in.quat[i] = load<L>(qp + 4 * g + i, 4);
  for (int i = 0; i < 3; ++i) in.scale[i] = load<L>(sp + 3 * g + i, 3);
  in.opacity = load<L>(op + g, 1);
  return in;
}

// Everything the forward computes for one Gaussian (per lane) that the backward needs again.
template <typename L>
struct Projection {
  B_<L> keep;
  L p[3];          // camera-space mean
  B_<L> clamp_x, clamp_y;
  L tx, ty;        // clamped linearisation point (times z)
  L J[6];          // [2, 3] row-major
  L Rg[9];         // rotation of the normalised quaternion
  L qn[4];         // normalised quaternion
  L qnorm;         // |q| clamped at 1e-12
  B_<L> qclamped;
  L M[9];          // Rg diag(s)
  L cov3[9];       // M M^T
  L JW[6];         // J R
  L a, b, c, det;  // 2D covariance (+ eps2d) and its determinant
  L radius;
  L ext[2];
};

template <typename L>
void project_one(const Camera<S_<L>>& cam, const Inputs<L>& in, Projection<L>& P) {
  using S = S_<L>;
  const L* mean = in.mean;
  const L* quat = in.quat;
  const L* scale = in.scale;
  for (int i = 0; i < 3; ++i)
    P.p[i] = cam.R[3 * i] * mean[0] + cam.R[3 * i + 1] * mean[1] + cam.R[3 * i + 2] * mean[2] + cam.t[i];
  B_<L> ok = finite(P.p[0]) & finite(P.p[1]) & finite(P.p[2]);
  for (int i = 0; i < 3; ++i) ok &= finite(scale[i]);
  for (int i = 0; i < 4; ++i) ok &= finite(quat[i]);
  const L tz = P.p[2];
  ok &= (tz > cam.near_plane) & (tz < cam.far_plane);
  const L u = P.p[0] / tz, v = P.p[1] / tz;
  const L ux = vmin(vmax(u, cst<L>(-cam.lim_x_neg)), cst<L>(cam.lim_x_pos));
  const L vy = vmin(vmax(v, cst<L>(-cam.lim_y_neg)), cst<L>(cam.lim_y_pos));
  P.clamp_x = ux != u;
  P.clamp_y = vy != v;
  P.tx = tz * ux;
  P.ty = tz * vy;
  P.J[0] = cam.fx / tz;
  P.J[1] = cst<L>(0);
  P.J[2] = -cam.fx * P.tx / (tz * tz);
  P.J[3] = cst<L>(0);
  P.J[4] = cam.fy / tz;
  P.J[5] = -cam.fy * P.ty / (tz * tz);

  const L n = vsqrt(quat[0] * quat[0] + quat[1] * quat[1] + quat[2] * quat[2] + quat[3] * quat[3]);
  P.qclamped = mnot(n > S(1e-12));
  P.qnorm = sel(P.qclamped, cst<L>(1e-12), n);
  for (int i = 0; i < 4; ++i) P.qn[i] = quat[i] / P.qnorm;
  const L w = P.qn[0], x = P.qn[1], y = P.qn[2], z = P.qn[3];
  L* R = P.Rg;
  R[0] = S(1) - S(2) * (y * y + z * z);
  R[1] = S(2) * (x * y - w * z);
  R[2] = S(2) * (x * z + w * y);
  R[3] = S(2) * (x * y + w * z);
  R[4] = S(1) - S(2) * (x * x + z * z);
  R[5] = S(2) * (y * z - w * x);
  R[6] = S(2) * (x * z - w * y);
  R[7] = S(2) * (y * z + w * x);
  R[8] = S(1) - S(2) * (x * x + y * y);
  for (int i = 0; i < 3; ++i)
    for (int j = 0; j < 3; ++j) P.M[3 * i + j] = R[3 * i + j] * scale[j];
  for (int i = 0; i < 3; ++i)
    for (int j = 0; j < 3; ++j)
      P.cov3[3 * i + j] = P.M[3 * i] * P.M[3 * j] + P.M[3 * i + 1] * P.M[3 * j + 1] + P.M[3 * i + 2] * P.M[3 * j + 2];
  for (int i = 0; i < 2; ++i)
    for (int j = 0; j < 3; ++j)
      P.JW[3 * i + j] = P.J[3 * i] * cam.R[j] + P.J[3 * i + 1] * cam.R[3 + j] + P.J[3 * i + 2] * cam.R[6 + j];
  // cov2 = JW cov3 JW^T: only (0,0), (0,1), (1,1) are used
  L tmp[6];  // JW cov3
  for (int i = 0; i < 2; ++i)
    for (int j = 0; j < 3; ++j)
      tmp[3 * i + j] = P.JW[3 * i] * P.cov3[j] + P.JW[3 * i + 1] * P.cov3[3 + j] + P.JW[3 * i + 2] * P.cov3[6 + j];
  const L c00 = tmp[0] * P.JW[0] + tmp[1] * P.JW[1] + tmp[2] * P.JW[2];
  const L c01 = tmp[0] * P.JW[3] + tmp[1] * P.JW[4] + tmp[2] * P.JW[5];
  const L c11 = tmp[3] * P.JW[3] + tmp[4] * P.JW[4] + tmp[5] * P.JW[5];
  P.a = c00 + cam.eps2d;
  P.b = c01;
  P.c = c11 + cam.eps2d;
  P.det = P.a * P.c - P.b * P.b;
  ok &= (P.det > S(0)) & finite(P.det);

  const L mx = cam.fx * P.p[0] / tz + cam.cx, my = cam.fy * P.p[1] / tz + cam.cy;
  const L mid = S(0.5) * (P.a + P.c);
  const L lam = mid + vsqrt(vmax(mid * mid - P.det, cst<L>(0.1)));
  L radius = vceil(S(3) * vsqrt(vmax(lam, cst<L>(0))));
  radius = vmin(sel(finite(radius), radius, cst<L>(0)), cst<L>(1e7));
  const L k = vsqrt(S(2) * vlog(vmax(S(255) * in.opacity, cst<L>(1))));
  for (int i = 0; i < 2; ++i) {
    const L e = vceil(k * vsqrt(vmax(i == 0 ? P.a : P.c, cst<L>(0))));
    P.ext[i] = vmin(sel(finite(e), e, cst<L>(0)), cst<L>(1e7));
  }
  const B_<L> on_screen = (mx + P.ext[0] > S(0)) & (mx - P.ext[0] < S(cam.width)) & (my + P.ext[1] > S(0)) &
                          (my - P.ext[1] < S(cam.height)) & (P.ext[0] > S(0)) & (P.ext[1] > S(0));
  P.radius = radius;
  P.keep = ok & on_screen & (radius >= S(1));  // radius is a whole number: int(radius) > 0
}

// Real SH basis values up to degree 3 at unit direction d: out[16].
template <typename L>
inline void sh_basis(int degree, L x, L y, L z, L* out) {
  using S = S_<L>;
  out[0] = cst<L>(SH_C0);
  if (degree < 1) return;
  out[1] = -S(SH_C1) * y;
  out[2] = S(SH_C1) * z;
  out[3] = -S(SH_C1) * x;
  if (degree < 2) return;
  const L xx = x * x, yy = y * y, zz = z * z, xy = x * y, yz = y * z, xz = x * z;
  out[4] = S(SH_C2[0]) * xy;
  out[5] = S(SH_C2[1]) * yz;
  out[6] = S(SH_C2[2]) * (S(2) * zz - xx - yy);
  out[7] = S(SH_C2[3]) * xz;
  out[8] = S(SH_C2[4]) * (xx - yy);
  if (degree < 3) return;
  out[9] = S(SH_C3[0]) * y * (S(3) * xx - yy);
  out[10] = S(SH_C3[1]) * xy * z;
  out[11] = S(SH_C3[2]) * y * (S(4) * zz - xx - yy);
  out[12] = S(SH_C3[3]) * z * (S(2) * zz - S(3) * xx - S(3) * yy);
  out[13] = S(SH_C3[4]) * x * (S(4) * zz - xx - yy);
  out[14] = S(SH_C3[5]) * z * (xx - yy);
  out[15] = S(SH_C3[6]) * x * (xx - S(3) * yy);
}

// sum_k w_k d(basis_k)/d(x, y, z) for k = 1 .. (degree + 1)^2 - 1: g[3].
template <typename L>
inline void sh_basis_grad_dot(int degree, L x, L y, L z, const L* w, L* g) {
  using S = S_<L>;
  g[0] = g[1] = g[2] = cst<L>(0);
  if (degree < 1) return;
  g[1] += w[1] * -S(SH_C1);
  g[2] += w[2] * S(SH_C1);
  g[0] += w[3] * -S(SH_C1);
  if (degree < 2) return;
  const L xx = x * x, yy = y * y, zz = z * z;
  g[0] += w[4] * (S(SH_C2[0]) * y), g[1] += w[4] * (S(SH_C2[0]) * x);
  g[1] += w[5] * (S(SH_C2[1]) * z), g[2] += w[5] * (S(SH_C2[1]) * y);
  g[0] += w[6] * (-S(2 * SH_C2[2]) * x), g[1] += w[6] * (-S(2 * SH_C2[2]) * y), g[2] += w[6] * (S(4 * SH_C2[2]) * z);
  g[0] += w[7] * (S(SH_C2[3]) * z), g[2] += w[7] * (S(SH_C2[3]) * x);
  g[0] += w[8] * (S(2 * SH_C2[4]) * x), g[1] += w[8] * (-S(2 * SH_C2[4]) * y);
  if (degree < 3) return;
  g[0] += w[9] * (S(SH_C3[0]) * S(6) * x * y), g[1] += w[9] * (S(SH_C3[0]) * S(3) * (xx - yy));
  g[0] += w[10] * (S(SH_C3[1]) * y * z), g[1] += w[10] * (S(SH_C3[1]) * x * z), g[2] += w[10] * (S(SH_C3[1]) * x * y);
  g[0] += w[11] * (-S(SH_C3[2]) * S(2) * x * y), g[1] += w[11] * (S(SH_C3[2]) * (S(4) * zz - xx - S(3) * yy)),
      g[2] += w[11] * (S(SH_C3[2]) * S(8) * y * z);
  g[0] += w[12] * (-S(SH_C3[3]) * S(6) * x * z), g[1] += w[12] * (-S(SH_C3[3]) * S(6) * y * z),
      g[2] += w[12] * (S(SH_C3[3]) * (S(6) * zz - S(3) * xx - S(3) * yy));
  g[0] += w[13] * (S(SH_C3[4]) * (S(4) * zz - S(3) * xx - yy)), g[1] += w[13] * (-S(SH_C3[4]) * S(2) * x * y),
      g[2] += w[13] * (S(SH_C3[4]) * S(8) * x * z);
  g[0] += w[14] * (S(SH_C3[5]) * S(2) * x * z), g[1] += w[14] * (-S(SH_C3[5]) * S(2) * y * z),
      g[2] += w[14] * (S(SH_C3[5]) * (xx - yy));
  g[0] += w[15] * (S(SH_C3[6]) * S(3) * (xx - yy)), g[1] += w[15] * (-S(SH_C3[6]) * S(6) * x * y);
}

// Unit view direction from the camera centre to the mean (zero for non-finite means); returns the mask of
// lanes whose norm was clamped at 1e-12, and `raw_ok` the lanes whose offset was finite.
template <typename L>
inline B_<L> view_dir(const Camera<S_<L>>& cam, const L* mean, L* d, L& norm, B_<L>& raw_ok) {
  for (int i = 0; i < 3; ++i) d[i] = mean[i] - cam.campos[i];
  raw_ok = finite(d[0]) & finite(d[1]) & finite(d[2]);
  for (int i = 0; i < 3; ++i) d[i] = sel(raw_ok, d[i], cst<L>(0));
  const L n = vsqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2]);
  const B_<L> clamped = mnot(n > S_<L>(1e-12));
  norm = sel(clamped, cst<L>(1e-12), n);
  for (int i = 0; i < 3; ++i) d[i] = d[i] / norm;
  return clamped;
}

// A lane group's view-dependent colour before the clamp at 0, and what the backward needs of it again.
template <typename L>
struct Shading {
  L d[3], dn;  // unit view direction, distance (clamped at 1e-12)
  B_<L> dclamped, raw_ok;  // view_dir's masks
  L basis[16];
  L coef[48];  // SH coefficients, q = 3 k + channel
  L v[3];      // sum_k basis_k coef_k + 0.5, per channel
};

// c: the group's first SH row (row floats per Gaussian).
template <typename L>
inline void shade(const Camera<S_<L>>& cam, const L* mean, const S_<L>* c, int64_t row, int degree, Shading<L>& s) {
  const int nb = (degree + 1) * (degree + 1);
  s.dclamped = view_dir(cam, mean, s.d, s.dn, s.raw_ok);
  sh_basis(degree, s.d[0], s.d[1], s.d[2], s.basis);
  load_sh<L>(c, row, 3 * nb, s.coef);
  for (int ch = 0; ch < 3; ++ch) {
    L v = cst<L>(0);
    for (int k = 0; k < nb; ++k) v += s.basis[k] * s.coef[3 * k + ch];
    s.v[ch] = v + S_<L>(0.5);
  }
}

template <typename T>
Camera<T> make_camera(const at::Tensor& viewmat, const at::Tensor& K, const at::Tensor& campos, int64_t width,
                      int64_t height, double near_plane, double far_plane, double eps2d) {
  auto vm = viewmat.to(at::kDouble).contiguous();
  auto k = K.to(at::kDouble).contiguous();
  auto cp = campos.to(at::kDouble).contiguous();
  const double* V = vm.data_ptr<double>();
  const double* Kp = k.data_ptr<double>();
  Camera<T> cam;
  for (int i = 0; i < 3; ++i) {
    for (int j = 0; j < 3; ++j) cam.R[3 * i + j] = T(V[4 * i + j]);
    cam.t[i] = T(V[4 * i + 3]);
    cam.campos[i] = T(cp.data_ptr<double>()[i]);
  }
  cam.fx = T(Kp[0]);
  cam.fy = T(Kp[4]);
  cam.cx = T(Kp[2]);
  cam.cy = T(Kp[5]);
  const T W = T(width), H = T(height);
  cam.lim_x_pos = (W - cam.cx) / cam.fx + T(0.3) * (T(0.5) * W / cam.fx);
  cam.lim_x_neg = cam.cx / cam.fx + T(0.3) * (T(0.5) * W / cam.fx);
  cam.lim_y_pos = (H - cam.cy) / cam.fy + T(0.3) * (T(0.5) * H / cam.fy);
  cam.lim_y_neg = cam.cy / cam.fy + T(0.3) * (T(0.5) * H / cam.fy);
  cam.width = width;
  cam.height = height;
  cam.near_plane = T(near_plane);
  cam.far_plane = T(far_plane);
  cam.eps2d = T(eps2d);
  return cam;
}

void check_inputs(const at::Tensor& means, const at::Tensor& quats, const at::Tensor& scales,
                  const at::Tensor& opacities, const at::Tensor& sh, int64_t sh_degree) {
  const auto N = means.size(0);
  TORCH_CHECK(means.device().is_cpu(), "metegs cpu projection: tensors must be on the CPU");
  TORCH_CHECK(means.dim() == 2 && means.size(1) == 3, "means must be [N, 3]");
  TORCH_CHECK(quats.dim() == 2 && quats.size(0) == N && quats.size(1) == 4, "quats must be [N, 4]");
  TORCH_CHECK(scales.dim() == 2 && scales.size(0) == N && scales.size(1) == 3, "scales must be [N, 3]");
  TORCH_CHECK(opacities.dim() == 1 && opacities.size(0) == N, "opacities must be [N]");
  TORCH_CHECK(sh.dim() == 3 && sh.size(0) == N && sh.size(2) == 3, "sh must be [N, K, 3]");
  TORCH_CHECK(sh_degree >= 0 && sh_degree <= 3, "sh_degree must be in 0..3");
  TORCH_CHECK(sh.size(1) >= (sh_degree + 1) * (sh_degree + 1), "sh has fewer coefficients than sh_degree needs");
  TORCH_CHECK(N * std::max<int64_t>(sh.size(1) * 3, 4) < (int64_t(1) << 31), "too many Gaussians for int32 offsets");
  const auto dt = means.scalar_type();
  TORCH_CHECK(quats.scalar_type() == dt && scales.scalar_type() == dt && opacities.scalar_type() == dt &&
                  sh.scalar_type() == dt,
              "means, quats, scales, opacities and sh must share one dtype");
}

// Runs body(L{}, g) over [0, N), L the lane type: blocks of 16 Gaussians as float32 vectors, the rest (and
// every float64 Gaussian) one at a time.
template <typename T, typename F>
void for_lanes(int64_t N, const F& body) {
  constexpr int64_t step = std::is_same_v<T, float> ? LANES : 1;
  const int64_t blocks = N / step;
  metegs::parallel_for(0, blocks, std::max<int64_t>(1, 512 / step), [&](int64_t begin, int64_t end) {
    for (int64_t i = begin; i < end; ++i) {
      if constexpr (step > 1) body(VF{}, i * step);
      else body(T{}, i);
    }
  });
  for (int64_t g = blocks * step; g < N; ++g) body(T{}, g);
}

}  // namespace

std::vector<at::Tensor> project_forward(at::Tensor means, at::Tensor quats, at::Tensor scales, at::Tensor opacities,
                                        at::Tensor sh, at::Tensor viewmat, at::Tensor K, at::Tensor campos,
                                        int64_t width, int64_t height, double near_plane, double far_plane,
                                        double eps2d, int64_t sh_degree) {
  check_inputs(means, quats, scales, opacities, sh, sh_degree);
  means = means.contiguous(), quats = quats.contiguous(), scales = scales.contiguous();
  opacities = opacities.contiguous(), sh = sh.contiguous();
  const int64_t N = means.size(0), KS = sh.size(1);
  const auto opts = means.options();
  // every element is written below: no fill
  auto means2d = at::empty({N, 2}, opts);
  auto conics = at::empty({N, 3}, opts);
  auto depths = at::empty({N}, opts);
  auto colors = at::empty({N, 3}, opts);
  auto radii = at::empty({N}, opts.dtype(at::kInt));
  auto extents = at::empty({N, 2}, opts);
  AT_DISPATCH_FLOATING_TYPES(means.scalar_type(), "metegs_project_forward", [&] {
    using T = scalar_t;
    const auto cam = make_camera<T>(viewmat, K, campos, width, height, near_plane, far_plane, eps2d);
    const T *mp = means.data_ptr<T>(), *qp = quats.data_ptr<T>(), *sp = scales.data_ptr<T>();
    const T *op = opacities.data_ptr<T>(), *shp = sh.data_ptr<T>();
    T *m2 = means2d.data_ptr<T>(), *co = conics.data_ptr<T>(), *de = depths.data_ptr<T>();
    T *col = colors.data_ptr<T>(), *ex = extents.data_ptr<T>();
    int32_t* ra = radii.data_ptr<int32_t>();
    const int deg = static_cast<int>(sh_degree);
    for_lanes<T>(N, [&](auto lane, int64_t g) {
      using L = decltype(lane);
      const Inputs<L> in = load_inputs<L>(mp, qp, sp, op, g);
      Projection<L> P;
      project_one(cam, in, P);
      const L zero = cst<L>(0), tz = P.p[2];
      const B_<L> keep = P.keep;
      store<L>(m2 + 2 * g, 2, sel(keep, cam.fx * P.p[0] / tz + cam.cx, zero));
      store<L>(m2 + 2 * g + 1, 2, sel(keep, cam.fy * P.p[1] / tz + cam.cy, zero));
      store<L>(co + 3 * g, 3, sel(keep, P.c / P.det, zero));
      store<L>(co + 3 * g + 1, 3, sel(keep, -P.b / P.det, zero));
      store<L>(co + 3 * g + 2, 3, sel(keep, P.a / P.det, zero));
      store<L>(de + g, 1, sel(keep, tz, cst<L>(1)));
      store_i32(ra + g, to_i32(sel(keep, P.radius, zero)));
      store<L>(ex + 2 * g, 2, sel(keep, P.ext[0], zero));
      store<L>(ex + 2 * g + 1, 2, sel(keep, P.ext[1], zero));
      Shading<L> sc;
      shade(cam, in.mean, shp + g * KS * 3, KS * 3, deg, sc);
      for (int ch = 0; ch < 3; ++ch) store<L>(col + 3 * g + ch, 3, sel(sc.v[ch] > T(0), sc.v[ch], zero));
    });
  });
  return {means2d, conics, depths, colors, radii, extents};
}

std::vector<at::Tensor> project_backward(at::Tensor means, at::Tensor quats, at::Tensor scales,
                                         at::Tensor opacities, at::Tensor sh, at::Tensor viewmat, at::Tensor K,
                                         at::Tensor campos, int64_t width, int64_t height, double near_plane,
                                         double far_plane, double eps2d, int64_t sh_degree, at::Tensor g_means2d,
                                         at::Tensor g_conics, at::Tensor g_depths, at::Tensor g_colors) {
  check_inputs(means, quats, scales, opacities, sh, sh_degree);
  means = means.contiguous(), quats = quats.contiguous(), scales = scales.contiguous();
  opacities = opacities.contiguous(), sh = sh.contiguous();
  const int64_t N = means.size(0), KS = sh.size(1);
  const auto dt = means.scalar_type();
  g_means2d = g_means2d.to(dt).contiguous(), g_conics = g_conics.to(dt).contiguous();
  g_depths = g_depths.to(dt).contiguous(), g_colors = g_colors.to(dt).contiguous();
  TORCH_CHECK(g_means2d.numel() == 2 * N && g_conics.numel() == 3 * N && g_depths.numel() == N &&
                  g_colors.numel() == 3 * N,
              "bad gradient shapes for the projection backward");
  const int deg = static_cast<int>(sh_degree);
  const int nb = (deg + 1) * (deg + 1);
  // every element is written below (zeros in the SH bands above sh_degree): no fill
  auto gm = at::empty({N, 3}, means.options());
  auto gq = at::empty({N, 4}, means.options());
  auto gs = at::empty({N, 3}, means.options());
  auto gsh = at::empty({N, KS, 3}, means.options());
  AT_DISPATCH_FLOATING_TYPES(dt, "metegs_project_backward", [&] {
    using T = scalar_t;
    const auto cam = make_camera<T>(viewmat, K, campos, width, height, near_plane, far_plane, eps2d);
    const T *mp = means.data_ptr<T>(), *qp = quats.data_ptr<T>(), *sp = scales.data_ptr<T>();
    const T *op = opacities.data_ptr<T>(), *shp = sh.data_ptr<T>();
    const T *gm2 = g_means2d.data_ptr<T>(), *gco = g_conics.data_ptr<T>(), *gde = g_depths.data_ptr<T>();
    const T* gcol = g_colors.data_ptr<T>();
    T *ogm = gm.data_ptr<T>(), *ogq = gq.data_ptr<T>(), *ogs = gs.data_ptr<T>(), *ogsh = gsh.data_ptr<T>();
    for_lanes<T>(N, [&](auto lane, int64_t g) {
      using L = decltype(lane);
      using W = typename Lane<L>::W;
      const L zero = cst<L>(0);
      const Inputs<L> in = load_inputs<L>(mp, qp, sp, op, g);
      // ---- colours: d colour / d (sh, direction) ----
      Shading<L> sc;
      shade(cam, in.mean, shp + g * KS * 3, KS * 3, deg, sc);
      const L *basis = sc.basis, *coef = sc.coef, *d = sc.d;
      L gc[3];
      B_<L> any = zero != zero;
      for (int ch = 0; ch < 3; ++ch) {
        gc[ch] = sel(sc.v[ch] >= T(0), load<L>(gcol + 3 * g + ch, 3), zero);  // clamp_min(0) passes it at v >= 0
        any |= gc[ch] != T(0);
      }
      L gsh_q[48];
      for (int k = 0; k < nb; ++k)
        for (int ch = 0; ch < 3; ++ch) gsh_q[3 * k + ch] = basis[k] * gc[ch];
      store_sh<L>(ogsh + g * KS * 3, KS * 3, 3 * nb, gsh_q);
      L gmean[3] = {zero, zero, zero};
      if (deg > 0) {
        L w[16], gd[3];
        for (int k = 1; k < nb; ++k) w[k] = coef[3 * k] * gc[0] + coef[3 * k + 1] * gc[1] + coef[3 * k + 2] * gc[2];
        sh_basis_grad_dot(deg, d[0], d[1], d[2], w, gd);
        const L dot = sel(sc.dclamped, zero, d[0] * gd[0] + d[1] * gd[1] + d[2] * gd[2]);
        for (int i = 0; i < 3; ++i) gmean[i] = sel(any & sc.raw_ok, (gd[i] - d[i] * dot) / sc.dn, zero);
      }

      // ---- geometry ----
      Projection<L> P;
      project_one(cam, in, P);
      const B_<L> keep = P.keep;
      const L tz = P.p[2], tz2 = tz * tz;
      const L g_mx = load<L>(gm2 + 2 * g, 2), g_my = load<L>(gm2 + 2 * g + 1, 2);
      L gp[3] = {zero, zero, zero};
      // means2d and depth
      gp[0] += cam.fx / tz * g_mx;
      gp[1] += cam.fy / tz * g_my;
      L gtz = -cam.fx * P.p[0] / tz2 * g_mx - cam.fy * P.p[1] / tz2 * g_my + load<L>(gde + g, 1);
      // conic (c/det, -b/det, a/det) -> (a, b, c), in double and written with the ratios a/det, b/det,
      // c/det, 1/det (bounded by about 1/eps2d and 1/eps2d^2): the products a*a, a*c, b*b, c*c and det*det of
      // the textbook form overflow (float32: det*det from det ~ 2e19, a*a near 3e38, giving inf/inf = NaN)
      // for huge Gaussians whose forward is still finite. Same chain as the torch reference's autograd,
      // d(x/det) = dx/det - (x/det)/det d(det) with d(det) = c da + a dc - 2 b db, and the same det
      // (the forward's, in T), so the normal regime is unchanged up to rounding.
      const W A = widen(load<L>(gco + 3 * g, 3)), B = widen(load<L>(gco + 3 * g + 1, 3));
      const W C = widen(load<L>(gco + 3 * g + 2, 3));
      const W det = widen(P.det), id = 1.0 / det, ia = widen(P.a) / det, ib = widen(P.b) / det,
              ic = widen(P.c) / det;
      const W ga_d = -A * (ic * ic) + B * (ib * ic) + C * (id - ia * ic);
      const W gb_d = A * (2.0 * ib * ic) - B * (id + 2.0 * ib * ib) + C * (2.0 * ia * ib);
      const W gc_d = A * (id - ic * ia) + B * (ib * ia) - C * (ia * ia);
      const L ga = narrow<L>(ga_d), gb = narrow<L>(gb_d), gcv = narrow<L>(gc_d);
      // cov2 = JW cov3 JW^T with dL/dcov2 = V (symmetric form: V01 = V10 = gb / 2)
      const L V[4] = {ga, T(0.5) * gb, T(0.5) * gb, gcv};
      // dL/dJW = 2 V JW cov3 ; dL/dcov3 = JW^T V JW
      L JWc[6];
      for (int i = 0; i < 2; ++i)
        for (int j = 0; j < 3; ++j)
          JWc[3 * i + j] = P.JW[3 * i] * P.cov3[j] + P.JW[3 * i + 1] * P.cov3[3 + j] + P.JW[3 * i + 2] * P.cov3[6 + j];
      L gJW[6];
      for (int i = 0; i < 2; ++i)
        for (int j = 0; j < 3; ++j) gJW[3 * i + j] = T(2) * (V[2 * i] * JWc[j] + V[2 * i + 1] * JWc[3 + j]);
      L gcov3[9];
      for (int i = 0; i < 3; ++i)
        for (int j = 0; j < 3; ++j) {
          L acc = zero;
          for (int r = 0; r < 2; ++r)
            for (int s2 = 0; s2 < 2; ++s2) acc += P.JW[3 * r + i] * V[2 * r + s2] * P.JW[3 * s2 + j];
          gcov3[3 * i + j] = acc;
        }
      // cov3 = M M^T -> dL/dM = 2 gcov3 M (gcov3 symmetric)
      L gM[9];
      for (int i = 0; i < 3; ++i)
        for (int j = 0; j < 3; ++j)
          gM[3 * i + j] =
              T(2) * (gcov3[3 * i] * P.M[j] + gcov3[3 * i + 1] * P.M[3 + j] + gcov3[3 * i + 2] * P.M[6 + j]);
      // M = Rg diag(s)
      L G[9];
      for (int i = 0; i < 3; ++i)
        for (int j = 0; j < 3; ++j) G[3 * i + j] = gM[3 * i + j] * in.scale[j];
      for (int j = 0; j < 3; ++j)
        store<L>(ogs + 3 * g + j, 3, sel(keep, gM[j] * P.Rg[j] + gM[3 + j] * P.Rg[3 + j] + gM[6 + j] * P.Rg[6 + j], zero));
      const L w = P.qn[0], x = P.qn[1], y = P.qn[2], z = P.qn[3];
      L gqn[4];
      gqn[0] = T(2) * (-z * G[1] + y * G[2] + z * G[3] - x * G[5] - y * G[6] + x * G[7]);
      gqn[1] = T(2) * (y * G[1] + z * G[2] + y * G[3] - T(2) * x * G[4] - w * G[5] + z * G[6] + w * G[7] -
                       T(2) * x * G[8]);
      gqn[2] = T(2) * (-T(2) * y * G[0] + x * G[1] + w * G[2] + x * G[3] + z * G[5] - w * G[6] + z * G[7] -
                       T(2) * y * G[8]);
      gqn[3] = T(2) * (-T(2) * z * G[0] - w * G[1] + x * G[2] + w * G[3] - T(2) * z * G[4] + y * G[5] +
                       x * G[6] + y * G[7]);
      const L qdot = sel(P.qclamped, zero, w * gqn[0] + x * gqn[1] + y * gqn[2] + z * gqn[3]);
      for (int i = 0; i < 4; ++i) store<L>(ogq + 4 * g + i, 4, sel(keep, (gqn[i] - P.qn[i] * qdot) / P.qnorm, zero));
      // JW = J R -> dL/dJ = dL/dJW R^T (only J00, J02, J11, J12 depend on the mean)
      L gJ[6];
      for (int i = 0; i < 2; ++i)
        for (int j = 0; j < 3; ++j)
          gJ[3 * i + j] =
              gJW[3 * i] * cam.R[3 * j] + gJW[3 * i + 1] * cam.R[3 * j + 1] + gJW[3 * i + 2] * cam.R[3 * j + 2];
      const L tz3 = tz2 * tz;
      gtz += -cam.fx / tz2 * gJ[0] + T(2) * cam.fx * P.tx / tz3 * gJ[2] - cam.fy / tz2 * gJ[4] +
             T(2) * cam.fy * P.ty / tz3 * gJ[5];
      const L gtx = -cam.fx / tz2 * gJ[2], gty = -cam.fy / tz2 * gJ[5];
      // tx = tz * clamp(px / tz): = px inside the limits, tz * limit outside
      gtz += sel(P.clamp_x, gtx * (P.tx / tz), zero);
      gp[0] += sel(P.clamp_x, zero, gtx);
      gtz += sel(P.clamp_y, gty * (P.ty / tz), zero);
      gp[1] += sel(P.clamp_y, zero, gty);
      gp[2] += gtz;
      for (int j = 0; j < 3; ++j) {
        const L geo = cam.R[j] * gp[0] + cam.R[3 + j] * gp[1] + cam.R[6 + j] * gp[2];
        store<L>(ogm + 3 * g + j, 3, sel(keep, gmean[j] + geo, gmean[j]));
      }
    });
  });
  return {gm, gq, gs, gsh};
}

}  // namespace metegs_cpu
