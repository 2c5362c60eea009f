// Point-to-plane alignment of one depth camera to its dense map: torchtrack/map/dense_map.py's DenseMap._fit_torch
// (the reference and test oracle, tests/test_dense_op.py) as one CPU operator, torchtrack::dense_fit, and the points
// a keyframe adds to the map, torchtrack::depth_points (below). The reference spends ~30 ms per alignment in ~150
// tensor operations on a few thousand points; here each stage is one loop.
//
// Stages, as in the reference: the surface of the depth grid (any strides: a view of the frame needs no copy;
// vertices, normals of the central differences, validity: depth (> 0: not 0, negative or NaN) at the pixel and its
// four neighbours, none farther than max_step x z; here computed at a pixel when a point first lands on it, not over
// the whole grid); the map points culled to
// those in front of the camera and inside the image and evenly thinned to max_points
// (point i * (n - 1) / (max_points - 1), integer division); then Gauss-Newton on the pose: each point projected to
// its nearest pixel, paired with the surface there, the Huber- and depth-weighted point-to-plane normal equations
// plus the prior, a 6x6 Cholesky solve, the step applied on the left by the SE(3) exponential (closed form; the
// reference uses matrix_exp), stop once a step's largest component is below `tolerance`. All in float64; sums run in
// another order than the reference's BLAS, so the fits agree within float error, not bit for bit
// (tests/tolerances.py DENSE_OP_*).
//
// Returns the correction delta (4, 4) (the aligned world-to-camera pose is delta @ T_cw), its twist xi (6,) (the sum
// of the steps: the prior's residual), the data's information sum w J J^T (6, 6) of the last iteration (the weak-
// direction gate runs in Python on it) and (pairs of the last iteration, the last step's largest component (inf where
// fewer than 6 pairs were left), the steps taken, 1 where some direction's information may be below weak times the
// prior's and 0 where it is clearly above in every one: the information whitened by the prior minus weak x I has
// Cholesky pivots above 1e-9 of its largest diagonal entry; the gate's eigenproblem is then skipped).
//
// torchtrack::depth_points: the points a keyframe's depth adds to the map (DenseMap.add; DenseMap._points_torch is
// the reference): every stride-th pixel of the depth with 0 < z <= max_depth (inside the region where given) of the
// sequences in mask, back-projected through the strided grid's intrinsics and moved into the world, in (sequence,
// row, column) order: one pass instead of the reference's ~10 tensor operations over the whole grid (3.4 against
// 0.49 ms per 640x480 keyframe).

#include <ATen/core/Tensor.h>
#include <ATen/ops/empty.h>
#include <ATen/ops/zeros.h>
#include <torch/library.h>

#include <algorithm>
#include <array>
#include <cmath>
#include <cstdint>
#include <limits>
#include <memory>
#include <optional>
#include <tuple>
#include <vector>

