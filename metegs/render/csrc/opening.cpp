// opening.cpp: grey-scale opening of images (each channel) by a k x k square, the erosion's minimum then the
// dilation's maximum over windows clipped at the borders (reference: metegs.losses.photometric.open_bright, two
// stride-1 max_pool2d), with the input pixel each output was picked from; and a render and a photo with their
// thin bright strokes taken out (reference: metegs.losses.robust.without_bright_strokes' torch path).
//
// The square is separable: a row pass then a column pass each way, k compares per pixel and pass where the pooled
// reference visits k^2. Each pass carries the flat index of the input pixel its value came from, so the backward
// is one scatter of the output's gradient onto those pixels (strokes_out_backward). Ties go to the first pixel in row-major order of the
// window, as max_pool2d's do: the row pass keeps the leftmost, the column pass the topmost.
#include "metegs_cpu.h"

namespace metegs_cpu {
namespace {

constexpr int64_t ROWS_PER_CHUNK = 8;

// One pass over the rows of `B` images of `H` rows of `W` pixels of `C` interleaved channels: out[p] = the best
// (least where `TakeMin`, else greatest) of src[q] over the window of p along x (`along_rows`) or y, radius r;
// where `Index`, out_index[p] = src_index[q] (or q itself where src_index is null). The first best in scan order
// wins. Selects without branches: on a photo's noise a branch per compare is mispredicted every other time.
template <typename T, bool TakeMin, bool Index>
void pass(const T* src, const int32_t* src_index, T* out, int32_t* out_index, int64_t B, int64_t H, int64_t W,
          int64_t C, int64_t r, bool along_rows) {
  const int64_t n = W * C;
  metegs::parallel_for(0, B * H, ROWS_PER_CHUNK, [&](int64_t begin, int64_t end) {
    std::vector<int32_t> q_row(Index ? n : 0);
    int32_t* q_best = q_row.data();
    for (int64_t row = begin; row < end; ++row) {
      T* o = out + row * n;
      if (along_rows) {
        for (int64_t x = 0; x < W; ++x) {
          const int64_t lo = std::max<int64_t>(0, x - r), hi = std::min<int64_t>(W - 1, x + r);
          for (int64_t c = 0; c < C; ++c) {
            int32_t best_q = int32_t(row * n + lo * C + c);
            T best = src[best_q];
            for (int32_t q = best_q + int32_t(C), m = int32_t(lo) + 1; m <= hi; ++m, q += int32_t(C)) {
              const T v = src[q];
              const bool take = TakeMin ? v < best : v > best;
              best = take ? v : best;
              if constexpr (Index) best_q = take ? q : best_q;
            }
            o[x * C + c] = best;
            if constexpr (Index) q_best[x * C + c] = best_q;
          }
        }
      } else {  // whole rows at a time: the window's rows top to bottom
        const int64_t y = row % H, image_row0 = row - y;
        const int64_t lo = std::max<int64_t>(0, y - r), hi = std::min<int64_t>(H - 1, y + r);
        const int32_t first = int32_t((image_row0 + lo) * n);
        std::copy(src + first, src + first + n, o);
        if constexpr (Index)
          for (int32_t i = 0; i < n; ++i) q_best[i] = first + i;
        for (int64_t yy = lo + 1; yy <= hi; ++yy) {
          const int32_t base = int32_t((image_row0 + yy) * n);
          const T* s = src + base;
          for (int32_t i = 0; i < n; ++i) {
            const bool take = TakeMin ? s[i] < o[i] : s[i] > o[i];
            o[i] = take ? s[i] : o[i];
            if constexpr (Index) q_best[i] = take ? base + i : q_best[i];
          }
        }
      }
      if constexpr (Index) {
        int32_t* oi = out_index + row * n;
        if (src_index)
          for (int64_t i = 0; i < n; ++i) oi[i] = src_index[q_best[i]];
        else
          std::copy(q_best, q_best + n, oi);
      }
    }
  });
}

template <typename T, bool Index>
void open(const T* x, T* out, T* tmp, int32_t* index, int32_t* tmp_index, int64_t B, int64_t H, int64_t W, int64_t C,
          int64_t r) {
  pass<T, true, Index>(x, nullptr, tmp, tmp_index, B, H, W, C, r, true);  // erosion along x
  pass<T, true, Index>(tmp, tmp_index, out, index, B, H, W, C, r, false);  // ... and along y
  pass<T, false, Index>(out, index, tmp, tmp_index, B, H, W, C, r, true);  // dilation along x
  pass<T, false, Index>(tmp, tmp_index, out, index, B, H, W, C, r, false);  // ... and along y
}

}  // namespace

std::vector<at::Tensor> opening_forward(at::Tensor x, int64_t k, bool with_index) {
  TORCH_CHECK(x.dim() == 4, "opening: images must be [B, H, W, C], got ", x.sizes());
  TORCH_CHECK(x.is_cpu(), "opening: CPU tensors only");
  TORCH_CHECK(k >= 1 && k % 2 == 1, "opening: the square's width must be odd and positive, got ", k);
  TORCH_CHECK(x.numel() < (int64_t(1) << 31), "opening: images of 2^31 values or more are not supported");
  x = x.contiguous();
  const int64_t B = x.size(0), H = x.size(1), W = x.size(2), C = x.size(3), r = k / 2;
  auto out = at::empty_like(x), tmp = at::empty_like(x);
  const auto index_options = x.options().dtype(at::kInt);
  auto index = at::empty(with_index ? x.sizes() : at::IntArrayRef{0}, index_options);
  auto tmp_index = at::empty(with_index ? x.sizes() : at::IntArrayRef{0}, index_options);
  AT_DISPATCH_FLOATING_TYPES(x.scalar_type(), "metegs_opening_forward", [&] {
    const scalar_t* px = x.data_ptr<scalar_t>();
    scalar_t *o = out.data_ptr<scalar_t>(), *t = tmp.data_ptr<scalar_t>();
    if (with_index)
      open<scalar_t, true>(px, o, t, index.data_ptr<int32_t>(), tmp_index.data_ptr<int32_t>(), B, H, W, C, r);
    else
      open<scalar_t, false>(px, o, t, nullptr, nullptr, B, H, W, C, r);
  });
  return {out, index};
}

std::vector<at::Tensor> strokes_out_forward(at::Tensor render, at::Tensor photo, int64_t k, double min_excess,
                                            bool with_index) {
  TORCH_CHECK(render.sizes() == photo.sizes(), "strokes_out: shapes differ, ", render.sizes(), " vs ", photo.sizes());
  TORCH_CHECK(render.scalar_type() == photo.scalar_type(), "strokes_out: dtypes differ");
  auto r_open = opening_forward(render, k, with_index), p_open = opening_forward(photo, k, false);
  render = render.contiguous(), photo = photo.contiguous();
  const int64_t pixels = render.numel() / render.size(3), C = render.size(3);
  auto r_out = at::empty_like(render), p_out = at::empty_like(photo);
  auto stroke = at::empty({render.size(0), render.size(1), render.size(2)}, render.options().dtype(at::kBool));
  AT_DISPATCH_FLOATING_TYPES(render.scalar_type(), "metegs_strokes_out_forward", [&] {
    const scalar_t *r = render.data_ptr<scalar_t>(), *p = photo.data_ptr<scalar_t>();
    const scalar_t *ro = r_open[0].data_ptr<scalar_t>(), *po = p_open[0].data_ptr<scalar_t>();
    scalar_t *r_dst = r_out.data_ptr<scalar_t>(), *p_dst = p_out.data_ptr<scalar_t>();
    bool* s = stroke.data_ptr<bool>();
    const scalar_t m = scalar_t(min_excess);
    metegs::parallel_for(0, pixels, 4096, [&](int64_t begin, int64_t end) {
      for (int64_t i = begin; i < end; ++i) {
        scalar_t excess_r = 0, excess_p = 0;  // summed in channel order, then / C: as mean(dim=-1)
        for (int64_t c = 0; c < C; ++c) excess_r += r[i * C + c] - ro[i * C + c], excess_p += p[i * C + c] - po[i * C + c];
        const bool taken = excess_p / scalar_t(C) > m || excess_r / scalar_t(C) > m;
        s[i] = taken;
        for (int64_t c = 0; c < C; ++c) {
          r_dst[i * C + c] = taken ? ro[i * C + c] : r[i * C + c];
          p_dst[i * C + c] = taken ? po[i * C + c] : p[i * C + c];
        }
      }
    });
  });
  return {r_out, p_out, r_open[1], stroke};
}

at::Tensor strokes_out_backward(at::Tensor index, at::Tensor stroke, at::Tensor g_out) {
  TORCH_CHECK(index.sizes() == g_out.sizes() && index.scalar_type() == at::kInt,
              "strokes_out_backward: index (int32) and g_out must have one shape");
  TORCH_CHECK(stroke.numel() * g_out.size(-1) == g_out.numel() && stroke.scalar_type() == at::kBool,
              "strokes_out_backward: stroke must be the bool mask of g_out's pixels");
  index = index.contiguous(), stroke = stroke.contiguous(), g_out = g_out.contiguous();
  const int64_t C = g_out.size(-1), pixels = stroke.numel();
  auto g_x = at::empty_like(g_out);
  AT_DISPATCH_FLOATING_TYPES(g_out.scalar_type(), "metegs_strokes_out_backward", [&] {
    const scalar_t* g = g_out.data_ptr<scalar_t>();
    const int32_t* idx = index.data_ptr<int32_t>();
    const bool* s = stroke.data_ptr<bool>();
    scalar_t* gx = g_x.data_ptr<scalar_t>();
    for (int64_t i = 0; i < pixels; ++i)  // the render as it is where no stroke was taken
      for (int64_t c = 0; c < C; ++c) gx[i * C + c] = s[i] ? scalar_t(0) : g[i * C + c];
    for (int64_t i = 0; i < pixels; ++i)  // serial: opened pixels share sources
      if (s[i])
        for (int64_t c = 0; c < C; ++c) gx[idx[i * C + c]] += g[i * C + c];
  });
  return g_x;
}

}  // namespace metegs_cpu
