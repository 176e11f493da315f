// fwk's own kernels (``fwk.native.ops``): the layout copy between batch-major and vertex-major activations, and the
// L1 loss's forward and backward in one pass each. Both are memory-bound; torch does them in more passes:
//
//   swap01(x) = x.transpose(0, 1).contiguous() for x (A, B, C) contiguous. torch's copy of a transposed view whose
//   rows are C = 3 floats runs its innermost loop over those 3 floats (0.27 ms for (16, 11,248, 3) floats on 2
//   threads, against 0.03 ms for a plain copy of the same floats). Here the copy goes tile by tile (TILE x TILE rows
//   of C floats), so that every read and every write stays within a few cache lines of the last.
//
//   l1_mean(a, b) = mean |a - b|, one read of a and b (torch: a - b written, its abs written, then summed);
//   l1_grad(a, b, g) = g sgn(a - b), one read of a and b and one write (torch, for mean |a - b|: g / N expanded and
//   written, sgn(a - b) written, their product written). The gradient is the same floats as torch's: g is the
//   already divided g / N (a float), and sgn is -1, 0 or 1 (0 for a NaN difference, as torch's), so each product
//   is exact.
//
// The sums are deterministic for a thread count: at::parallel_for splits [0, n) statically, each thread's range is
// summed in blocks of BLOCK floats (a float sum each, vectorised) added into a double, and the threads' doubles are
// added in thread order.
#include <torch/extension.h>
#include <ATen/Parallel.h>

#include <cmath>
#include <cstdint>
#include <vector>

namespace {

// compiled for AVX-512 as well as the baseline (GCC's target_clones; see fwk_vcconv's native.cpp)
#if defined(__GNUC__) && defined(__x86_64__) && !defined(__clang__)
#define FWK_CORE_CLONES __attribute__((target_clones("avx512f", "default")))
#else
#define FWK_CORE_CLONES
#endif

constexpr int64_t TILE = 32;     // rows of a tile of swap01, each way
constexpr int64_t BLOCK = 4096;  // floats summed in float before the double

void check_float(const torch::Tensor& t, const char* name) {
  TORCH_CHECK(t.device().is_cpu() && t.scalar_type() == at::kFloat, name, ": expected a float32 CPU tensor");
  TORCH_CHECK(t.is_contiguous(), name, ": expected a contiguous tensor");
}

// the tile [i0, i1) x [j0, j1) of swap01: out[j][i][:] = x[i][j][:]
template <int64_t CC>
inline void swap_tile(float* __restrict out, const float* __restrict x, int64_t A, int64_t B, int64_t C, int64_t i0,
                      int64_t i1, int64_t j0, int64_t j1) {
  const int64_t c = CC > 0 ? CC : C;
  for (int64_t j = j0; j < j1; ++j)
    for (int64_t i = i0; i < i1; ++i) {
      const float* s = x + (i * B + j) * c;
      float* d = out + (j * A + i) * c;
      for (int64_t k = 0; k < c; ++k) d[k] = s[k];
    }
}

FWK_CORE_CLONES void swap_tiles(float* out, const float* x, int64_t A, int64_t B, int64_t C, int64_t t0, int64_t t1) {
  const int64_t tb = (B + TILE - 1) / TILE;
  for (int64_t t = t0; t < t1; ++t) {
    const int64_t i0 = (t / tb) * TILE, j0 = (t % tb) * TILE;
    const int64_t i1 = std::min(A, i0 + TILE), j1 = std::min(B, j0 + TILE);
    switch (C) {  // the channel counts of meshes' coordinates and small features, unrolled
      case 1: swap_tile<1>(out, x, A, B, C, i0, i1, j0, j1); break;
      case 2: swap_tile<2>(out, x, A, B, C, i0, i1, j0, j1); break;
      case 3: swap_tile<3>(out, x, A, B, C, i0, i1, j0, j1); break;
      case 4: swap_tile<4>(out, x, A, B, C, i0, i1, j0, j1); break;
      default: swap_tile<0>(out, x, A, B, C, i0, i1, j0, j1);
    }
  }
}

FWK_CORE_CLONES double l1_range(const float* __restrict a, const float* __restrict b, int64_t lo, int64_t hi) {
  double total = 0.0;
  for (int64_t s = lo; s < hi; s += BLOCK) {
    const int64_t e = std::min(hi, s + BLOCK);
    float acc = 0.f;
#pragma omp simd reduction(+ : acc)
    for (int64_t i = s; i < e; ++i) acc += std::fabs(a[i] - b[i]);
    total += acc;
  }
  return total;
}

FWK_CORE_CLONES void l1_grad_range(float* __restrict o, const float* __restrict a, const float* __restrict b, float g,
                                   int64_t lo, int64_t hi) {
#pragma omp simd
  for (int64_t i = lo; i < hi; ++i) {
    const float d = a[i] - b[i];
    const float s = d > 0.f ? 1.f : (d < 0.f ? -1.f : 0.f);  // torch's sgn: 0 at a NaN as well
    o[i] = g * s;
  }
}

}  // namespace

