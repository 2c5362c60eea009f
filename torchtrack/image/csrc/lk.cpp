// Pyramidal Lucas-Kanade (Bouguet), the inner loop of torchtrack/image/lk.py as one CPU operator.
//
// torchtrack::lk_track runs, per point and independently of every other point (at::parallel_for over points):
// the templates of all levels (bilinear window with a 1-pixel rim, Scharr gradients, gradient matrix H, OpenCV's
// min_eig rule), then coarse to fine the inverse-compositional steps H^-1 g (T - J), Newton steps on the same normal
// equations from iteration ic_iters on, per-point early stop (update <= eps, left the sampleable area, a Newton step
// not halved), the status rule (converged at level 0 and ended inside the image) and the residual (mean |J - T| over
// the final level-0 windows). The arithmetic follows the pure-torch reference step by step (lk.py: _Sampler.bilinear,
// _gradients, _template, _inverse_2x2, _newton, _iterate, _track_chunk) in float32; sums run in another order, so the
// tracks agree within tests/tolerances.py (LK_OP_PX), not bit for bit.
//
// Buffers are those of torchtrack.image.pyramid.Pyramid: one flat (C, R, S) float32 buffer per pyramid, channel
// stride `plane`, row stride `stride`, every image padded by `pad` pixels; base[l, b] is the flat index of pixel
// (0, 0) of level l of image b (channel 0).

#include <ATen/Parallel.h>
#include <ATen/core/Tensor.h>
#include <ATen/ops/empty.h>
#include <torch/library.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <vector>

