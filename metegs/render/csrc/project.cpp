// Fused EWA projection + spherical-harmonics shading for the metegs `cpu` rasteriser, forward and
// hand-written backward, one Gaussian per loop iteration (parallel over Gaussians).
//
// Same semantics as metegs.render.projection.project_gaussians followed by
// metegs.render.pipeline.gaussian_colors (the torch reference): the same culling rules (near/far,
// non-finite input, non-positive 2D determinant, box off screen), the same clamp of the
// linearisation point to 1.3x the field of view, opacity-aware binning extents, colours clamped at 0.
// Culled Gaussians get finite placeholders (zeros, depth 1) and zero gradients. The backward
// recomputes the forward quantities of each Gaussian instead of saving them.

#include "metegs_cpu.h"

#include <ATen/Parallel.h>

#include <algorithm>
#include <cmath>
#include <limits>

namespace metegs_cpu {
namespace {

constexpr double SH_C0 = 0.28209479177387814;
constexpr double SH_C1 = 0.4886025119029199;
constexpr double SH_C2[5] = {1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792,
                             0.5462742152960396};
constexpr double SH_C3[7] = {-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154,
                             -0.4570457994644658, 1.445305721320277, -0.5900435899266435};

template <typename T>
struct Camera {
  T R[9], t[3], fx, fy, cx, cy, campos[3];
  T lim_x_pos, lim_x_neg, lim_y_pos, lim_y_neg;
  int64_t width, height;
  T near_plane, far_plane, eps2d;
};

// Everything the forward computes for one Gaussian that the backward needs again.
template <typename T>
struct Projection {
  bool keep = false;
  T p[3];          // camera-space mean
  T u, v;          // p.x / z and p.y / z before the clamp
  bool clamp_x, clamp_y;
  T tx, ty;        // clamped linearisation point (times z)
  T J[6];          // [2, 3] row-major
  T Rg[9];         // rotation of the normalised quaternion
  T qn[4];         // normalised quaternion
  T qnorm;         // |q| clamped at 1e-12
  bool qclamped;
  T s[3];          // scales
  T M[9];          // Rg diag(s)
  T cov3[9];       // M M^T
  T JW[6];         // J R
  T a, b, c, det;  // 2D covariance (+ eps2d) and its determinant
  T radius;
  T ext[2];
};

template <typename T>
inline bool all_finite(const T* x, int n) {
  for (int i = 0; i < n; ++i)
    if (!std::isfinite(x[i])) return false;
  return true;
}

template <typename T>
void project_one(const Camera<T>& cam, const T* mean, const T* quat, const T* scale, T opacity, Projection<T>& P) {
  for (int i = 0; i < 3; ++i)
    P.p[i] = cam.R[3 * i] * mean[0] + cam.R[3 * i + 1] * mean[1] + cam.R[3 * i + 2] * mean[2] + cam.t[i];
  const bool finite = all_finite(P.p, 3) && all_finite(scale, 3) && all_finite(quat, 4);
  const T tz = P.p[2];
  P.keep = false;
  if (!(finite && tz > cam.near_plane && tz < cam.far_plane)) return;
  P.u = P.p[0] / tz;
  P.v = P.p[1] / tz;
  const T ux = std::min(std::max(P.u, -cam.lim_x_neg), cam.lim_x_pos);
  const T vy = std::min(std::max(P.v, -cam.lim_y_neg), cam.lim_y_pos);
  P.clamp_x = ux != P.u;
  P.clamp_y = vy != P.v;
  P.tx = tz * ux;
  P.ty = tz * vy;
  P.J[0] = cam.fx / tz;
  P.J[1] = 0;
  P.J[2] = -cam.fx * P.tx / (tz * tz);
  P.J[3] = 0;
  P.J[4] = cam.fy / tz;
  P.J[5] = -cam.fy * P.ty / (tz * tz);

  const T n = std::sqrt(quat[0] * quat[0] + quat[1] * quat[1] + quat[2] * quat[2] + quat[3] * quat[3]);
  P.qclamped = !(n > T(1e-12));
  P.qnorm = P.qclamped ? T(1e-12) : n;
  for (int i = 0; i < 4; ++i) P.qn[i] = quat[i] / P.qnorm;
  const T w = P.qn[0], x = P.qn[1], y = P.qn[2], z = P.qn[3];
  T* R = P.Rg;
  R[0] = 1 - 2 * (y * y + z * z);
  R[1] = 2 * (x * y - w * z);
  R[2] = 2 * (x * z + w * y);
  R[3] = 2 * (x * y + w * z);
  R[4] = 1 - 2 * (x * x + z * z);
  R[5] = 2 * (y * z - w * x);
  R[6] = 2 * (x * z - w * y);
  R[7] = 2 * (y * z + w * x);
  R[8] = 1 - 2 * (x * x + y * y);
  for (int i = 0; i < 3; ++i) P.s[i] = scale[i];
  for (int i = 0; i < 3; ++i)
    for (int j = 0; j < 3; ++j) P.M[3 * i + j] = R[3 * i + j] * P.s[j];
  for (int i = 0; i < 3; ++i)
    for (int j = 0; j < 3; ++j)
      P.cov3[3 * i + j] = P.M[3 * i] * P.M[3 * j] + P.M[3 * i + 1] * P.M[3 * j + 1] + P.M[3 * i + 2] * P.M[3 * j + 2];
  for (int i = 0; i < 2; ++i)
    for (int j = 0; j < 3; ++j)
      P.JW[3 * i + j] = P.J[3 * i] * cam.R[j] + P.J[3 * i + 1] * cam.R[3 + j] + P.J[3 * i + 2] * cam.R[6 + j];
  // cov2 = JW cov3 JW^T: only (0,0), (0,1), (1,1) are used
  T tmp[6];  // JW cov3
  for (int i = 0; i < 2; ++i)
    for (int j = 0; j < 3; ++j)
      tmp[3 * i + j] = P.JW[3 * i] * P.cov3[j] + P.JW[3 * i + 1] * P.cov3[3 + j] + P.JW[3 * i + 2] * P.cov3[6 + j];
  const T c00 = tmp[0] * P.JW[0] + tmp[1] * P.JW[1] + tmp[2] * P.JW[2];
  const T c01 = tmp[0] * P.JW[3] + tmp[1] * P.JW[4] + tmp[2] * P.JW[5];
  const T c11 = tmp[3] * P.JW[3] + tmp[4] * P.JW[4] + tmp[5] * P.JW[5];
  P.a = c00 + cam.eps2d;
  P.b = c01;
  P.c = c11 + cam.eps2d;
  P.det = P.a * P.c - P.b * P.b;
  if (!(P.det > 0 && std::isfinite(P.det))) return;

  const T mx = cam.fx * P.p[0] / tz + cam.cx, my = cam.fy * P.p[1] / tz + cam.cy;
  const T mid = T(0.5) * (P.a + P.c);
  const T lam = mid + std::sqrt(std::max(mid * mid - P.det, T(0.1)));
  T radius = std::ceil(T(3) * std::sqrt(std::max(lam, T(0))));
  if (!std::isfinite(radius)) radius = 0;
  radius = std::min(radius, T(1e7));
  const T k = std::sqrt(T(2) * std::log(std::max(T(255) * opacity, T(1))));
  for (int i = 0; i < 2; ++i) {
    T e = std::ceil(k * std::sqrt(std::max(i == 0 ? P.a : P.c, T(0))));
    if (!std::isfinite(e)) e = 0;
    P.ext[i] = std::min(e, T(1e7));
  }
  const bool on_screen = mx + P.ext[0] > 0 && mx - P.ext[0] < T(cam.width) && my + P.ext[1] > 0 &&
                         my - P.ext[1] < T(cam.height) && P.ext[0] > 0 && P.ext[1] > 0;
  P.radius = radius;
  P.keep = on_screen && static_cast<int32_t>(radius) > 0;
}

// Real SH basis values up to degree 3 at unit direction d: out[16].
template <typename T>
inline void sh_basis(int degree, T x, T y, T z, T* out) {
  out[0] = T(SH_C0);
  if (degree < 1) return;
  out[1] = -T(SH_C1) * y;
  out[2] = T(SH_C1) * z;
  out[3] = -T(SH_C1) * x;
  if (degree < 2) return;
  const T xx = x * x, yy = y * y, zz = z * z, xy = x * y, yz = y * z, xz = x * z;
  out[4] = T(SH_C2[0]) * xy;
  out[5] = T(SH_C2[1]) * yz;
  out[6] = T(SH_C2[2]) * (T(2) * zz - xx - yy);
  out[7] = T(SH_C2[3]) * xz;
  out[8] = T(SH_C2[4]) * (xx - yy);
  if (degree < 3) return;
  out[9] = T(SH_C3[0]) * y * (T(3) * xx - yy);
  out[10] = T(SH_C3[1]) * xy * z;
  out[11] = T(SH_C3[2]) * y * (T(4) * zz - xx - yy);
  out[12] = T(SH_C3[3]) * z * (T(2) * zz - T(3) * xx - T(3) * yy);
  out[13] = T(SH_C3[4]) * x * (T(4) * zz - xx - yy);
  out[14] = T(SH_C3[5]) * z * (xx - yy);
  out[15] = T(SH_C3[6]) * x * (xx - T(3) * yy);
}

// d(basis_k)/d(x, y, z) for k = 1 .. 15: grad[3 * k + axis] (k = 0 has none).
template <typename T>
inline void sh_basis_grad(int degree, T x, T y, T z, T* g) {
  std::fill(g, g + 48, T(0));
  if (degree < 1) return;
  g[3 * 1 + 1] = -T(SH_C1);
  g[3 * 2 + 2] = T(SH_C1);
  g[3 * 3 + 0] = -T(SH_C1);
  if (degree < 2) return;
  const T xx = x * x, yy = y * y, zz = z * z;
  g[3 * 4 + 0] = T(SH_C2[0]) * y, g[3 * 4 + 1] = T(SH_C2[0]) * x;
  g[3 * 5 + 1] = T(SH_C2[1]) * z, g[3 * 5 + 2] = T(SH_C2[1]) * y;
  g[3 * 6 + 0] = -T(2 * SH_C2[2]) * x, g[3 * 6 + 1] = -T(2 * SH_C2[2]) * y, g[3 * 6 + 2] = T(4 * SH_C2[2]) * z;
  g[3 * 7 + 0] = T(SH_C2[3]) * z, g[3 * 7 + 2] = T(SH_C2[3]) * x;
  g[3 * 8 + 0] = T(2 * SH_C2[4]) * x, g[3 * 8 + 1] = -T(2 * SH_C2[4]) * y;
  if (degree < 3) return;
  g[3 * 9 + 0] = T(SH_C3[0]) * T(6) * x * y, g[3 * 9 + 1] = T(SH_C3[0]) * T(3) * (xx - yy);
  g[3 * 10 + 0] = T(SH_C3[1]) * y * z, g[3 * 10 + 1] = T(SH_C3[1]) * x * z, g[3 * 10 + 2] = T(SH_C3[1]) * x * y;
  g[3 * 11 + 0] = -T(SH_C3[2]) * T(2) * x * y, g[3 * 11 + 1] = T(SH_C3[2]) * (T(4) * zz - xx - T(3) * yy),
             g[3 * 11 + 2] = T(SH_C3[2]) * T(8) * y * z;
  g[3 * 12 + 0] = -T(SH_C3[3]) * T(6) * x * z, g[3 * 12 + 1] = -T(SH_C3[3]) * T(6) * y * z,
             g[3 * 12 + 2] = T(SH_C3[3]) * (T(6) * zz - T(3) * xx - T(3) * yy);
  g[3 * 13 + 0] = T(SH_C3[4]) * (T(4) * zz - T(3) * xx - yy), g[3 * 13 + 1] = -T(SH_C3[4]) * T(2) * x * y,
             g[3 * 13 + 2] = T(SH_C3[4]) * T(8) * x * z;
  g[3 * 14 + 0] = T(SH_C3[5]) * T(2) * x * z, g[3 * 14 + 1] = -T(SH_C3[5]) * T(2) * y * z,
             g[3 * 14 + 2] = T(SH_C3[5]) * (xx - yy);
  g[3 * 15 + 0] = T(SH_C3[6]) * T(3) * (xx - yy), g[3 * 15 + 1] = -T(SH_C3[6]) * T(6) * x * y;
}

// Unit view direction from the camera centre to the mean (zero for non-finite means).
template <typename T>
inline bool view_dir(const Camera<T>& cam, const T* mean, T* d, T& norm) {
  for (int i = 0; i < 3; ++i) d[i] = mean[i] - cam.campos[i];
  if (!all_finite(d, 3)) {
    d[0] = d[1] = d[2] = 0;
  }
  const T n = std::sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2]);
  const bool clamped = !(n > T(1e-12));
  norm = clamped ? T(1e-12) : n;
  for (int i = 0; i < 3; ++i) d[i] /= norm;
  return clamped;
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
  const auto dt = means.scalar_type();
  TORCH_CHECK(quats.scalar_type() == dt && scales.scalar_type() == dt && opacities.scalar_type() == dt &&
                  sh.scalar_type() == dt,
              "means, quats, scales, opacities and sh must share one dtype");
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
  auto means2d = at::zeros({N, 2}, opts);
  auto conics = at::zeros({N, 3}, opts);
  auto depths = at::ones({N}, opts);
  auto colors = at::empty({N, 3}, opts);
  auto radii = at::zeros({N}, opts.dtype(at::kInt));
  auto extents = at::zeros({N, 2}, opts);
  AT_DISPATCH_FLOATING_TYPES(means.scalar_type(), "metegs_project_forward", [&] {
    using T = scalar_t;
    const auto cam = make_camera<T>(viewmat, K, campos, width, height, near_plane, far_plane, eps2d);
    const T *mp = means.data_ptr<T>(), *qp = quats.data_ptr<T>(), *sp = scales.data_ptr<T>();
    const T *op = opacities.data_ptr<T>(), *shp = sh.data_ptr<T>();
    T *m2 = means2d.data_ptr<T>(), *co = conics.data_ptr<T>(), *de = depths.data_ptr<T>();
    T *col = colors.data_ptr<T>(), *ex = extents.data_ptr<T>();
    int32_t* ra = radii.data_ptr<int32_t>();
    const int deg = static_cast<int>(sh_degree);
    const int nb = (deg + 1) * (deg + 1);
    metegs::parallel_for(0, N, 512, [&](int64_t begin, int64_t end) {
      Projection<T> P;
      T basis[16], d[3], dn;
      for (int64_t g = begin; g < end; ++g) {
        project_one(cam, mp + 3 * g, qp + 4 * g, sp + 3 * g, op[g], P);
        if (P.keep) {
          const T tz = P.p[2];
          m2[2 * g] = cam.fx * P.p[0] / tz + cam.cx;
          m2[2 * g + 1] = cam.fy * P.p[1] / tz + cam.cy;
          co[3 * g] = P.c / P.det;
          co[3 * g + 1] = -P.b / P.det;
          co[3 * g + 2] = P.a / P.det;
          de[g] = tz;
          ra[g] = static_cast<int32_t>(P.radius);
          ex[2 * g] = P.ext[0];
          ex[2 * g + 1] = P.ext[1];
        }
        view_dir(cam, mp + 3 * g, d, dn);
        sh_basis(deg, d[0], d[1], d[2], basis);
        const T* c = shp + g * KS * 3;
        for (int ch = 0; ch < 3; ++ch) {
          T v = 0;
          for (int k = 0; k < nb; ++k) v += basis[k] * c[3 * k + ch];
          v += T(0.5);
          col[3 * g + ch] = v > T(0) ? v : T(0);
        }
      }
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
  // every element is written below (zeros for culled Gaussians and for SH bands above sh_degree): no fill
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
    const int deg = static_cast<int>(sh_degree);
    const int nb = (deg + 1) * (deg + 1);
    metegs::parallel_for(0, N, 512, [&](int64_t begin, int64_t end) {
      Projection<T> P;
      T basis[16], bgrad[48], d[3], dn;
      for (int64_t g = begin; g < end; ++g) {
        // ---- colours: d colour / d (sh, direction) ----
        const bool dclamped = view_dir(cam, mp + 3 * g, d, dn);
        sh_basis(deg, d[0], d[1], d[2], basis);
        const T* c = shp + g * KS * 3;
        T gc[3];
        bool any = false;
        for (int ch = 0; ch < 3; ++ch) {
          T v = 0;
          for (int k = 0; k < nb; ++k) v += basis[k] * c[3 * k + ch];
          v += T(0.5);
          gc[ch] = v >= T(0) ? gcol[3 * g + ch] : T(0);  // clamp_min(0) passes the gradient at v >= 0
          any = any || gc[ch] != T(0);
        }
        T* osh = ogsh + g * KS * 3;
        for (int k = 0; k < nb; ++k)
          for (int ch = 0; ch < 3; ++ch) osh[3 * k + ch] = basis[k] * gc[ch];
        std::fill(osh + 3 * nb, osh + 3 * KS, T(0));
        T gmean[3] = {0, 0, 0};
        if (any && deg > 0) {
          sh_basis_grad(deg, d[0], d[1], d[2], bgrad);
          T gd[3] = {0, 0, 0};
          for (int k = 1; k < nb; ++k) {
            const T w = c[3 * k] * gc[0] + c[3 * k + 1] * gc[1] + c[3 * k + 2] * gc[2];
            for (int i = 0; i < 3; ++i) gd[i] += w * bgrad[3 * k + i];
          }
          const T dot = dclamped ? T(0) : d[0] * gd[0] + d[1] * gd[1] + d[2] * gd[2];
          T raw[3];
          for (int i = 0; i < 3; ++i) raw[i] = mp[3 * g + i] - cam.campos[i];
          if (all_finite(raw, 3))
            for (int i = 0; i < 3; ++i) gmean[i] = (gd[i] - d[i] * dot) / dn;
        }

        // ---- geometry ----
        project_one(cam, mp + 3 * g, qp + 4 * g, sp + 3 * g, op[g], P);
        if (P.keep) {
          const T tz = P.p[2], tz2 = tz * tz;
          T gp[3] = {0, 0, 0};
          // means2d and depth
          gp[0] += cam.fx / tz * gm2[2 * g];
          gp[1] += cam.fy / tz * gm2[2 * g + 1];
          T gtz = -cam.fx * P.p[0] / tz2 * gm2[2 * g] - cam.fy * P.p[1] / tz2 * gm2[2 * g + 1] + gde[g];
          // conic (c/det, -b/det, a/det) -> (a, b, c), in double and written with the ratios a/det, b/det,
          // c/det, 1/det (bounded by about 1/eps2d and 1/eps2d^2): the products a*a, a*c, b*b, c*c and det*det of
          // the textbook form overflow (float32: det*det from det ~ 2e19, a*a near 3e38, giving inf/inf = NaN)
          // for huge Gaussians whose forward is still finite. Same chain as the torch reference's autograd,
          // d(x/det) = dx/det - (x/det)/det d(det) with d(det) = c da + a dc - 2 b db, and the same det
          // (the forward's, in T), so the normal regime is unchanged up to rounding.
          const double A = gco[3 * g], B = gco[3 * g + 1], C = gco[3 * g + 2];
          const double det = P.det, id = 1.0 / det, ia = double(P.a) / det, ib = double(P.b) / det,
                       ic = double(P.c) / det;
          const double ga_d = -A * (ic * ic) + B * (ib * ic) + C * (id - ia * ic);
          const double gb_d = A * (2.0 * ib * ic) - B * (id + 2.0 * ib * ib) + C * (2.0 * ia * ib);
          const double gc_d = A * (id - ic * ia) + B * (ib * ia) - C * (ia * ia);
          const T ga = T(ga_d), gb = T(gb_d), gcv = T(gc_d);
          // cov2 = JW cov3 JW^T with dL/dcov2 = V (symmetric form: V01 = V10 = gb / 2)
          const T V[4] = {ga, T(0.5) * gb, T(0.5) * gb, gcv};
          // dL/dJW = 2 V JW cov3 ; dL/dcov3 = JW^T V JW
          T JWc[6];
          for (int i = 0; i < 2; ++i)
            for (int j = 0; j < 3; ++j)
              JWc[3 * i + j] =
                  P.JW[3 * i] * P.cov3[j] + P.JW[3 * i + 1] * P.cov3[3 + j] + P.JW[3 * i + 2] * P.cov3[6 + j];
          T gJW[6];
          for (int i = 0; i < 2; ++i)
            for (int j = 0; j < 3; ++j) gJW[3 * i + j] = T(2) * (V[2 * i] * JWc[j] + V[2 * i + 1] * JWc[3 + j]);
          T gcov3[9];
          for (int i = 0; i < 3; ++i)
            for (int j = 0; j < 3; ++j) {
              T acc = 0;
              for (int r = 0; r < 2; ++r)
                for (int s2 = 0; s2 < 2; ++s2) acc += P.JW[3 * r + i] * V[2 * r + s2] * P.JW[3 * s2 + j];
              gcov3[3 * i + j] = acc;
            }
          // cov3 = M M^T -> dL/dM = 2 gcov3 M (gcov3 symmetric)
          T gM[9];
          for (int i = 0; i < 3; ++i)
            for (int j = 0; j < 3; ++j)
              gM[3 * i + j] = T(2) * (gcov3[3 * i] * P.M[j] + gcov3[3 * i + 1] * P.M[3 + j] + gcov3[3 * i + 2] * P.M[6 + j]);
          // M = Rg diag(s)
          T G[9];
          for (int i = 0; i < 3; ++i)
            for (int j = 0; j < 3; ++j) G[3 * i + j] = gM[3 * i + j] * P.s[j];
          for (int j = 0; j < 3; ++j)
            ogs[3 * g + j] = gM[j] * P.Rg[j] + gM[3 + j] * P.Rg[3 + j] + gM[6 + j] * P.Rg[6 + j];
          const T w = P.qn[0], x = P.qn[1], y = P.qn[2], z = P.qn[3];
          T gqn[4];
          gqn[0] = T(2) * (-z * G[1] + y * G[2] + z * G[3] - x * G[5] - y * G[6] + x * G[7]);
          gqn[1] = T(2) * (y * G[1] + z * G[2] + y * G[3] - T(2) * x * G[4] - w * G[5] + z * G[6] + w * G[7] -
                           T(2) * x * G[8]);
          gqn[2] = T(2) * (-T(2) * y * G[0] + x * G[1] + w * G[2] + x * G[3] + z * G[5] - w * G[6] + z * G[7] -
                           T(2) * y * G[8]);
          gqn[3] = T(2) * (-T(2) * z * G[0] - w * G[1] + x * G[2] + w * G[3] - T(2) * z * G[4] + y * G[5] +
                           x * G[6] + y * G[7]);
          const T qdot = P.qclamped ? T(0) : w * gqn[0] + x * gqn[1] + y * gqn[2] + z * gqn[3];
          for (int i = 0; i < 4; ++i) ogq[4 * g + i] = (gqn[i] - P.qn[i] * qdot) / P.qnorm;
          // JW = J R -> dL/dJ = dL/dJW R^T (only J00, J02, J11, J12 depend on the mean)
          T gJ[6];
          for (int i = 0; i < 2; ++i)
            for (int j = 0; j < 3; ++j)
              gJ[3 * i + j] = gJW[3 * i] * cam.R[3 * j] + gJW[3 * i + 1] * cam.R[3 * j + 1] + gJW[3 * i + 2] * cam.R[3 * j + 2];
          const T tz3 = tz2 * tz;
          gtz += -cam.fx / tz2 * gJ[0] + T(2) * cam.fx * P.tx / tz3 * gJ[2] - cam.fy / tz2 * gJ[4] +
                 T(2) * cam.fy * P.ty / tz3 * gJ[5];
          const T gtx = -cam.fx / tz2 * gJ[2], gty = -cam.fy / tz2 * gJ[5];
          // tx = tz * clamp(px / tz): = px inside the limits, tz * limit outside
          if (P.clamp_x)
            gtz += gtx * (P.tx / tz);
          else
            gp[0] += gtx;
          if (P.clamp_y)
            gtz += gty * (P.ty / tz);
          else
            gp[1] += gty;
          gp[2] += gtz;
          for (int j = 0; j < 3; ++j) gmean[j] += cam.R[j] * gp[0] + cam.R[3 + j] * gp[1] + cam.R[6 + j] * gp[2];
        } else {
          std::fill(ogq + 4 * g, ogq + 4 * g + 4, T(0));
          std::fill(ogs + 3 * g, ogs + 3 * g + 3, T(0));
        }
        for (int j = 0; j < 3; ++j) ogm[3 * g + j] = gmean[j];
      }
    });
  });
  return {gm, gq, gs, gsh};
}

}  // namespace metegs_cpu