namespace {

using Mat4 = std::array<double, 16>;  // row major

Mat4 mul4(const Mat4& a, const Mat4& b) {
  Mat4 c{};
  for (int i = 0; i < 4; ++i)
    for (int j = 0; j < 4; ++j) {
      double s = 0.0;
      for (int k = 0; k < 4; ++k) s += a[4 * i + k] * b[4 * k + j];
      c[4 * i + j] = s;
    }
  return c;
}

// exp of the twist (v, w) in SE(3): R = I + A [w]x + B [w]x^2, t = (I + B [w]x + C [w]x^2) v; Taylor near 0.
Mat4 se3_exp(const double* xi) {
  const double v0 = xi[0], v1 = xi[1], v2 = xi[2], w0 = xi[3], w1 = xi[4], w2 = xi[5];
  const double th2 = w0 * w0 + w1 * w1 + w2 * w2, th = std::sqrt(th2);
  double A, B, C;
  if (th < 1e-4) {  // the series to the term below double precision at this angle
    A = 1.0 - th2 / 6.0 + th2 * th2 / 120.0;
    B = 0.5 - th2 / 24.0 + th2 * th2 / 720.0;
    C = 1.0 / 6.0 - th2 / 120.0 + th2 * th2 / 5040.0;
  } else {
    A = std::sin(th) / th;
    B = (1.0 - std::cos(th)) / th2;
    C = (th - std::sin(th)) / (th2 * th);
  }
  const double W[9] = {0, -w2, w1, w2, 0, -w0, -w1, w0, 0};
  double W2[9];
  for (int i = 0; i < 3; ++i)
    for (int j = 0; j < 3; ++j) W2[3 * i + j] = W[3 * i] * W[j] + W[3 * i + 1] * W[3 + j] + W[3 * i + 2] * W[6 + j];
  Mat4 T{};
  const double v[3] = {v0, v1, v2};
  for (int i = 0; i < 3; ++i) {
    double t = 0.0;
    for (int j = 0; j < 3; ++j) {
      const double e = i == j ? 1.0 : 0.0;
      T[4 * i + j] = e + A * W[3 * i + j] + B * W2[3 * i + j];
      t += (e + B * W[3 * i + j] + C * W2[3 * i + j]) * v[j];
    }
    T[4 * i + 3] = t;
  }
  T[15] = 1.0;
  return T;
}

// The Cholesky factor of a symmetric 6x6 H in its lower triangle (in place); whether every pivot (before its square
// root) was above `floor`. A pivot at or below 0 leaves NaN behind it: the caller that needs a factor checks first.
bool cholesky6(double* H, double floor) {
  bool above = true;
  for (int j = 0; j < 6; ++j) {
    double d = H[6 * j + j];
    for (int k = 0; k < j; ++k) d -= H[6 * j + k] * H[6 * j + k];
    above &= d > floor;
    d = std::sqrt(d);
    H[6 * j + j] = d;
    for (int i = j + 1; i < 6; ++i) {
      double s = H[6 * i + j];
      for (int k = 0; k < j; ++k) s -= H[6 * i + k] * H[6 * j + k];
      H[6 * i + j] = s / d;
    }
  }
  return above;
}

// H x = g for a symmetric positive definite 6x6 H (Cholesky); H is overwritten.
void solve6(double* H, const double* g, double* x) {
  cholesky6(H, 0.0);
  double y[6];
  for (int i = 0; i < 6; ++i) {
    double s = g[i];
    for (int k = 0; k < i; ++k) s -= H[6 * i + k] * y[k];
    y[i] = s / H[6 * i + i];
  }
  for (int i = 5; i >= 0; --i) {
    double s = y[i];
    for (int k = i + 1; k < 6; ++k) s -= H[6 * k + i] * x[k];
    x[i] = s / H[6 * i + i];
  }
}

// dense_map.py surface() of a depth grid (h, w) seen through fx, fy, cx, cy, computed at a pixel when a point first
// lands on it (an alignment pairs a few thousand of the grid's pixels, over and over): the same arithmetic as the
// reference's, pixel by pixel. A pixel's vertex and normal share one cache line.
class Surface {
 public:
  // depth: pixel (i, j) at depth[i * row + j * col] (a strided view of a larger image needs no copy)
  Surface(const float* depth, int64_t h, int64_t w, int64_t row, int64_t col, double fx, double fy, double cx,
          double cy, double max_step)
      : h(static_cast<int>(h)), w(static_cast<int>(w)), row_(row), col_(col), depth_(depth), fx_(fx), fy_(fy),
        cx_(cx), cy_(cy), max_step_(max_step), slot_(h * w, kUnknown) {
    px_.reserve(h * w);  // never moved: at()'s pointers stay valid
  }

  // The vertex (3) and unit normal (3) at pixel (i, j), or nullptr where it has no surface: a border pixel, no depth
  // there or at one of its four neighbours, or one of them farther than max_step x z in depth.
  const double* at(int i, int j) {
    int32_t& s = slot_[static_cast<int64_t>(i) * w + j];
    if (s == kUnknown) {
      Pixel px;
      s = compute(i, j, px.vn) ? static_cast<int32_t>(px_.size()) : kNone;
      if (s >= 0) px_.push_back(px);
    }
    return s >= 0 ? px_[s].vn : nullptr;
  }

  const int h, w;

 private:
  struct alignas(64) Pixel {
    double vn[6];  // vertex, normal
  };

  void vertex(int i, int j, double* p) const {
    const double z = depth_[i * row_ + j * col_];
    p[0] = (j - cx_) / fx_ * z;
    p[1] = (i - cy_) / fy_ * z;
    p[2] = z;
  }

