// Tile binning for the metegs `cpu` rasteriser: per 16x16 tile, the ids of the Gaussians that can
// touch it, front to back, as one flat list with offsets (CSR).
//
// Candidate tiles are the same boxes as metegs.render.tiles.bin_gaussians (the opacity-aware
// extents). With `cull`, a candidate tile is kept only if the Gaussian's alpha can reach 1/255 at
// one of the tile's pixel centres (the conic's quadratic form at most 2 ln(255 o) somewhere in the rectangle
// of pixel centres, with a small safety margin; found per tile row, see for_each_tile_row), so no
// contribution is lost and the image is unchanged, while the long thin footprints of anisotropic Gaussians
// stop costing whole rows of tiles. Ordering: a stable depth sort of the Gaussians, then a parallel
// counting sort by tile (O(N + M)), instead of a sort of M 64-bit keys.

#include "metegs_cpu.h"

#include <ATen/Parallel.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <type_traits>
#include <utility>
#include <limits>

namespace metegs_cpu {
namespace {

struct Rect {
  int64_t x0, x1, y0, y1;  // tile range [x0, x1) x [y0, y1)
};

template <typename T>
inline Rect tile_rect(const T* m, const T* e, int64_t tiles_x, int64_t tiles_y) {
  // the same arithmetic (in the input dtype) as tiles.bin_gaussians
  auto clampi = [](T v, int64_t hi) { return std::min<int64_t>(std::max<int64_t>(static_cast<int64_t>(v), 0), hi); };
  const T ts = T(TILE);
  Rect r;
  r.x0 = clampi(std::floor((m[0] - e[0]) / ts), tiles_x);
  r.x1 = clampi(std::floor((m[0] + e[0]) / ts) + T(1), tiles_x);
  r.y0 = clampi(std::floor((m[1] - e[1]) / ts), tiles_y);
  r.y1 = clampi(std::floor((m[1] + e[1]) / ts) + T(1), tiles_y);
  return r;
}

// One Gaussian's footprint as the tile test needs it: its conic (a, b, c) and mean, and the ellipse
// q(dx, dy) = a dx^2 + 2 b dx dy + c dy^2 <= t where its alpha can reach 1/255. t is 2 ln(255 o) plus a margin
// that covers float32 rounding in the compositing: 1e-4 (1 + t + qabs), with qabs the bound
// t (1 + 2 (ac + b^2) / (ac - b^2)) on |a| dx^2 + 2 |b dx dy| + |c| dy^2 inside the ellipse (the size of the
// terms whose cancellation the compositing rounds; it grows with the anisotropy).
struct Footprint {
  double b, det, inv_a, mx, my, at;  // at = a t
  double ymax, y_right;  // half-height of the ellipse; dy of its rightmost point (-y_right: of its leftmost)
  bool definite;         // a > 0, c > 0 and ac - b^2 > 0; else every candidate tile is kept (no culling)
};

template <typename T>
inline Footprint footprint(const T* m, const T* conic, double thresh) {
  Footprint f;
  const double a = conic[0], b = conic[1], c = conic[2];
  f.b = b, f.det = a * c - b * b;
  f.mx = m[0], f.my = m[1];
  f.definite = a > 0 && c > 0 && f.det > 0;
  if (!f.definite) return f;
  const double inv_det = 1.0 / f.det, t = thresh + 1e-4 * (1.0 + thresh * (2.0 + 2.0 * (a * c + b * b) * inv_det));
  f.inv_a = 1.0 / a;
  f.at = a * t;
  f.ymax = std::sqrt(f.at * inv_det);
  f.y_right = -b * std::sqrt(t * inv_det / c);  // the rightmost point: (sqrt(t c / det), -b sqrt(t / (c det)))
  return f;
}

// fn(ty, lo, hi) for each tile row ty of the candidate rectangle r with the columns [lo, hi) whose rectangle of
// pixel centres meets the footprint's ellipse (rows where none does are skipped). The ellipse's part within a
// band of rows dy in [y0, y1] spans, in dx, from its left boundary at the band's dy nearest the leftmost point
// to its right boundary at the band's dy nearest the rightmost point (the boundaries are convex and concave in
// dy), so a tile is reached iff its centres' dx range meets that span: the same tiles as testing the minimum
// of q over each tile's rectangle, for two square roots per tile row instead of work per tile.
template <typename Fn>
inline void for_each_tile_row(const Footprint& f, const Rect& r, bool cull, int64_t W, int64_t H, Fn&& fn) {
  if (!cull || !f.definite) {
    for (int64_t ty = r.y0; ty < r.y1; ++ty) fn(ty, r.x0, r.x1);
    return;
  }
  const double col_lo = double(r.x0) - 1.0, col_hi = double(r.x1) + 1.0;
  auto column = [&](double v) { return static_cast<int64_t>(std::min(std::max(v, col_lo), col_hi)); };
  for (int64_t ty = r.y0; ty < r.y1; ++ty) {
    const double y0 = std::max(double(ty * TILE) + 0.5 - f.my, -f.ymax);
    const double y1 = std::min(double(std::min((ty + 1) * TILE, H) - 1) + 0.5 - f.my, f.ymax);
    if (!(y0 <= y1)) continue;
    const double yr = std::clamp(f.y_right, y0, y1), yl = std::clamp(-f.y_right, y0, y1);
    const double right = (std::sqrt(std::max(0.0, f.at - f.det * yr * yr)) - f.b * yr) * f.inv_a + f.mx;
    const double left = (-std::sqrt(std::max(0.0, f.at - f.det * yl * yl)) - f.b * yl) * f.inv_a + f.mx;
    // tile tx: centres x in [16 tx + 0.5, min(16 tx + 16, W) - 0.5]; kept iff its first centre <= right and
    // its last >= left
    int64_t lo = std::max(r.x0, column(std::ceil((left + 0.5) * (1.0 / TILE) - 1.0)));
    while (lo < r.x1 && double(std::min((lo + 1) * TILE, W)) - 0.5 < left) ++lo;
    const int64_t hi = std::min(r.x1, column(std::floor((right - 0.5) * (1.0 / TILE)) + 1.0));
    if (lo < hi) fn(ty, lo, hi);
  }
}

// A Gaussian's reached tiles as found by for_each_tile_row, kept between the counting and the writing pass:
// up to ROWS tile rows (lo, hi) from row ty0; more rows (a large footprint; rare) are found again when written.
constexpr int ROWS = 4;
struct Spans {
  int32_t ty0 = 0;
  int16_t nrows = 0;  // -1: more than ROWS rows
  uint16_t lo[ROWS], hi[ROWS];
};

// Order-preserving unsigned image of a float / double (negative values flipped): a < b iff key(a) < key(b)
// for every non-NaN value.
inline uint32_t sort_key(float v) {
  uint32_t u;
  std::memcpy(&u, &v, sizeof u);
  return (u & 0x80000000u) ? ~u : (u | 0x80000000u);
}
inline uint64_t sort_key(double v) {
  uint64_t u;
  std::memcpy(&u, &v, sizeof u);
  return (u & 0x8000000000000000ull) ? ~u : (u | 0x8000000000000000ull);
}

// ``ids`` stably sorted by ascending ``depths[id]`` (ties keep the order of ``ids``). float: an LSD radix
// sort of (key << 32 | position) words, 8 bits per pass (256 buckets stay in the L1 cache while they are
// written), all four histograms in one read and a pass skipped where every key has the same digit (the
// exponent byte of depths within a factor of two); double: std::stable_sort.
template <typename T>
std::vector<int64_t> sorted_by_depth(const T* depths, std::vector<int64_t> ids) {
  const size_t n = ids.size();
  if constexpr (std::is_same_v<T, float>) {
    std::vector<uint64_t> word(n), word2(n);
    std::vector<uint32_t> hist(4 * 256, 0);
    for (size_t i = 0; i < n; ++i) {
      const uint32_t key = sort_key(depths[ids[i]]);
      word[i] = (uint64_t(key) << 32) | uint64_t(i);
      for (int p = 0; p < 4; ++p) ++hist[p * 256 + ((key >> (8 * p)) & 255u)];
    }
    for (int p = 0; p < 4; ++p) {
      uint32_t* h = hist.data() + p * 256;
      if (n == 0 || h[(word[0] >> (32 + 8 * p)) & 255u] == n) continue;  // one digit: the order is unchanged
      uint32_t sum = 0;
      for (int d = 0; d < 256; ++d) sum += std::exchange(h[d], sum);
      for (size_t i = 0; i < n; ++i) word2[h[(word[i] >> (32 + 8 * p)) & 255u]++] = word[i];
      word.swap(word2);
    }
    std::vector<int64_t> out(n);
    for (size_t i = 0; i < n; ++i) out[i] = ids[word[i] & 0xffffffffu];
    return out;
  } else {
    std::stable_sort(ids.begin(), ids.end(),
                     [&](int64_t a, int64_t b) { return sort_key(depths[a]) < sort_key(depths[b]); });
  }
  return ids;
}

}  // namespace

std::vector<at::Tensor> bin_tiles(at::Tensor means2d, at::Tensor conics, at::Tensor opacities, at::Tensor extents,
                                  at::Tensor depths, int64_t width, int64_t height, bool cull) {
  const int64_t N = means2d.size(0);
  TORCH_CHECK(means2d.dim() == 2 && means2d.size(1) == 2, "means2d must be [N, 2]");
  TORCH_CHECK(N < (int64_t(1) << 32), "bin_tiles takes at most 2^32 - 1 Gaussians, got ", N);
  TORCH_CHECK(conics.dim() == 2 && conics.size(0) == N && conics.size(1) == 3, "conics must be [N, 3]");
  TORCH_CHECK(opacities.dim() == 1 && opacities.size(0) == N, "opacities must be [N]");
  TORCH_CHECK(extents.dim() == 2 && extents.size(0) == N && extents.size(1) == 2, "extents must be [N, 2]");
  TORCH_CHECK(depths.dim() == 1 && depths.size(0) == N, "depths must be [N]");
  means2d = means2d.contiguous(), conics = conics.contiguous(), opacities = opacities.contiguous();
  extents = extents.to(means2d.scalar_type()).contiguous();
  const int64_t tiles_x = (width + TILE - 1) / TILE, tiles_y = (height + TILE - 1) / TILE;
  const int64_t ntiles = tiles_x * tiles_y;
  depths = depths.contiguous();
  auto offsets = at::zeros({ntiles + 1}, means2d.options().dtype(at::kLong));
  auto rows = at::empty({N}, means2d.options().dtype(at::kDouble));
  double* rowp = rows.data_ptr<double>();
  at::Tensor ids;
  AT_DISPATCH_FLOATING_TYPES(means2d.scalar_type(), "metegs_bin_tiles", [&] {
    using T = scalar_t;
    const T *mp = means2d.data_ptr<T>(), *cp = conics.data_ptr<T>(), *op = opacities.data_ptr<T>();
    const T* ep = extents.data_ptr<T>();
    // Candidate tiles of Gaussian g: its extents' box (empty when the Gaussian is culled).
    auto candidates = [&](int64_t g) {
      const T* e = ep + 2 * g;
      return (e[0] > 0 && e[1] > 0) ? tile_rect(mp + 2 * g, e, tiles_x, tiles_y) : Rect{0, 0, 0, 0};
    };
    // fn(ty, lo, hi) for the reached tiles of Gaussian g, row by row (thresh = alpha_threshold(opacity of g)).
    auto for_each_row = [&](int64_t g, double thresh, auto&& fn) {
      const Rect r = candidates(g);
      if (r.x0 < r.x1 && r.y0 < r.y1)
        for_each_tile_row(footprint(mp + 2 * g, cp + 3 * g, thresh), r, cull, width, height, fn);
    };
    // Every Gaussian's row span (for the compositing) and its reached tiles (spans; more than ROWS tile rows:
    // found again when written).
    std::vector<double> thresh(N);
    std::vector<Spans> spans(N);
    metegs::parallel_for(0, N, 512, [&](int64_t begin, int64_t end) {
      for (int64_t g = begin; g < end; ++g) {
        thresh[g] = alpha_threshold(op[g]);  // one logarithm for the row span and the tile test
        rowp[g] = row_half_height_at(thresh[g], cp[3 * g], cp[3 * g + 1], cp[3 * g + 2]);
        Spans& S = spans[g];
        for_each_row(g, thresh[g], [&](int64_t ty, int64_t lo, int64_t hi) {
          if (S.nrows == 0) S.ty0 = static_cast<int32_t>(ty);
          const int64_t k = ty - S.ty0;
          if (S.nrows >= 0 && k < ROWS && hi <= UINT16_MAX) {  // else (a very wide image too): found again
            for (int64_t j = S.nrows; j < k; ++j) S.lo[j] = S.hi[j] = 0;  // rows skipped in between
            S.lo[k] = static_cast<uint16_t>(lo), S.hi[k] = static_cast<uint16_t>(hi);
            S.nrows = static_cast<int16_t>(k + 1);
          } else {
            S.nrows = -1;
          }
        });
      }
    });
    // fn(ty, lo, hi) for each row of g's reached tiles.
    auto each_span = [&](int64_t g, auto&& fn) {
      const Spans& S = spans[g];
      if (S.nrows >= 0) {
        for (int64_t k = 0; k < S.nrows; ++k) fn(S.ty0 + k, S.lo[k], S.hi[k]);
      } else {
        for_each_row(g, thresh[g], fn);
      }
    };
    // The Gaussians that reach a tile front to back (a stable sort: equal depths keep the id order), then a
    // parallel counting sort by tile: the front-to-back list is cut into chunks; each chunk counts its
    // entries per tile, which gives every chunk its own start in every tile's list, and the chunks then write
    // independently.
    std::vector<int64_t> binned;
    for (int64_t g = 0; g < N; ++g)
      if (spans[g].nrows != 0) binned.push_back(g);
    const std::vector<int64_t> order = sorted_by_depth(depths.data_ptr<T>(), std::move(binned));
    const int64_t NB = static_cast<int64_t>(order.size());
    const int64_t* ord = order.data();
    const int64_t nchunks = std::max<int64_t>(1, std::min<int64_t>(8 * metegs::num_threads(), NB / 512));
    const int64_t per_chunk = (NB + nchunks - 1) / nchunks;
    std::vector<int64_t> cursor(nchunks * ntiles, 0);
    // fn(tile, g) for each list entry of chunk c, front to back.
    auto for_each_entry = [&](int64_t c, auto&& fn) {
      for (int64_t i = c * per_chunk, e = std::min(NB, (c + 1) * per_chunk); i < e; ++i)
        each_span(ord[i], [&](int64_t ty, int64_t lo, int64_t hi) {
          for (int64_t tx = lo; tx < hi; ++tx) fn(ty * tiles_x + tx, ord[i]);
        });
    };
    metegs::parallel_for(0, nchunks, 1, [&](int64_t begin, int64_t end) {
      for (int64_t c = begin; c < end; ++c) {
        int64_t* row_count = cursor.data() + c * ntiles;
        for_each_entry(c, [&](int64_t t, int64_t) { ++row_count[t]; });
      }
    });
    int64_t* off = offsets.data_ptr<int64_t>();
    int64_t M = 0;
    for (int64_t t = 0; t < ntiles; ++t) {
      off[t] = M;
      for (int64_t c = 0; c < nchunks; ++c) {
        const int64_t n = cursor[c * ntiles + t];
        cursor[c * ntiles + t] = M;
        M += n;
      }
    }
    off[ntiles] = M;
    ids = at::empty({M}, offsets.options());
    int64_t* idp = ids.data_ptr<int64_t>();
    metegs::parallel_for(0, nchunks, 1, [&](int64_t begin, int64_t end) {
      for (int64_t c = begin; c < end; ++c) {
        int64_t* next = cursor.data() + c * ntiles;
        for_each_entry(c, [&](int64_t t, int64_t g) { idp[next[t]++] = g; });
      }
    });
  });
  return {ids, offsets, rows};
}

}  // namespace metegs_cpu
