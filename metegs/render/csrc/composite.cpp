// Tile compositing for the metegs `cpu` rasteriser: forward and hand-written backward.
//
// Same semantics as metegs.render.torch_backend.composite_tiles (3DGS rules): per 16x16 tile, the
// tile's Gaussians front to back; pixel centre (x + 0.5, y + 0.5);
//   power = -0.5 (a dx^2 + c dy^2) - b dx dy,  alpha = min(0.99, o exp(min(power, 0))),
// skipped when alpha < 1/255; a pixel stops before the Gaussian that would take T below 1e-4.
//
// Layout (the design that measured fastest on CPU, see shared/research/cpu-rasteriser.md): threads
// take whole tiles from a shared counter (dynamic scheduling on metegs::parallel_for's pool, pool.h,
// sized by torch's intra-op thread count); inside a tile the Gaussians are the outer loop and the tile's
// rows the inner one, each row of 16 pixels one vector (GCC vector extensions: one AVX-512 register for
// float32, two AVX2 ones elsewhere) with a polynomial exp for float32. Per Gaussian, the column terms of the
// conic's quadratic form (a dx^2, b dx) are computed once and each row adds its own (c dy^2, dy), and the
// backward's sums stay in vector registers until the Gaussian's last row. The forward saves per pixel the
// final transmittance and the number of list entries it used; the backward walks back to front from that
// state, recovering T_i = T_{i+1} / (1 - alpha_i) (alpha <= 0.99, so stable), and skips the rows whose pixels
// all stopped before the Gaussian. What lies behind a Gaussian (colours and depth composited after it) enters
// the gradients only through its dot product with the image gradients, so the backward carries that one sum
// per pixel instead of one per channel. Gradients are written per intersection (tile, list position) — every
// slot has one owner, so no atomics — and then summed per Gaussian over two fixed halves of the list, each in
// list order. Deterministic, and the same for any thread count.
// Each op first gathers every Gaussian's inputs into one 64-byte record (Packed) and prefetches the records a
// few list entries ahead: the lists visit Gaussians in scattered order, and those loads were the largest
// stall (benchmarks/ab_kernels.py: 1.3x forward, 1.2x backward at 20k Gaussians, 300x200, 1 thread).
//
// Built with -ffp-contract=off so that the forward and the backward recompute bit-identical alphas
// (the skip decision alpha >= 1/255 must agree): multiply-adds are fused only where written (fmadd), the
// same way in both, and the alpha itself comes from the one function both use (row_alpha).

#include "metegs_cpu.h"

#include <ATen/Parallel.h>

#include <algorithm>
#include <atomic>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <limits>
#include <memory>
#include <type_traits>
#include <vector>

