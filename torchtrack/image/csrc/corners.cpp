// Harris cornerness with the binomial window, torchtrack/image/corners.py's harris(window="binomial",
// method="harris") as one CPU operator (torchtrack::harris_binomial): per image plane the Sobel gradients (replicate
// border, scaled by 1/8), the three products, the binomial window (reflect-101 border) along rows then columns, and
// det M - k tr(M)^2, in a few passes over one plane instead of ~40 tensor operations over the whole batch (the
// selection computes it on every new model frame). The arithmetic follows the reference in float32 term by term and
// in its order; a vectorising compiler may fuse a multiply and an add where torch rounds twice, so the two agree to
// float32 rounding, not bit for bit (tests/test_corners.py).

#include <ATen/Parallel.h>
#include <ATen/core/Tensor.h>
#include <ATen/ops/empty.h>
#include <torch/library.h>

#include <algorithm>
#include <cstdint>
#include <memory>
#include <vector>

namespace {

#if defined(__x86_64__) && defined(__GNUC__) && !defined(__clang__) && __GNUC__ >= 11  // x86-64-v3: GCC 11+
#define CORNER_CLONES __attribute__((target_clones("arch=x86-64-v3", "default")))
#else
#define CORNER_CLONES
#endif

// One pass of the window along a row of n values (n >= 5) into b: corners.py _binomial_window's shifted adds in its
// order (centre; -2, +2 and the reflected ends for 5 taps; -1, +1 and the reflected ends).
template <int TAPS>
inline void window_row(const float* __restrict__ a, float* __restrict__ b, int n) {
  for (int j = 0; j < n; ++j) b[j] = a[j] * (TAPS == 5 ? 0.375f : 0.5f);
  if (TAPS == 5) {
    for (int j = 2; j < n; ++j) b[j] = b[j] + 0.0625f * a[j - 2];
    for (int j = 0; j < n - 2; ++j) b[j] = b[j] + 0.0625f * a[j + 2];
    b[0] = b[0] + 0.0625f * a[2];
    b[1] = b[1] + 0.0625f * a[1];
    b[n - 1] = b[n - 1] + 0.0625f * a[n - 3];
    b[n - 2] = b[n - 2] + 0.0625f * a[n - 2];
  }
  for (int j = 1; j < n; ++j) b[j] = b[j] + 0.25f * a[j - 1];
  for (int j = 0; j < n - 1; ++j) b[j] = b[j] + 0.25f * a[j + 1];
  b[0] = b[0] + 0.25f * a[1];
  b[n - 1] = b[n - 1] + 0.25f * a[n - 2];
}

// Along columns whole rows at a time (the same adds per pixel as window_row, vectorised across the row).
template <int TAPS>
void window_columns(const float* __restrict__ a, float* __restrict__ b, int h, int w) {
  auto madd = [&](int i, int k, float c) {
    float* __restrict__ o = b + int64_t(i) * w;
    const float* __restrict__ x = a + int64_t(k) * w;
    for (int j = 0; j < w; ++j) o[j] = o[j] + c * x[j];
  };
  for (int i = 0; i < h; ++i) {
    const float* __restrict__ x = a + int64_t(i) * w;
    float* __restrict__ o = b + int64_t(i) * w;
    for (int j = 0; j < w; ++j) o[j] = x[j] * (TAPS == 5 ? 0.375f : 0.5f);
  }
  if (TAPS == 5) {
    for (int i = 2; i < h; ++i) madd(i, i - 2, 0.0625f);
    for (int i = 0; i < h - 2; ++i) madd(i, i + 2, 0.0625f);
    madd(0, 2, 0.0625f);
    madd(1, 1, 0.0625f);
    madd(h - 1, h - 3, 0.0625f);
    madd(h - 2, h - 2, 0.0625f);
  }
  for (int i = 1; i < h; ++i) madd(i, i - 1, 0.25f);
  for (int i = 0; i < h - 1; ++i) madd(i, i + 1, 0.25f);
  madd(0, 1, 0.25f);
  madd(h - 1, h - 2, 0.25f);
}

// The window on one (h, w) plane, in place through a scratch plane.
void window(float* x, float* y, int h, int w, int passes) {
  std::vector<int> taps(passes / 2, 5);
  if (passes % 2) taps.push_back(3);
  float *src = x, *dst = y;
  for (int t : taps) {
    for (int i = 0; i < h; ++i) {
      const float* a = src + int64_t(i) * w;
      float* b = dst + int64_t(i) * w;
      t == 5 ? window_row<5>(a, b, w) : window_row<3>(a, b, w);
    }
    std::swap(src, dst);
  }
  for (int t : taps) {
    t == 5 ? window_columns<5>(src, dst, h, w) : window_columns<3>(src, dst, h, w);
    std::swap(src, dst);
  }
  if (src != x) std::copy(src, src + int64_t(h) * w, x);
}

// One plane: image (H, W) -> cornerness (H, W).
CORNER_CLONES void harris_one(const float* img, int H, int W, float k, int passes, float* out) {
  const int64_t n = int64_t(H) * W;
  std::unique_ptr<float[]> buffer(new float[7 * n]);  // uninitialised: every value is written before it is read
  float *dx = buffer.get(), *dy = dx + n, *hx = dy + n, *a = hx + n, *b = a + n, *c = b + n, *scratch = c + n;
  // hx of every row: I[r][j + 1] - I[r][j - 1], replicate border
  for (int r = 0; r < H; ++r) {
    const float* a = img + int64_t(r) * W;
    float* o = hx + int64_t(r) * W;
    o[0] = a[std::min(1, W - 1)] - a[0];
    for (int j = 1; j < W - 1; ++j) o[j] = a[j + 1] - a[j - 1];
    o[W - 1] = a[W - 1] - a[std::max(W - 2, 0)];
  }
  for (int i = 0; i < H; ++i) {
    const float* mid = hx + int64_t(i) * W;
    const float* up = hx + int64_t(std::max(i - 1, 0)) * W;
    const float* down = hx + int64_t(std::min(i + 1, H - 1)) * W;
    float* o = dx + int64_t(i) * W;
    for (int j = 0; j < W; ++j) o[j] = mid[j] * 0.25f;
    for (int j = 0; j < W; ++j) o[j] = o[j] + 0.125f * up[j];
    for (int j = 0; j < W; ++j) o[j] = o[j] + 0.125f * down[j];
    // dy: hy(c) = I[i + 1][c] - I[i - 1][c] over the replicate-padded columns c = -1 .. W
    const float* a = img + int64_t(std::min(i + 1, H - 1)) * W;
    const float* z = img + int64_t(std::max(i - 1, 0)) * W;
    float* hy = scratch;
    for (int j = 0; j < W; ++j) hy[j] = a[j] - z[j];
    float* q = dy + int64_t(i) * W;
    for (int j = 0; j < W; ++j) q[j] = hy[j] * 0.25f;
    q[0] = q[0] + 0.125f * hy[0];
    for (int j = 1; j < W; ++j) q[j] = q[j] + 0.125f * hy[j - 1];
    for (int j = 0; j < W - 1; ++j) q[j] = q[j] + 0.125f * hy[j + 1];
    q[W - 1] = q[W - 1] + 0.125f * hy[W - 1];
  }
  for (int64_t j = 0; j < n; ++j) {
    a[j] = dx[j] * dx[j];
    b[j] = dx[j] * dy[j];
    c[j] = dy[j] * dy[j];
  }
  for (float* plane : {a, b, c}) window(plane, scratch, H, W, passes);
  for (int64_t j = 0; j < n; ++j) {
    const float tr = a[j] + c[j];
    float r = a[j] * c[j];
    r = r + (-1.0f * b[j]) * b[j];
    out[j] = r + (-k * tr) * tr;
  }
}

at::Tensor harris_binomial_cpu(const at::Tensor& image, double k, int64_t passes) {
  TORCH_CHECK(image.device().is_cpu() && image.scalar_type() == at::kFloat && image.is_contiguous() &&
                  image.dim() == 4,
              "harris_binomial: image must be a contiguous float32 (B, C, H, W) CPU tensor");
  TORCH_CHECK(passes >= 1, "harris_binomial: passes must be >= 1");
  const int64_t planes = image.size(0) * image.size(1), H = image.size(2), W = image.size(3);
  TORCH_CHECK(H >= 5 && W >= 5, "harris_binomial: image too small (need H, W >= 5)");
  auto out = at::empty(image.sizes(), image.options());
  const float* src = image.data_ptr<float>();
  float* dst = out.data_ptr<float>();
  at::parallel_for(0, planes, 1, [&](int64_t begin, int64_t end) {
    for (int64_t i = begin; i < end; ++i)
      harris_one(src + i * H * W, int(H), int(W), float(k), int(passes), dst + i * H * W);
  });
  return out;
}

}  // namespace

TORCH_LIBRARY_FRAGMENT(torchtrack, m) { m.def("harris_binomial(Tensor image, float k, int passes) -> Tensor"); }

TORCH_LIBRARY_IMPL(torchtrack, CPU, m) { m.impl("harris_binomial", &harris_binomial_cpu); }
