// The voxel map's index (torchtrack/mapping/voxel_grid.py, VoxelPointMap) as one CPU operator, torchtrack::voxel_index:
// a hash table with open addressing and linear probing, slot -> row of the voxel (-1: free), the voxel's key read from
// the rows' keys. VoxelPointMap._index_torch is the reference (vectorised probing; tests/test_mapping.py): the same rows
// for the same keys, whatever the table's layout. Probing voxel by voxel here costs one or two cache misses per
// voxel; the vectorised reference spends ~10 tensor operations per round of probes.
//
// For each query key (distinct), in order: its row where the table holds it; else the next new row (n, n + 1, ...),
// its key written to `keys` and the row entered in the table. The slot of a key: Fibonacci hashing, the top
// log2(size) bits of key x 0x9E3779B97F4A7C15 (wrapping), as the reference computes it in int64.

#include <ATen/core/Tensor.h>
#include <ATen/ops/empty.h>
#include <torch/library.h>

#include <cstdint>

namespace {

at::Tensor voxel_index_cpu(at::Tensor& table, at::Tensor& keys, int64_t n, const at::Tensor& query) {
  TORCH_CHECK(table.dim() == 1 && table.scalar_type() == at::kLong && table.is_contiguous(),
              "voxel_index: table (S,) int64 contiguous");
  const int64_t size = table.size(0);
  TORCH_CHECK(size >= 2 && (size & (size - 1)) == 0, "voxel_index: the table's size must be a power of two");
  TORCH_CHECK(keys.dim() == 1 && keys.scalar_type() == at::kLong && keys.is_contiguous(),
              "voxel_index: keys (C,) int64 contiguous");
  TORCH_CHECK(query.dim() == 1 && query.scalar_type() == at::kLong && query.is_contiguous(),
              "voxel_index: query (Q,) int64 contiguous");
  TORCH_CHECK(n >= 0 && n + query.size(0) <= keys.size(0), "voxel_index: keys must have room for every query as new");
  TORCH_CHECK(2 * (n + query.size(0)) <= size, "voxel_index: the table must stay at most half full");
  int shift = 64;
  for (int64_t s = size; s > 1; s >>= 1) --shift;  // 64 - log2(size)
  const uint64_t mask = static_cast<uint64_t>(size - 1);
  int64_t* t = table.data_ptr<int64_t>();
  int64_t* k = keys.data_ptr<int64_t>();
  const int64_t* q = query.data_ptr<int64_t>();
  const int64_t Q = query.size(0);
  auto out = at::empty({Q}, query.options());
  int64_t* rows = out.data_ptr<int64_t>();
  for (int64_t i = 0; i < Q; ++i) {
    const int64_t key = q[i];
    uint64_t s = ((static_cast<uint64_t>(key) * 0x9E3779B97F4A7C15ull) >> shift) & mask;
    while (true) {
      const int64_t r = t[s];
      if (r < 0) {  // free: the key is new
        k[n] = key;
        t[s] = n;
        rows[i] = n++;
        break;
      }
      if (k[r] == key) {
        rows[i] = r;
        break;
      }
      s = (s + 1) & mask;
    }
  }
  return out;
}

}  // namespace

TORCH_LIBRARY_FRAGMENT(torchtrack, m) {
  m.def("voxel_index(Tensor(a!) table, Tensor(b!) keys, int n, Tensor query) -> Tensor");
}

TORCH_LIBRARY_IMPL(torchtrack, CPU, m) { m.impl("voxel_index", &voxel_index_cpu); }
