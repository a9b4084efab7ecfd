// Tile compositing for the metegs `cpu` rasteriser: forward and hand-written backward.
//
// Same semantics as metegs.render.torch_backend.composite_tiles (3DGS rules): per 16x16 tile, the
// tile's Gaussians front to back; pixel centre (x + 0.5, y + 0.5);
//   power = -0.5 (a dx^2 + c dy^2) - b dx dy,  alpha = min(0.99, o exp(min(power, 0))),
// skipped when alpha < 1/255; a pixel stops before the Gaussian that would take T below 1e-4.
//
// Layout (the design that measured fastest on CPU, see shared/research/cpu-rasteriser.md): threads
// take whole tiles from a shared counter (dynamic scheduling on metegs::parallel_for's pool, pool.h,
// sized by torch's intra-op thread count); inside a tile the Gaussians are the outer loop and the 256 pixels the inner,
// branch-free, vectorised loop (with a polynomial exp for float32). The forward saves per pixel
// the final transmittance and the number of list entries it used; the backward walks back to
// front from that state, recovering T_i = T_{i+1} / (1 - alpha_i) (alpha <= 0.99, so stable).
// Gradients are written per intersection (tile, list position) — every slot has one owner, so no
// atomics — and then summed per Gaussian in list order. Deterministic.
//
// Built with -ffp-contract=off so that the forward and the backward recompute bit-identical alphas
// (the skip decision alpha >= 1/255 must agree) and the operation order matches the torch code.

#include "metegs_cpu.h"

#include <ATen/Parallel.h>

#include <algorithm>
#include <atomic>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <limits>
#include <vector>

