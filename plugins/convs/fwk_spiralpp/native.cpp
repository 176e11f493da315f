// SpiralNet++'s gather and product without the gathered matrix (fwk_spiralpp.native).
//
//     y_i = W [x_{s(i,1)} || ... || x_{s(i,L)}] + b        x (n_in, b, c) vertex-major, W (o, L c)
//
// A block of output vertices at a time (about BLOCK_BYTES of gathered rows, which stay in the
// core's L2), each thread its own blocks (at::parallel_for's static split): the block's rows are
// gathered into G (k b, L c), row (i, s) holding x[s(i, l), s] in column block l, and one BLAS call
// gives Y (k b, o) = G W^T (+ b). The backward gathers again for dW += dY^T G (as fast as reading
// back a kept copy, without keeping the (n b, L c) matrix: 200 MB in the thesis's largest layer)
// and scatters dG = dY W to dx. dW and dx go to per-thread accumulators summed in thread order
// (fwk_native.h): the same bits on every run with the same thread count.
#include "fwk_native.h"  // gemm, add_row, check, check_range, thread_accumulator, reduce (fwk.native)

#include <algorithm>
#include <cstring>
#include <vector>

namespace {

using namespace fwk_native;

// gathered floats per block: 256 KB (measured against 64 KB and 1 MB on the main job's PB network and the
// spiral++ AE, 1 thread: 1.15 / 1.12x, 1.15 / 1.10x and 1.08 / 1.08x over the torch code)
constexpr int64_t BLOCK_FLOATS = 64 * 1024;

// G (k b, L c) for output vertices [i0, i0 + k): row (i, s), column block l = x[idx[i, l], s] (c floats)
inline void gather_spiral(float* G, const float* x, const int64_t* idx, int64_t i0, int64_t k, int64_t L, int64_t b,
                          int64_t c) {
  const int64_t Lc = L * c;
  for (int64_t i = 0; i < k; ++i)
    for (int64_t l = 0; l < L; ++l) {
      const float* src = x + idx[(i0 + i) * L + l] * b * c;
      float* dst = G + i * b * Lc + l * c;
      for (int64_t s = 0; s < b; ++s) std::memcpy(dst + s * Lc, src + s * c, c * sizeof(float));
    }
}

// gather_spiral's transpose: G's blocks added to x's rows
inline void scatter_spiral(const float* G, float* x, const int64_t* idx, int64_t i0, int64_t k, int64_t L, int64_t b,
                           int64_t c) {
  const int64_t Lc = L * c;
  for (int64_t i = 0; i < k; ++i)
    for (int64_t l = 0; l < L; ++l) {
      float* dst = x + idx[(i0 + i) * L + l] * b * c;
      const float* src = G + i * b * Lc + l * c;
      for (int64_t s = 0; s < b; ++s) add_row(dst + s * c, src + s * Lc, c);
    }
}

void check_args(const torch::Tensor& x, const torch::Tensor& W, const torch::Tensor& index) {
  check(x, "x", at::kFloat, 3);
  check(W, "weight", at::kFloat, 2);
  check(index, "index", at::kLong, 2);
  TORCH_CHECK(W.size(1) == index.size(1) * x.size(2), "weight: expected ", index.size(1) * x.size(2), " columns (L c)");
  check_range(index, "index", x.size(0));
}

int64_t block_rows(int64_t b, int64_t Lc) { return std::max<int64_t>(1, BLOCK_FLOATS / std::max<int64_t>(1, b * Lc)); }

}  // namespace

