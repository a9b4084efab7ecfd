// Tile binning for the metegs `cpu` rasteriser: per 16x16 tile, the ids of the Gaussians that can
// touch it, front to back, as one flat list with offsets (CSR).
//
// Candidate tiles are the same boxes as metegs.render.tiles.bin_gaussians (the opacity-aware
// extents). With `cull`, a candidate tile is kept only if the Gaussian's alpha can reach 1/255 at
// one of the tile's pixel centres: the minimum of the conic's quadratic form over the rectangle of
// pixel centres is compared with 2 ln(255 o), with a small safety margin, so no contribution is
// lost and the image is unchanged, while the long thin footprints of anisotropic Gaussians stop
// costing whole rows of tiles. Ordering: a stable depth sort of the Gaussians, then a counting sort
// by tile (O(N log N + M)), instead of a sort of M 64-bit keys.

#include "metegs_cpu.h"

#include <ATen/Parallel.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <type_traits>
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

// One Gaussian's footprint as the tile test needs it: its conic (a, b, c) with the reciprocals of a and c
// (the test runs for every candidate tile; divisions there cost more than the rest of it), its mean and
// the bound 2 ln(255 o) on the quadratic form.
struct Footprint {
  double a, b, c, inv_a, inv_c, mx, my, thresh;
  bool definite;  // a > 0, c > 0 and ac - b^2 > 0; else every candidate tile is kept (no culling)
};

template <typename T>
inline Footprint footprint(const T* m, const T* conic, double thresh) {
  Footprint f;
  f.a = conic[0], f.b = conic[1], f.c = conic[2];
  f.definite = f.a > 0 && f.c > 0 && f.a * f.c - f.b * f.b > 0;
  f.inv_a = f.definite ? 1.0 / f.a : 0.0;
  f.inv_c = f.definite ? 1.0 / f.c : 0.0;
  f.mx = m[0], f.my = m[1];
  f.thresh = thresh;
  return f;
}

// Minimum of q(dx, dy) = a dx^2 + 2 b dx dy + c dy^2 (positive definite) over [X0, X1] x [Y0, Y1],
// and |a| dx^2 + 2 |b dx dy| + |c| dy^2 at the minimiser (the size of the rounding error there).
inline void quad_min(const Footprint& f, double X0, double X1, double Y0, double Y1, double& qmin, double& qabs) {
  if (X0 <= 0 && 0 <= X1 && Y0 <= 0 && 0 <= Y1) {
    qmin = 0;
    qabs = 0;
    return;
  }
  const double a = f.a, b = f.b, c = f.c;
  qmin = std::numeric_limits<double>::infinity();
  qabs = 0;
  auto consider = [&](double x, double y) {
    const double q = a * x * x + 2 * b * x * y + c * y * y;
    if (q < qmin) {
      qmin = q;
      qabs = std::abs(a) * x * x + 2 * std::abs(b * x * y) + std::abs(c) * y * y;
    }
  };
  for (double X : {X0, X1}) consider(X, std::clamp(-b * X * f.inv_c, Y0, Y1));
  for (double Y : {Y0, Y1}) consider(std::clamp(-b * Y * f.inv_a, X0, X1), Y);
}

