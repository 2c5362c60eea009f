// The voxel map's CPU operators (torchtrack/map/voxel_grid.py): a frame's fusion, torchtrack::voxel_add
// (VoxelPointMap.add; VoxelPointMap._add_torch is the reference, tests/test_mapping.py), the table's refill,
// torchtrack::voxel_rehash, and the dense alignment's pool after a fusion, torchtrack::pool_update (DenseMap._updated
// in torchtrack/map/dense_map.py is its reference). The map's index is a hash
// table with open addressing and linear probing, slot -> row of the voxel (-1: free), the voxel's key read from the
// rows' keys; the slot of a key: Fibonacci hashing, the top log2(size) bits of key x 0x9E3779B97F4A7C15 (wrapping),
// as the reference computes it in int64.
//
// In one pass: each point's voxel key (floor(p / voxel_size) per axis, as voxel_keys), the frame's points summed per
// voxel in their order (a small table of the frame's own voxels), each voxel's row (an existing one, or new rows in
// ascending key order, as the reference's sorted unique keys get them), its frame sum added to the row's. The same
// additions in the same order as the reference: the same sums. The reference spends ~10 tensor operations on
// sorting, grouping and probing; here each point and voxel costs a cache miss or two.

#include <ATen/core/Tensor.h>
#include <ATen/ops/empty.h>
#include <torch/library.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <tuple>
#include <utility>
#include <vector>