// x (n_in, b, c), W (o, L c), bias (o) or empty, index (n_out, L) -> y (n_out, b, o)
torch::Tensor gather_linear_forward(torch::Tensor x, torch::Tensor W, torch::Tensor bias, torch::Tensor index) {
  check_args(x, W, index);
  const int64_t b = x.size(1), c = x.size(2), n_out = index.size(0), L = index.size(1), o = W.size(0);
  const bool has_bias = bias.numel() > 0;
  if (has_bias) {
    check(bias, "bias", at::kFloat, 1);
    TORCH_CHECK(bias.size(0) == o, "bias: expected ", o, " entries");
  }
  auto y = torch::empty({n_out, b, o}, x.options());
  const float* xp = x.data_ptr<float>();
  const float* Wp = W.data_ptr<float>();
  const float* bp = has_bias ? bias.data_ptr<float>() : nullptr;
  const int64_t* ip = index.data_ptr<int64_t>();
  float* yp = y.data_ptr<float>();
  const int64_t Lc = L * c, rows = block_rows(b, Lc);
  at::parallel_for(0, n_out, 1, [&](int64_t a0, int64_t a1) {
    std::vector<float> G(std::max<int64_t>(1, std::min(rows, a1 - a0) * b * Lc));
    for (int64_t i0 = a0; i0 < a1; i0 += rows) {
      const int64_t k = std::min(rows, a1 - i0);
      gather_spiral(G.data(), xp, ip, i0, k, L, b, c);
      float* Y = yp + i0 * b * o;
      if (has_bias)
        for (int64_t r = 0; r < k * b; ++r) std::memcpy(Y + r * o, bp, o * sizeof(float));
      // Y (k b x o) = G (k b x L c) W^T (L c x o) (+ Y holding the bias)
      gemm('T', 'N', o, k * b, Lc, 1.f, Wp, Lc, G.data(), Lc, has_bias ? 1.f : 0.f, Y, o);
    }
  });
  return y;
}

// gy (n_out, b, o) -> dx (n_in, b, c) and dW (o, L c) (empty where not asked for); the bias's gradient is
// gy's sum, left to torch
std::vector<torch::Tensor> gather_linear_backward(torch::Tensor gy, torch::Tensor x, torch::Tensor W,
                                                  torch::Tensor index, bool need_x, bool need_w) {
  check_args(x, W, index);
  check(gy, "gy", at::kFloat, 3);
  const int64_t n_in = x.size(0), b = x.size(1), c = x.size(2), n_out = index.size(0), L = index.size(1),
                o = W.size(0);
  TORCH_CHECK(gy.size(0) == n_out && gy.size(1) == b && gy.size(2) == o, "gy: expected (", n_out, ", ", b, ", ", o,
              ")");
  const int64_t Lc = L * c, rows = block_rows(b, Lc);
  const int nt = at::get_num_threads();
  auto empty = torch::empty({0}, x.options());
  auto dxa = need_x ? torch::zeros({nt, n_in, b, c}, x.options()) : empty;
  auto dWa = need_w ? torch::zeros({nt, o, Lc}, x.options()) : empty;
  const float* xp = x.data_ptr<float>();
  const float* Wp = W.data_ptr<float>();
  const float* gp = gy.data_ptr<float>();
  const int64_t* ip = index.data_ptr<int64_t>();
  float* dxp = need_x ? dxa.data_ptr<float>() : nullptr;
  float* dWp = need_w ? dWa.data_ptr<float>() : nullptr;
  at::parallel_for(0, n_out, 1, [&](int64_t a0, int64_t a1) {
    float* dx = need_x ? thread_accumulator(dxp, nt, n_in * b * c) : nullptr;
    float* dW = need_w ? thread_accumulator(dWp, nt, o * Lc) : nullptr;
    std::vector<float> G(std::max<int64_t>(1, std::min(rows, a1 - a0) * b * Lc));
    for (int64_t i0 = a0; i0 < a1; i0 += rows) {
      const int64_t k = std::min(rows, a1 - i0);
      const float* gyk = gp + i0 * b * o;
      if (need_w) {
        gather_spiral(G.data(), xp, ip, i0, k, L, b, c);
        // dW (o x L c) += dY^T (o x k b) G (k b x L c)
        gemm('N', 'T', Lc, o, k * b, 1.f, G.data(), Lc, gyk, o, 1.f, dW, Lc);
      }
      if (need_x) {
        // dG (k b x L c) = dY (k b x o) W (o x L c), scattered to dx
        gemm('N', 'N', Lc, k * b, o, 1.f, Wp, Lc, gyk, o, 0.f, G.data(), Lc);
        scatter_spiral(G.data(), dx, ip, i0, k, L, b, c);
      }
    }
  });
  return {need_x ? reduce(dxa) : dxa, need_w ? reduce(dWa) : dWa};
}

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
  m.def("gather_linear_forward", &gather_linear_forward);
  m.def("gather_linear_backward", &gather_linear_backward);
}
