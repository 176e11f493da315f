// fwk's own kernels (``fwk.native.ops``): the L1 loss's forward and backward in one pass each, both memory-bound,
// where torch makes more passes:
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
#include "fwk_native.h"  // FWK_CLONES (the loops for AVX-512 and the baseline), check

#include <cmath>
#include <cstdint>
#include <vector>

using fwk_native::check;

namespace {

constexpr int64_t BLOCK = 4096;  // floats summed in float before the double

FWK_CLONES double l1_range(const float* __restrict a, const float* __restrict b, int64_t lo, int64_t hi) {
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

FWK_CLONES void l1_grad_range(float* __restrict o, const float* __restrict a, const float* __restrict b, float g,
                                   int64_t lo, int64_t hi) {
#pragma omp simd
  for (int64_t i = lo; i < hi; ++i) {
    const float d = a[i] - b[i];
    const float s = d > 0.f ? 1.f : (d < 0.f ? -1.f : 0.f);  // torch's sgn: 0 at a NaN as well
    o[i] = g * s;
  }
}

}  // namespace

// mean |a - b| (a float32 scalar tensor: the sum and the division in double, rounded once) over a and b of the
// same shape
torch::Tensor l1_mean(torch::Tensor a, torch::Tensor b) {
  check(a, "a", at::kFloat, a.dim());
  check(b, "b", at::kFloat, b.dim());
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
  check(a, "a", at::kFloat, a.dim());
  check(b, "b", at::kFloat, b.dim());
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
  m.def("l1_mean", &l1_mean);
  m.def("l1_grad", &l1_grad);
}