// x (A, B, C) contiguous -> (B, A, C) contiguous
torch::Tensor swap01(torch::Tensor x) {
  check_float(x, "x");
  TORCH_CHECK(x.dim() == 3, "x: expected 3 dimensions, got ", x.dim());
  const int64_t A = x.size(0), B = x.size(1), C = x.size(2);
  auto out = torch::empty({B, A, C}, x.options());
  if (out.numel() == 0) return out;
  const float* xp = x.data_ptr<float>();
  float* op = out.data_ptr<float>();
  const int64_t tiles = ((A + TILE - 1) / TILE) * ((B + TILE - 1) / TILE);
  // a tile is TILE^2 C floats: about 16 tiles (3 KB each at C = 3) a thread's chunk at least
  at::parallel_for(0, tiles, 16, [&](int64_t t0, int64_t t1) { swap_tiles(op, xp, A, B, C, t0, t1); });
  return out;
}

// mean |a - b| (a float32 scalar tensor: the sum and the division in double, rounded once) over a and b of the
// same shape
torch::Tensor l1_mean(torch::Tensor a, torch::Tensor b) {
  check_float(a, "a");
  check_float(b, "b");
  TORCH_CHECK(a.sizes() == b.sizes(), "a and b: expected the same shape, got ", a.sizes(), " and ", b.sizes());
  const int64_t n = a.numel();
  const float* ap = a.data_ptr<float>();
  const float* bp = b.data_ptr<float>();
  std::vector<double> part(at::get_num_threads(), 0.0);
  at::parallel_for(0, n, 8 * BLOCK, [&](int64_t lo, int64_t hi) { part[at::get_thread_num()] = l1_range(ap, bp, lo, hi); });
  double total = 0.0;
  for (double p : part) total += p;
  return torch::full({}, (float)(total / (double)n), a.options());
}

// g sgn(a - b) (a's shape), g a float32 scalar tensor
torch::Tensor l1_grad(torch::Tensor a, torch::Tensor b, torch::Tensor g) {
  check_float(a, "a");
  check_float(b, "b");
  TORCH_CHECK(a.sizes() == b.sizes(), "a and b: expected the same shape, got ", a.sizes(), " and ", b.sizes());
  TORCH_CHECK(g.numel() == 1, "g: expected one value");
  const float gg = g.to(at::kFloat).item<float>();
  auto out = torch::empty_like(a);
  const float* ap = a.data_ptr<float>();
  const float* bp = b.data_ptr<float>();
  float* op = out.data_ptr<float>();
  at::parallel_for(0, a.numel(), 8 * BLOCK, [&](int64_t lo, int64_t hi) { l1_grad_range(op, ap, bp, gg, lo, hi); });
  return out;
}

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
  m.def("swap01", &swap01);
  m.def("l1_mean", &l1_mean);
  m.def("l1_grad", &l1_grad);
}