  bool compute(int i, int j, double* vn) const {
    if (i < 1 || j < 1 || i >= h - 1 || j >= w - 1) return false;
    double c[3], l[3], r[3], u[3], d[3];
    vertex(i, j, c);
    vertex(i, j - 1, l);
    vertex(i, j + 1, r);
    vertex(i - 1, j, u);
    vertex(i + 1, j, d);
    const double zc = c[2];
    auto near = [&](double a) { return a > 0 && std::abs(a - zc) <= max_step_ * zc; };
    if (!(zc > 0 && near(r[2]) && near(l[2]) && near(d[2]) && near(u[2]))) return false;
    const double a0 = r[0] - l[0], a1 = r[1] - l[1], a2 = r[2] - l[2];
    const double b0 = d[0] - u[0], b1 = d[1] - u[1], b2 = d[2] - u[2];
    const double n0 = a1 * b2 - a2 * b1, n1 = a2 * b0 - a0 * b2, n2 = a0 * b1 - a1 * b0;
    const double norm = std::max(std::sqrt(n0 * n0 + n1 * n1 + n2 * n2), 1e-12);
    vn[0] = c[0];
    vn[1] = c[1];
    vn[2] = c[2];
    vn[3] = n0 / norm;
    vn[4] = n1 / norm;
    vn[5] = n2 / norm;
    return true;
  }