namespace {

constexpr int kAxisBits = 18;
constexpr int64_t kHalf = int64_t{1} << (kAxisBits - 1);

inline uint64_t slot_of(int64_t key, int shift, uint64_t mask) {
  return ((static_cast<uint64_t>(key) * 0x9E3779B97F4A7C15ull) >> shift) & mask;
}

// The first free slot (-1) of table t from slot s on, probing linearly.
inline uint64_t free_slot(const int64_t* t, uint64_t s, uint64_t mask) {
  while (t[s] >= 0) s = (s + 1) & mask;
  return s;
}

int shift_of(int64_t size) {  // 64 - log2(size)
  int shift = 64;
  for (int64_t s = size; s > 1; s >>= 1) --shift;
  return shift;
}

// Returns (the keys of the voxels created, ascending; their rows; the keys of the voxels the map had that took points,
// in the order their first points came; their rows; the points outside the representable range).
std::tuple<at::Tensor, at::Tensor, at::Tensor, at::Tensor, int64_t> voxel_add_cpu(
    at::Tensor& table, at::Tensor& keys, at::Tensor& sums, int64_t n, const at::Tensor& points, const at::Tensor& rgb,
    const at::Tensor& batch, double voxel_size) {
  TORCH_CHECK(points.dim() == 2 && points.size(1) == 3 && points.scalar_type() == at::kDouble && points.is_contiguous(),
              "voxel_add: points (P, 3) float64 contiguous");
  TORCH_CHECK(rgb.sizes() == points.sizes() && rgb.scalar_type() == at::kDouble && rgb.is_contiguous(),
              "voxel_add: rgb (P, 3) float64 contiguous");
  TORCH_CHECK(batch.dim() == 1 && batch.size(0) == points.size(0) && batch.scalar_type() == at::kLong &&
                  batch.is_contiguous(),
              "voxel_add: batch (P,) int64 contiguous");
  TORCH_CHECK(table.dim() == 1 && table.scalar_type() == at::kLong && table.is_contiguous(),
              "voxel_add: table (S,) int64 contiguous");
  TORCH_CHECK(keys.dim() == 1 && keys.scalar_type() == at::kLong && keys.is_contiguous(),
              "voxel_add: keys (C,) int64 contiguous");
  TORCH_CHECK(sums.dim() == 2 && sums.size(1) == 7 && sums.size(0) == keys.size(0) &&
                  sums.scalar_type() == at::kDouble && sums.is_contiguous(),
              "voxel_add: sums (C, 7) float64 contiguous");
  const int64_t size = table.size(0), P = points.size(0);
  TORCH_CHECK(size >= 2 && (size & (size - 1)) == 0, "voxel_add: the table's size must be a power of two");
  TORCH_CHECK(n >= 0 && n + P <= keys.size(0), "voxel_add: the buffers must have room for every point as a new voxel");
  TORCH_CHECK(2 * (n + P) <= size, "voxel_add: the table must stay at most half full");
  const double* p = points.data_ptr<double>();
  const double* c = rgb.data_ptr<double>();
  const int64_t* b = batch.data_ptr<int64_t>();

  // the frame's voxels: a table of its own (at most half full), their sums in the order their points come
  int64_t local_size = 2;
  while (local_size < 2 * P) local_size *= 2;
  const int local_shift = shift_of(local_size);
  const uint64_t local_mask = static_cast<uint64_t>(local_size - 1);
  std::vector<int32_t> local(local_size, -1);
  std::vector<int64_t> vkeys;
  std::vector<double> vsums;
  vkeys.reserve(P);
  vsums.reserve(7 * P);
  int64_t dropped = 0;
  for (int64_t i = 0; i < P; ++i) {
    int64_t ijk[3];
    bool inside = true;
    for (int a = 0; a < 3; ++a) {
      ijk[a] = static_cast<int64_t>(std::floor(p[3 * i + a] / voxel_size)) + kHalf;
      inside &= ijk[a] >= 0 && ijk[a] < 2 * kHalf;
    }
    if (!inside) {
      ++dropped;
      continue;
    }
    const int64_t key = (b[i] << (3 * kAxisBits)) | (ijk[0] << (2 * kAxisBits)) | (ijk[1] << kAxisBits) | ijk[2];
    uint64_t s = slot_of(key, local_shift, local_mask);
    while (local[s] >= 0 && vkeys[local[s]] != key) s = (s + 1) & local_mask;
    if (local[s] < 0) {
      local[s] = static_cast<int32_t>(vkeys.size());
      vkeys.push_back(key);
      vsums.insert(vsums.end(), 7, 0.0);
    }
    double* v = &vsums[7 * static_cast<int64_t>(local[s])];
    v[0] += p[3 * i];
    v[1] += p[3 * i + 1];
    v[2] += p[3 * i + 2];
    v[3] += c[3 * i];
    v[4] += c[3 * i + 1];
    v[5] += c[3 * i + 2];
    v[6] += 1.0;
  }

  // each voxel's row: an existing one, else new rows in ascending key order
  const int shift = shift_of(size);
  const uint64_t mask = static_cast<uint64_t>(size - 1);
  int64_t* t = table.data_ptr<int64_t>();
  int64_t* k = keys.data_ptr<int64_t>();
  double* S = sums.data_ptr<double>();
  const int64_t V = static_cast<int64_t>(vkeys.size());
  std::vector<int64_t> fresh;                        // the frame's voxels the map does not have
  std::vector<std::pair<int64_t, int64_t>> known;  // (key, row) of those it has
  // The table, the keys and the sums are large (MBs) and read at random: their lines are fetched ahead, the table's
  // slot 16 voxels ahead and, once that has arrived, the row's key and sums 8 ahead.
  std::vector<uint64_t> first(V);
  for (int64_t j = 0; j < V; ++j) first[j] = slot_of(vkeys[j], shift, mask);
  for (int64_t j = 0; j < V; ++j) {
    if (j + 16 < V) __builtin_prefetch(t + first[j + 16]);
    if (j + 8 < V && t[first[j + 8]] >= 0) {
      __builtin_prefetch(k + t[first[j + 8]]);
      __builtin_prefetch(S + 7 * t[first[j + 8]]);
    }
    const int64_t key = vkeys[j];
    uint64_t s = first[j];
    while (t[s] >= 0 && k[t[s]] != key) s = (s + 1) & mask;
    if (t[s] >= 0) {
      double* row = S + 7 * t[s];
      for (int a = 0; a < 7; ++a) row[a] += vsums[7 * j + a];
      known.emplace_back(key, t[s]);
    } else {
      fresh.push_back(j);
    }
  }
  std::sort(fresh.begin(), fresh.end(), [&](int64_t x, int64_t y) { return vkeys[x] < vkeys[y]; });
  const int64_t G = static_cast<int64_t>(known.size());
  auto known_keys = at::empty({G}, batch.options()), known_rows = at::empty({G}, batch.options());
  int64_t* kk = known_keys.data_ptr<int64_t>();
  int64_t* kr = known_rows.data_ptr<int64_t>();
  for (int64_t g = 0; g < G; ++g) std::tie(kk[g], kr[g]) = known[g];
  const int64_t F = static_cast<int64_t>(fresh.size());
  auto new_keys = at::empty({F}, batch.options()), new_rows = at::empty({F}, batch.options());
  int64_t* nk = new_keys.data_ptr<int64_t>();
  int64_t* nr = new_rows.data_ptr<int64_t>();
  for (int64_t f = 0; f < F; ++f) {
    if (f + 16 < F) __builtin_prefetch(t + first[fresh[f + 16]]);
    const int64_t j = fresh[f], key = vkeys[j], r = n + f;
    t[free_slot(t, first[j], mask)] = r;  // the earlier fresh voxels may have taken its first slot
    k[r] = key;
    double* row = S + 7 * r;
    for (int a = 0; a < 7; ++a) row[a] = 0.0 + vsums[7 * j + a];  // as the reference: zeros, then its sum added
    nk[f] = key;
    nr[f] = r;
  }
  return {new_keys, new_rows, known_keys, known_rows, dropped};
}

// The table (S,) filled anew with the voxels of rows 0 .. n - 1 (keys (C,)): each takes the first free slot from its
// own, in row order (as VoxelPointMap._rehash's reference, which enters them as new keys of an empty table).
void voxel_rehash_cpu(at::Tensor& table, const at::Tensor& keys, int64_t n) {
  TORCH_CHECK(table.dim() == 1 && table.scalar_type() == at::kLong && table.is_contiguous(),
              "voxel_rehash: table (S,) int64 contiguous");
  TORCH_CHECK(keys.dim() == 1 && keys.scalar_type() == at::kLong && keys.is_contiguous(),
              "voxel_rehash: keys (C,) int64 contiguous");
  const int64_t size = table.size(0);
  TORCH_CHECK(size >= 2 && (size & (size - 1)) == 0, "voxel_rehash: the table's size must be a power of two");
  TORCH_CHECK(n >= 0 && n <= keys.size(0) && 2 * n <= size, "voxel_rehash: n rows, the table at most half full");
  const int shift = shift_of(size);
  const uint64_t mask = static_cast<uint64_t>(size - 1);
  int64_t* t = table.data_ptr<int64_t>();
  const int64_t* k = keys.data_ptr<int64_t>();
  std::fill(t, t + size, int64_t{-1});
  for (int64_t r = 0; r < n; ++r) t[free_slot(t, slot_of(k[r], shift, mask), mask)] = r;
}

// A sequence's pool of map points (torchtrack/map/dense_map.py: DenseMap._updated is the reference) after an add:
// its voxels' keys (M,) ascending and means xyz (M, 3); of the add's voxels those of sequence b that the spatial hash
// picks (every > 1: hash % every == 0, voxel_grid.spatial_hash) enter it: the known ones (in the pool already) get
// their means anew from sums (C, 7), the new ones (keys ascending) are merged in. Returns the pool's keys and xyz.
std::tuple<at::Tensor, at::Tensor> pool_update_cpu(const at::Tensor& keys, const at::Tensor& xyz, const at::Tensor& sums,
                                                   const at::Tensor& known_keys, const at::Tensor& known_rows,
                                                   const at::Tensor& new_keys, const at::Tensor& new_rows, int64_t b,
                                                   int64_t every) {
  for (const at::Tensor* t : {&keys, &known_keys, &known_rows, &new_keys, &new_rows})
    TORCH_CHECK(t->dim() == 1 && t->scalar_type() == at::kLong && t->is_contiguous(),
                "pool_update: keys and rows (n,) int64 contiguous");
  TORCH_CHECK(xyz.dim() == 2 && xyz.size(0) == keys.size(0) && xyz.size(1) == 3 && xyz.scalar_type() == at::kDouble &&
                  xyz.is_contiguous(),
              "pool_update: xyz (M, 3) float64 contiguous, one row per key");
  TORCH_CHECK(sums.dim() == 2 && sums.size(1) == 7 && sums.scalar_type() == at::kDouble && sums.is_contiguous(),
              "pool_update: sums (C, 7) float64 contiguous");
  TORCH_CHECK(known_rows.size(0) == known_keys.size(0) && new_rows.size(0) == new_keys.size(0),
              "pool_update: one row per key");
  const int64_t mask = (int64_t{1} << kAxisBits) - 1;
  const auto picked = [&](int64_t key) {
    if ((key >> (3 * kAxisBits)) != b) return false;
    if (every <= 1) return true;
    const int64_t h = (((key >> (2 * kAxisBits)) & mask) * 73856093) ^ (((key >> kAxisBits) & mask) * 19349663) ^
                      ((key & mask) * 83492791);
    return h % every == 0;
  };
  const double* S = sums.data_ptr<double>();
  const int64_t C = sums.size(0);
  const auto mean = [&](int64_t r, double* out) {
    TORCH_CHECK(r >= 0 && r < C, "pool_update: a row outside the sums");
    for (int a = 0; a < 3; ++a) out[a] = S[7 * r + a] / S[7 * r + 6];
  };
  const int64_t M = keys.size(0), N = new_keys.size(0);
  const int64_t* k = keys.data_ptr<int64_t>();
  const double* X = xyz.data_ptr<double>();
  const int64_t* nk = new_keys.data_ptr<int64_t>();
  const int64_t* nr = new_rows.data_ptr<int64_t>();
  std::vector<int64_t> take;  // the new voxels picked
  for (int64_t i = 0; i < N; ++i)
    if (picked(nk[i])) take.push_back(i);
  const int64_t K = static_cast<int64_t>(take.size());
  auto out_keys = at::empty({M + K}, keys.options()), out_xyz = at::empty({M + K, 3}, xyz.options());
  int64_t* ok = out_keys.data_ptr<int64_t>();
  double* oX = out_xyz.data_ptr<double>();
  int64_t i = 0, j = 0, o = 0;
  while (i < M || j < K) {  // both ascending: merged
    TORCH_CHECK(i == M || j == K || nk[take[j]] != k[i], "pool_update: a new voxel is in the pool already");
    if (j < K && (i == M || nk[take[j]] < k[i])) {
      ok[o] = nk[take[j]];
      mean(nr[take[j]], oX + 3 * o);
      ++j;
    } else {
      ok[o] = k[i];
      std::copy(X + 3 * i, X + 3 * i + 3, oX + 3 * o);
      ++i;
    }
    ++o;
  }
  const int64_t* kk = known_keys.data_ptr<int64_t>();
  const int64_t* kr = known_rows.data_ptr<int64_t>();
  const int64_t G = known_keys.size(0);
  for (int64_t g = 0; g < G; ++g) {
    if (!picked(kk[g])) continue;
    const int64_t* at = std::lower_bound(ok, ok + M + K, kk[g]);
    TORCH_CHECK(at != ok + M + K && *at == kk[g], "pool_update: a known voxel is not in the pool");
    mean(kr[g], oX + 3 * (at - ok));
  }
  return {out_keys, out_xyz};
}

}  // namespace

TORCH_LIBRARY_FRAGMENT(torchtrack, m) {
  m.def(
      "voxel_add(Tensor(a!) table, Tensor(b!) keys, Tensor(c!) sums, int n, Tensor points, Tensor rgb, Tensor batch, "
      "float voxel_size) -> (Tensor, Tensor, Tensor, Tensor, int)");
  m.def("voxel_rehash(Tensor(a!) table, Tensor keys, int n) -> ()");
  m.def(
      "pool_update(Tensor keys, Tensor xyz, Tensor sums, Tensor known_keys, Tensor known_rows, Tensor new_keys, "
      "Tensor new_rows, int b, int every) -> (Tensor, Tensor)");
}

TORCH_LIBRARY_IMPL(torchtrack, CPU, m) {
  m.impl("voxel_add", &voxel_add_cpu);
  m.impl("voxel_rehash", &voxel_rehash_cpu);
  m.impl("pool_update", &pool_update_cpu);
}