inline bool tile_reached(const Footprint& f, int64_t tx, int64_t ty, int64_t W, int64_t H) {
  if (!f.definite) return true;
  const double X0 = double(tx * TILE) + 0.5 - f.mx, X1 = double(std::min((tx + 1) * TILE, W) - 1) + 0.5 - f.mx;
  const double Y0 = double(ty * TILE) + 0.5 - f.my, Y1 = double(std::min((ty + 1) * TILE, H) - 1) + 0.5 - f.my;
  double qmin, qabs;
  quad_min(f, X0, X1, Y0, Y1, qmin, qabs);
  return qmin <= f.thresh + 1e-4 * (1.0 + f.thresh + qabs);
}

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
// sort (3 passes of 11 bits, O(n)), several times faster than a comparison sort; double: std::stable_sort.
template <typename T>
std::vector<int64_t> sorted_by_depth(const T* depths, std::vector<int64_t> ids) {
  const size_t n = ids.size();
  if constexpr (std::is_same_v<T, float>) {
    std::vector<uint32_t> key(n), key2(n);
    std::vector<int64_t> ids2(n);
    for (size_t i = 0; i < n; ++i) key[i] = sort_key(depths[ids[i]]);
    for (int shift = 0; shift < 32; shift += 11) {
      std::vector<size_t> hist(2049, 0);
      for (size_t i = 0; i < n; ++i) ++hist[((key[i] >> shift) & 2047u) + 1];
      for (int b = 0; b < 2048; ++b) hist[b + 1] += hist[b];
      for (size_t i = 0; i < n; ++i) {
        const size_t dst = hist[(key[i] >> shift) & 2047u]++;
        key2[dst] = key[i];
        ids2[dst] = ids[i];
      }
      key.swap(key2);
      ids.swap(ids2);
    }
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
  TORCH_CHECK(conics.dim() == 2 && conics.size(0) == N && conics.size(1) == 3, "conics must be [N, 3]");
  TORCH_CHECK(opacities.dim() == 1 && opacities.size(0) == N, "opacities must be [N]");
  TORCH_CHECK(extents.dim() == 2 && extents.size(0) == N && extents.size(1) == 2, "extents must be [N, 2]");
  TORCH_CHECK(depths.dim() == 1 && depths.size(0) == N, "depths must be [N]");
  means2d = means2d.contiguous(), conics = conics.contiguous(), opacities = opacities.contiguous();
  extents = extents.to(means2d.scalar_type()).contiguous();
  const int64_t tiles_x = (width + TILE - 1) / TILE, tiles_y = (height + TILE - 1) / TILE;
  const int64_t ntiles = tiles_x * tiles_y;
  depths = depths.contiguous();
  std::vector<int64_t> count(N, 0);
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
    // fn(j) for each candidate tile of g that passes the test, j = its row-major index in the rectangle r;
    // thresh = alpha_threshold(opacity of g).
    auto for_each_tile = [&](int64_t g, const Rect& r, double thresh, auto&& fn) {
      const int64_t w = r.x1 - r.x0;
      if (!cull) {
        for (int64_t j = 0; j < w * (r.y1 - r.y0); ++j) fn(j);
        return;
      }
      const Footprint f = footprint(mp + 2 * g, cp + 3 * g, thresh);
      for (int64_t ty = r.y0; ty < r.y1; ++ty)
        for (int64_t tx = r.x0; tx < r.x1; ++tx)
          if (tile_reached(f, tx, ty, width, height)) fn((ty - r.y0) * w + tx - r.x0);
    };
    auto tile_of = [&](const Rect& r, int64_t j) {
      const int64_t w = r.x1 - r.x0;
      return static_cast<int32_t>((r.y0 + j / w) * tiles_x + r.x0 + j % w);
    };
    // The first pass (counting) also remembers the kept tiles as a bit mask over the rectangle when it has at
    // most 64 tiles (almost every Gaussian), so that the second pass (writing the lists) repeats the test only
    // for the few large ones (and for a 64-tile rectangle with every tile kept, whose mask reads as NO_MASK).
    std::vector<uint64_t> mask(N, 0);
    constexpr uint64_t NO_MASK = ~uint64_t(0);
    metegs::parallel_for(0, N, 256, [&](int64_t begin, int64_t end) {
      for (int64_t g = begin; g < end; ++g) {
        const double thresh = alpha_threshold(op[g]);  // one logarithm for the row span and the tile test
        rowp[g] = row_half_height_at(thresh, cp[3 * g], cp[3 * g + 1], cp[3 * g + 2]);
        const Rect r = candidates(g);
        const int64_t area = (r.x1 - r.x0) * (r.y1 - r.y0);
        int64_t n = 0;
        uint64_t bits = 0;
        if (area <= 64) {
          for_each_tile(g, r, thresh, [&](int64_t j) {
            bits |= uint64_t(1) << j;
            ++n;
          });
        } else {
          for_each_tile(g, r, thresh, [&](int64_t) { ++n; });
          bits = NO_MASK;
        }
        mask[g] = bits;
        count[g] = n;
      }
    });
    // The binned Gaussians front to back (a stable sort: equal depths keep the id order), their
    // Gaussian-major tile lists, then a stable counting sort by tile.
    std::vector<int64_t> binned;
    for (int64_t g = 0; g < N; ++g)
      if (count[g] > 0) binned.push_back(g);
    const std::vector<int64_t> order = sorted_by_depth(depths.data_ptr<T>(), std::move(binned));
    const int64_t NB = static_cast<int64_t>(order.size());
    const int64_t* ord = order.data();
    std::vector<int64_t> start(NB + 1, 0);
    for (int64_t i = 0; i < NB; ++i) start[i + 1] = start[i] + count[ord[i]];
    const int64_t M = start[NB];
    std::vector<int32_t> tiles_of(M);
    metegs::parallel_for(0, NB, 256, [&](int64_t begin, int64_t end) {
      for (int64_t i = begin; i < end; ++i) {
        const int64_t g = ord[i];
        const Rect r = candidates(g);
        int64_t k = start[i];
        if (mask[g] == NO_MASK)
          for_each_tile(g, r, alpha_threshold(op[g]), [&](int64_t j) { tiles_of[k++] = tile_of(r, j); });
        else
          for (uint64_t bits = mask[g]; bits; bits &= bits - 1) tiles_of[k++] = tile_of(r, __builtin_ctzll(bits));
      }
    });
    int64_t* off = offsets.data_ptr<int64_t>();
    for (int64_t k = 0; k < M; ++k) ++off[tiles_of[k] + 1];
    for (int64_t t = 0; t < ntiles; ++t) off[t + 1] += off[t];
    ids = at::empty({M}, offsets.options());
    int64_t* idp = ids.data_ptr<int64_t>();
    std::vector<int64_t> cursor(off, off + ntiles);
    for (int64_t i = 0; i < NB; ++i) {
      const int64_t g = ord[i];
      for (int64_t k = start[i]; k < start[i + 1]; ++k) idp[cursor[tiles_of[k]]++] = g;
    }
  });
  return {ids, offsets, rows};
}

}  // namespace metegs_cpu