namespace {

// AVX2 + FMA and baseline builds of the hot functions, picked at load time (the cached library runs on any x86-64).
#if defined(__x86_64__) && defined(__GNUC__) && !defined(__clang__) && __GNUC__ >= 11  // x86-64-v3: GCC 11+
#define CLONES __attribute__((target_clones("arch=x86-64-v3", "default")))
#else
#define CLONES
#endif

constexpr float kGradScale = 13.0f / 32.0f;  // lk.py _GRAD_SCALE: the gradients below are Scharr / this

// torch.lerp's formula (ATen/native/Lerp.h), one weight for a whole row: base + coeff * (b - a), base = a when
// |w| < 0.5, else b. Loops take the base as a pointer offset (off = 0 or 1), which keeps them free of branches.
struct Lerp {
  int off;
  float coeff;
  explicit Lerp(float w) : off(std::abs(w) < 0.5f ? 0 : 1), coeff(off ? w - 1.0f : w) {}
};

struct Geometry {
  const float* prev;
  const float* next;
  const int64_t* base_prev;  // (L, B)
  const int64_t* base_next;  // (L, B)
  const int64_t* sizes;      // (L, 2): H_l, W_l
  int64_t batch, stride, plane, channels, pad;
  int window;
};

// Bilinear (C, m, m) window centred at q (level px), m = window + 2 extra: lk.py _Sampler.bilinear (no clamping; the
// caller keeps q inside the padded image). rows: scratch of (m + 1) floats.
CLONES void bilinear(const Geometry& g, const float* flat, int64_t base, float qx, float qy, int m, float* out, float* rows) {
  const float flx = std::floor(qx), fly = std::floor(qy);
  const Lerp ly(qy - fly), lx(qx - flx);
  const int h = m / 2;
  const int64_t start = base + (static_cast<int64_t>(fly) - h) * g.stride + static_cast<int64_t>(flx) - h;
  for (int64_t c = 0; c < g.channels; ++c) {
    const float* p = flat + c * g.plane + start;
    for (int i = 0; i < m; ++i, out += m) {
      const float* r0 = p + i * g.stride;
      const float* r1 = r0 + g.stride;
      const float* rb = ly.off ? r1 : r0;
      for (int j = 0; j <= m; ++j) rows[j] = rb[j] + ly.coeff * (r1[j] - r0[j]);
      const float* xb = rows + lx.off;
      for (int j = 0; j < m; ++j) out[j] = xb[j] + lx.coeff * (rows[j + 1] - rows[j]);
    }
  }
}

// Template of one point at one level: lk.py _template. gx, gy: (C, w, w + 1) unscaled Scharr gradients, column w 0.
struct Template {
  float tg0, tg1;                   // g . T
  float hi00, hi01, hi10, hi11;     // H^-1 / _GRAD_SCALE
  float det;                        // det H
  bool degenerate;
};

CLONES Template make_template(const Geometry& g, int64_t base, float x, float y, float min_eig, float* gx, float* gy,
                       float* scratch) {
  const int w = g.window, m = w + 2;
  float* patch = scratch;  // (C, m, m)
  float* rows = scratch + g.channels * m * m;
  bilinear(g, g.prev, base, x, y, m, patch, rows);
  const float w3 = 3.0f / 13.0f;  // lk.py _gradients: lerp(centre, sum of the outer rows, 3/13)
  float a00 = 0, a01 = 0, a11 = 0, t0 = 0, t1 = 0;
  for (int64_t c = 0; c < g.channels; ++c) {
    const float* p = patch + c * m * m;
    for (int i = 0; i < w; ++i) {
      const float* r0 = p + i * m;
      const float* r1 = r0 + m;
      const float* r2 = r1 + m;
      float* ox = gx + (c * w + i) * (w + 1);
      float* oy = gy + (c * w + i) * (w + 1);
      ox[w] = oy[w] = 0.0f;
#pragma omp simd reduction(+ : a00, a01, a11, t0, t1)
      for (int j = 0; j < w; ++j) {
        const float dx0 = r0[j + 2] - r0[j], dx1 = r1[j + 2] - r1[j], dx2 = r2[j + 2] - r2[j];
        const float dy0 = r2[j] - r0[j], dy1 = r2[j + 1] - r0[j + 1], dy2 = r2[j + 2] - r0[j + 2];
        const float vx = dx1 + w3 * (dx0 + dx2 - dx1), vy = dy1 + w3 * (dy0 + dy2 - dy1), t = r1[j + 1];
        ox[j] = vx;
        oy[j] = vy;
        a00 += vx * vx;
        a01 += vx * vy;
        a11 += vy * vy;
        t0 += vx * t;
        t1 += vy * t;
      }
    }
  }
  Template out;
  out.tg0 = t0;
  out.tg1 = t1;
  const float lam = 0.5f * (a00 + a11 - std::sqrt((a00 - a11) * (a00 - a11) + 4.0f * a01 * a01));
  // OpenCV's minEig: intensities on 0..255, 1/32-scaled Scharr (1/1024 on products), per window pixel.
  const float unit = static_cast<float>(double(kGradScale) * kGradScale * 255.0 * 255.0 / 1024.0 / (w * w));
  out.det = a00 * a11 + a01 * (-a01);
  const float s = static_cast<float>(1.0 / double(kGradScale)) / out.det;
  out.hi00 = a11 * s;
  out.hi01 = -a01 * s;
  out.hi10 = -a01 * s;
  out.hi11 = a00 * s;
  out.degenerate = lam * unit < min_eig || !(out.det > 0.0f);
  return out;
}

struct Settings {
  int iters, ic_iters;
  float eps2, min_eig;
};

// LK iterations at one level from q (level px): lk.py _iterate for one point. Returns converged.
// The sums run over flat rows of w + 1 values (gx, gy have a zero column w), so that they vectorise as one loop.
CLONES bool iterate(const Geometry& g, int level, int64_t base, const Template& t, const float* gx, const float* gy,
                    const Settings& s, float& qx, float& qy, float* scratch) {
  const int w = g.window, r = w / 2, n1 = w + 1, len = w * n1;
  const float lo = static_cast<float>(r + 1 - g.pad);
  const float hix = static_cast<float>(g.sizes[2 * level + 1] + g.pad - r - 3);
  const float hiy = static_cast<float>(g.sizes[2 * level] + g.pad - r - 3);
  float* jy = scratch;           // (w, w + 1) + 1: the y-interpolated patch (lk.py _iterate's jy)
  float* dpy = jy + len + 1;     // (w, w + 1) + 1: the patch's y differences (lk.py _newton's dpy)
  jy[len] = dpy[len] = 0.0f;
  float d2_prev = 0.0f;
  for (int j = 0; j < s.iters; ++j) {
    if (!(std::isfinite(qx) && std::isfinite(qy))) return false;
    const float fl0x = std::floor(qx), fl0y = std::floor(qy);
    const float flx = std::min(std::max(fl0x, lo), hix), fly = std::min(std::max(fl0y, lo), hiy);
    const Lerp ly(qy - fly), lx(qx - flx);
    const bool newton = j >= s.ic_iters;
    const int64_t start = base + (static_cast<int64_t>(fly) - r) * g.stride + static_cast<int64_t>(flx) - r;
    float s0 = 0, s1 = 0, m00 = 0, m01 = 0, m10 = 0, m11 = 0;
    for (int64_t c = 0; c < g.channels; ++c) {
      const float* p = g.next + c * g.plane + start;
      for (int i = 0; i < w; ++i) {
        const float* r0 = p + i * g.stride;
        const float* r1 = r0 + g.stride;
        float* o = jy + i * n1;
        const float* rb = ly.off ? r1 : r0;
        for (int k = 0; k < n1; ++k) o[k] = rb[k] + ly.coeff * (r1[k] - r0[k]);
        if (newton) {
          float* d = dpy + i * n1;
          for (int k = 0; k < n1; ++k) d[k] = r1[k] - r0[k];
        }
      }
      const float* ax = gx + c * len;
      const float* ay = gy + c * len;
      const float* jb = jy + lx.off;
      const float* db = dpy + lx.off;
      const float cx = lx.coeff;
      if (!newton) {
#pragma omp simd reduction(+ : s0, s1)
        for (int k = 0; k < len; ++k) {
          const float v = jb[k] + cx * (jy[k + 1] - jy[k]);
          s0 += v * ax[k];
          s1 += v * ay[k];
        }
      } else {  // lk.py _newton: d/dx from jy, d/dy from the raw patch, interpolated in x
#pragma omp simd reduction(+ : s0, s1, m00, m01, m10, m11)
        for (int k = 0; k < len; ++k) {
          const float djx = jy[k + 1] - jy[k];
          const float v = jb[k] + cx * djx, djy = db[k] + cx * (dpy[k + 1] - dpy[k]);
          s0 += v * ax[k];
          s1 += v * ay[k];
          m00 += djx * ax[k];
          m01 += djx * ay[k];
          m10 += djy * ax[k];
          m11 += djy * ay[k];
        }
      }
    }
    const float r0 = t.tg0 - s0, r1 = t.tg1 - s1;  // (T - J) g^T
    float dx = r0 * t.hi00 + r1 * t.hi10, dy = r0 * t.hi01 + r1 * t.hi11;  // inverse-compositional step
    if (newton) {
      const float det = m00 * m11 + m01 * (-m10);
      if (det > static_cast<float>(0.01 * double(kGradScale)) * t.det) {  // det(H^-1 M) > 0.01
        const float inv = 1.0f / det;
        const float i00 = m11 * inv, i01 = -m01 * inv, i10 = -m10 * inv, i11 = m00 * inv;
        dx = r0 * i00 + r1 * i10;
        dy = r0 * i01 + r1 * i11;
      }
    }
    qx += dx;
    qy += dy;
    const float d2 = dx * dx + dy * dy;
    const bool conv = d2 <= s.eps2;
    bool stop = conv || flx != fl0x || fly != fl0y;  // converged, or left the sampleable area
    if (j > s.ic_iters) stop = stop || d2 > 0.25f * d2_prev;  // a Newton step not halved: no convergence
    d2_prev = d2;
    if (stop) return conv;
  }
  return false;
}

inline bool inside(float x, float y, int64_t h, int64_t w) {
  return x >= 0.0f && y >= 0.0f && x <= static_cast<float>(w - 1) && y <= static_cast<float>(h - 1);
}

std::tuple<at::Tensor, at::Tensor, at::Tensor> lk_track_cpu(
    const at::Tensor& prev, const at::Tensor& next, const at::Tensor& base_prev, const at::Tensor& base_next,
    const at::Tensor& sizes, const at::Tensor& points, const at::Tensor& image_index, const at::Tensor& init,
    int64_t stride, int64_t plane, int64_t pad, int64_t window, int64_t iters, int64_t ic_iters, double eps,
    double min_eig, bool with_residual) {
  TORCH_CHECK(prev.device().is_cpu() && next.device().is_cpu(), "lk_track: CPU tensors only");
  TORCH_CHECK(prev.scalar_type() == at::kFloat && next.scalar_type() == at::kFloat && prev.is_contiguous() &&
                  next.is_contiguous() && prev.dim() == 1 && next.dim() == 1 &&
                  (next.numel() == prev.numel() || prev.numel() == plane),
              "lk_track: prev and next must be contiguous 1-D float32 buffers, equal unless of one channel");
  const int64_t levels = sizes.size(0), batch = base_prev.size(1);
  TORCH_CHECK(sizes.dim() == 2 && sizes.size(1) == 2 && base_prev.dim() == 2 && base_prev.size(0) == levels &&
                  base_next.sizes() == base_prev.sizes() && levels >= 1,
              "lk_track: sizes (L, 2), base_prev and base_next (L, B)");
  for (const auto* t : {&sizes, &base_prev, &base_next, &image_index})
    TORCH_CHECK(t->scalar_type() == at::kLong && t->is_contiguous(), "lk_track: index tensors must be int64");
  const int64_t n = points.size(0);
  TORCH_CHECK(points.scalar_type() == at::kFloat && init.scalar_type() == at::kFloat && points.is_contiguous() &&
                  init.is_contiguous() && points.dim() == 2 && points.size(1) == 2 && init.sizes() == points.sizes() &&
                  image_index.dim() == 1 && image_index.size(0) == n,
              "lk_track: points and init (P, 2) float32, image_index (P,)");
  TORCH_CHECK(window >= 3 && window % 2 == 1 && window / 2 + 3 <= pad && iters >= 1 && plane > 0 &&
                  prev.numel() % plane == 0,
              "lk_track: need an odd window >= 3 that fits the padding, iters >= 1");
  const int64_t* img = image_index.data_ptr<int64_t>();
  for (int64_t i = 0; i < n; ++i) TORCH_CHECK(img[i] >= 0 && img[i] < batch, "lk_track: image_index out of range");

  Geometry g{prev.data_ptr<float>(), next.data_ptr<float>(), base_prev.data_ptr<int64_t>(),
             base_next.data_ptr<int64_t>(), sizes.data_ptr<int64_t>(), batch, stride, plane, prev.numel() / plane,
             pad, static_cast<int>(window)};
  const Settings s{static_cast<int>(iters), static_cast<int>(ic_iters), static_cast<float>(eps * eps),
                   static_cast<float>(min_eig)};
  auto out = at::empty({n, 2}, points.options());
  auto status = at::empty({n}, points.options().dtype(at::kBool));
  auto residual = at::empty({n}, points.options());
  const float* x0 = points.data_ptr<float>();
  const float* x1 = init.data_ptr<float>();
  float* po = out.data_ptr<float>();
  bool* so = status.data_ptr<bool>();
  float* ro = residual.data_ptr<float>();
  const int64_t k = g.channels * window * (window + 1), h0 = g.sizes[0], w0 = g.sizes[1];
  const int64_t m = window + 2;

  at::parallel_for(0, n, 16, [&](int64_t begin, int64_t end) {
    std::vector<float> grads(2 * levels * k), scratch(std::max(g.channels * m * m + m + 1, 2 * k + 2));
    std::vector<Template> tpl(levels);
    for (int64_t p = begin; p < end; ++p) {
      const float px = x0[2 * p], py = x0[2 * p + 1];
      po[2 * p] = px;  // the input where not tracked
      po[2 * p + 1] = py;
      so[p] = false;
      ro[p] = 0.0f;
      if (!inside(px, py, h0, w0)) continue;
      for (int64_t l = 0; l < levels; ++l) {  // level coordinates x0 * 0.5^l (exact)
        const float sc = std::ldexp(1.0f, -static_cast<int>(l));
        tpl[l] = make_template(g, g.base_prev[l * batch + img[p]], px * sc, py * sc, s.min_eig,
                               grads.data() + 2 * l * k, grads.data() + (2 * l + 1) * k, scratch.data());
      }
      // degenerate at the finest level: not tracked at all (lk.py _track_chunk)
      if (tpl[0].degenerate) continue;
      float ux = x1[2 * p], uy = x1[2 * p + 1];
      bool conv = false;
      for (int64_t l = levels - 1; l >= 0; --l) {
        if (tpl[l].degenerate) continue;  // degenerate at a coarse level: skip it (OpenCV)
        const float sc = std::ldexp(1.0f, -static_cast<int>(l));
        float qx = ux * sc, qy = uy * sc;
        conv = iterate(g, static_cast<int>(l), g.base_next[l * batch + img[p]], tpl[l], grads.data() + 2 * l * k,
                       grads.data() + (2 * l + 1) * k, s, qx, qy, scratch.data());
        ux = qx / sc;
        uy = qy / sc;
      }
      po[2 * p] = ux;
      po[2 * p + 1] = uy;
      const bool ok = conv && inside(ux, uy, h0, w0);
      so[p] = ok;
      if (ok && with_residual) {  // lk.py _residual: mean |J - T| over the final level-0 windows
        float* t = grads.data();  // the templates are no longer needed
        float* j = grads.data() + k;
        bilinear(g, g.prev, g.base_prev[img[p]], px, py, static_cast<int>(window), t, scratch.data());
        bilinear(g, g.next, g.base_next[img[p]], ux, uy, static_cast<int>(window), j, scratch.data());
        const int64_t kw = g.channels * window * window;
        double sum = 0.0;
        for (int64_t i = 0; i < kw; ++i) sum += std::abs(j[i] - t[i]);
        ro[p] = static_cast<float>(sum / static_cast<double>(kw));
      }
    }
  });
  return {out, status, residual};
}

}  // namespace

TORCH_LIBRARY(torchtrack, m) {
  m.def(
      "lk_track(Tensor prev, Tensor next, Tensor base_prev, Tensor base_next, Tensor sizes, Tensor points, "
      "Tensor image_index, Tensor init, int stride, int plane, int pad, int window, int iters, int ic_iters, "
      "float eps, float min_eig, bool with_residual) -> (Tensor, Tensor, Tensor)");
}

TORCH_LIBRARY_IMPL(torchtrack, CPU, m) { m.impl("lk_track", &lk_track_cpu); }
