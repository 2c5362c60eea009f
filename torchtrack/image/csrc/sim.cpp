// Shape index map of a depth image, eq. (8): torchtrack/image/shape_index.py's shape_index + compute_sim's image as
// one CPU operator (torchtrack::shape_index_map), a pass per stage over one image's decimated grid instead of ~60
// tensor operations. The arithmetic follows the reference stage by stage in float32 (normalised binomial smoothing
// of inverse depth, depth-step mask grown over the smoothing window, curvatures of the smoothed inverse-depth
// surface, SI and curvedness, masks, linear upsampling with NaN marking masked samples, the 8-bit-like image); the
// reference stays the test oracle (tests/test_sim_op.py).

#include <ATen/Parallel.h>
#include <ATen/core/Tensor.h>
#include <ATen/ops/empty.h>
#include <torch/library.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <limits>
#include <vector>

namespace {

#if defined(__x86_64__) && defined(__GNUC__) && !defined(__clang__) && __GNUC__ >= 11  // x86-64-v3: GCC 11+
#define SIM_CLONES __attribute__((target_clones("arch=x86-64-v3", "default")))
#else
#define SIM_CLONES
#endif

// shape_index.py _binomial along one axis of an (h, w) grid: ``passes`` [1 2 1]/4 filters, pairs as [1 4 6 4 1]/16,
// zero padding; the terms are added centre, then -2, +2, -1, +1, without FMA (the reference, kornia's convolution,
// sums in its own order: tests/tolerances.py SIM_OP_*). Along rows (x) the interior runs without branches; along
// columns (y) whole rows are combined, so both loops vectorise.
inline float tap5(float c, float m2, float p2, float m1, float p1) {
  return ((((c * 0.375f) + 0.0625f * m2) + 0.0625f * p2) + 0.25f * m1) + 0.25f * p1;
}
inline float tap3(float c, float m1, float p1) { return ((c * 0.5f) + 0.25f * m1) + 0.25f * p1; }

void binomial_x(const float* a, float* b, int h, int w, int taps) {
  for (int i = 0; i < h; ++i, a += w, b += w) {
    if (w < 5) {  // tiny rows: the general form
      for (int j = 0; j < w; ++j) {
        auto at = [&](int k) { return k >= 0 && k < w ? a[k] : 0.0f; };
        b[j] = taps == 5 ? tap5(a[j], at(j - 2), at(j + 2), at(j - 1), at(j + 1)) : tap3(a[j], at(j - 1), at(j + 1));
      }
      continue;
    }
    if (taps == 5) {
      b[0] = ((a[0] * 0.375f) + 0.0625f * a[2]) + 0.25f * a[1];
      b[1] = (((a[1] * 0.375f) + 0.0625f * a[3]) + 0.25f * a[0]) + 0.25f * a[2];
      for (int j = 2; j < w - 2; ++j) b[j] = tap5(a[j], a[j - 2], a[j + 2], a[j - 1], a[j + 1]);
      b[w - 2] = (((a[w - 2] * 0.375f) + 0.0625f * a[w - 4]) + 0.25f * a[w - 3]) + 0.25f * a[w - 1];
      b[w - 1] = ((a[w - 1] * 0.375f) + 0.0625f * a[w - 3]) + 0.25f * a[w - 2];
    } else {
      b[0] = (a[0] * 0.5f) + 0.25f * a[1];
      for (int j = 1; j < w - 1; ++j) b[j] = tap3(a[j], a[j - 1], a[j + 1]);
      b[w - 1] = (a[w - 1] * 0.5f) + 0.25f * a[w - 2];
    }
  }
}

void binomial_y(const float* a, float* b, int h, int w, int taps) {
  for (int i = 0; i < h; ++i) {
    const float* c = a + int64_t(i) * w;
    const float* m1 = i >= 1 ? c - w : nullptr;
    const float* p1 = i + 1 < h ? c + w : nullptr;
    const float* m2 = i >= 2 ? c - 2 * w : nullptr;
    const float* p2 = i + 2 < h ? c + 2 * w : nullptr;
    float* o = b + int64_t(i) * w;
    const float k0 = taps == 5 ? 0.375f : 0.5f;
    for (int j = 0; j < w; ++j) o[j] = c[j] * k0;
    if (taps == 5) {
      if (m2) for (int j = 0; j < w; ++j) o[j] = o[j] + 0.0625f * m2[j];
      if (p2) for (int j = 0; j < w; ++j) o[j] = o[j] + 0.0625f * p2[j];
    }
    if (m1) for (int j = 0; j < w; ++j) o[j] = o[j] + 0.25f * m1[j];
    if (p1) for (int j = 0; j < w; ++j) o[j] = o[j] + 0.25f * p1[j];
  }
}

void binomial(std::vector<float>& x, std::vector<float>& y, int h, int w, int passes) {
  std::vector<int> taps(passes / 2, 5);
  if (passes % 2) taps.push_back(3);
  for (int t : taps) {
    binomial_x(x.data(), y.data(), h, w, t);
    std::swap(x, y);
  }
  for (int t : taps) {
    binomial_y(x.data(), y.data(), h, w, t);
    std::swap(x, y);
  }
}

// Dilation of a {0, 1} mask by a (2 r + 1)^2 square (shape_index.py _grow: box sums > 0.5), separable.
void grow(std::vector<uint8_t>& m, int h, int w, int r) {
  if (r <= 0) return;
  std::vector<uint8_t> t(m.size());
  for (int i = 0; i < h; ++i) {  // rows: running count over the window
    const uint8_t* a = m.data() + int64_t(i) * w;
    uint8_t* b = t.data() + int64_t(i) * w;
    int count = 0;
    for (int j = 0; j < std::min(r, w); ++j) count += a[j];
    for (int j = 0; j < w; ++j) {
      if (j + r < w) count += a[j + r];
      if (j - r - 1 >= 0) count -= a[j - r - 1];
      b[j] = count > 0;
    }
  }
  std::vector<int> count(w, 0);
  for (int i = 0; i < std::min(r, h); ++i)
    for (int j = 0; j < w; ++j) count[j] += t[int64_t(i) * w + j];
  for (int i = 0; i < h; ++i) {
    if (i + r < h)
      for (int j = 0; j < w; ++j) count[j] += t[int64_t(i + r) * w + j];
    if (i - r - 1 >= 0)
      for (int j = 0; j < w; ++j) count[j] -= t[int64_t(i - r - 1) * w + j];
    for (int j = 0; j < w; ++j) m[int64_t(i) * w + j] = count[j] > 0;
  }
}

struct Params {
  double smooth_sigma, min_curvature, max_step, min_support, max_incidence, fill;
  int decimate;
};

// One image: depth (H, W) metres, K (3, 3) -> si, valid, image (H, W).
SIM_CLONES void sim_one(const float* depth, const float* K, int H, int W, const Params& p, float* si_out,
                        bool* valid_out, float* image_out) {
  const int d = p.decimate, h = (H + d - 1) / d, w = (W + d - 1) / d;
  const int64_t n = int64_t(h) * w;
  const float fx = K[0] / float(d), fy = K[4] / float(d), cx = K[2] / float(d), cy = K[5] / float(d);
  std::vector<float> z(n), has(n), sup(n), inv(n), tmp(n);
  for (int i = 0; i < h; ++i)
    for (int j = 0; j < w; ++j) {
      const float v = depth[int64_t(d) * i * W + int64_t(d) * j];
      const int64_t k = int64_t(i) * w + j;
      z[k] = v;
      has[k] = v > 0.0f ? 1.0f : 0.0f;
      sup[k] = has[k];
      inv[k] = has[k] / (v + (1.0f - has[k]));  // inverse depth, 0 where missing
    }
  const double q = p.smooth_sigma / d;
  const int passes = static_cast<int>(std::nearbyint(2.0 * q * q));  // Python's round: half to even
  if (passes) {
    for (auto* x : {&sup, &inv}) binomial(*x, tmp, h, w, passes);
  }
  // edges: a valid 4-neighbour more than max_step * d * depth away, grown over the smoothing window
  const float ms = static_cast<float>(p.max_step * d);
  std::vector<uint8_t> jx(n, 0), jy(n, 0), edge(n, 0);
  for (int i = 0; i < h; ++i)
    for (int j = 0; j < w; ++j) {
      const int64_t k = int64_t(i) * w + j;
      if (j + 1 < w) jx[k] = (std::abs(z[k + 1] - z[k]) - ms * std::min(z[k + 1], z[k]) > 0.0f) && has[k] > 0 && has[k + 1] > 0;
      if (i + 1 < h) jy[k] = (std::abs(z[k + w] - z[k]) - ms * std::min(z[k + w], z[k]) > 0.0f) && has[k] > 0 && has[k + w] > 0;
    }
  for (int i = 0; i < h; ++i)
    for (int j = 0; j < w; ++j) {
      const int64_t k = int64_t(i) * w + j;
      edge[k] = jx[k] || (j > 0 && jx[k - 1]) || jy[k] || (i > 0 && jy[k - w]);
    }
  grow(edge, h, w, passes + 1);
  const float min_support = static_cast<float>(p.min_support), min_curv = static_cast<float>(p.min_curvature);
  const float min_cos = static_cast<float>(std::cos(p.max_incidence * M_PI / 180.0));
  const float nan = std::numeric_limits<float>::quiet_NaN(), pi = static_cast<float>(M_PI);
  std::vector<float> ws(n), si(n);
  for (int64_t k = 0; k < n; ++k) {
    float v = inv[k] / std::max(sup[k], 1e-6f);
    ws[k] = v <= 0.0f ? 1.0f : v;  // 1 where nothing is known (masked anyway)
  }
  for (int i = 0; i < h; ++i) {
    const int iu = std::max(i - 1, 0), id = std::min(i + 1, h - 1);  // replicate padding
    const float y = (float(i) - cy) / fy;
    for (int j = 0; j < w; ++j) {
      const int64_t k = int64_t(i) * w + j;
      const bool ok = i > 0 && j > 0 && i < h - 1 && j < w - 1 && has[k] > 0 && sup[k] >= min_support && !edge[k];
      if (!ok) {
        si[k] = nan;
        continue;
      }
      const int jl = std::max(j - 1, 0), jr = std::min(j + 1, w - 1);
      const float* ru = ws.data() + int64_t(iu) * w;
      const float* rc = ws.data() + int64_t(i) * w;
      const float* rd = ws.data() + int64_t(id) * w;
      const float c = rc[j], l = rc[jl], r = rc[jr], up = ru[j], dn = rd[j];
      // shape_index.py _curvatures, term by term
      const float w_s = 0.5f * fx * (r - l), w_t = 0.5f * fy * (dn - up);
      const float c2x = 2.0f * c;
      const float w_ss = fx * fx * (r + l - c2x), w_tt = fy * fy * (dn + up - c2x);
      const float w_st = 0.25f * fx * fy * (rd[jr] - rd[jl] - ru[jr] + ru[jl]);
      const float x = (float(j) - cx) / fx;
      const float xs = x * w_s, ys = y * w_s, xt = x * w_t, yt = y * w_t;
      const float ax = c - xs, by = c - yt;
      const float ws2 = w_s * w_s, wt2 = w_t * w_t;
      const float q2 = ws2 + wt2 + (ax - yt) * (ax - yt);
      const float aa = ax * ax + ys * ys + ws2, bb = xt * xt + by * by + wt2, ab = w_s * w_t - ax * xt - ys * by;
      const float qq = std::sqrt(q2);
      const float mean_c = c * (aa * w_tt - 2.0f * ab * w_st + bb * w_ss) / (2.0f * q2 * qq);
      const float c2 = c * c;
      const float gauss_c = c2 * c2 * (w_ss * w_tt - w_st * w_st) / (q2 * q2);
      const float cos_inc = c / (qq * std::sqrt(1.0f + x * x + y * y));
      const float disc = std::sqrt(std::max(mean_c * mean_c - gauss_c, 1e-30f));  // (k1 - k2) / 2
      const float s = 0.5f - std::atan2(mean_c, disc) / pi;                     // eq. (8)
      const float curv = std::sqrt(std::max(2.0f * mean_c * mean_c - gauss_c, 1e-30f));
      si[k] = (curv >= min_curv && cos_inc >= min_cos) ? s : nan;
    }
  }
  // linear upsampling to (H, W), edge-clamped; NaN spreads to every pixel that mixes a masked sample
  const float fill = static_cast<float>(p.fill);
  auto lerp = [](float a, float b, float t) { return std::abs(t) < 0.5f ? a + t * (b - a) : b - (b - a) * (1.0f - t); };
  std::vector<float> rows(int64_t(h) * W), line(W);
  for (int i = 0; i < h; ++i) {
    const float* a = si.data() + int64_t(i) * w;
    float* o = rows.data() + int64_t(i) * W;
    for (int X = 0; X < W; ++X) {
      const int j = X / d, ph = X % d;
      o[X] = (ph == 0 || j == w - 1) ? a[j] : lerp(a[j], a[j + 1], float(ph) / float(d));
    }
  }
  for (int Y = 0; Y < H; ++Y) {
    const int i = Y / d, ph = Y % d;
    const float* a = rows.data() + int64_t(i) * W;
    const float* v = a;
    if (ph != 0 && i != h - 1) {  // lerp(a, b, t) of two sample rows (torch.lerp's formula)
      const float* b = a + W;
      const float t = float(ph) / float(d);
      const bool small = std::abs(t) < 0.5f;
      const float* base = small ? a : b;
      const float coeff = small ? t : t - 1.0f;
      for (int X = 0; X < W; ++X) line[X] = base[X] + coeff * (b[X] - a[X]);
      v = line.data();
    }
    const int64_t k = int64_t(Y) * W;
    for (int X = 0; X < W; ++X) {
      const bool ok = v[X] == v[X];
      const float s = ok ? v[X] : fill;
      si_out[k + X] = s;
      valid_out[k + X] = ok;
      image_out[k + X] = std::nearbyint(s * 255.0f) / 255.0f;
    }
  }
}

std::tuple<at::Tensor, at::Tensor, at::Tensor> shape_index_map_cpu(const at::Tensor& depth, const at::Tensor& K,
                                                                   double smooth_sigma, double min_curvature,
                                                                   double max_step, double min_support,
                                                                   double max_incidence, int64_t decimate,
                                                                   double fill) {
  TORCH_CHECK(depth.device().is_cpu() && depth.scalar_type() == at::kFloat && depth.is_contiguous() &&
                  depth.dim() == 4 && depth.size(1) == 1,
              "shape_index_map: depth must be a contiguous float32 (B, 1, H, W) CPU tensor");
  TORCH_CHECK(K.scalar_type() == at::kFloat && K.is_contiguous() && K.dim() == 3 && K.size(0) == depth.size(0) &&
                  K.size(1) == 3 && K.size(2) == 3,
              "shape_index_map: K must be a contiguous float32 (B, 3, 3)");
  TORCH_CHECK(decimate >= 1, "shape_index_map: decimate must be >= 1");
  const int64_t B = depth.size(0), H = depth.size(2), W = depth.size(3);
  TORCH_CHECK(H >= 3 * decimate && W >= 3 * decimate, "shape_index_map: image too small");
  const Params p{smooth_sigma, min_curvature, max_step, min_support, max_incidence, fill, static_cast<int>(decimate)};
  auto si = at::empty(depth.sizes(), depth.options()), image = at::empty(depth.sizes(), depth.options());
  auto valid = at::empty(depth.sizes(), depth.options().dtype(at::kBool));
  const float* dp = depth.data_ptr<float>();
  const float* kp = K.data_ptr<float>();
  at::parallel_for(0, B, 1, [&](int64_t begin, int64_t end) {
    for (int64_t b = begin; b < end; ++b)
      sim_one(dp + b * H * W, kp + 9 * b, int(H), int(W), p, si.data_ptr<float>() + b * H * W,
              valid.data_ptr<bool>() + b * H * W, image.data_ptr<float>() + b * H * W);
  });
  return {si, valid, image};
}

}  // namespace

TORCH_LIBRARY_FRAGMENT(torchtrack, m) {
  m.def(
      "shape_index_map(Tensor depth, Tensor K, float smooth_sigma, float min_curvature, float max_step, "
      "float min_support, float max_incidence, int decimate, float fill) -> (Tensor, Tensor, Tensor)");
}

TORCH_LIBRARY_IMPL(torchtrack, CPU, m) { m.impl("shape_index_map", &shape_index_map_cpu); }
