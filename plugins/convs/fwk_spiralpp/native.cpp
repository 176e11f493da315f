// SpiralNet++'s gather and product without the gathered matrix, and its conv of an up-sampled
// input (fwk_spiralpp.native).
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
#include "fwk_native.h"  // gemm, rows_gemm, tall_mm, tall_tn, add_row, check, check_range, check_csr,
                          // ThreadAccumulators, reduce (fwk.native)

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
  fwk_native::parallel_for(0, n_out, 1, [&](int64_t a0, int64_t a1) {
    std::vector<float> G(std::max<int64_t>(1, std::min(rows, a1 - a0) * b * Lc)), tmp;
    for (int64_t i0 = a0; i0 < a1; i0 += rows) {
      const int64_t k = std::min(rows, a1 - i0);
      gather_spiral(G.data(), xp, ip, i0, k, L, b, c);
      float* Y = yp + i0 * b * o;
      if (has_bias)
        for (int64_t r = 0; r < k * b; ++r) std::memcpy(Y + r * o, bp, o * sizeof(float));
      // Y (k b x o) = G (k b x L c) W^T (L c x o) (+ Y holding the bias); narrow o the long side first
      rows_gemm(k * b, o, Lc, G.data(), Lc, Wp, true, has_bias ? 1.f : 0.f, Y, o, tmp);
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
  auto empty = torch::empty({0}, x.options());
  ThreadAccumulators dxa({need_x ? n_in : 0, b, c}, x.options()), dWa({need_w ? o : 0, Lc}, x.options());
  const float* xp = x.data_ptr<float>();
  const float* Wp = W.data_ptr<float>();
  const float* gp = gy.data_ptr<float>();
  const int64_t* ip = index.data_ptr<int64_t>();
  fwk_native::parallel_for(0, n_out, 1, [&](int64_t a0, int64_t a1) {
    float* dx = need_x ? dxa.mine() : nullptr;
    float* dW = need_w ? dWa.mine() : nullptr;
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
  return {need_x ? reduce(dxa.done()) : empty, need_w ? reduce(dWa.done()) : empty};
}

// ---- forward_up: the conv of an up-sampled input, y = S Z with Z_l = x W_l^T on the coarse vertices
//
//     y_i = b + sum_{(l, j, u) in row i of S} u Z_l[j]      Z (L, n_c, b, o), Z_l = x (n_c b, c) W_l^T,
//
// W' (L o, c) the weight laid out per spiral entry (W'[l o + p, :] = W[p, l c : (l + 1) c]); S (n, L n_c)
// CSR with column l n_c + j (fwk_spiralpp.SpiralPP._up_tables), so that a column names one row of Z
// viewed as (L n_c, b o). Output rows are independent: each sums its non-zeros in CSR order (the
// same bits on any thread count). Backward: dZ = S^T dy, row by row (rows of S^T are rows of dZ: no
// accumulators), then dx = sum_l dZ_l W'_l and dW'_l = dZ_l^T x.

namespace {

// a sparse matrix as CSR (crow, col, val): fwk_native.h's structure check and one value a column index
void check_csr_rows(const torch::Tensor& crow, const torch::Tensor& col, const torch::Tensor& val, int64_t rows,
                    int64_t cols, const char* name) {
  check_csr(crow, col, rows, cols, name, name);
  check(val, name, at::kFloat, 1);
  TORCH_CHECK(col.size(0) == val.size(0), name, ": one value a non-zero");
}

inline void axpy(float* __restrict y, const float* __restrict x, float a, int64_t n) {
#pragma omp simd
  for (int64_t t = 0; t < n; ++t) y[t] += a * x[t];
}

// out (rows, w) = M z for CSR M (rows x *) and row-major z (*, w); out's rows start from init (w floats) or 0
void csr_rows(const int64_t* rp, const int64_t* cp, const float* vp, const float* z, int64_t rows, int64_t w,
              const float* init, float* out) {
  fwk_native::parallel_for(0, rows, 1, [&](int64_t r0, int64_t r1) {
    for (int64_t r = r0; r < r1; ++r) {
      float* yr = out + r * w;
      if (init)
        std::memcpy(yr, init, w * sizeof(float));
      else
        std::fill(yr, yr + w, 0.f);
      for (int64_t k = rp[r]; k < rp[r + 1]; ++k) axpy(yr, z + cp[k] * w, vp[k], w);
    }
  });
}

}  // namespace

// x (n_c, b, c), Wp (L o, c), bias (o) or empty, S = (crow, col, val) (n, L n_c) -> y (n, b, o)
torch::Tensor up_linear_forward(torch::Tensor x, torch::Tensor Wp, torch::Tensor bias, torch::Tensor crow,
                                torch::Tensor col, torch::Tensor val, int64_t L) {
  check(x, "x", at::kFloat, 3);
  check(Wp, "weight", at::kFloat, 2);
  const int64_t n_c = x.size(0), b = x.size(1), c = x.size(2), Lo = Wp.size(0), o = Lo / std::max<int64_t>(L, 1);
  TORCH_CHECK(L > 0 && o * L == Lo && Wp.size(1) == c, "weight: expected (L o, ", c, ") rows per spiral entry");
  const int64_t n = crow.size(0) - 1, m = n_c * b;
  check_csr_rows(crow, col, val, n, L * n_c, "S");
  const bool has_bias = bias.numel() > 0;
  if (has_bias) {
    check(bias, "bias", at::kFloat, 1);
    TORCH_CHECK(bias.size(0) == o, "bias: expected ", o, " entries");
  }
  auto Z = torch::empty({L, m, o}, x.options());
  auto y = torch::empty({n, b, o}, x.options());
  const float* Wpp = Wp.data_ptr<float>();
  const float* xp = x.data_ptr<float>();
  float* Zp = Z.data_ptr<float>();
  // Z_l (n_c b x o) = x (n_c b x c) W'_l^T (c x o): tall and narrow (fwk_native.h's tall_mm)
  for (int64_t l = 0; l < L; ++l) tall_mm(xp, Wpp + l * o * c, true, nullptr, Zp + l * m * o, m, c, o);
  std::vector<float> init;
  if (has_bias) {
    init.resize(b * o);
    for (int64_t s = 0; s < b; ++s) std::memcpy(init.data() + s * o, bias.data_ptr<float>(), o * sizeof(float));
  }
  csr_rows(crow.data_ptr<int64_t>(), col.data_ptr<int64_t>(), val.data_ptr<float>(), Zp, n, b * o,
           has_bias ? init.data() : nullptr, y.data_ptr<float>());
  return y;
}

// dy (n, b, o), x (n_c, b, c), Wp (L o, c), S^T = (crow, col, val) (L n_c, n) -> dx (n_c, b, c), dWp (L o, c)
std::vector<torch::Tensor> up_linear_backward(torch::Tensor dy, torch::Tensor x, torch::Tensor Wp, torch::Tensor crow,
                                              torch::Tensor col, torch::Tensor val, int64_t L, bool need_x,
                                              bool need_w) {
  check(dy, "dy", at::kFloat, 3);
  check(x, "x", at::kFloat, 3);
  check(Wp, "weight", at::kFloat, 2);
  const int64_t n_c = x.size(0), b = x.size(1), c = x.size(2), Lo = Wp.size(0), o = Lo / std::max<int64_t>(L, 1),
                n = dy.size(0), m = n_c * b;
  TORCH_CHECK(L > 0 && o * L == Lo && Wp.size(1) == c, "weight: expected (L o, ", c, ") rows per spiral entry");
  TORCH_CHECK(dy.size(1) == b && dy.size(2) == o, "dy: expected (n, ", b, ", ", o, ")");
  check_csr_rows(crow, col, val, L * n_c, n, "S^T");
  auto dZ = torch::empty({L, m, o}, x.options());
  float* dZp = dZ.data_ptr<float>();
  csr_rows(crow.data_ptr<int64_t>(), col.data_ptr<int64_t>(), val.data_ptr<float>(), dy.data_ptr<float>(), L * n_c,
           b * o, nullptr, dZp);
  auto empty = torch::empty({0}, x.options());
  auto dx = need_x ? torch::empty({n_c, b, c}, x.options()) : empty;
  auto dWp = need_w ? torch::empty({Lo, c}, x.options()) : empty;
  const float* Wpp = Wp.data_ptr<float>();
  const float* xp = x.data_ptr<float>();
  for (int64_t l = 0; l < L; ++l) {
    // dx (n_c b x c) += dZ_l (n_c b x o) W'_l (o x c)  (tall and narrow: fwk_native.h's tall_mm)
    if (need_x) tall_mm(dZp + l * m * o, Wpp + l * o * c, false, nullptr, dx.data_ptr<float>(), m, o, c, l > 0);
    // dW'_l (o x c) = dZ_l^T (o x n_c b) x (n_c b x c)  (tall_tn: row blocks summed per thread)
    if (need_w) dWp.narrow(0, l * o, o).copy_(tall_tn(dZp + l * m * o, xp, m, o, c, x.options()));
  }
  return {dx, dWp};
}

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
  m.def("gather_linear_forward", &gather_linear_forward);
  m.def("gather_linear_backward", &gather_linear_backward);
  m.def("up_linear_forward", &up_linear_forward);
  m.def("up_linear_backward", &up_linear_backward);
}