namespace metegs_cpu {
namespace {

constexpr int TS = TILE;
constexpr int TP = TS * TS;   // pixels per tile
constexpr int NGRAD = 7;      // per-intersection geometry gradients: mx, my, a, b, c, opacity, depth
static_assert(TS == 16, "a tile row is one 16-lane vector");

// A tile row: 16 lanes of scalar_t (Vec) and the lane masks / integers of the same width (Mask, MaskInt); VecN
// (metegs_cpu.h) is one GCC vector with AVX-512, else a Split of native vectors.
template <typename scalar_t>
using Vec = typename VecN<scalar_t, TS>::type;
template <typename scalar_t>
using MaskInt = std::conditional_t<sizeof(scalar_t) == 4, int32_t, int64_t>;
template <typename scalar_t>
using Mask = typename VecN<MaskInt<scalar_t>, TS>::type;
using I32 = VecN<int32_t, TS>::type;  // a tile row of the saved list lengths

template <typename V, typename S>
inline __attribute__((always_inline)) V splat(S s) {
  return V{} + s;
}

// Sum of the N lanes of v by halving (log2 N vector additions), always in the same order: deterministic.
template <typename S, int N>
inline __attribute__((always_inline)) S hsum(typename VecN<S, N>::type v) {
  if constexpr (N == 2) {
    return v[0] + v[1];
  } else {
    typename VecN<S, N / 2>::type lo, hi;
    std::memcpy(&lo, &v, sizeof(lo));
    std::memcpy(&hi, reinterpret_cast<const char*>(&v) + sizeof(lo), sizeof(hi));
    return hsum<S, N / 2>(lo + hi);
  }
}

template <typename scalar_t>
inline __attribute__((always_inline)) scalar_t row_sum(Vec<scalar_t> v) {
  return hsum<scalar_t, TS>(v);
}

// One level of a transposing reduction tree: x and y each hold partial sums in blocks of 2H lanes; the result
// holds, per block, the sums of x's two halves (H lanes) and then those of y's. 16 / (2H) blocks.
template <int H>
inline __attribute__((always_inline)) Vec<float> fold(Vec<float> x, Vec<float> y) {
  I32 lo, hi;
  for (int l = 0; l < TS; ++l) {
    const int block = l / (2 * H) * (2 * H), from_y = (l % (2 * H)) / H, k = l % H;
    lo[l] = 16 * from_y + block + k;
    hi[l] = 16 * from_y + block + H + k;
  }
#if !METEGS_AVX512
  {
    constexpr int P = Vec<float>::P;
    Vec<float> r;
    if constexpr (H >= P) {  // whole parts: lane l * P of the result sums parts of x or y
      for (int q = 0; q < Vec<float>::K; ++q) {
        const Vec<float>& src = lo[q * P] >= 16 ? y : x;
        r.p[q] = src.p[(lo[q * P] % 16) / P] + src.p[(hi[q * P] % 16) / P];
      }
    } else {  // blocks inside a part: the same shuffle on each pair of parts
      typedef int32_t PartIdx __attribute__((vector_size(P * sizeof(int32_t))));
      PartIdx plo, phi;
      for (int l = 0; l < P; ++l) {
        const int block = l / (2 * H) * (2 * H), from_y = (l % (2 * H)) / H, k = l % H;
        plo[l] = P * from_y + block + k;
        phi[l] = P * from_y + block + H + k;
      }
      for (int q = 0; q < Vec<float>::K; ++q)
        r.p[q] = __builtin_shuffle(x.p[q], y.p[q], plo) + __builtin_shuffle(x.p[q], y.p[q], phi);
    }
    return r;
  }
#else
  return __builtin_shuffle(x, y, lo) + __builtin_shuffle(x, y, hi);
#endif
}

// The lane sums of v[0..9] as lanes 0..9 of one vector (lanes 10..15: 0), by four levels of `fold` (16 -> 8 ->
// 4 -> 2 -> 1 partial sums per input): about 35 shuffles and adds instead of 10 separate 16-lane reductions
// (about 80). Fixed order: deterministic.
inline __attribute__((always_inline)) Vec<float> row_sums10(const Vec<float> (&v)[10]) {
  const Vec<float> z{};
  const Vec<float> c0 = fold<4>(fold<8>(v[0], v[1]), fold<8>(v[2], v[3]));
  const Vec<float> c1 = fold<4>(fold<8>(v[4], v[5]), fold<8>(v[6], v[7]));
  const Vec<float> c2 = fold<4>(fold<8>(v[8], v[9]), z);
  const Vec<float> e = fold<1>(fold<2>(c0, c1), fold<2>(c2, z));
  // lane i of e holds input bitreverse4(i); the same permutation puts input k in lane k
  constexpr int order[TS] = {0, 8, 4, 12, 2, 10, 6, 14, 1, 9, 5, 13, 3, 11, 7, 15};
#if !METEGS_AVX512
  Vec<float> r;
  for (int l = 0; l < TS; ++l) r[l] = e[order[l]];
  return r;
#else
  I32 idx;
  for (int l = 0; l < TS; ++l) idx[l] = order[l];
  return __builtin_shuffle(e, idx);
#endif
}

template <typename scalar_t>
struct Consts {
  static constexpr scalar_t alpha_max = scalar_t(0.99);
  static constexpr scalar_t alpha_min = scalar_t(1.0 / 255.0);
  static constexpr scalar_t t_min = scalar_t(1e-4);
};

// a * b + c per lane, rounded once where the CPU fuses it (fmadd16: float32 with AVX-512, or AVX2 with FMA), else
// rounded twice. Forward and backward compute their alphas with the same calls (row_alpha), so they agree bit
// for bit either way; the rest of the file is built with -ffp-contract=off and fuses nothing on its own.
inline __attribute__((always_inline)) Vec<float> fmadd(Vec<float> a, Vec<float> b, Vec<float> c) {
  return fmadd16(a, b, c);
}

inline __attribute__((always_inline)) Vec<double> fmadd(Vec<double> a, Vec<double> b, Vec<double> c) {
  return a * b + c;  // float64 serves the gradient checks, not speed
}

// exp(x) for x <= 0, per lane. float: Cephes-style range reduction + degree-6 polynomial (about 1 ulp),
// branch-free; double: libm lane by lane (used for gradcheck).
// The float argument is clamped at -20: exp(-20) = 2e-9 is far below alpha_min / o for any opacity
// o <= 1 (every alpha below 1/255 is skipped, so the clamp changes no output or gradient), and
// without it most pixels of a small Gaussian's rows produce subnormal floats (exp(-87) = 2^-126),
// whose arithmetic is many times slower than normal floats.
inline __attribute__((always_inline)) Vec<float> neg_exp(Vec<float> x) {
  using V = Vec<float>;
  const V lo = splat<V>(-20.0f);
  x = select(x < lo, lo, x);
  // round(x / ln 2) with the 1.5 * 2^23 trick (exact for |x / ln 2| < 2^22; no -ffast-math here).
  const V t = fmadd(x, splat<V>(1.44269504088896341f), splat<V>(12582912.0f));
  const V n = t - 12582912.0f;
  V r = fmadd(n, splat<V>(-0.693359375f), x);
  r = fmadd(n, splat<V>(2.12194440e-4f), r);
  // p(r) = (e^r - 1 - r) / r^2 by Estrin's scheme (three multiply-add levels instead of Horner's five: the
  // compositing row loops wait on this chain)
  const V r2 = r * r;
  const V pa = fmadd(splat<V>(1.9875691500e-4f), r, splat<V>(1.3981999507e-3f));
  const V pb = fmadd(splat<V>(8.3334519073e-3f), r, splat<V>(4.1665795894e-2f));
  const V pc = fmadd(splat<V>(1.6666665459e-1f), r, splat<V>(5.0000001201e-1f));
  const V p = fmadd(fmadd(pa, r2, pb), r2, pc);
  const V y = fmadd(p, r2, r + 1.0f);
#if METEGS_AVX512
  return (V)_mm512_scalef_ps((__m512)y, (__m512)n);  // y 2^n
#else
  const Mask<float> bits = (convert<Mask<float>>(n) + 127) << 23;  // n in [-29, 0]: a normal 2^n
  return y * bitcast<V>(bits);
#endif
}

inline __attribute__((always_inline)) Vec<double> neg_exp(Vec<double> x) {
  for (int i = 0; i < TS; ++i) x[i] = std::exp(x[i]);
  return x;
}

// 1 / x per lane for x in [0.01, 1] (1 - alpha). AVX-512: the 14-bit estimate and one Newton step (relative
// error about 1e-7, well under the gradients' tolerance; a division stalls the backward's row loop); else 1 / x.
inline __attribute__((always_inline)) Vec<float> recip(Vec<float> x) {
#if METEGS_AVX512
  const Vec<float> r = (Vec<float>)_mm512_rcp14_ps((__m512)x);
  return fmadd(r, fmadd(-x, r, splat<Vec<float>>(1.0f)), r);  // r + r (1 - x r)
#else
  return 1.0f / x;
#endif
}

inline __attribute__((always_inline)) Vec<double> recip(Vec<double> x) {
  return 1.0 / x;
}

// One Gaussian's alphas on one tile row, the single definition used by forward and backward so that both
// compute them bit-identically (the skip decision alpha >= 1/255 must agree). adx2 = (a dx) dx and
// bdx = b dx are the Gaussian's column terms; dy the row's offset from its centre.
template <typename scalar_t>
struct RowAlpha {
  Vec<scalar_t> power, e, oe, alpha;  // exponent, exp(min(power, 0)), o e, min(o e, alpha_max)
};

template <typename scalar_t>
inline __attribute__((always_inline)) RowAlpha<scalar_t> row_alpha(Vec<scalar_t> adx2, Vec<scalar_t> bdx,
                                                                   scalar_t dy, scalar_t c, scalar_t o) {
  using V = Vec<scalar_t>;
  const V zero = V{}, amax = splat<V>(Consts<scalar_t>::alpha_max);
  RowAlpha<scalar_t> r;
  r.power = scalar_t(-0.5) * (adx2 + (c * dy) * dy) - bdx * dy;
  r.e = neg_exp(select(r.power < zero, r.power, zero));
  r.oe = o * r.e;
  r.alpha = select(r.oe < amax, r.oe, amax);
  return r;
}

// One Gaussian's compositing inputs in one cache line. The tile lists visit each Gaussian in many tiles, in
// scattered order; gathering its fields once per call into a record makes each visit one cache line instead of
// five arrays (and the row span two integers instead of a floor, a ceiling and two clamps in double).
// row0, row1: the image rows [row0, row1) outside which its alpha stays below 1/255 (from rows[g], its
// row_half_height; the whole int32 range when that is infinite or not a number). Skipping the other rows
// changes nothing (their alpha would be skipped) and saves most of the work of Gaussians smaller than a tile.
template <typename scalar_t>
struct alignas(64) Packed {
  scalar_t mx, my, a, b, c, o, z;
  scalar_t col[3];  // colours when D == 3
  int32_t row0, row1;
};

// How many list entries ahead the kernels prefetch a Gaussian's record: the lists visit the records in
// scattered order (no hardware prefetch), and a record may come from the L3 cache (~20k Gaussians fill L2).
constexpr int64_t PREFETCH = 8;

template <typename scalar_t>
std::vector<Packed<scalar_t>> pack_gaussians(const scalar_t* means2d, const scalar_t* conics, const scalar_t* opac,
                                             const scalar_t* colors, const scalar_t* depths, const double* rows,
                                             int64_t N, int64_t D) {
  std::vector<Packed<scalar_t>> out(N);
  constexpr double lim = 1 << 30;
  metegs::parallel_for(0, N, 2048, [&](int64_t begin, int64_t end) {
    for (int64_t g = begin; g < end; ++g) {
      Packed<scalar_t>& P = out[g];
      P.mx = means2d[2 * g], P.my = means2d[2 * g + 1];
      P.a = conics[3 * g], P.b = conics[3 * g + 1], P.c = conics[3 * g + 2];
      P.o = opac[g], P.z = depths[g];
      for (int d = 0; d < 3; ++d) P.col[d] = D == 3 ? colors[3 * g + d] : scalar_t(0);
      const double h = rows[g];
      const double lo = std::ceil(double(P.my) - h - 0.5), hi = std::floor(double(P.my) + h - 0.5) + 1.0;
      if (!(h < std::numeric_limits<double>::infinity())) {
        P.row0 = -(1 << 30), P.row1 = 1 << 30;  // no culling
      } else if (lo == lo && hi == hi) {
        P.row0 = static_cast<int32_t>(std::min(std::max(lo, -lim), lim));
        P.row1 = static_cast<int32_t>(std::min(std::max(hi, -lim), lim));
      } else {
        P.row0 = P.row1 = 0;  // a mean that is not a number: no rows
      }
    }
  });
  return out;
}

// The tile rows [r0, r1) of a Gaussian's row span (tile top row y0).
template <typename scalar_t>
inline __attribute__((always_inline)) void row_range(const Packed<scalar_t>& P, int64_t y0, int& r0, int& r1) {
  const int64_t lo = int64_t(P.row0) - y0, hi = int64_t(P.row1) - y0;
  r0 = static_cast<int>(std::min<int64_t>(std::max<int64_t>(lo, 0), TS));
  r1 = std::max(r0, static_cast<int>(std::min<int64_t>(std::max<int64_t>(hi, 0), TS)));
}

// Runs `worker` once per kernel thread (metegs::num_threads(), pool.h); workers pull tiles from a shared counter, and a
// worker that starts late finds none left (the caller may already have run its share, pool.h).
template <typename F>
void run_on_threads(F&& worker) {
  const int64_t nt = metegs::num_threads();
  metegs::parallel_for(0, nt, 1, [&](int64_t begin, int64_t end) {
    for (int64_t i = begin; i < end; ++i) worker();
  });
}

// Colour channels as a compile-time constant (DC > 0: the row loops carry the colours in registers)
// or a run-time one (DC == 0: one extra pass over the rows per channel).
template <int DC>
inline int64_t channels(int64_t D) {
  return DC > 0 ? DC : D;
}

// The column offsets x0 + c + 0.5 of a tile (c = 0..15).
template <typename scalar_t>
inline Vec<scalar_t> column_centres(int64_t x0) {
  Vec<scalar_t> v;
  for (int c = 0; c < TS; ++c) v[c] = static_cast<scalar_t>(x0 + c) + scalar_t(0.5);
  return v;
}

// The n values at src as the lanes [0, n) of a vector, zeros in the others (float: load_first; else n = 16 is
// one unaligned load).
template <typename V, typename S>
inline __attribute__((always_inline)) V load_lanes(const S* src, int64_t n) {
  if constexpr (std::is_same_v<S, float>) return load_first<V>(src, n);
  V v{};
  if (n == TS) std::memcpy(&v, src, sizeof(V));
  else for (int64_t i = 0; i < n; ++i) v[i] = src[i];
  return v;
}

// Stores the lanes [0, n) of v at dst (float: store_first; else n = 16 is one unaligned vector store).
template <typename V, typename S>
inline __attribute__((always_inline)) void store_lanes(S* dst, const V& v, int64_t n) {
  if constexpr (std::is_same_v<S, float>) {
    store_first(dst, v, n);
  } else {
    if (n == TS) std::memcpy(dst, &v, sizeof(V));
    else for (int64_t i = 0; i < n; ++i) dst[i] = v[i];
  }
}

template <typename scalar_t, int DC>
void forward_kernel(const Packed<scalar_t>* __restrict__ pk, const scalar_t* __restrict__ colors,
                    const int64_t* __restrict__ ids, const int64_t* __restrict__ offsets, int64_t D_,
                    int64_t tiles_x, int64_t tiles_y, int64_t W, int64_t H, scalar_t* __restrict__ out_color,
                    scalar_t* __restrict__ out_alpha, scalar_t* __restrict__ out_depth, scalar_t* __restrict__ out_T,
                    int32_t* __restrict__ out_last) {
  using C = Consts<scalar_t>;
  using V = Vec<scalar_t>;
  using M = Mask<scalar_t>;
  const int64_t D = channels<DC>(D_);
  const int64_t ntiles = tiles_x * tiles_y;
  std::atomic<int64_t> next{0};
  run_on_threads([&]() {
    // Masks are kept as 0/1 values (as the torch reference's arithmetic) and every branch is a lane select.
    // One record per tile row, so that a row's state shares cache lines.
    struct alignas(64) Row {
      V T, dep, done, col[3];
      M last;
      V w;
    } st[TS];
    std::vector<V> colbuf(DC == 3 ? 0 : D * TS);  // [D][row] for DC == 0
    const V zero = V{}, one = splat<V>(scalar_t(1)), half = splat<V>(scalar_t(0.5));
    const V amin = splat<V>(C::alpha_min), tmin = splat<V>(C::t_min);
    for (;;) {
      const int64_t t = next.fetch_add(1, std::memory_order_relaxed);
      if (t >= ntiles) break;
      const int64_t x0 = (t % tiles_x) * TS, y0 = (t / tiles_x) * TS;
      const V px = column_centres<scalar_t>(x0);
      for (int r = 0; r < TS; ++r) {
        st[r].T = one;
        st[r].dep = zero;
        st[r].last = M{};
        for (int c = 0; c < TS; ++c) st[r].done[c] = (x0 + c < W && y0 + r < H) ? scalar_t(0) : scalar_t(1);  // padding
        for (int d = 0; d < 3; ++d) st[r].col[d] = zero;
      }
      std::fill(colbuf.begin(), colbuf.end(), zero);
      const int64_t off = offsets[t];
      const int64_t n = offsets[t + 1] - off;
      for (int64_t j = 0; j < n; ++j) {
        const int64_t g = ids[off + j];
        if (j + PREFETCH < n) __builtin_prefetch(pk + ids[off + j + PREFETCH]);
        const Packed<scalar_t>& P = pk[g];
        const scalar_t my = P.my, c = P.c, o = P.o, z = P.z;
        const M jp1 = M{} + static_cast<MaskInt<scalar_t>>(j + 1);
        int r0, r1;
        row_range(P, y0, r0, r1);
        const V dx = px - P.mx, adx2 = (P.a * dx) * dx, bdx = P.b * dx;
        for (int r = r0; r < r1; ++r) {
          const scalar_t dy = (static_cast<scalar_t>(y0 + r) + scalar_t(0.5)) - my;
          const V alpha = row_alpha<scalar_t>(adx2, bdx, dy, c, o).alpha;
          const V valid = select(alpha >= amin, one - st[r].done, zero);
          const V Tn = st[r].T * (one - alpha);
          const V stop = select(Tn < tmin, valid, zero);  // T would fall below T_MIN
          const V contrib = valid - stop;
          const V wv = contrib * (alpha * st[r].T);
          st[r].dep = fmadd(wv, splat<V>(z), st[r].dep);
          const M used = contrib > half;
          st[r].T = select(used, Tn, st[r].T);
          st[r].last = select(used, jp1, st[r].last);
          st[r].done += stop;
          if constexpr (DC == 3) {
            st[r].col[0] = fmadd(wv, splat<V>(P.col[0]), st[r].col[0]);
            st[r].col[1] = fmadd(wv, splat<V>(P.col[1]), st[r].col[1]);
            st[r].col[2] = fmadd(wv, splat<V>(P.col[2]), st[r].col[2]);
          } else {
            st[r].w = wv;
          }
        }
        if constexpr (DC != 3) {
          for (int64_t d = 0; d < D; ++d) {
            const scalar_t cd = colors[g * D + d];
            V* cr = colbuf.data() + d * TS;
            for (int r = r0; r < r1; ++r) cr[r] = fmadd(st[r].w, splat<V>(cd), cr[r]);
          }
        }
        if ((j & 7) == 7) {  // whole-tile early exit
          V nd = zero;
          for (int r = 0; r < TS; ++r) nd += st[r].done;
          if (row_sum<scalar_t>(nd) >= scalar_t(TP)) break;
        }
      }
      // outputs: the saved state in tile layout (whole rows), the images row by row (the lanes inside the image)
      const int64_t nx = std::min<int64_t>(TS, W - x0);
      for (int r = 0; r < TS; ++r) {
        std::memcpy(out_T + t * TP + r * TS, &st[r].T, sizeof(V));
        const I32 lr = convert<I32>(st[r].last);
        std::memcpy(out_last + t * TP + r * TS, &lr, sizeof(I32));
        const int64_t y = y0 + r;
        if (y >= H) continue;
        const int64_t pix = y * W + x0;
        store_lanes(out_alpha + pix, one - st[r].T, nx);
        store_lanes(out_depth + pix, st[r].dep, nx);
        for (int64_t cx = 0; cx < nx; ++cx)
          for (int64_t d = 0; d < D; ++d) {
            if constexpr (DC == 3) out_color[(pix + cx) * D + d] = st[r].col[d][cx];
            else out_color[(pix + cx) * D + d] = colbuf[d * TS + r][cx];
          }
      }
    }
  });
}

template <typename scalar_t, int DC>
void backward_kernel(const Packed<scalar_t>* __restrict__ pk, const scalar_t* __restrict__ colors,
                     const int64_t* __restrict__ ids, const int64_t* __restrict__ offsets,
                     const scalar_t* __restrict__ saved_T, const int32_t* __restrict__ saved_last,
                     const scalar_t* __restrict__ g_color, const scalar_t* __restrict__ g_alpha,
                     const scalar_t* __restrict__ g_depth, int64_t D_, int64_t tiles_x, int64_t tiles_y, int64_t W,
                     int64_t H, scalar_t* __restrict__ out) {
  using C = Consts<scalar_t>;
  using V = Vec<scalar_t>;
  using M = Mask<scalar_t>;
  const int64_t D = channels<DC>(D_);
  const int64_t ntiles = tiles_x * tiles_y;
  const int64_t stride = NGRAD + D;
  std::atomic<int64_t> next{0};
  run_on_threads([&]() {
    // One record per tile row, so that a row's state shares cache lines. gAT: dL/dalpha_image T_final;
    // gC3 (DC == 3): dL/dcolour image per channel; U: what is composited behind the current Gaussian, weighted by
    // the image gradients, sum_d behind_d dL/dC_d + behind_depth dL/dD (the only form in which the colours and
    // depth behind enter the gradients, so one vector replaces one per channel).
    struct alignas(64) Row {
      V T, gAT, gD, U, gC3[3];
      M last;
      V w;
    } st[TS];
    int32_t row_last[TS];  // per row, the largest list length a pixel used
    std::vector<V> gC(DC == 3 ? 0 : D * TS);  // DC == 0: dL/dcolour image, [D][row]
    const V zero = V{}, one = splat<V>(scalar_t(1)), half = splat<V>(scalar_t(0.5));
    const V amin = splat<V>(C::alpha_min), amax = splat<V>(C::alpha_max);
    for (;;) {
      const int64_t t = next.fetch_add(1, std::memory_order_relaxed);
      if (t >= ntiles) break;
      const int64_t off = offsets[t];
      const int64_t n = offsets[t + 1] - off;
      if (n == 0) continue;
      const int64_t x0 = (t % tiles_x) * TS, y0 = (t / tiles_x) * TS;
      const V px = column_centres<scalar_t>(x0);
      int32_t jmax = 0;
      const int64_t nx = std::min<int64_t>(TS, W - x0);
      for (int r = 0; r < TS; ++r) {
        V Tf;
        std::memcpy(&Tf, saved_T + t * TP + r * TS, sizeof(V));
        st[r].T = Tf;
        I32 lr;
        std::memcpy(&lr, saved_last + t * TP + r * TS, sizeof(I32));
        st[r].last = convert<M>(lr);
        row_last[r] = 0;
        for (int cx = 0; cx < TS; ++cx) row_last[r] = std::max(row_last[r], lr[cx]);
        jmax = std::max(jmax, row_last[r]);
        const int64_t y = y0 + r;
        const int64_t n_in = y < H ? nx : 0, pix = y < H ? y * W + x0 : 0;
        st[r].gAT = load_lanes<V>(g_alpha + pix, n_in) * Tf;
        st[r].gD = load_lanes<V>(g_depth + pix, n_in);
        for (int64_t d = 0; d < D; ++d) {
          V gcd = zero;
          for (int64_t cx = 0; cx < n_in; ++cx) gcd[cx] = g_color[(pix + cx) * D + d];
          if constexpr (DC == 3) st[r].gC3[d] = gcd;
          else gC[d * TS + r] = gcd;
        }
        st[r].U = zero;
      }
      // list entries no pixel reached get zero gradients
      std::fill(out + (off + jmax) * stride, out + (off + n) * stride, scalar_t(0));
      for (int64_t j = static_cast<int64_t>(jmax) - 1; j >= 0; --j) {
        const int64_t g = ids[off + j];
        if (j >= PREFETCH) __builtin_prefetch(pk + ids[off + j - PREFETCH]);
        const Packed<scalar_t>& P = pk[g];
        const scalar_t mx = P.mx, my = P.my, a = P.a, b = P.b, c = P.c, o = P.o, z = P.z;
        const scalar_t* __restrict__ cg = DC == 3 ? P.col : colors + g * D;
        const M jj = M{} + static_cast<MaskInt<scalar_t>>(j);
        int r0, r1;
        row_range(P, y0, r0, r1);
        const V dx = px - mx, adx2 = (a * dx) * dx, bdx = b * dx;
        // dpower/d(a, b, c, mx, my) are products of dx (per lane) and dy (per row): the row loop sums
        // dL/dpower, dL/dpower dy and dL/dpower dy^2 (s0, s1, s2), and the lanes' factors are applied once.
        V s0 = zero, s1 = zero, s2 = zero, go = zero, gz = zero, gk0 = zero, gk1 = zero, gk2 = zero;
        for (int r = r0; r < r1; ++r) {
          if (row_last[r] <= j) continue;  // every pixel of the row stopped before this Gaussian
          const scalar_t dy = (static_cast<scalar_t>(y0 + r) + scalar_t(0.5)) - my;
          const auto ra = row_alpha<scalar_t>(adx2, bdx, dy, c, o);
          const V power = ra.power, e = ra.e, oe = ra.oe, alpha = ra.alpha;
          const V listed = select(jj < st[r].last, one, zero);
          const V valid = select(alpha >= amin, listed, zero);
          const V inv_om = recip(one - alpha);  // alpha <= 0.99
          const V Tj = select(valid > half, st[r].T * inv_om, st[r].T);  // transmittance in front of it
          const V a_v = valid * alpha;
          const V wv = a_v * Tj;
          // q = (c - colour behind) . dL/dC + (z - depth behind) dL/dD
          V cgz = z * st[r].gD;
          if constexpr (DC == 3) {
            cgz = fmadd(splat<V>(cg[0]), st[r].gC3[0], cgz);
            cgz = fmadd(splat<V>(cg[1]), st[r].gC3[1], cgz);
            cgz = fmadd(splat<V>(cg[2]), st[r].gC3[2], cgz);
          } else {
            for (int64_t d = 0; d < D; ++d) cgz = fmadd(splat<V>(cg[d]), gC[d * TS + r], cgz);
          }
          const V q = cgz - st[r].U;
          // d(colour, depth)/dalpha = T_j q; d(1 - T_final)/dalpha = T_final / (1 - alpha)
          const V dLda = fmadd(Tj, q, st[r].gAT * inv_om);
          const V unclamped = select(oe <= amax, valid, zero);
          const V dLdoe = select(unclamped > half, dLda, zero);
          go = fmadd(dLdoe, e, go);
          const V dLdpow = select(power <= zero, dLdoe * oe, zero);
          s0 += dLdpow;
          s1 = fmadd(dLdpow, splat<V>(dy), s1);
          s2 = fmadd(dLdpow, splat<V>(dy * dy), s2);
          gz = fmadd(wv, st[r].gD, gz);
          st[r].U = fmadd(a_v, q, st[r].U);
          st[r].T = Tj;
          if constexpr (DC == 3) {
            gk0 = fmadd(wv, st[r].gC3[0], gk0);
            gk1 = fmadd(wv, st[r].gC3[1], gk1);
            gk2 = fmadd(wv, st[r].gC3[2], gk2);
          } else {
            st[r].w = wv;
          }
        }
        // power = -0.5 (a dx^2 + c dy^2) - b dx dy with dx = px - mx, dy = py - my
        scalar_t* __restrict__ o_row = out + (off + j) * stride;
        const V per_lane[7] = {
            fmadd(a * dx, s0, b * s1),          // mx: dpower/dmx = a dx + b dy
            fmadd(splat<V>(c), s1, bdx * s0),   // my: dpower/dmy = c dy + b dx
            ((scalar_t(-0.5) * dx) * dx) * s0,  // a
            -dx * s1,                           // b
            scalar_t(-0.5) * s2,                // c
            go, gz};
        if constexpr (DC == 3 && std::is_same_v<scalar_t, float>) {
          store_lanes(o_row, row_sums10({per_lane[0], per_lane[1], per_lane[2], per_lane[3], per_lane[4], per_lane[5],
                                         per_lane[6], gk0, gk1, gk2}),
                      NGRAD + 3);
        } else {
          for (int k = 0; k < NGRAD; ++k) o_row[k] = row_sum<scalar_t>(per_lane[k]);
          if constexpr (DC == 3) {
            o_row[NGRAD] = row_sum<scalar_t>(gk0);
            o_row[NGRAD + 1] = row_sum<scalar_t>(gk1);
            o_row[NGRAD + 2] = row_sum<scalar_t>(gk2);
          } else {
            for (int64_t d = 0; d < D; ++d) {
              V gcol = zero;
              for (int r = r0; r < r1; ++r) {
                if (row_last[r] <= j) continue;
                gcol = fmadd(st[r].w, gC[d * TS + r], gcol);
              }
              o_row[NGRAD + d] = row_sum<scalar_t>(gcol);
            }
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


// pack_gaussians on the op's tensors.
template <typename scalar_t>
std::vector<Packed<scalar_t>> pack(const at::Tensor& means2d, const at::Tensor& conics, const at::Tensor& opac,
                                   const at::Tensor& colors, const at::Tensor& depths, const at::Tensor& row_h) {
  return pack_gaussians<scalar_t>(means2d.data_ptr<scalar_t>(), conics.data_ptr<scalar_t>(),
                                  opac.data_ptr<scalar_t>(), colors.data_ptr<scalar_t>(), depths.data_ptr<scalar_t>(),
                                  row_h.data_ptr<double>(), means2d.size(0), colors.size(1));
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
  // every pixel lies in a tile, and the kernel writes them all: no fill
  auto color = at::empty({height, width, D}, opts);
  auto alpha = at::empty({height, width}, opts);
  auto depth = at::empty({height, width}, opts);
  auto T = at::empty({tiles_x * tiles_y, TP}, opts);
  auto last = at::empty({tiles_x * tiles_y, TP}, opts.dtype(at::kInt));
  AT_DISPATCH_FLOATING_TYPES(means2d.scalar_type(), "metegs_composite_forward", [&] {
    const auto pk = pack<scalar_t>(means2d, conics, opac, colors, depths, row_h);
    auto run = [&](auto kernel) {
      kernel(pk.data(), colors.data_ptr<scalar_t>(), ids.data_ptr<int64_t>(), offsets.data_ptr<int64_t>(), D,
             tiles_x, tiles_y, width, height, color.data_ptr<scalar_t>(), alpha.data_ptr<scalar_t>(),
             depth.data_ptr<scalar_t>(), T.data_ptr<scalar_t>(), last.data_ptr<int32_t>());
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
  std::vector<at::Tensor> outs = {at::empty({N, 2}, opts), at::empty({N, 3}, opts), at::empty({N}, opts),
                                  at::empty({N, D}, opts), at::empty({N}, opts)};  // every element written below
  AT_DISPATCH_FLOATING_TYPES(dt, "metegs_composite_backward", [&] {
    const auto pk = pack<scalar_t>(means2d, conics, opac, colors, depths, row_h);
    auto run = [&](auto kernel) {
      kernel(pk.data(), colors.data_ptr<scalar_t>(), ids.data_ptr<int64_t>(), offsets.data_ptr<int64_t>(),
             saved_T.data_ptr<scalar_t>(), saved_last.data_ptr<int32_t>(), g_color.data_ptr<scalar_t>(),
             g_alpha.data_ptr<scalar_t>(), g_depth.data_ptr<scalar_t>(), D, tiles_x, tiles_y, width, height,
             per_isect.data_ptr<scalar_t>());
    };
    if (D == 3) run(backward_kernel<scalar_t, 3>);
    else run(backward_kernel<scalar_t, 0>);
    // Reduce the intersections to their Gaussians: two fixed halves of the list, each summed in list order into
    // its own [N, S] buffer (one scattered cache line per intersection, on two threads when there are two), then
    // both added into the outputs. The same sums for any thread count: deterministic.
    const int64_t* __restrict__ idp = ids.data_ptr<int64_t>();
    const scalar_t* __restrict__ src = per_isect.data_ptr<scalar_t>();
    // each half zero-filled by the thread that sums into it (1.6 MB at 20k Gaussians: serial, it took 0.1 ms)
    const std::unique_ptr<scalar_t[]> acc(new scalar_t[2 * N * S]);
    metegs::parallel_for(0, 2, 1, [&](int64_t begin, int64_t end) {
      for (int64_t h = begin; h < end; ++h) {
        scalar_t* __restrict__ dst = acc.get() + h * N * S;
        std::fill(dst, dst + N * S, scalar_t(0));
        for (int64_t m = h * M / 2, m1 = (h + 1) * M / 2; m < m1; ++m) {
          scalar_t* __restrict__ row = dst + idp[m] * S;
          const scalar_t* __restrict__ r = src + m * S;
          for (int64_t c = 0; c < S; ++c) row[c] += r[c];
        }
      }
    });
    scalar_t *g_m2 = outs[0].data_ptr<scalar_t>(), *g_con = outs[1].data_ptr<scalar_t>();
    scalar_t *g_op = outs[2].data_ptr<scalar_t>(), *g_col = outs[3].data_ptr<scalar_t>();
    scalar_t* g_dep = outs[4].data_ptr<scalar_t>();
    metegs::parallel_for(0, N, 4096, [&](int64_t begin, int64_t end) {
      for (int64_t g = begin; g < end; ++g) {
        const scalar_t *p = acc.get() + g * S, *q = p + N * S;
        g_m2[2 * g] = p[0] + q[0], g_m2[2 * g + 1] = p[1] + q[1];
        for (int k = 0; k < 3; ++k) g_con[3 * g + k] = p[2 + k] + q[2 + k];
        g_op[g] = p[5] + q[5];
        g_dep[g] = p[6] + q[6];
        for (int64_t d = 0; d < D; ++d) g_col[D * g + d] = p[NGRAD + d] + q[NGRAD + d];
      }
    });
  });
  return outs;
}

namespace {
void check_finish(const at::Tensor& alpha, const at::Tensor& other, const char* name, int64_t channels) {
  TORCH_CHECK(alpha.dim() == 2, "alpha must be [H, W]");
  const bool ok = channels ? (other.dim() == 3 && other.size(2) == channels) : other.dim() == 2;
  TORCH_CHECK(ok && other.size(0) == alpha.size(0) && other.size(1) == alpha.size(1), name, " must be [H, W",
              channels ? ", 3]" : "]", " like alpha");
  TORCH_CHECK(other.scalar_type() == alpha.scalar_type(), name, " must have alpha's dtype");
}
}  // namespace

std::vector<at::Tensor> finish_forward(at::Tensor color, at::Tensor alpha, at::Tensor depth_sum, at::Tensor background) {
  check_finish(alpha, color, "color", 3);
  check_finish(alpha, depth_sum, "depth_sum", 0);
  TORCH_CHECK(background.numel() == 3, "background must have 3 values");
  color = color.contiguous(), alpha = alpha.contiguous(), depth_sum = depth_sum.contiguous();
  background = background.to(alpha.scalar_type()).contiguous();
  auto rgb = at::empty_like(color), depth = at::empty_like(alpha);
  const int64_t P = alpha.numel();
  AT_DISPATCH_FLOATING_TYPES(alpha.scalar_type(), "metegs_finish_forward", [&] {
    const scalar_t *c = color.data_ptr<scalar_t>(), *a = alpha.data_ptr<scalar_t>(), *d = depth_sum.data_ptr<scalar_t>();
    const scalar_t* bg = background.data_ptr<scalar_t>();
    scalar_t *out = rgb.data_ptr<scalar_t>(), *dep = depth.data_ptr<scalar_t>();
    const scalar_t amin = scalar_t(DEPTH_ALPHA_MIN);
    metegs::parallel_for(0, P, 16384, [&](int64_t begin, int64_t end) {
      for (int64_t p = begin; p < end; ++p) {
        const scalar_t t = scalar_t(1) - a[p];
        for (int k = 0; k < 3; ++k) out[3 * p + k] = c[3 * p + k] + t * bg[k];
        dep[p] = d[p] / std::max(a[p], amin);
      }
    });
  });
  return {rgb, depth};
}

std::vector<at::Tensor> finish_backward(at::Tensor alpha, at::Tensor depth_sum, at::Tensor background, at::Tensor g_rgb,
                                        c10::optional<at::Tensor> g_depth) {
  check_finish(alpha, g_rgb, "g_rgb", 3);
  check_finish(alpha, depth_sum, "depth_sum", 0);
  const bool has_gd = g_depth.has_value() && g_depth->defined();
  if (has_gd) check_finish(alpha, *g_depth, "g_depth", 0);
  alpha = alpha.contiguous(), depth_sum = depth_sum.contiguous(), g_rgb = g_rgb.contiguous();
  background = background.to(alpha.scalar_type()).contiguous();
  const at::Tensor gd = has_gd ? g_depth->contiguous() : at::Tensor();
  auto g_alpha = at::empty_like(alpha);
  auto g_depth_sum = has_gd ? at::empty_like(alpha) : at::zeros_like(alpha);
  const int64_t P = alpha.numel();
  AT_DISPATCH_FLOATING_TYPES(alpha.scalar_type(), "metegs_finish_backward", [&] {
    const scalar_t *a = alpha.data_ptr<scalar_t>(), *d = depth_sum.data_ptr<scalar_t>(), *gr = g_rgb.data_ptr<scalar_t>();
    const scalar_t* bg = background.data_ptr<scalar_t>();
    const scalar_t* gdp = has_gd ? gd.data_ptr<scalar_t>() : nullptr;
    scalar_t *out_a = g_alpha.data_ptr<scalar_t>(), *out_d = g_depth_sum.data_ptr<scalar_t>();
    const scalar_t amin = scalar_t(DEPTH_ALPHA_MIN);
    metegs::parallel_for(0, P, 16384, [&](int64_t begin, int64_t end) {
      for (int64_t p = begin; p < end; ++p) {
        // rgb = color + (1 - alpha) bg; depth = depth_sum / max(alpha, amin) (torch's clamp_min passes the
        // gradient where alpha >= amin)
        scalar_t g = -(gr[3 * p] * bg[0] + gr[3 * p + 1] * bg[1] + gr[3 * p + 2] * bg[2]);
        if (gdp) {
          const scalar_t den = std::max(a[p], amin);
          out_d[p] = gdp[p] / den;
          if (a[p] >= amin) g -= gdp[p] * d[p] / (den * den);
        }
        out_a[p] = g;
      }
    });
  });
  return {g_rgb, g_alpha, g_depth_sum};
}

}  // namespace metegs_cpu