namespace metegs_cpu {
namespace {

constexpr int TS = TILE;
constexpr int TP = TS * TS;   // pixels per tile
constexpr int NGRAD = 7;      // per-intersection geometry gradients: mx, my, a, b, c, opacity, depth

template <typename scalar_t>
struct Consts {
  static constexpr scalar_t alpha_max = scalar_t(0.99);
  static constexpr scalar_t alpha_min = scalar_t(1.0 / 255.0);
  static constexpr scalar_t t_min = scalar_t(1e-4);
};

// exp(x) for x <= 0. float: Cephes-style range reduction + degree-6 polynomial (about 1 ulp),
// branch-free so that GCC vectorises the pixel loop; double: libm (used for gradcheck).
// The float argument is clamped at -20: exp(-20) = 2e-9 is far below alpha_min / o for any opacity
// o <= 1 (every alpha below 1/255 is skipped, so the clamp changes no output or gradient), and
// without it most pixels of a small Gaussian's rows produce subnormal floats (exp(-87) = 2^-126),
// whose arithmetic is many times slower than normal floats.
template <typename scalar_t>
inline __attribute__((always_inline)) scalar_t neg_exp(scalar_t x);

template <>
inline __attribute__((always_inline)) float neg_exp<float>(float x) {
  x = x < -20.0f ? -20.0f : x;
  // round(x / ln 2) with the 1.5 * 2^23 trick (exact for |x / ln 2| < 2^22; no -ffast-math here).
  const float t = x * 1.44269504088896341f + 12582912.0f;
  const float n = t - 12582912.0f;
  float r = x - n * 0.693359375f;
  r = r - n * -2.12194440e-4f;
  float p = 1.9875691500e-4f;
  p = p * r + 1.3981999507e-3f;
  p = p * r + 8.3334519073e-3f;
  p = p * r + 4.1665795894e-2f;
  p = p * r + 1.6666665459e-1f;
  p = p * r + 5.0000001201e-1f;
  const float y = p * (r * r) + r + 1.0f;
  const int32_t bits = (static_cast<int32_t>(n) + 127) << 23;  // n in [-126, 0]: a normal 2^n
  float scale;
  std::memcpy(&scale, &bits, sizeof(float));
  return y * scale;
}

template <>
inline __attribute__((always_inline)) double neg_exp<double>(double x) {
  return std::exp(x);
}

// One Gaussian's alpha at one pixel centre, the single definition used by forward and backward so that
// both compute it bit-identically (the skip decision alpha >= 1/255 must agree).
template <typename scalar_t>
struct PixelAlpha {
  scalar_t dx, dy, power, e, oe, alpha;  // offset, exponent, exp(min(power, 0)), o e, min(o e, alpha_max)
};

template <typename scalar_t>
inline __attribute__((always_inline)) PixelAlpha<scalar_t> pixel_alpha(scalar_t px, scalar_t py, scalar_t mx,
                                                                       scalar_t my, scalar_t a, scalar_t b,
                                                                       scalar_t c, scalar_t o) {
  PixelAlpha<scalar_t> r;
  r.dx = px - mx;
  r.dy = py - my;
  r.power = scalar_t(-0.5) * ((a * r.dx * r.dx) + (c * r.dy * r.dy)) - (b * r.dx) * r.dy;
  r.e = neg_exp<scalar_t>(r.power < scalar_t(0) ? r.power : scalar_t(0));
  r.oe = o * r.e;
  r.alpha = r.oe < Consts<scalar_t>::alpha_max ? r.oe : Consts<scalar_t>::alpha_max;
  return r;
}

// Pixel range [pbeg, pend) of a tile (whole rows, row-major) outside which a Gaussian's alpha stays
// below 1/255 (h: its row_half_height). Skipping the other rows changes nothing (their alpha would be
// skipped) and saves most of the work of Gaussians smaller than a tile.
template <typename scalar_t>
inline void row_range(scalar_t my, double h, int64_t y0, int& pbeg, int& pend) {
  pbeg = 0;
  pend = TP;
  if (!(h < std::numeric_limits<double>::infinity())) return;
  const double lo = std::ceil(double(my) - h - 0.5) - double(y0);
  const double hi = std::floor(double(my) + h - 0.5) - double(y0) + 1.0;
  const int r0 = static_cast<int>(std::min(std::max(lo, 0.0), double(TS)));
  const int r1 = static_cast<int>(std::min(std::max(hi, 0.0), double(TS)));
  pbeg = r0 * TS;
  pend = std::max(r1, r0) * TS;
}

// Runs `worker` once per intra-op thread (at::get_num_threads()); workers pull tiles from a shared counter, and a
// worker that starts late finds none left (the caller may already have run its share, pool.h).
template <typename F>
void run_on_threads(F&& worker) {
  const int64_t nt = std::max<int64_t>(1, at::get_num_threads());
  metegs::parallel_for(0, nt, 1, [&](int64_t begin, int64_t end) {
    for (int64_t i = begin; i < end; ++i) worker();
  });
}

// Colour channels as a compile-time constant (DC > 0: the pixel loops carry the colours in registers)
// or a run-time one (DC == 0: one extra pass over the pixels per channel).
template <int DC>
inline int64_t channels(int64_t D) {
  return DC > 0 ? DC : D;
}

template <typename scalar_t, int DC>
void forward_kernel(const scalar_t* __restrict__ means2d, const scalar_t* __restrict__ conics,
                    const scalar_t* __restrict__ opac, const scalar_t* __restrict__ colors,
                    const scalar_t* __restrict__ depths, const int64_t* __restrict__ ids,
                    const int64_t* __restrict__ offsets, const double* __restrict__ rows, int64_t D_,
                    int64_t tiles_x, int64_t tiles_y, int64_t W, int64_t H, scalar_t* __restrict__ out_color,
                    scalar_t* __restrict__ out_alpha,
                    scalar_t* __restrict__ out_depth, scalar_t* __restrict__ out_T,
                    int32_t* __restrict__ out_last) {
  using C = Consts<scalar_t>;
  const int64_t D = channels<DC>(D_);
  const int64_t ntiles = tiles_x * tiles_y;
  std::atomic<int64_t> next{0};
  run_on_threads([&]() {
    // Masks are kept as 0/1 floating-point values and every branch is a select: GCC only
    // vectorises the pixel loop in that form.
    alignas(64) scalar_t px[TP], py[TP], T[TP], dep[TP], w[TP], done[TP];
    alignas(64) int32_t last[TP];
    std::vector<scalar_t> colbuf(std::max<int64_t>(D, 3) * TP);
    scalar_t* __restrict__ col = colbuf.data();  // [D][TP]
    scalar_t* __restrict__ col0 = col;
    scalar_t* __restrict__ col1 = col + TP;
    scalar_t* __restrict__ col2 = col + 2 * TP;
    for (;;) {
      const int64_t t = next.fetch_add(1, std::memory_order_relaxed);
      if (t >= ntiles) break;
      const int64_t x0 = (t % tiles_x) * TS, y0 = (t / tiles_x) * TS;
      for (int p = 0; p < TP; ++p) {
        const int64_t x = x0 + (p % TS), y = y0 + (p / TS);
        px[p] = static_cast<scalar_t>(x) + scalar_t(0.5);
        py[p] = static_cast<scalar_t>(y) + scalar_t(0.5);
        T[p] = scalar_t(1);
        dep[p] = scalar_t(0);
        last[p] = 0;
        done[p] = (x < W && y < H) ? scalar_t(0) : scalar_t(1);  // padding pixels never composite
      }
      std::fill(col, col + D * TP, scalar_t(0));
      const int64_t off = offsets[t];
      const int64_t n = offsets[t + 1] - off;
      for (int64_t j = 0; j < n; ++j) {
        const int64_t g = ids[off + j];
        const scalar_t mx = means2d[2 * g], my = means2d[2 * g + 1];
        const scalar_t a = conics[3 * g], b = conics[3 * g + 1], c = conics[3 * g + 2];
        const scalar_t o = opac[g], z = depths[g];
        const scalar_t c0 = DC == 3 ? colors[3 * g] : scalar_t(0);
        const scalar_t c1 = DC == 3 ? colors[3 * g + 1] : scalar_t(0);
        const scalar_t c2 = DC == 3 ? colors[3 * g + 2] : scalar_t(0);
        const int32_t jp1 = static_cast<int32_t>(j + 1);
        int pbeg, pend;
        row_range(my, rows[g], y0, pbeg, pend);
#pragma omp simd
        for (int p = pbeg; p < pend; ++p) {
          const scalar_t alpha = pixel_alpha(px[p], py[p], mx, my, a, b, c, o).alpha;
          const scalar_t valid = alpha >= C::alpha_min ? scalar_t(1) - done[p] : scalar_t(0);
          const scalar_t Tn = T[p] * (scalar_t(1) - alpha);
          const scalar_t stop = Tn < C::t_min ? valid : scalar_t(0);  // T would fall below T_MIN
          const scalar_t contrib = valid - stop;
          const scalar_t wv = contrib * (alpha * T[p]);
          dep[p] += wv * z;
          T[p] = contrib > scalar_t(0.5) ? Tn : T[p];
          last[p] = contrib > scalar_t(0.5) ? jp1 : last[p];
          done[p] += stop;
          if constexpr (DC == 3) {
            col0[p] += wv * c0;
            col1[p] += wv * c1;
            col2[p] += wv * c2;
          } else {
            w[p] = wv;
          }
        }
        if constexpr (DC != 3) {
          for (int64_t d = 0; d < D; ++d) {
            const scalar_t cd = colors[g * D + d];
            scalar_t* __restrict__ cr = col + d * TP;
#pragma omp simd
            for (int p = pbeg; p < pend; ++p) cr[p] += w[p] * cd;
          }
        }
        if ((j & 7) == 7) {  // whole-tile early exit
          scalar_t nd = 0;
#pragma omp simd reduction(+ : nd)
          for (int p = 0; p < TP; ++p) nd += done[p];
          if (nd >= scalar_t(TP)) break;
        }
      }
      for (int p = 0; p < TP; ++p) {
        out_T[t * TP + p] = T[p];
        out_last[t * TP + p] = last[p];
        const int64_t x = x0 + (p % TS), y = y0 + (p / TS);
        if (x >= W || y >= H) continue;
        const int64_t pix = y * W + x;
        out_alpha[pix] = scalar_t(1) - T[p];
        out_depth[pix] = dep[p];
        for (int64_t d = 0; d < D; ++d) out_color[pix * D + d] = col[d * TP + p];
      }
    }
  });
}

template <typename scalar_t, int DC>
void backward_kernel(const scalar_t* __restrict__ means2d, const scalar_t* __restrict__ conics,
                     const scalar_t* __restrict__ opac, const scalar_t* __restrict__ colors,
                     const scalar_t* __restrict__ depths, const int64_t* __restrict__ ids,
                     const int64_t* __restrict__ offsets, const scalar_t* __restrict__ saved_T,
                     const int32_t* __restrict__ saved_last, const scalar_t* __restrict__ g_color,
                     const scalar_t* __restrict__ g_alpha, const scalar_t* __restrict__ g_depth,
                     const double* __restrict__ rows, int64_t D_, int64_t tiles_x, int64_t tiles_y, int64_t W,
                     int64_t H,
                     scalar_t* __restrict__ out) {
  using C = Consts<scalar_t>;
  const int64_t D = channels<DC>(D_);
  const int64_t ntiles = tiles_x * tiles_y;
  const int64_t stride = NGRAD + D;
  std::atomic<int64_t> next{0};
  run_on_threads([&]() {
    alignas(64) scalar_t px[TP], py[TP], T[TP], Tf[TP], gA[TP], gD[TP], restZ[TP], s[TP], av[TP], w[TP];
    alignas(64) int32_t last[TP];
    const int64_t Dbuf = std::max<int64_t>(D, 3);
    std::vector<scalar_t> buf(2 * Dbuf * TP);
    scalar_t* __restrict__ gC = buf.data();                 // [D][TP] dL/dcolor image
    scalar_t* __restrict__ restC = buf.data() + Dbuf * TP;  // [D][TP] colour behind
    const scalar_t* __restrict__ gC0 = gC;
    const scalar_t* __restrict__ gC1 = gC + TP;
    const scalar_t* __restrict__ gC2 = gC + 2 * TP;
    scalar_t* __restrict__ rC0 = restC;
    scalar_t* __restrict__ rC1 = restC + TP;
    scalar_t* __restrict__ rC2 = restC + 2 * TP;
    for (;;) {
      const int64_t t = next.fetch_add(1, std::memory_order_relaxed);
      if (t >= ntiles) break;
      const int64_t off = offsets[t];
      const int64_t n = offsets[t + 1] - off;
      if (n == 0) continue;
      const int64_t x0 = (t % tiles_x) * TS, y0 = (t / tiles_x) * TS;
      int32_t jmax = 0;
      for (int p = 0; p < TP; ++p) jmax = std::max(jmax, saved_last[t * TP + p]);
      // list entries no pixel reached get zero gradients
      std::fill(out + (off + jmax) * stride, out + (off + n) * stride, scalar_t(0));
      for (int p = 0; p < TP; ++p) {
        const int64_t x = x0 + (p % TS), y = y0 + (p / TS);
        px[p] = static_cast<scalar_t>(x) + scalar_t(0.5);
        py[p] = static_cast<scalar_t>(y) + scalar_t(0.5);
        T[p] = Tf[p] = saved_T[t * TP + p];
        last[p] = saved_last[t * TP + p];
        restZ[p] = scalar_t(0);
        const bool in = x < W && y < H;
        const int64_t pix = in ? y * W + x : 0;
        gA[p] = in ? g_alpha[pix] : scalar_t(0);
        gD[p] = in ? g_depth[pix] : scalar_t(0);
        for (int64_t d = 0; d < D; ++d) {
          gC[d * TP + p] = in ? g_color[pix * D + d] : scalar_t(0);
          restC[d * TP + p] = scalar_t(0);
        }
      }
      for (int64_t j = static_cast<int64_t>(jmax) - 1; j >= 0; --j) {
        const int64_t g = ids[off + j];
        const scalar_t mx = means2d[2 * g], my = means2d[2 * g + 1];
        const scalar_t a = conics[3 * g], b = conics[3 * g + 1], c = conics[3 * g + 2];
        const scalar_t o = opac[g], z = depths[g];
        const scalar_t* __restrict__ cg = colors + g * D;
        const scalar_t c0 = DC == 3 ? cg[0] : scalar_t(0);
        const scalar_t c1 = DC == 3 ? cg[1] : scalar_t(0);
        const scalar_t c2 = DC == 3 ? cg[2] : scalar_t(0);
        const int32_t jj = static_cast<int32_t>(j);
        int pbeg, pend;
        row_range(my, rows[g], y0, pbeg, pend);
        if constexpr (DC != 3) {
          // s = sum_d (c_d - colour composited behind) * dL/dC_d: needs no alpha of this Gaussian.
#pragma omp simd
          for (int p = pbeg; p < pend; ++p) s[p] = scalar_t(0);
          for (int64_t d = 0; d < D; ++d) {
            const scalar_t cd = cg[d];
            const scalar_t* __restrict__ gc = gC + d * TP;
            const scalar_t* __restrict__ rc = restC + d * TP;
#pragma omp simd
            for (int p = pbeg; p < pend; ++p) s[p] += (cd - rc[p]) * gc[p];
          }
        }
        scalar_t gmx = 0, gmy = 0, ga = 0, gb = 0, gc_ = 0, go = 0, gz = 0, gk0 = 0, gk1 = 0, gk2 = 0;
#pragma omp simd reduction(+ : gmx, gmy, ga, gb, gc_, go, gz, gk0, gk1, gk2)
        for (int p = pbeg; p < pend; ++p) {
          const auto pa = pixel_alpha(px[p], py[p], mx, my, a, b, c, o);
          const scalar_t dx = pa.dx, dy = pa.dy, power = pa.power, e = pa.e, oe = pa.oe, alpha = pa.alpha;
          const scalar_t listed = jj < last[p] ? scalar_t(1) : scalar_t(0);
          const scalar_t valid = alpha >= C::alpha_min ? listed : scalar_t(0);
          const scalar_t inv_om = scalar_t(1) / (scalar_t(1) - alpha);  // alpha <= 0.99
          const scalar_t Tdiv = T[p] * inv_om;
          const scalar_t Tj = valid > scalar_t(0.5) ? Tdiv : T[p];  // transmittance in front of it
          const scalar_t a_v = valid * alpha;
          const scalar_t wv = a_v * Tj;
          scalar_t sp;
          if constexpr (DC == 3) {
            sp = (c0 - rC0[p]) * gC0[p];
            sp += (c1 - rC1[p]) * gC1[p];
            sp += (c2 - rC2[p]) * gC2[p];
          } else {
            sp = s[p];
          }
          // d(colour, depth)/dalpha = T_j (c - behind); d(1 - T_final)/dalpha = T_final / (1 - alpha)
          const scalar_t dLda = Tj * (sp + (z - restZ[p]) * gD[p]) + gA[p] * Tf[p] * inv_om;
          const scalar_t unclamped = oe <= C::alpha_max ? valid : scalar_t(0);
          const scalar_t dLdoe = unclamped > scalar_t(0.5) ? dLda : scalar_t(0);
          go += dLdoe * e;
          const scalar_t dLdpow = power <= scalar_t(0) ? dLdoe * oe : scalar_t(0);
          ga += dLdpow * (scalar_t(-0.5) * dx * dx);
          gc_ += dLdpow * (scalar_t(-0.5) * dy * dy);
          gb += dLdpow * (-dx * dy);
          gmx += dLdpow * (a * dx + b * dy);  // dpower/dmx = -dpower/ddx
          gmy += dLdpow * (c * dy + b * dx);
          gz += wv * gD[p];
          restZ[p] = restZ[p] * (scalar_t(1) - a_v) + a_v * z;
          T[p] = Tj;
          if constexpr (DC == 3) {
            gk0 += wv * gC0[p];
            gk1 += wv * gC1[p];
            gk2 += wv * gC2[p];
            rC0[p] = rC0[p] * (scalar_t(1) - a_v) + a_v * c0;
            rC1[p] = rC1[p] * (scalar_t(1) - a_v) + a_v * c1;
            rC2[p] = rC2[p] * (scalar_t(1) - a_v) + a_v * c2;
          } else {
            av[p] = a_v;
            w[p] = wv;
          }
        }
        scalar_t* __restrict__ o_row = out + (off + j) * stride;
        o_row[0] = gmx;
        o_row[1] = gmy;
        o_row[2] = ga;
        o_row[3] = gb;
        o_row[4] = gc_;
        o_row[5] = go;
        o_row[6] = gz;
        if constexpr (DC == 3) {
          o_row[NGRAD] = gk0;
          o_row[NGRAD + 1] = gk1;
          o_row[NGRAD + 2] = gk2;
        } else {
          for (int64_t d = 0; d < D; ++d) {
            const scalar_t cd = cg[d];
            const scalar_t* __restrict__ gc = gC + d * TP;
            scalar_t* __restrict__ rc = restC + d * TP;
            scalar_t gcol = 0;
#pragma omp simd reduction(+ : gcol)
            for (int p = pbeg; p < pend; ++p) {
              gcol += w[p] * gc[p];
              rc[p] = rc[p] * (scalar_t(1) - av[p]) + av[p] * cd;
            }
            o_row[NGRAD + d] = gcol;
          }
        }
      }
    }
  });
}

// Checks the inputs shared by forward and backward and makes them contiguous in place.
void prepare_inputs(at::Tensor& means2d, at::Tensor& conics, at::Tensor& opac, at::Tensor& colors,
                    at::Tensor& depths, at::Tensor& ids, at::Tensor& offsets, int64_t tiles_x, int64_t tiles_y) {
  const auto N = means2d.size(0);
  TORCH_CHECK(means2d.device().is_cpu(), "metegs cpu composite: tensors must be on the CPU");
  TORCH_CHECK(means2d.dim() == 2 && means2d.size(1) == 2, "means2d must be [N, 2]");
  TORCH_CHECK(conics.dim() == 2 && conics.size(0) == N && conics.size(1) == 3, "conics must be [N, 3]");
  TORCH_CHECK(opac.dim() == 1 && opac.size(0) == N, "opacities must be [N]");
  TORCH_CHECK(colors.dim() == 2 && colors.size(0) == N, "colors must be [N, D]");
  TORCH_CHECK(depths.dim() == 1 && depths.size(0) == N, "depths must be [N]");
  const auto dt = means2d.scalar_type();
  TORCH_CHECK(conics.scalar_type() == dt && opac.scalar_type() == dt && colors.scalar_type() == dt &&
                  depths.scalar_type() == dt,
              "means2d, conics, opacities, colors and depths must share one dtype");
  TORCH_CHECK(ids.scalar_type() == at::kLong && offsets.scalar_type() == at::kLong,
              "gaussian_ids and offsets must be int64");
  TORCH_CHECK(offsets.dim() == 1 && offsets.size(0) == tiles_x * tiles_y + 1, "offsets must be [tiles + 1]");
  TORCH_CHECK(ids.numel() < (int64_t(1) << 31), "too many intersections for int32 list positions");
  for (at::Tensor* t : {&means2d, &conics, &opac, &colors, &depths, &ids, &offsets}) *t = t->contiguous();
}

// The [N] float64 row half-heights: those bin_tiles gave (checked), else computed here from the conics
// and opacities (callers with other tile lists).
at::Tensor resolve_rows(const c10::optional<at::Tensor>& rows, const at::Tensor& conics, const at::Tensor& opac) {
  const int64_t N = conics.size(0);
  if (rows.has_value() && rows->defined()) {
    TORCH_CHECK(rows->dim() == 1 && rows->size(0) == N && rows->scalar_type() == at::kDouble,
                "rows must be the [N] float64 row half-heights of bin_tiles");
    return rows->contiguous();
  }
  auto out = at::empty({N}, conics.options().dtype(at::kDouble));
  double* h = out.data_ptr<double>();
  AT_DISPATCH_FLOATING_TYPES(conics.scalar_type(), "metegs_row_half_heights", [&] {
    const scalar_t *c = conics.data_ptr<scalar_t>(), *o = opac.data_ptr<scalar_t>();
    metegs::parallel_for(0, N, 1024, [&](int64_t begin, int64_t end) {
      for (int64_t g = begin; g < end; ++g) h[g] = row_half_height(c[3 * g], c[3 * g + 1], c[3 * g + 2], o[g]);
    });
  });
  return out;
}

}  // namespace

std::vector<at::Tensor> composite_forward(at::Tensor means2d, at::Tensor conics, at::Tensor opac,
                                          at::Tensor colors, at::Tensor depths, at::Tensor ids,
                                          at::Tensor offsets, int64_t tiles_x, int64_t tiles_y, int64_t width,
                                          int64_t height, c10::optional<at::Tensor> rows) {
  prepare_inputs(means2d, conics, opac, colors, depths, ids, offsets, tiles_x, tiles_y);
  const at::Tensor row_h = resolve_rows(rows, conics, opac);
  TORCH_CHECK(width <= tiles_x * TS && height <= tiles_y * TS, "image larger than the tile grid");
  const int64_t D = colors.size(1);
  const auto opts = means2d.options();
  auto color = at::zeros({height, width, D}, opts);
  auto alpha = at::zeros({height, width}, opts);
  auto depth = at::zeros({height, width}, opts);
  auto T = at::empty({tiles_x * tiles_y, TP}, opts);
  auto last = at::empty({tiles_x * tiles_y, TP}, opts.dtype(at::kInt));
  AT_DISPATCH_FLOATING_TYPES(means2d.scalar_type(), "metegs_composite_forward", [&] {
    auto run = [&](auto kernel) {
      kernel(means2d.data_ptr<scalar_t>(), conics.data_ptr<scalar_t>(), opac.data_ptr<scalar_t>(),
             colors.data_ptr<scalar_t>(), depths.data_ptr<scalar_t>(), ids.data_ptr<int64_t>(),
             offsets.data_ptr<int64_t>(), row_h.data_ptr<double>(), D, tiles_x, tiles_y, width, height,
             color.data_ptr<scalar_t>(), alpha.data_ptr<scalar_t>(), depth.data_ptr<scalar_t>(),
             T.data_ptr<scalar_t>(), last.data_ptr<int32_t>());
    };
    if (D == 3) run(forward_kernel<scalar_t, 3>);
    else run(forward_kernel<scalar_t, 0>);
  });
  return {color, alpha, depth, T, last};
}

// Returns the per-Gaussian gradients (means2d [N, 2], conics [N, 3], opacities [N], colours [N, D], depths [N]),
// each the sum of its Gaussian's per-intersection gradients.
std::vector<at::Tensor> composite_backward(at::Tensor means2d, at::Tensor conics, at::Tensor opac, at::Tensor colors,
                                           at::Tensor depths, at::Tensor ids, at::Tensor offsets, at::Tensor saved_T,
                                           at::Tensor saved_last, at::Tensor g_color, at::Tensor g_alpha,
                                           at::Tensor g_depth, int64_t tiles_x, int64_t tiles_y, int64_t width,
                                           int64_t height, c10::optional<at::Tensor> rows) {
  prepare_inputs(means2d, conics, opac, colors, depths, ids, offsets, tiles_x, tiles_y);
  const int64_t D = colors.size(1);
  const auto dt = means2d.scalar_type();
  TORCH_CHECK(g_color.sizes() == at::IntArrayRef({height, width, D}) && g_color.scalar_type() == dt,
              "grad color must be [H, W, D] of the input dtype");
  TORCH_CHECK(g_alpha.sizes() == at::IntArrayRef({height, width}) && g_alpha.scalar_type() == dt,
              "grad alpha must be [H, W]");
  TORCH_CHECK(g_depth.sizes() == at::IntArrayRef({height, width}) && g_depth.scalar_type() == dt,
              "grad depth must be [H, W]");
  TORCH_CHECK(saved_T.numel() == tiles_x * tiles_y * TP && saved_last.scalar_type() == at::kInt,
              "bad saved forward state");
  saved_T = saved_T.contiguous();
  saved_last = saved_last.contiguous();
  g_color = g_color.contiguous();
  g_alpha = g_alpha.contiguous();
  g_depth = g_depth.contiguous();
  const int64_t N = means2d.size(0), M = ids.size(0), S = NGRAD + D;
  const at::Tensor row_h = resolve_rows(rows, conics, opac);
  auto per_isect = at::empty({M, S}, means2d.options());
  const auto opts = means2d.options();
  std::vector<at::Tensor> outs = {at::zeros({N, 2}, opts), at::zeros({N, 3}, opts), at::zeros({N}, opts),
                                  at::zeros({N, D}, opts), at::zeros({N}, opts)};
  AT_DISPATCH_FLOATING_TYPES(dt, "metegs_composite_backward", [&] {
    auto run = [&](auto kernel) {
      kernel(means2d.data_ptr<scalar_t>(), conics.data_ptr<scalar_t>(), opac.data_ptr<scalar_t>(),
             colors.data_ptr<scalar_t>(), depths.data_ptr<scalar_t>(), ids.data_ptr<int64_t>(),
             offsets.data_ptr<int64_t>(), saved_T.data_ptr<scalar_t>(), saved_last.data_ptr<int32_t>(),
             g_color.data_ptr<scalar_t>(), g_alpha.data_ptr<scalar_t>(), g_depth.data_ptr<scalar_t>(),
             row_h.data_ptr<double>(), D,
             tiles_x, tiles_y, width, height, per_isect.data_ptr<scalar_t>());
    };
    if (D == 3) run(backward_kernel<scalar_t, 3>);
    else run(backward_kernel<scalar_t, 0>);
    // Reduce the intersections to their Gaussians, one output tensor per task (no two threads share a
    // cache line), each summed in list order: deterministic.
    const int64_t first[5] = {0, 2, 5, 7, 6};  // per_isect column of each output's first column
    const int64_t* __restrict__ idp = ids.data_ptr<int64_t>();
    const scalar_t* __restrict__ src = per_isect.data_ptr<scalar_t>();
    metegs::parallel_for(0, 5, 1, [&](int64_t begin, int64_t end) {
      for (int64_t k = begin; k < end; ++k) {
        const int64_t w = outs[k].numel() / std::max<int64_t>(N, 1), c0 = first[k];
        scalar_t* __restrict__ dst = outs[k].data_ptr<scalar_t>();
        for (int64_t m = 0; m < M; ++m) {
          scalar_t* __restrict__ row = dst + idp[m] * w;
          const scalar_t* __restrict__ r = src + m * S + c0;
          for (int64_t c = 0; c < w; ++c) row[c] += r[c];
        }
      }
    });
  });
  return outs;
}

}  // namespace metegs_cpu
