// ssim.cpp: the SSIM map of the 3DGS training loss (zero-padded 'same' Gaussian windows; reference:
// metegs.eval.metrics.ssim_map(..., crop_border=False)) and its backward with respect to the first image.
//
// Each way is two separable passes over the pixels (horizontal blur of every row, then vertical blur with the
// pointwise maths), where the torch reference runs about thirty ops and keeps their intermediates for autograd.
// The forward keeps the three partial derivatives of the map with respect to the blurred statistics that depend on
// x (mean, E[x^2], E[xy]); the backward weighs them by the incoming gradient and blurs them back: the window is
// symmetric and zero-padded, so the blur is its own adjoint.
#include "metegs_cpu.h"

namespace metegs_cpu {
namespace {

// out[i] = sum_k g[k] in[i + (k - K/2) stride] over a row of n values (n / stride pixels of `stride` channels),
// zero outside the row. Taps are added in the order k = 0..K-1, as torch's convolution does.
template <typename T>
inline void blur_row(const T* in, T* out, int64_t n, int64_t stride, const T* g, int64_t K) {
  const int64_t r = K / 2;
  std::fill(out, out + n, T(0));
  for (int64_t k = 0; k < K; ++k) {
    const int64_t shift = (k - r) * stride;
    const int64_t lo = std::max<int64_t>(0, -shift), hi = std::min<int64_t>(n, n - shift);
    const T w = g[k];
    for (int64_t i = lo; i < hi; ++i) out[i] += w * in[i + shift];
  }
}

// acc[s n + i] = sum_k g[k] rows[s plane + (image_row0 + y + k - K/2) n + i] for the `planes` planes of horizontally
// blurred rows, over the rows of one image (H rows from image_row0), zero outside it.
template <typename T>
inline void blur_column(const T* rows, T* acc, int64_t planes, int64_t plane, int64_t image_row0, int64_t y,
                        int64_t H, int64_t n, const T* g, int64_t K) {
  const int64_t r = K / 2;
  std::fill(acc, acc + planes * n, T(0));
  for (int64_t k = 0; k < K; ++k) {
    const int64_t src = y + k - r;
    if (src < 0 || src >= H) continue;
    const T w = g[k];
    for (int64_t s = 0; s < planes; ++s) {
      const T* in = rows + s * plane + (image_row0 + src) * n;
      T* a = acc + s * n;
      for (int64_t i = 0; i < n; ++i) a[i] += w * in[i];
    }
  }
}

void check_images(const at::Tensor& x, const at::Tensor& y, const at::Tensor& window) {
  TORCH_CHECK(x.dim() == 4, "ssim: images must be [B, H, W, C], got ", x.sizes());
  TORCH_CHECK(x.sizes() == y.sizes(), "ssim: shapes differ, ", x.sizes(), " vs ", y.sizes());
  TORCH_CHECK(x.is_cpu() && y.is_cpu(), "ssim: CPU tensors only");
  TORCH_CHECK(x.scalar_type() == y.scalar_type(), "ssim: dtypes differ");
  TORCH_CHECK(window.dim() == 1 && window.numel() % 2 == 1, "ssim: the window must be 1D with an odd length");
}

constexpr int64_t ROWS_PER_CHUNK = 4;

}  // namespace

std::vector<at::Tensor> ssim_forward(at::Tensor x, at::Tensor y, at::Tensor window, double c1, double c2) {
  check_images(x, y, window);
  x = x.contiguous(), y = y.contiguous(), window = window.to(x.scalar_type()).contiguous();
  const int64_t B = x.size(0), H = x.size(1), C = x.size(3), n = x.size(2) * C, K = window.numel();
  const int64_t plane = B * H * n;
  auto rows = at::empty({5, B * H, n}, x.options());  // horizontally blurred x, y, x^2, y^2, xy
  auto map = at::empty_like(x);
  auto partials = at::empty({3, B, H, x.size(2), C}, x.options());  // dS/dmean_x, dS/dE[x^2], dS/dE[xy]
  AT_DISPATCH_FLOATING_TYPES(x.scalar_type(), "metegs_ssim_forward", [&] {
    const scalar_t *px = x.data_ptr<scalar_t>(), *py = y.data_ptr<scalar_t>(), *g = window.data_ptr<scalar_t>();
    scalar_t *t = rows.data_ptr<scalar_t>(), *out = map.data_ptr<scalar_t>(), *d = partials.data_ptr<scalar_t>();
    metegs::parallel_for(0, B * H, ROWS_PER_CHUNK, [&](int64_t begin, int64_t end) {
      std::vector<scalar_t> prod(n);
      for (int64_t row = begin; row < end; ++row) {
        const scalar_t *xr = px + row * n, *yr = py + row * n;
        blur_row(xr, t + row * n, n, C, g, K);
        blur_row(yr, t + plane + row * n, n, C, g, K);
        for (int64_t i = 0; i < n; ++i) prod[i] = xr[i] * xr[i];
        blur_row(prod.data(), t + 2 * plane + row * n, n, C, g, K);
        for (int64_t i = 0; i < n; ++i) prod[i] = yr[i] * yr[i];
        blur_row(prod.data(), t + 3 * plane + row * n, n, C, g, K);
        for (int64_t i = 0; i < n; ++i) prod[i] = xr[i] * yr[i];
        blur_row(prod.data(), t + 4 * plane + row * n, n, C, g, K);
      }
    });
    const scalar_t k1 = scalar_t(c1), k2 = scalar_t(c2);
    metegs::parallel_for(0, B * H, ROWS_PER_CHUNK, [&](int64_t begin, int64_t end) {
      std::vector<scalar_t> acc(5 * n);
      for (int64_t row = begin; row < end; ++row) {
        blur_column(t, acc.data(), 5, plane, row - row % H, row % H, H, n, g, K);
        const scalar_t *mx = acc.data(), *my = mx + n, *exx = my + n, *eyy = exx + n, *exy = eyy + n;
        scalar_t *s_out = out + row * n, *d_mu = d + row * n, *d_xx = d_mu + plane, *d_xy = d_xx + plane;
        for (int64_t i = 0; i < n; ++i) {
          const scalar_t a1 = 2 * mx[i] * my[i] + k1, a2 = 2 * (exy[i] - mx[i] * my[i]) + k2;
          const scalar_t b1 = mx[i] * mx[i] + my[i] * my[i] + k1;
          const scalar_t b2 = (exx[i] - mx[i] * mx[i]) + (eyy[i] - my[i] * my[i]) + k2;
          const scalar_t den = b1 * b2, s = (a1 * a2) / den;
          s_out[i] = s;
          // S = a1 a2 / (b1 b2) with a1(mean_x), a2(E[xy], mean_x), b1(mean_x), b2(E[x^2], mean_x)
          d_mu[i] = 2 * my[i] * (a2 - a1) / den - 2 * mx[i] * s * (1 / b1 - 1 / b2);
          d_xx[i] = -s / b2;
          d_xy[i] = 2 * a1 / den;
        }
      }
    });
  });
  return {map, partials};
}

at::Tensor ssim_backward(at::Tensor x, at::Tensor y, at::Tensor window, at::Tensor partials, at::Tensor g_map) {
  check_images(x, y, window);
  TORCH_CHECK(g_map.sizes() == x.sizes(), "ssim_backward: g_map must have the images' shape");
  TORCH_CHECK(partials.dim() == 5 && partials.size(0) == 3 && partials.numel() == 3 * x.numel(),
              "ssim_backward: partials must be [3, B, H, W, C] from ssim_forward");
  x = x.contiguous(), y = y.contiguous(), window = window.to(x.scalar_type()).contiguous();
  partials = partials.to(x.scalar_type()).contiguous(), g_map = g_map.to(x.scalar_type()).contiguous();
  const int64_t B = x.size(0), H = x.size(1), C = x.size(3), n = x.size(2) * C, K = window.numel();
  const int64_t plane = B * H * n;
  auto rows = at::empty({3, B * H, n}, x.options());
  auto g_x = at::empty_like(x);
  AT_DISPATCH_FLOATING_TYPES(x.scalar_type(), "metegs_ssim_backward", [&] {
    const scalar_t *px = x.data_ptr<scalar_t>(), *py = y.data_ptr<scalar_t>(), *g = window.data_ptr<scalar_t>();
    const scalar_t *d = partials.data_ptr<scalar_t>(), *gm = g_map.data_ptr<scalar_t>();
    scalar_t *t = rows.data_ptr<scalar_t>(), *out = g_x.data_ptr<scalar_t>();
    metegs::parallel_for(0, B * H, ROWS_PER_CHUNK, [&](int64_t begin, int64_t end) {
      std::vector<scalar_t> prod(n);
      for (int64_t row = begin; row < end; ++row) {
        const scalar_t* gr = gm + row * n;
        for (int64_t s = 0; s < 3; ++s) {
          const scalar_t* dr = d + s * plane + row * n;
          for (int64_t i = 0; i < n; ++i) prod[i] = gr[i] * dr[i];
          blur_row(prod.data(), t + s * plane + row * n, n, C, g, K);
        }
      }
    });
    metegs::parallel_for(0, B * H, ROWS_PER_CHUNK, [&](int64_t begin, int64_t end) {
      std::vector<scalar_t> acc(3 * n);
      for (int64_t row = begin; row < end; ++row) {
        blur_column(t, acc.data(), 3, plane, row - row % H, row % H, H, n, g, K);
        const scalar_t *b_mu = acc.data(), *b_xx = b_mu + n, *b_xy = b_xx + n;
        const scalar_t *xr = px + row * n, *yr = py + row * n;
        scalar_t* o = out + row * n;
        for (int64_t i = 0; i < n; ++i) o[i] = b_mu[i] + 2 * xr[i] * b_xx[i] + yr[i] * b_xy[i];
      }
    });
  });
  return g_x;
}

}  // namespace metegs_cpu