  const int64_t row_, col_;
  const float* depth_;
  const double fx_, fy_, cx_, cy_, max_step_;
  // The surfaces computed, in the order they were first asked for (written one after the other, not scattered over a
  // grid-sized array: each scattered first write was a cache miss), and each pixel's place among them.
  static constexpr int32_t kUnknown = -2, kNone = -1;
  std::vector<Pixel> px_;
  std::vector<int32_t> slot_;
};

// AVX2 + FMA and baseline builds of the hot loop, picked at load time (as csrc/lk.cpp).
#if defined(__x86_64__) && defined(__GNUC__) && !defined(__clang__) && __GNUC__ >= 11  // x86-64-v3: GCC 11+
#define DENSE_CLONES __attribute__((target_clones("arch=x86-64-v3", "default")))
#else
#define DENSE_CLONES
#endif

// One Gauss-Newton iteration's normal equations: the points (X0, Y0, Z0) moved by delta, each paired with the surface
// at its nearest grid pixel; info (6, 6) = sum w J J^T and g (6) = sum w J r over the pairs. Returns the pairs.
DENSE_CLONES int64_t normal_equations(const double* X0, const double* Y0, const double* Z0, int64_t n,
                                      const Mat4& delta, Surface& s, double fx, double fy, double cx, double cy,
                                      double max_distance, double huber, double sigma, double* info, double* g) {
  const int h = s.h, w = s.w;
  const double far2 = (2.0 * max_distance) * (2.0 * max_distance);
  double acc[27] = {};  // the lower triangle of info (21), then g (6): locals, not the caller's arrays
  int64_t pairs = 0;
  for (int64_t i = 0; i < n; ++i) {
    const double x = delta[0] * X0[i] + delta[1] * Y0[i] + delta[2] * Z0[i] + delta[3];
    const double y = delta[4] * X0[i] + delta[5] * Y0[i] + delta[6] * Z0[i] + delta[7];
    const double z = delta[8] * X0[i] + delta[9] * Y0[i] + delta[10] * Z0[i] + delta[11];
    if (!(z > 0.1)) continue;
    const double iz = 1.0 / z;
    const double uf = std::nearbyint(x * iz * fx + cx), vf = std::nearbyint(y * iz * fy + cy);
    if (!(uf >= 0 && uf < w && vf >= 0 && vf < h)) continue;
    const double* q = s.at(static_cast<int>(vf), static_cast<int>(uf));
    if (!q) continue;
    const double* nn = q + 3;
    const double d0 = x - q[0], d1 = y - q[1], d2 = z - q[2];
    const double r = d0 * nn[0] + d1 * nn[1] + d2 * nn[2], ra = std::abs(r);
    if (!(ra <= max_distance) || !(d0 * d0 + d1 * d1 + d2 * d2 <= far2)) continue;
    ++pairs;
    const double hub = ra <= huber ? 1.0 : huber / std::max(ra, 1e-12);
    const double sd = sigma * std::max(z * z, 1.0);
    const double wgt = hub / (sd * sd);
    const double J[6] = {nn[0], nn[1], nn[2], y * nn[2] - z * nn[1], z * nn[0] - x * nn[2], x * nn[1] - y * nn[0]};
    int k = 0;
    for (int a = 0; a < 6; ++a) {
      const double wa = wgt * J[a];
      for (int b = 0; b <= a; ++b) acc[k++] += wa * J[b];
      acc[21 + a] += wa * r;
    }
  }
  int k = 0;
  for (int a = 0; a < 6; ++a) {
    for (int b = 0; b <= a; ++b, ++k) info[6 * a + b] = info[6 * b + a] = acc[k];
    g[a] = acc[21 + a];
  }
  return pairs;
}

// The indices (written to seen, returned: how many) of the points P (M, 3) in front of the camera T_cw (row major 4x4),
// within max_depth and inside the w x h image, in order. Two passes: a flag per point (no branch: the loop
// vectorises), then the flagged indices packed.
DENSE_CLONES int64_t visible(const double* P, int64_t M, const double* Tc, double fx, double fy, double cx, double cy,
                             int w, int h, double max_depth, uint8_t* in, int64_t* seen) {
  const double wl = w - 0.5, hl = h - 0.5;
  for (int64_t m = 0; m < M; ++m) {
    const double px = P[3 * m], py = P[3 * m + 1], pz = P[3 * m + 2];
    const double x = px * Tc[0] + py * Tc[1] + pz * Tc[2] + Tc[3];
    const double y = px * Tc[4] + py * Tc[5] + pz * Tc[6] + Tc[7];
    const double z = px * Tc[8] + py * Tc[9] + pz * Tc[10] + Tc[11];
    const double u = fx * x + cx * z, v = fy * y + cy * z;
    in[m] = (z > 0.1) & (z <= max_depth) & (u > -0.5 * z) & (v > -0.5 * z) & (u < wl * z) & (v < hl * z);
  }
  int64_t n = 0;
  for (int64_t m = 0; m < M; ++m) {
    seen[n] = m;
    n += in[m];
  }
  return n;
}

std::tuple<at::Tensor, at::Tensor, at::Tensor, at::Tensor> dense_fit_cpu(
    const at::Tensor& world, const at::Tensor& depth, const at::Tensor& K, const at::Tensor& T_cw,
    int64_t max_points, int64_t iterations, double max_depth, double max_distance, double huber, double sigma,
    double prior_m, double prior_rad, double tolerance, double max_step, double weak) {
  TORCH_CHECK(world.dim() == 2 && world.size(1) == 3 && world.scalar_type() == at::kDouble && world.is_contiguous(),
              "dense_fit: world (M, 3) float64 contiguous");
  TORCH_CHECK(depth.dim() == 2 && depth.scalar_type() == at::kFloat, "dense_fit: depth (H, W) float32");
  TORCH_CHECK(K.sizes() == at::IntArrayRef({3, 3}) && K.scalar_type() == at::kDouble && K.is_contiguous(),
              "dense_fit: K (3, 3) float64 contiguous");
  TORCH_CHECK(T_cw.sizes() == at::IntArrayRef({4, 4}) && T_cw.scalar_type() == at::kDouble && T_cw.is_contiguous(),
              "dense_fit: T_cw (4, 4) float64 contiguous");
  TORCH_CHECK(max_points >= 1 && iterations >= 1, "dense_fit: max_points, iterations >= 1");
  const auto opt = world.options();
  auto delta_t = at::empty({4, 4}, opt), xi_t = at::zeros({6}, opt), info_t = at::zeros({6, 6}, opt);
  auto stats_t = at::empty({4}, opt);

  const double* k = K.data_ptr<double>();
  const double fx = k[0], fy = k[4], cx = k[2], cy = k[5];
  Surface s(depth.data_ptr<float>(), depth.size(0), depth.size(1), depth.stride(0), depth.stride(1), fx, fy, cx, cy,
            max_step);
  const int h = s.h, w = s.w;
  // the map points the camera can see, evenly thinned
  const double* P = world.data_ptr<double>();
  const int64_t M = world.size(0);
  std::unique_ptr<int64_t[]> seen(new int64_t[M]);
  std::unique_ptr<uint8_t[]> in(new uint8_t[M]);
  const double* Tc = T_cw.data_ptr<double>();
  int64_t n = visible(P, M, Tc, fx, fy, cx, cy, w, h, max_depth, in.get(), seen.get());
  if (n > max_points) {
    for (int64_t i = 0; i < max_points; ++i) seen[i] = seen[max_points > 1 ? i * (n - 1) / (max_points - 1) : 0];
    n = max_points;
  }
  // the points in the starting camera, structure of arrays
  std::vector<double> X0(n), Y0(n), Z0(n);
  for (int64_t i = 0; i < n; ++i) {
    const double* p = P + 3 * seen[i];
    X0[i] = Tc[0] * p[0] + Tc[1] * p[1] + Tc[2] * p[2] + Tc[3];
    Y0[i] = Tc[4] * p[0] + Tc[5] * p[1] + Tc[6] * p[2] + Tc[7];
    Z0[i] = Tc[8] * p[0] + Tc[9] * p[1] + Tc[10] * p[2] + Tc[11];
  }

  const double pri[6] = {1.0 / (prior_m * prior_m), 1.0 / (prior_m * prior_m), 1.0 / (prior_m * prior_m),
                         1.0 / (prior_rad * prior_rad), 1.0 / (prior_rad * prior_rad), 1.0 / (prior_rad * prior_rad)};
  double xi[6] = {0, 0, 0, 0, 0, 0}, info[36];
  Mat4 delta{1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1};
  double last = std::numeric_limits<double>::infinity();
  int64_t pairs = 0, steps = 0;
  for (int64_t it = 0; it < iterations; ++it) {
    double g[6];
    pairs = normal_equations(X0.data(), Y0.data(), Z0.data(), n, delta, s, fx, fy, cx, cy, max_distance, huber, sigma,
                             info, g);
    if (pairs < 6) {
      std::fill(info, info + 36, 0.0);
      last = std::numeric_limits<double>::infinity();
      break;
    }
    double Hm[36], step[6];
    for (int a = 0; a < 36; ++a) Hm[a] = info[a];
    for (int a = 0; a < 6; ++a) {
      Hm[7 * a] += pri[a];
      g[a] += pri[a] * xi[a];
    }
    solve6(Hm, g, step);
    last = 0.0;
    for (int a = 0; a < 6; ++a) {
      step[a] = -step[a];
      xi[a] += step[a];
      last = std::max(last, std::abs(step[a]));
    }
    delta = mul4(se3_exp(step), delta);  // left perturbation
    ++steps;
    if (last < tolerance) break;
  }
  // the gate's shortcut: is (whitened information - weak I) clearly positive definite?
  const double sd[6] = {prior_m, prior_m, prior_m, prior_rad, prior_rad, prior_rad};
  double A[36], top = 0.0;
  for (int a = 0; a < 6; ++a)
    for (int b = 0; b < 6; ++b) A[6 * a + b] = info[6 * a + b] * sd[a] * sd[b] - (a == b ? weak : 0.0);
  for (int a = 0; a < 6; ++a) top = std::max(top, std::abs(A[7 * a]));
  const bool clear = cholesky6(A, 1e-9 * top);
  std::copy(delta.begin(), delta.end(), delta_t.data_ptr<double>());
  std::copy(xi, xi + 6, xi_t.data_ptr<double>());
  std::copy(info, info + 36, info_t.data_ptr<double>());
  stats_t.data_ptr<double>()[0] = static_cast<double>(pairs);
  stats_t.data_ptr<double>()[1] = last;
  stats_t.data_ptr<double>()[2] = static_cast<double>(steps);
  stats_t.data_ptr<double>()[3] = clear ? 0.0 : 1.0;
  return {delta_t, xi_t, info_t, stats_t};
}

// Returns the world points (P, 3) float64 and their sequence (P,) int64 (see the header).
std::tuple<at::Tensor, at::Tensor> depth_points_cpu(const at::Tensor& depth, const std::optional<at::Tensor>& region,
                                                    const at::Tensor& K, const at::Tensor& T, const at::Tensor& mask,
                                                    int64_t stride, double max_depth) {
  TORCH_CHECK(depth.dim() == 4 && depth.size(1) == 1 && depth.scalar_type() == at::kFloat && depth.is_contiguous(),
              "depth_points: depth (B, 1, H, W) float32 contiguous");
  const int64_t B = depth.size(0), H = depth.size(2), W = depth.size(3);
  TORCH_CHECK(K.sizes() == at::IntArrayRef({B, 3, 3}) && K.scalar_type() == at::kDouble && K.is_contiguous(),
              "depth_points: K (B, 3, 3) float64 contiguous");
  TORCH_CHECK(T.sizes() == at::IntArrayRef({B, 4, 4}) && T.scalar_type() == at::kDouble && T.is_contiguous(),
              "depth_points: T (B, 4, 4) float64 contiguous");
  TORCH_CHECK(mask.sizes() == at::IntArrayRef({B}) && mask.scalar_type() == at::kBool && mask.is_contiguous(),
              "depth_points: mask (B,) bool contiguous");
  TORCH_CHECK(!region || (region->sizes() == depth.sizes() && region->scalar_type() == at::kBool &&
                          region->is_contiguous()),
              "depth_points: region (B, 1, H, W) bool contiguous, as depth");
  TORCH_CHECK(stride >= 1, "depth_points: stride >= 1");
  const int64_t h = (H + stride - 1) / stride, w = (W + stride - 1) / stride;
  const float* d = depth.data_ptr<float>();
  const bool* r = region ? region->data_ptr<bool>() : nullptr;
  const bool* m = mask.data_ptr<bool>();
  auto taken = [&](int64_t at) {
    const float z = d[at];
    return z > 0 && z <= max_depth && (!r || r[at]);  // NaN fails z > 0
  };
  int64_t P = 0;  // two passes: count, then write
  for (int64_t b = 0; b < B; ++b)
    for (int64_t i = 0; m[b] && i < h; ++i)
      for (int64_t j = 0, row = (b * H + i * stride) * W; j < w; ++j) P += taken(row + j * stride);
  at::Tensor points = at::empty({P, 3}, depth.options().dtype(at::kDouble));
  at::Tensor batch = at::empty({P}, depth.options().dtype(at::kLong));
  double* X = points.data_ptr<double>();
  int64_t* bo = batch.data_ptr<int64_t>();
  for (int64_t b = 0; b < B; ++b) {
    if (!m[b]) continue;
    const double* k = K.data_ptr<double>() + 9 * b;
    const double* t = T.data_ptr<double>() + 16 * b;
    // the reference's arithmetic: the strided grid's intrinsics, then x = (j - cx) / fx * z
    const double fx = k[0] / stride, cx = k[2] / stride, fy = k[4] / stride, cy = k[5] / stride;
    for (int64_t i = 0; i < h; ++i) {
      const double y1 = (i - cy) / fy;
      for (int64_t j = 0, row = (b * H + i * stride) * W; j < w; ++j) {
        const int64_t at = row + j * stride;
        if (!taken(at)) continue;
        const double z = d[at], x = (j - cx) / fx * z, y = y1 * z;
        for (int a = 0; a < 3; ++a) X[a] = t[4 * a] * x + t[4 * a + 1] * y + t[4 * a + 2] * z + t[4 * a + 3];
        X += 3;
        *bo++ = b;
      }
    }
  }
  return {points, batch};
}

}  // namespace

TORCH_LIBRARY_FRAGMENT(torchtrack, m) {
  m.def(
      "dense_fit(Tensor world, Tensor depth, Tensor K, Tensor T_cw, int max_points, int iterations, "
      "float max_depth, float max_distance, float huber, float sigma, float prior_m, float prior_rad, "
      "float tolerance, float max_step, float weak) -> (Tensor, Tensor, Tensor, Tensor)");
  m.def(
      "depth_points(Tensor depth, Tensor? region, Tensor K, Tensor T, Tensor mask, int stride, float max_depth) -> "
      "(Tensor, Tensor)");
}

TORCH_LIBRARY_IMPL(torchtrack, CPU, m) {
  m.impl("dense_fit", &dense_fit_cpu);
  m.impl("depth_points", &depth_points_cpu);
}
