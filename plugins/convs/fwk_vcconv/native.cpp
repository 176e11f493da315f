// vcconv's per-vertex products without the gathered intermediates (fwk_vcconv.native).
//
// Both orders of ``fwk_vcconv`` multiply, for every vertex v, a small matrix of coefficients by
// the rows of other vertices that v's support names. In torch that takes a gather of those rows
// into one large tensor (slots x b c floats: 51 MB for the thesis's second encoder layer), a
// batched product over padded supports, and a scatter back; the kernels below gather a vertex's
// rows into a buffer that stays in cache, call BLAS once per vertex on the exact (unpadded)
// support, and accumulate straight into the result.
//
// Layout and per-thread accumulators: fwk_native.h (fwk.native).
//
// ``sum`` order (output side, the encoder's strided layers): for output vertex i with slots
// s in [offs[i], offs[i+1]), X_i = x[src[s]] (K_i x B, B = b c), A_i (K_i x Mx) the rows coef[pos[s]]
// (M floats) beside w[pos[s]] when the residual's weights are given (Mx = M + 1):
//     T_i = X_i^T A_i[:, :M]  (B x M),   r_i = X_i^T A_i[:, M]  (B; only when Mx = M + 1)
// with the gradients dX_i = A_i dT_i^T (+ a_i dr_i^T), scattered to x's rows, and dA_i = X_i dT_i;
// ``basis`` order (input side, the decoder's transposed layers): for input vertex j with slots
// s in [offs[j], offs[j+1]), Z_j (B' x M) and A_j (K'_j x M) the rows coef[pos[s]]:
//     y[dst[s]] += (A_j Z_j^T)[s]   (rows of B' floats)
// with dA_j = dY_j Z_j and dZ_j = dY_j^T A_j (dY_j = dy's rows at dst).
//
// The coefficients are read where the conv keeps them (pos: each slot's row of the conv's
// (n_out K, M) coefficients, distinct) and their gradients written there, so no gathered copy and
// no scatter-add of them is made. Scatters into a shared result (the ``sum`` order's dx, the
// ``basis`` order's y) go to per-thread accumulators (fwk_native.h).
#include "fwk_native.h"  // gemm, add_row, axpy_row, check, check_csr, ThreadAccumulators, thread_accumulator, reduce, tall_mm, tall_tn (fwk.native)

#include <algorithm>
#include <cstring>
#include <vector>
#if defined(__GNUC__) && !defined(__clang__) && defined(__x86_64__)
#include <immintrin.h>  // the lane kernels' masked loads and stores (AVX-512, in their target region below)
#endif

namespace {

using namespace fwk_native;

int64_t max_run(const int64_t* offs, int64_t n) {
  int64_t k = 0;
  for (int64_t i = 0; i < n; ++i) k = std::max(k, offs[i + 1] - offs[i]);
  return k;
}

// rows base[idx[s]] (B floats each) of slots [s0, s0 + K) into buf (K x B)
inline void gather_rows(float* buf, const float* base, const int64_t* idx, int64_t s0, int64_t K, int64_t B) {
  for (int64_t k = 0; k < K; ++k) std::memcpy(buf + k * B, base + idx[s0 + k] * B, B * sizeof(float));
}

// the rows of buf (K x B) added to base[idx[s]] for slots [s0, s0 + K) (gather_rows' transpose)
inline void scatter_add_rows(const float* buf, float* base, const int64_t* idx, int64_t s0, int64_t K, int64_t B) {
  for (int64_t k = 0; k < K; ++k) add_row(base + idx[s0 + k] * B, buf + k * B, B);
}

// the coefficient rows of slots [s0, s0 + K) into buf (K x Mx): coef[pos[s]] (M floats) and, when
// Mx == M + 1, w[pos[s]] in the last column
inline void gather_coef(float* buf, const float* coef, const float* w, const int64_t* pos, int64_t s0, int64_t K,
                        int64_t M, int64_t Mx) {
  for (int64_t k = 0; k < K; ++k) {
    std::memcpy(buf + k * Mx, coef + pos[s0 + k] * M, M * sizeof(float));
    if (Mx > M) buf[k * Mx + M] = w[pos[s0 + k]];
  }
}

// the rows of a (K x Mx) block back to their coefficient rows (positions are distinct: no conflicts)
inline void scatter_coef(const float* buf, float* dcoef, float* dw, const int64_t* pos, int64_t s0, int64_t K,
                         int64_t M, int64_t Mx) {
  for (int64_t k = 0; k < K; ++k) {
    if (dcoef) std::memcpy(dcoef + pos[s0 + k] * M, buf + k * Mx, M * sizeof(float));
    if (dw && Mx > M) dw[pos[s0 + k]] = buf[k * Mx + M];
  }
}

// a row x (b x c, row-major) into the columns [0, c) of b rows of ld floats (dst row q at dst + q ld); c is
// a few floats (3-32): plain loops, not a memcpy call per piece
inline void gather_transposed(float* dst, int64_t ld, const float* x, int64_t b, int64_t c) {
  for (int64_t q = 0; q < b; ++q)
    for (int64_t p = 0; p < c; ++p) dst[q * ld + p] = x[q * c + p];
}

void check_coef(const torch::Tensor& coef, const torch::Tensor& w, const torch::Tensor& pos, int64_t slots) {
  check(coef, "coef", at::kFloat, 2);
  check(w, "w", at::kFloat, 1);
  TORCH_CHECK(w.size(0) == 0 || w.size(0) == coef.size(0), "w: one weight per coefficient row, or none");
  TORCH_CHECK(pos.dim() == 1 && pos.size(0) == slots, "pos: expected one entry a slot (", slots, ")");
  // the backward writes each slot's coefficient row in place: positions must be distinct
  check_distinct(pos, "pos", coef.size(0));
}

// the gradient (rows, cols) of per-row parameters (coefficients, kernels, residual weights) that a backward writes
// row by row at the rows its slots name (check_coef: each at most once): zero-filled first only where some row is
// named by no slot (8 MB a step in the chapter 5 width's last layer otherwise)
inline torch::Tensor row_grad(bool need, int64_t rows, int64_t cols, int64_t slots, const at::TensorOptions& opt) {
  if (!need) return torch::empty({0}, opt);
  const auto size = cols > 0 ? std::vector<int64_t>{rows, cols} : std::vector<int64_t>{rows};
  return slots == rows ? torch::empty(size, opt) : torch::zeros(size, opt);
}

}  // namespace

// The lane kernels that take the kernels (the coefficients' M columns, and the residual's weight in the sum order) as
// the vector hold them as NV vectors of 16 floats and, where the last 1-8 would fill half a vector or less, a half
// vector (H = 1) for those: W = 16 NV + 8 H floats a row, zero past the kernels. Zen 4 runs a 16-float multiply-add
// as two 8-float halves, so M = 35 (36 with the residual) costs 2.5 vectors a row instead of 3 (13 of 48 lanes wasted).
struct KernelChunks {
  int64_t NV, H, W;
};
inline KernelChunks kernel_chunks(int64_t Mx) {
  int64_t NV = Mx / 16, H = 0;
  const int64_t rem = Mx % 16;
  if (rem > 8 || (rem > 0 && NV == 0)) ++NV;
  else if (rem > 0) H = 1;
  return {NV, H, 16 * NV + 8 * H};
}

// (the lane kernels, compiled for AVX-512 below) T_i and r_i of one output vertex (its slots [s0, s0 + K)) with the
// kernels as the vector; A (K W floats) and X (K pointers) are the caller's buffers
void sum_vertex_lanes(float* Ti, float* ri, const float* x, const float* coef, const float* w, const int64_t* src,
                      const int64_t* pos, int64_t s0, int64_t K, int64_t M, int64_t B, KernelChunks ch, float* A,
                      const float** X);
// (the same) the coefficients' gradient of one output vertex's slots, written to their rows of dcoef and dw (either
// null where not asked for), with the kernels as the vector; dA (K W floats) and X (K pointers) the caller's buffers
void sum_vertex_lanes_backward(float* dcoef, float* dw, const float* x, const int64_t* src, const int64_t* pos,
                               int64_t s0, int64_t K, const float* dTi, const float* dri, int64_t M, int64_t B,
                               KernelChunks ch, std::vector<float>& work, float* dA, const float** X);
// (the same) x's gradient of one output vertex's slots, dX_k = A_k dT_i^T (+ a_k dr_i^T), added to their rows of
// acc (n_in x B): dT_i (and dr_i) transposed into dTt (the caller's buffer, at least (M + 1) round16(B) floats), the
// batch as the vector
void sum_vertex_lanes_dx(float* acc, const float* dTi, const float* dri, const float* coef, const float* w,
                         const int64_t* src, const int64_t* pos, int64_t s0, int64_t K, int64_t M, int64_t B,
                         float* dTt);
inline int64_t round16(int64_t n) { return (n + 15) / 16 * 16; }
bool lanes_supported();
// a caller's ``lanes``: refused where this build or CPU does not run the lane kernels
inline void check_lanes(bool lanes) {
  TORCH_CHECK(!lanes || lanes_supported(), "lanes: this build or CPU does not run the lane kernels");
}
// (the same) C (R x N) = A (R x K) op(B) + bias (N, or null); op(B) = B (K x N) or, with bt, B^T (B: N x K).
// Taken for results of at most TALL_LANES_MAX_N columns: 1.2-3.0x tall_mm's BLAS calls for 3-35 (the chapter 5
// width's products with its basis and residual maps, alternating), 1.28-1.40x for 72-128 (forward products of 35 to
// 1,120 terms a value, the thesis width's), 0.8-1.1x for 280 and 560 (the gradients dA of 16 and 32 terms, whose rows
// are written at the memory's rate either way). (The basis's gradient A^T dC stays with tall_tn: the same in lanes,
// the rows of C the vectors, was 0.5-0.9x.)
constexpr int64_t TALL_LANES_MAX_N = 128;
void tall_lanes(const float* A, const float* B, bool bt, const float* bias, float* C, int64_t R, int64_t K, int64_t N);

// sum order, forward. x (n_in, B); coef (R, M) and w (R, or empty) are read at pos (slots); offs
// (n_out + 1), src (slots). Returns T (n_out, B, M) and r (n_out, B) (empty (0,) without w). Each T_i by one BLAS
// call on the gathered rows, or with ``lanes`` (on CPUs that run them: lanes_supported) by sum_vertex_lanes.
std::vector<torch::Tensor> sum_forward(torch::Tensor x, torch::Tensor coef, torch::Tensor w, torch::Tensor offs,
                                       torch::Tensor src, torch::Tensor pos, bool lanes) {
  check(x, "x", at::kFloat, 2);
  const int64_t n_in = x.size(0), B = x.size(1), M = coef.size(1), n_out = offs.size(0) - 1;
  check_csr(offs, src, n_out, n_in);
  check_coef(coef, w, pos, src.size(0));
  const bool res = w.size(0) > 0;
  const int64_t Mx = M + (res ? 1 : 0);
  const KernelChunks ch = kernel_chunks(Mx);  // the kernels' vectors (lanes): W floats a slot
  TORCH_CHECK(!lanes || Mx <= 64, "coef: at most ", 64 - (res ? 1 : 0), " kernels in lanes");
  check_lanes(lanes);
  auto T = torch::empty({n_out, B, M}, x.options());
  auto r = res ? torch::empty({n_out, B}, x.options()) : torch::empty({0}, x.options());
  const float* xp = x.data_ptr<float>();
  const float* cp = coef.data_ptr<float>();
  const float* wp = res ? w.data_ptr<float>() : nullptr;
  const int64_t* op = offs.data_ptr<int64_t>();
  const int64_t* sp = src.data_ptr<int64_t>();
  const int64_t* pp = pos.data_ptr<int64_t>();
  float* Tp = T.data_ptr<float>();
  float* rp = res ? r.data_ptr<float>() : nullptr;
  const int64_t Kmax = max_run(op, n_out);
  fwk_native::parallel_for(0, n_out, 1, [&](int64_t i0, int64_t i1) {
    std::vector<float> buf(lanes ? 1 : std::max<int64_t>(Kmax * B, 1));
    std::vector<float> A(std::max<int64_t>(Kmax * (lanes ? ch.W : Mx), 1));
    std::vector<const float*> X(std::max<int64_t>(Kmax, 1));
    for (int64_t i = i0; i < i1; ++i) {
      const int64_t s0 = op[i], K = op[i + 1] - s0;
      if (i + 1 < i1) prefetch_rows(xp, sp, op[i + 1], op[i + 2], B, B * sizeof(float));  // the next vertex's x rows
      if (lanes) {  // the rows read in place; each slot's coefficients (and w in column M) zero-padded to W
        sum_vertex_lanes(Tp + i * B * M, res ? rp + i * B : nullptr, xp, cp, wp, sp, pp, s0, K, M, B, ch, A.data(),
                         X.data());
        continue;
      }
      gather_rows(buf.data(), xp, sp, s0, K, B);
      gather_coef(A.data(), cp, wp, pp, s0, K, M, Mx);
      // T_i (B x M) = X_i^T (B x K) A_i (K x M)
      gemm('N', 'T', M, B, K, 1.f, A.data(), Mx, buf.data(), B, 0.f, Tp + i * B * M, M);
      // r_i (1 x B) = a_i^T (1 x K) X_i (K x B)
      if (res) gemm('N', 'T', 1, B, K, 1.f, A.data() + M, Mx, buf.data(), B, 0.f, rp + i * B, 1);
    }
  });
  return {T, r};
}

// sum order, backward. dT (n_out, B, M), dr (n_out, B) or empty; returns dx (n_in, B), dcoef (R, M)
// and dw (R) (zero at the rows no slot reads; empty where not asked for). dx, dcoef and dw by one BLAS call per
// vertex, or with ``lanes`` dcoef and dw by sum_vertex_lanes_backward (the kernels as the vector, the x rows in
// place) and dx by sum_vertex_lanes_dx (dT_i transposed, the batch as the vector).
std::vector<torch::Tensor> sum_backward(torch::Tensor dT, torch::Tensor dr, torch::Tensor x, torch::Tensor coef,
                                        torch::Tensor w, torch::Tensor offs, torch::Tensor src, torch::Tensor pos,
                                        bool need_dx, bool need_dcoef, bool need_dw, bool lanes) {
  check(dT, "dT", at::kFloat, 3);
  const int64_t n_in = x.size(0), B = x.size(1), M = coef.size(1), n_out = offs.size(0) - 1;
  const bool res = w.size(0) > 0;
  const int64_t Mx = M + (res ? 1 : 0);
  const KernelChunks ch = kernel_chunks(Mx);
  TORCH_CHECK(!lanes || Mx <= 64, "coef: at most ", 64 - (res ? 1 : 0), " kernels in lanes");
  check_lanes(lanes);
  if (res) check(dr, "dr", at::kFloat, 2);
  need_dw = need_dw && res;
  auto empty = torch::empty({0}, x.options());
  ThreadAccumulators acc({need_dx ? n_in : 0, B}, x.options());
  auto dcoef = row_grad(need_dcoef, coef.size(0), M, src.size(0), x.options());
  auto dw = row_grad(need_dw, w.size(0), 0, src.size(0), x.options());
  const float* xp = x.data_ptr<float>();
  const float* cp = coef.data_ptr<float>();
  const float* wp = res ? w.data_ptr<float>() : nullptr;
  const float* dTp = dT.data_ptr<float>();
  const float* drp = res ? dr.data_ptr<float>() : nullptr;
  const int64_t* op = offs.data_ptr<int64_t>();
  const int64_t* sp = src.data_ptr<int64_t>();
  const int64_t* pp = pos.data_ptr<int64_t>();
  float* dcp = need_dcoef ? dcoef.data_ptr<float>() : nullptr;
  float* dwp = need_dw ? dw.data_ptr<float>() : nullptr;
  const int64_t Kmax = max_run(op, n_out);
  fwk_native::parallel_for(0, n_out, 1, [&](int64_t i0, int64_t i1) {
    float* mine = need_dx ? acc.mine() : nullptr;
    // the BLAS route's buffers (with ``lanes`` every gradient is made in the lane kernels' own)
    const int64_t rows = lanes ? 1 : std::max<int64_t>(Kmax * B, 1);
    const int64_t coefs = lanes ? 1 : std::max<int64_t>(Kmax * Mx, 1);
    std::vector<float> buf(rows), dbuf(rows), A(coefs), dA(coefs);
    std::vector<float> dAL(lanes ? Kmax * ch.W : 0), work, dTt(lanes && need_dx ? (M + 1) * round16(B) : 0);
    std::vector<const float*> X(lanes ? Kmax : 0);
    for (int64_t i = i0; i < i1; ++i) {
      const int64_t s0 = op[i], K = op[i + 1] - s0;
      if (i + 1 < i1) {  // the next vertex's x rows, and its rows of this thread's dx
        prefetch_rows(xp, sp, op[i + 1], op[i + 2], B, B * sizeof(float));
        if (need_dx) prefetch_rows<1>(mine, sp, op[i + 1], op[i + 2], B, B * sizeof(float));
        if (lanes) prefetch_block(dTp + (i + 1) * B * M, B * M);  // read once, from memory: dT_i is 18 KB at B 128
      }
      if (K == 0) continue;
      const float* dTi = dTp + i * B * M;
      if ((need_dcoef || need_dw) && lanes)  // the x rows read in place; dA_k padded to W (w's in column M)
        sum_vertex_lanes_backward(need_dcoef ? dcp : nullptr, need_dw ? dwp : nullptr, xp, sp, pp, s0, K, dTi,
                                  res ? drp + i * B : nullptr, M, B, ch, work, dAL.data(), X.data());
      if ((need_dcoef || need_dw) && !lanes) {
        gather_rows(buf.data(), xp, sp, s0, K, B);
        // dA_i[:, :M] (K x M) = X_i (K x B) dT_i (B x M)
        gemm('N', 'N', M, K, B, 1.f, dTi, M, buf.data(), B, 0.f, dA.data(), Mx);
        // dA_i[:, M] (K x 1) = X_i (K x B) dr_i (B x 1)
        if (res) gemm('N', 'N', 1, K, B, 1.f, drp + i * B, 1, buf.data(), B, 0.f, dA.data() + M, Mx);
        scatter_coef(dA.data(), dcp, dwp, pp, s0, K, M, Mx);
      }
      if (need_dx && lanes) {
        sum_vertex_lanes_dx(mine, dTi, res ? drp + i * B : nullptr, cp, wp, sp, pp, s0, K, M, B, dTt.data());
      } else if (need_dx) {
        gather_coef(A.data(), cp, wp, pp, s0, K, M, Mx);
        // dX_i (K x B) = A_i[:, :M] (K x M) dT_i^T (M x B)  (+ a_i (K x 1) dr_i^T (1 x B))
        gemm('T', 'N', B, K, M, 1.f, dTi, M, A.data(), Mx, 0.f, dbuf.data(), B);
        if (res) gemm('N', 'N', B, K, 1, 1.f, drp + i * B, B, A.data() + M, Mx, 1.f, dbuf.data(), B);
        scatter_add_rows(dbuf.data(), mine, sp, s0, K, B);
      }
    }
  });
  return {need_dx ? reduce(acc.done()) : empty, dcoef, dw};
}

// basis order, forward. Z (n_in, B, M); coef (R, M) read at pos (slots); offs (n_in + 1), dst
// (slots); y (n_out, B) = sum of the slots' rows (A_j Z_j^T)[s] at their outputs.
torch::Tensor basis_forward(torch::Tensor Z, torch::Tensor coef, torch::Tensor offs, torch::Tensor dst,
                            torch::Tensor pos, int64_t n_out) {
  check(Z, "Z", at::kFloat, 3);
  const int64_t n_in = Z.size(0), B = Z.size(1), M = Z.size(2);
  TORCH_CHECK(coef.dim() == 2 && coef.size(1) == M, "coef: expected ", M, " columns");
  check_csr(offs, dst, n_in, n_out);
  check_coef(coef, torch::empty({0}, Z.options()), pos, dst.size(0));
  ThreadAccumulators acc({n_out, B}, Z.options());
  const float* Zp = Z.data_ptr<float>();
  const float* cp = coef.data_ptr<float>();
  const int64_t* op = offs.data_ptr<int64_t>();
  const int64_t* dp = dst.data_ptr<int64_t>();
  const int64_t* pp = pos.data_ptr<int64_t>();
  const int64_t Kmax = max_run(op, n_in);
  fwk_native::parallel_for(0, n_in, 1, [&](int64_t j0, int64_t j1) {
    float* mine = acc.mine();
    std::vector<float> buf(std::max<int64_t>(Kmax * B, 1)), A(std::max<int64_t>(Kmax * M, 1));
    for (int64_t j = j0; j < j1; ++j) {
      const int64_t s0 = op[j], K = op[j + 1] - s0;
      if (K == 0) continue;
      gather_coef(A.data(), cp, nullptr, pp, s0, K, M, M);
      // Y_j (K x B) = A_j (K x M) Z_j^T (M x B)
      gemm('T', 'N', B, K, M, 1.f, Zp + j * B * M, M, A.data(), M, 0.f, buf.data(), B);
      scatter_add_rows(buf.data(), mine, dp, s0, K, B);
    }
  });
  return reduce(acc.done());
}

// basis order, backward. dy (n_out, B); returns dZ (n_in, B, M) and dcoef (R, M) (zero at the rows no
// slot reads; empty where not asked for).
std::vector<torch::Tensor> basis_backward(torch::Tensor dy, torch::Tensor Z, torch::Tensor coef, torch::Tensor offs,
                                          torch::Tensor dst, torch::Tensor pos, bool need_dZ, bool need_dcoef) {
  check(dy, "dy", at::kFloat, 2);
  const int64_t n_in = Z.size(0), B = Z.size(1), M = Z.size(2);
  auto empty = torch::empty({0}, Z.options());
  auto dZ = need_dZ ? torch::empty({n_in, B, M}, Z.options()) : empty;
  auto dcoef = row_grad(need_dcoef, coef.size(0), M, dst.size(0), Z.options());
  const float* Zp = Z.data_ptr<float>();
  const float* cp = coef.data_ptr<float>();
  const float* dyp = dy.data_ptr<float>();
  const int64_t* op = offs.data_ptr<int64_t>();
  const int64_t* dp = dst.data_ptr<int64_t>();
  const int64_t* pp = pos.data_ptr<int64_t>();
  float* dZp = need_dZ ? dZ.data_ptr<float>() : nullptr;
  float* dcp = need_dcoef ? dcoef.data_ptr<float>() : nullptr;
  const int64_t Kmax = max_run(op, n_in);
  fwk_native::parallel_for(0, n_in, 1, [&](int64_t j0, int64_t j1) {
    std::vector<float> buf(std::max<int64_t>(Kmax * B, 1)), A(std::max<int64_t>(Kmax * M, 1));
    for (int64_t j = j0; j < j1; ++j) {
      const int64_t s0 = op[j], K = op[j + 1] - s0;
      if (K == 0) {
        if (need_dZ) std::fill(dZp + j * B * M, dZp + (j + 1) * B * M, 0.f);
        continue;
      }
      gather_rows(buf.data(), dyp, dp, s0, K, B);
      if (need_dcoef) {
        // dA_j (K x M) = dY_j (K x B) Z_j (B x M)
        gemm('N', 'N', M, K, B, 1.f, Zp + j * B * M, M, buf.data(), B, 0.f, A.data(), M);
        scatter_coef(A.data(), dcp, nullptr, pp, s0, K, M, M);
      }
      if (need_dZ) {
        gather_coef(A.data(), cp, nullptr, pp, s0, K, M, M);
        // dZ_j (B x M) = dY_j^T (B x K) A_j (K x M)
        gemm('N', 'T', M, B, K, 1.f, A.data(), M, buf.data(), B, 0.f, dZp + j * B * M, M);
      }
    }
  });
  return {dZ, dcoef};
}

// kernel order, forward. x (n_in, b c); Wk (R, c o): each coefficient row's kernel W = sum_m A_m B_m
// (c x o, row-major); w (R, or empty) the residual's weights, read at pos (slots); offs (n_out + 1), src
// (slots). For output vertex i with slots s in [offs[i], offs[i+1]) (K of them):
//     y_i (b x o) = G_i (b x K c) W_i (K c x o),   G_i[beta, (k, p)] = x[src[s_k], beta, p],  W_i = Wk[pos[s_k]] stacked
//     r_i (b c) = sum_k w[pos[s_k]] x[src[s_k]]
// Returns y (n_out, b, o) (no bias) and r (n_out, b c) (empty (0,) without w).
std::vector<torch::Tensor> kernel_forward(torch::Tensor x, torch::Tensor Wk, torch::Tensor w, torch::Tensor offs,
                                          torch::Tensor src, torch::Tensor pos, int64_t b, int64_t c, int64_t o) {
  check(x, "x", at::kFloat, 2);
  check(Wk, "Wk", at::kFloat, 2);
  const int64_t n_in = x.size(0), B = x.size(1), n_out = offs.size(0) - 1, co = c * o;
  TORCH_CHECK(b > 0 && c > 0 && o > 0 && B == b * c, "x: expected b c = ", b * c, " columns");
  TORCH_CHECK(Wk.size(1) == co, "Wk: expected c o = ", co, " columns");
  check_csr(offs, src, n_out, n_in);
  check_coef(Wk, w, pos, src.size(0));
  const bool res = w.size(0) > 0;
  auto y = torch::empty({n_out, b, o}, x.options());
  auto r = res ? torch::empty({n_out, B}, x.options()) : torch::empty({0}, x.options());
  const float* xp = x.data_ptr<float>();
  const float* Wp = Wk.data_ptr<float>();
  const float* wp = res ? w.data_ptr<float>() : nullptr;
  const int64_t* op = offs.data_ptr<int64_t>();
  const int64_t* sp = src.data_ptr<int64_t>();
  const int64_t* pp = pos.data_ptr<int64_t>();
  float* yp = y.data_ptr<float>();
  float* rp = res ? r.data_ptr<float>() : nullptr;
  const int64_t Kmax = max_run(op, n_out);
  fwk_native::parallel_for(0, n_out, 1, [&](int64_t i0, int64_t i1) {
    std::vector<float> G(std::max<int64_t>(b * Kmax * c, 1)), Wi(std::max<int64_t>(Kmax * co, 1)), tmp;
    for (int64_t i = i0; i < i1; ++i) {
      const int64_t s0 = op[i], K = op[i + 1] - s0, Kc = K * c;
      if (i + 1 < i1) prefetch_rows(xp, sp, op[i + 1], op[i + 2], B, B * sizeof(float));  // the next vertex's x rows
      float* yi = yp + i * b * o;
      if (res) std::fill(rp + i * B, rp + (i + 1) * B, 0.f);
      if (K == 0) {
        std::fill(yi, yi + b * o, 0.f);
        continue;
      }
      for (int64_t k = 0; k < K; ++k) {
        const float* xr = xp + sp[s0 + k] * B;
        gather_transposed(G.data() + k * c, Kc, xr, b, c);
        if (res) {
          const float wk = wp[pp[s0 + k]];
          float* ri = rp + i * B;
          for (int64_t t = 0; t < B; ++t) ri[t] += wk * xr[t];
        }
      }
      gather_coef(Wi.data(), Wp, nullptr, pp, s0, K, co, co);  // W_i: the slots' kernels stacked (K c x o)
      rows_gemm(b, o, Kc, G.data(), Kc, Wi.data(), false, 0.f, yi, o, tmp);
    }
  });
  return {y, r};
}

// kernel order, backward. dy (n_out, b, o), dr (n_out, b c) or empty; returns dx (n_in, b c), dWk (R, c o)
// and dw (R) (zero at the rows no slot reads; empty where not asked for):
//     dW_i = G_i^T dy_i (to Wk's rows at pos),  dG_i = dy_i W_i^T (to x's rows),  dx[src] += w dr_i,  dw = x[src] . dr_i
std::vector<torch::Tensor> kernel_backward(torch::Tensor dy, torch::Tensor dr, torch::Tensor x, torch::Tensor Wk,
                                           torch::Tensor w, torch::Tensor offs, torch::Tensor src, torch::Tensor pos,
                                           int64_t b, int64_t c, int64_t o, bool need_x, bool need_W, bool need_w) {
  check(dy, "dy", at::kFloat, 3);
  const int64_t n_in = x.size(0), B = x.size(1), n_out = offs.size(0) - 1, co = c * o;
  TORCH_CHECK(dy.size(0) == n_out && dy.size(1) == b && dy.size(2) == o, "dy: expected (", n_out, ", ", b, ", ", o, ")");
  const bool res = w.size(0) > 0;
  if (res) check(dr, "dr", at::kFloat, 2);
  need_w = need_w && res;
  auto empty = torch::empty({0}, x.options());
  ThreadAccumulators acc({need_x ? n_in : 0, B}, x.options());
  auto dWk = row_grad(need_W, Wk.size(0), co, src.size(0), x.options());
  auto dw = row_grad(need_w, w.size(0), 0, src.size(0), x.options());
  const float* xp = x.data_ptr<float>();
  const float* Wp = Wk.data_ptr<float>();
  const float* wp = res ? w.data_ptr<float>() : nullptr;
  const float* dyp = dy.data_ptr<float>();
  const float* drp = res ? dr.data_ptr<float>() : nullptr;
  const int64_t* op = offs.data_ptr<int64_t>();
  const int64_t* sp = src.data_ptr<int64_t>();
  const int64_t* pp = pos.data_ptr<int64_t>();
  float* dWp = need_W ? dWk.data_ptr<float>() : nullptr;
  float* dwp = need_w ? dw.data_ptr<float>() : nullptr;
  const int64_t Kmax = max_run(op, n_out);
  fwk_native::parallel_for(0, n_out, 1, [&](int64_t i0, int64_t i1) {
    float* mine = need_x ? acc.mine() : nullptr;
    std::vector<float> G(std::max<int64_t>(b * Kmax * c, 1)), Wi(std::max<int64_t>(Kmax * co, 1)),
        T(std::max<int64_t>(Kmax * co, 1)), tmp;
    for (int64_t i = i0; i < i1; ++i) {
      const int64_t s0 = op[i], K = op[i + 1] - s0, Kc = K * c;
      if (i + 1 < i1) {  // the next vertex's x rows, and its rows of this thread's dx
        prefetch_rows(xp, sp, op[i + 1], op[i + 2], B, B * sizeof(float));
        if (need_x) prefetch_rows<1>(mine, sp, op[i + 1], op[i + 2], B, B * sizeof(float));
      }
      if (K == 0) continue;
      const float* dyi = dyp + i * b * o;
      if (need_W) {
        for (int64_t k = 0; k < K; ++k) gather_transposed(G.data() + k * c, Kc, xp + sp[s0 + k] * B, b, c);
        // column-major T (K c x o) = G_i^T (K c x b) dy_i (b x o): the long side first; Wk's rows take it back
        gemm('N', 'T', Kc, o, b, 1.f, G.data(), Kc, dyi, o, 0.f, T.data(), Kc);
        for (int64_t k = 0; k < K; ++k) {
          float* dst = dWp + pp[s0 + k] * co;
          for (int64_t p = 0; p < c; ++p)
            for (int64_t q = 0; q < o; ++q) dst[p * o + q] = T[q * Kc + k * c + p];
        }
      }
      if (need_x) {
        gather_coef(Wi.data(), Wp, nullptr, pp, s0, K, co, co);
        // dG_i (b x K c) = dy_i (b x o) W_i^T (o x K c), scattered to x's rows
        rows_gemm(b, Kc, o, dyi, o, Wi.data(), true, 0.f, G.data(), Kc, tmp);
        for (int64_t k = 0; k < K; ++k) {
          float* xr = mine + sp[s0 + k] * B;
          const float* g = G.data() + k * c;
          for (int64_t q = 0; q < b; ++q)
            for (int64_t p = 0; p < c; ++p) xr[q * c + p] += g[q * Kc + p];
        }
      }
      if (res) {
        const float* dri = drp + i * B;
        for (int64_t k = 0; k < K; ++k) {
          const int64_t j = sp[s0 + k];
          if (need_x) {
            const float wk = wp[pp[s0 + k]];
            float* xr = mine + j * B;
            for (int64_t t = 0; t < B; ++t) xr[t] += wk * dri[t];
          }
          if (need_w) {
            const float* xr = xp + j * B;
            float d = 0.f;
            for (int64_t t = 0; t < B; ++t) d += xr[t] * dri[t];
            dwp[pp[s0 + k]] = d;
          }
        }
      }
    }
  });
  return {need_x ? reduce(acc.done()) : empty, dWk, dw};
}

// the products with the basis: C (R, N) = A (R, K) B (K, N) + bias (N, or empty (0,)), R large, K and N
// small: with ``lanes`` (on CPUs that run them: lanes_supported) by tall_lanes where the result has at most
// TALL_LANES_MAX_N columns, else by fwk_native.h's tall_mm (row blocks in cache, one BLAS call each)
torch::Tensor tall_forward(torch::Tensor A, torch::Tensor B, torch::Tensor bias, bool lanes) {
  check(A, "A", at::kFloat, 2);
  check(B, "B", at::kFloat, 2);
  check(bias, "bias", at::kFloat, 1);
  const int64_t R = A.size(0), K = A.size(1), N = B.size(1);
  TORCH_CHECK(B.size(0) == K, "B: expected ", K, " rows, got ", B.size(0));
  TORCH_CHECK(bias.size(0) == 0 || bias.size(0) == N, "bias: expected ", N, " entries or none");
  check_lanes(lanes);
  auto C = torch::empty({R, N}, A.options());
  const float* biasp = bias.size(0) ? bias.data_ptr<float>() : nullptr;
  if (lanes && N <= TALL_LANES_MAX_N)
    tall_lanes(A.data_ptr<float>(), B.data_ptr<float>(), false, biasp, C.data_ptr<float>(), R, K, N);
  else tall_mm(A.data_ptr<float>(), B.data_ptr<float>(), false, biasp, C.data_ptr<float>(), R, K, N);
  return C;
}

// its backward: dA = dC B^T (R, K) (tall_lanes or tall_mm, as the forward) and dB = A^T dC (K, N) (tall_tn) (empty
// (0,) where not asked for)
std::vector<torch::Tensor> tall_backward(torch::Tensor dC, torch::Tensor A, torch::Tensor B, bool need_A,
                                         bool need_B, bool lanes) {
  check(dC, "dC", at::kFloat, 2);
  check(A, "A", at::kFloat, 2);
  check(B, "B", at::kFloat, 2);
  const int64_t R = A.size(0), K = A.size(1), N = B.size(1);
  TORCH_CHECK(dC.size(0) == R && dC.size(1) == N && B.size(0) == K, "dC: expected (", R, ", ", N, ")");
  auto empty = torch::empty({0}, A.options());
  torch::Tensor dA = empty, dB = empty;
  if (need_A) {
    check_lanes(lanes);
    dA = torch::empty({R, K}, A.options());  // dC (R x N) B^T: B (K x N) is op(B)'s transpose
    if (lanes && K <= TALL_LANES_MAX_N)
      tall_lanes(dC.data_ptr<float>(), B.data_ptr<float>(), true, nullptr, dA.data_ptr<float>(), R, N, K);
    else tall_mm(dC.data_ptr<float>(), B.data_ptr<float>(), true, nullptr, dA.data_ptr<float>(), R, N, K);
  }
  if (need_B) dB = tall_tn(A.data_ptr<float>(), dC.data_ptr<float>(), R, K, N, A.options());
  return {dA, dB};
}

// ---- the residual's weighted average on the output side (``weighted_rows``)
//
// r_i = sum_s w[pos[s]] x[src[s]] over output i's slots s in [offs[i], offs[i+1]) (rows of B floats), made row by
// row from the rows read in place: no scatter, so no per-thread accumulators to fill and sum. Its backward reads
// the same slots from the input side (ioffs, idst, ipos: input j's slots, their outputs and rows), again without a
// scatter:
//     dx_j = sum_s w[ipos[s]] dr[idst[s]]  (s in [ioffs[j], ioffs[j+1])),   dw[pos[s]] = <dr_i, x[src[s]]>
// The ``basis`` order's residual was ``basis_forward`` with one coefficient a slot: a scatter through per-thread
// accumulators and a BLAS call per vertex for products of one column.

namespace {

// FWK_CLONES (fwk_native.h): the loops below compiled for AVX-512 as well as for the baseline

// rows [i0, i1) of rows (B floats each) = sum_s w[pos[s]] base[idx[s]] over s in [offs[i], offs[i+1])
FWK_CLONES void weighted_gather_range(float* rows, const float* base, const float* w, const int64_t* offs,
                                      const int64_t* idx, const int64_t* pos, int64_t i0, int64_t i1, int64_t B) {
  for (int64_t i = i0; i < i1; ++i) {
    const int64_t s0 = offs[i], s1 = offs[i + 1];
    if (i + 1 < i1) prefetch_rows(base, idx, offs[i + 1], offs[i + 2], B, B * sizeof(float));
    float* __restrict ri = rows + i * B;
    if (s0 == s1) std::fill(ri, ri + B, 0.f);
    for (int64_t s = s0; s < s1; ++s) axpy_row(ri, base + idx[s] * B, w[pos[s]], B, s == s0);
  }
}

// the backward for inputs [j0, j1), from the input side (slots s in [ioffs[j], ioffs[j+1]), their outputs idst and
// weight rows ipos), each slot's dr row read once for both: dx_j = sum_s w[ipos[s]] dr[idst[s]] (when dx is given)
// and dw[ipos[s]] = <dr[idst[s]], x_j> (when dw is)
FWK_CLONES void weighted_backward_range(float* dx, float* dw, const float* dr, const float* x, const float* w,
                                        const int64_t* ioffs, const int64_t* idst, const int64_t* ipos, int64_t j0,
                                        int64_t j1, int64_t B) {
  for (int64_t j = j0; j < j1; ++j) {
    const int64_t s0 = ioffs[j], s1 = ioffs[j + 1];
    if (j + 1 < j1) prefetch_rows(dr, idst, ioffs[j + 1], ioffs[j + 2], B, B * sizeof(float));
    const float* __restrict xj = x + j * B;
    float* __restrict dxj = dx ? dx + j * B : nullptr;
    if (dxj && s0 == s1) std::fill(dxj, dxj + B, 0.f);
    for (int64_t s = s0; s < s1; ++s) {
      const float* __restrict d = dr + idst[s] * B;
      if (dxj) axpy_row(dxj, d, w[ipos[s]], B, s == s0);
      if (dw) {
        float acc = 0.f;
#pragma omp simd reduction(+ : acc)
        for (int64_t t = 0; t < B; ++t) acc += d[t] * xj[t];
        dw[ipos[s]] = acc;
      }
    }
  }
}

void check_weighted(const torch::Tensor& x, const torch::Tensor& w, const torch::Tensor& offs,
                    const torch::Tensor& src, const torch::Tensor& pos, int64_t n_out) {
  check(x, "x", at::kFloat, 2);
  check(w, "w", at::kFloat, 1);
  check_csr(offs, src, n_out, x.size(0), "offs", "src");
  check_coef(w.view({-1, 1}), w, pos, src.size(0));  // each slot's weight row, each named once
}

}  // namespace

// forward: x (n_in, B), w (R), offs (n_out + 1), src and pos (slots); returns r (n_out, B)
torch::Tensor weighted_forward(torch::Tensor x, torch::Tensor w, torch::Tensor offs, torch::Tensor src,
                               torch::Tensor pos) {
  const int64_t n_out = offs.size(0) - 1;
  check_weighted(x, w, offs, src, pos, n_out);
  auto r = torch::empty({n_out, x.size(1)}, x.options());
  float* rp = r.data_ptr<float>();
  const float* xp = x.data_ptr<float>();
  const float* wp = w.data_ptr<float>();
  const int64_t *op = offs.data_ptr<int64_t>(), *sp = src.data_ptr<int64_t>(), *pp = pos.data_ptr<int64_t>();
  const int64_t B = x.size(1);
  fwk_native::parallel_for(0, n_out, 1, [&](int64_t i0, int64_t i1) {
    weighted_gather_range(rp, xp, wp, op, sp, pp, i0, i1, B);
  });
  return r;
}

// backward: dr (n_out, B); the input side's CSR (ioffs (n_in + 1), idst and ipos: the same slots as offs, src and
// pos, listed by input vertex). Returns dx (n_in, B) and dw (R; zero at the rows no slot reads), empty (0,) where
// not asked for.
std::vector<torch::Tensor> weighted_backward(torch::Tensor dr, torch::Tensor x, torch::Tensor w, torch::Tensor offs,
                                             torch::Tensor src, torch::Tensor pos, torch::Tensor ioffs,
                                             torch::Tensor idst, torch::Tensor ipos, bool need_x, bool need_w) {
  const int64_t n_in = x.size(0), B = x.size(1), n_out = offs.size(0) - 1, slots = src.size(0);
  check_weighted(x, w, offs, src, pos, n_out);
  check(dr, "dr", at::kFloat, 2);
  TORCH_CHECK(dr.size(0) == n_out && dr.size(1) == B, "dr: expected (", n_out, ", ", B, ")");
  check_csr(ioffs, idst, n_in, n_out, "ioffs", "idst");
  check(ipos, "ipos", at::kLong, 1);
  TORCH_CHECK(idst.size(0) == slots && ipos.size(0) == slots, "idst, ipos: expected the ", slots, " slots of src");
  check_distinct(ipos, "ipos", w.size(0));  // dw is written at ipos
  torch::Tensor dx = need_x ? torch::empty({n_in, B}, x.options()) : torch::empty({0}, x.options());
  torch::Tensor dw = row_grad(need_w, w.size(0), 0, slots, x.options());
  if (need_x || need_w) {
    float* dxp = need_x ? dx.data_ptr<float>() : nullptr;
    float* dwp = need_w ? dw.data_ptr<float>() : nullptr;
    const float* drp = dr.data_ptr<float>();
    const float* xp = x.data_ptr<float>();
    const float* wp = w.data_ptr<float>();
    const int64_t *io = ioffs.data_ptr<int64_t>(), *id = idst.data_ptr<int64_t>(), *ip = ipos.data_ptr<int64_t>();
    fwk_native::parallel_for(0, n_in, 1, [&](int64_t j0, int64_t j1) {
      weighted_backward_range(dxp, dwp, drp, xp, wp, io, id, ip, j0, j1, B);
    });
  }
  return {dx, dw};
}

// ---- the residual's normalised weights (``residual_weights``)
//
// wn[pos[s]] = scale |w[pos[s]]| / max(S_i, eps), S_i = sum_s |w[pos[s]]| over output i's slots s in
// [offs[i], offs[i+1]): one pass per output instead of torch's abs, index_add, clamp, division, index_select and
// product (and as many again backward). Backward, with g = dwn and a = |w|:
//     dw[pos[s]] = sgn(w[pos[s]]) (scale g_s / max(S_i, eps) - [S_i >= eps] scale (sum_t a_t g_t) / S_i^2)
// (torch's: abs' gradient 0 at 0, clamp_min's none below eps). Rows no slot names get 0.
namespace {

constexpr float RESIDUAL_EPS = 1e-12f;

// both directions' checks of w, offs and pos, and their result: one float per row of w, zero-filled only where some
// row is named by no slot (row_grad)
torch::Tensor norm_weights_result(const torch::Tensor& w, const torch::Tensor& offs, const torch::Tensor& pos) {
  check(w, "w", at::kFloat, 1);
  check_csr(offs, pos, offs.size(0) - 1, w.size(0), "offs", "pos");
  check_coef(w.view({-1, 1}), w, pos, pos.size(0));
  return row_grad(true, w.size(0), 0, pos.size(0), w.options());
}

}  // namespace

torch::Tensor norm_weights_forward(torch::Tensor w, torch::Tensor offs, torch::Tensor pos, double scale) {
  auto wn = norm_weights_result(w, offs, pos);
  const int64_t n_out = offs.size(0) - 1;
  const float* wp = w.data_ptr<float>();
  const int64_t* op = offs.data_ptr<int64_t>();
  const int64_t* pp = pos.data_ptr<int64_t>();
  float* np_ = wn.data_ptr<float>();
  const float sc = (float)scale;
  fwk_native::parallel_for(0, n_out, 1024, [&](int64_t i0, int64_t i1) {
    for (int64_t i = i0; i < i1; ++i) {
      float S = 0.f;
      for (int64_t s = op[i]; s < op[i + 1]; ++s) S += std::abs(wp[pp[s]]);
      const float f = sc / std::max(S, RESIDUAL_EPS);
      for (int64_t s = op[i]; s < op[i + 1]; ++s) np_[pp[s]] = std::abs(wp[pp[s]]) * f;
    }
  });
  return wn;
}

torch::Tensor norm_weights_backward(torch::Tensor dwn, torch::Tensor w, torch::Tensor offs, torch::Tensor pos,
                                    double scale) {
  auto dw = norm_weights_result(w, offs, pos);
  check(dwn, "dwn", at::kFloat, 1);
  TORCH_CHECK(dwn.size(0) == w.size(0), "dwn: expected ", w.size(0), " entries");
  const int64_t n_out = offs.size(0) - 1;
  const float* wp = w.data_ptr<float>();
  const float* gp = dwn.data_ptr<float>();
  const int64_t* op = offs.data_ptr<int64_t>();
  const int64_t* pp = pos.data_ptr<int64_t>();
  float* dp = dw.data_ptr<float>();
  const float sc = (float)scale;
  fwk_native::parallel_for(0, n_out, 1024, [&](int64_t i0, int64_t i1) {
    for (int64_t i = i0; i < i1; ++i) {
      float S = 0.f, ag = 0.f;
      for (int64_t s = op[i]; s < op[i + 1]; ++s) {
        const float a = std::abs(wp[pp[s]]);
        S += a;
        ag += a * gp[pp[s]];
      }
      const float f = sc / std::max(S, RESIDUAL_EPS), t = S >= RESIDUAL_EPS ? sc * ag / (S * S) : 0.f;
      for (int64_t s = op[i]; s < op[i + 1]; ++s) {
        const float v = wp[pp[s]], sg = v > 0.f ? 1.f : (v < 0.f ? -1.f : 0.f);
        dp[pp[s]] = sg * (f * gp[pp[s]] - t);
      }
    }
  });
  return dw;
}

// ---- the basis order in lanes (``lanes_forward`` / ``lanes_backward``)
//
// The batch is the vector: a vertex's b rows are taken 16 batch entries at a time (one AVX-512 register of
// floats, zero past b), so every product below is a multiply-add of whole registers whatever the channel
// counts (3-32 at the chapter 5 width, where MKL runs the per-vertex products at 30-50 GFLOP/s). For input
// vertex j and a group of 16 batch entries:
//     Z_j[(m, q)] = sum_p B[m, p, q] x_j[p]                      (the basis product, made in cache: no Z tensor)
//     y[dst[s]][q] += sum_m A_s[m] Z_j[(m, q)]                   (per-thread accumulators in lanes, summed at the end)
// and the backward, with dY_s = dy[dst[s]] in lanes:
//     dZ_j[(m, q)] = sum_s A_s[m] dY_s[q],   dx_j[p] = sum_(m, q) B[m, p, q] dZ_j[(m, q)],
//     dB[m, p, q] += <x_j[p], dZ_j[(m, q)]>  (per-thread lane accumulators),
//     dA_s[m] = sum_(q, l) dY_s[q][l] Z_j[(m, q)][l]  (with Z_j laid out m-innermost, Zm: the kernels are the vector)
// Compiled for AVX-512 (the functions of this block only; ``lanes_supported`` says whether this CPU runs
// them, else ``fwk_vcconv`` keeps the tall product and ``basis_forward``).
#if defined(__GNUC__) && !defined(__clang__) && defined(__x86_64__)
#define FWK_VCCONV_LANES 1
#pragma GCC push_options
#pragma GCC target("avx512f,avx512vl,avx512bw,avx512dq,avx2,fma,prefer-vector-width=512")
#endif

namespace lanes {
constexpr int L = 16;  // lanes: batch entries per group
constexpr int64_t MAX_M = 4 * L;  // da_all / zm_all up to 4 chunks of L kernels

// one register of L floats (GCC's vector extension). The kernels' accumulators are arrays of these, zeroed a vector
// at a time (`zero`): declared as float arrays with `= {}`, GCC zero-filled them on the stack with `rep stos` (its
// start-up cost was 9-16 % of t_rows, da_block and lanes_forward in perf) before moving them to registers. ld / st:
// unaligned loads and stores.
typedef float vL __attribute__((vector_size(L * sizeof(float))));
typedef float vLu __attribute__((vector_size(L * sizeof(float)), aligned(4), may_alias));
inline vL ld(const float* p) { return *reinterpret_cast<const vLu*>(p); }
inline void st(float* p, vL v) { *reinterpret_cast<vLu*>(p) = v; }
// half a register: 8 floats (the kernels' last 1-8 where H = 1: KernelChunks; the kernel gradients' columns)
typedef float v8 __attribute__((vector_size(8 * sizeof(float))));
typedef float v8u __attribute__((vector_size(8 * sizeof(float)), aligned(4), may_alias));
inline v8 ld8(const float* p) { return *reinterpret_cast<const v8u*>(p); }
inline void st8(float* p, v8 v) { *reinterpret_cast<v8u*>(p) = v; }
// the first n floats of a register (n in [0, 16], or [0, 8] for a half): masked loads and stores, the rest of the
// register zero on a load. A copy of a run-time number of floats (M = 35 a row) was a call to the C library's memcpy
// per row: about 2 % of the chapter 5 width's step's samples in perf, in sum_forward, sum_backward and da_block.
#ifdef FWK_VCCONV_LANES
inline vL ld_n(const float* p, int64_t n) { return (vL)_mm512_maskz_loadu_ps((__mmask16)((1u << n) - 1), p); }
inline void st_n(float* p, vL v, int64_t n) { _mm512_mask_storeu_ps(p, (__mmask16)((1u << n) - 1), (__m512)v); }
inline v8 ld8_n(const float* p, int64_t n) { return (v8)_mm256_maskz_loadu_ps((__mmask8)((1u << n) - 1), p); }
inline void st8_n(float* p, v8 v, int64_t n) { _mm256_mask_storeu_ps(p, (__mmask8)((1u << n) - 1), (__m256)v); }
inline float lane_sum(vL v) { return _mm512_reduce_add_ps((__m512)v); }  // the sum of a register's 16 floats
#else  // other compilers and CPUs build these kernels too (lanes_supported says they do not run them): plain loops
template <typename V>
inline V ld_first(const float* p, int64_t n) {
  V v{};
  for (int64_t i = 0; i < n; ++i) v[i] = p[i];
  return v;
}
template <typename V>
inline void st_first(float* p, V v, int64_t n) {
  for (int64_t i = 0; i < n; ++i) p[i] = v[i];
}
inline vL ld_n(const float* p, int64_t n) { return ld_first<vL>(p, n); }
inline void st_n(float* p, vL v, int64_t n) { st_first(p, v, n); }
inline v8 ld8_n(const float* p, int64_t n) { return ld_first<v8>(p, n); }
inline void st8_n(float* p, v8 v, int64_t n) { st_first(p, v, n); }
inline float lane_sum(vL v) {
  float t = 0.f;
  for (int i = 0; i < L; ++i) t += v[i];
  return t;
}
#endif
inline int64_t clamp_to(int64_t n, int64_t hi) { return std::min(std::max<int64_t>(n, 0), hi); }
// d[0, n) = s[0, n) (n <= 64: a row of kernels or of their gradients)
inline void copy_n(float* d, const float* s, int64_t n) {
  int64_t i = 0;
  for (; i + L <= n; i += L) st(d + i, ld(s + i));
  if (i < n) st_n(d + i, ld_n(s + i, n - i), n - i);
}
// d[0, W) = s[0, n) and zeros past n (W = KernelChunks' row: a multiple of 8, n <= W)
inline void copy_padded(float* d, const float* s, int64_t n, int64_t W) {
  int64_t i = 0;
  for (; i + L <= W; i += L) st(d + i, ld_n(s + i, clamp_to(n - i, L)));
  if (i < W) st8(d + i, ld8_n(s + i, clamp_to(n - i, 8)));
}
// zeroed one vector at a time: an `= {}` initialiser of a whole array is still a memset (`rep stos`)
template <int N>
inline void zero(vL (&a)[N]) {
#pragma GCC unroll 32
  for (int i = 0; i < N; ++i) a[i] = vL{};
}
template <int N>
inline void zero(v8 (&a)[N]) {
#pragma GCC unroll 32
  for (int i = 0; i < N; ++i) a[i] = v8{};
}
template <int N1, int N2>
inline void zero(vL (&a)[N1][N2]) {
#pragma GCC unroll 32
  for (int i = 0; i < N1; ++i) zero(a[i]);
}

// acc[k] (and tail[k] where H = 1) = sum_r s[k][r] rows[r] for KB rows of scalars s[k] (R floats each) and rows
// (R x (NV L + 8 H)): each row of `rows` read once for the KB sums (KB (NV + H) chains of multiply-adds). The basis
// product Z_j in lanes (rows_times_lanes), basis_lanes' coefficient gradients dA_s = dY_s Zm_j (da_block), the slots'
// kernels W_s = A_s B (its second forward route) and the sum order's coefficient gradients dA_k = X_k^T dTx, each with
// its layout.
template <int KB, int NV, int H>
inline void combine_rows(vL (&acc)[KB][NV], v8 (&tail)[KB], const float* const* s, const float* __restrict rows,
                         int64_t R) {
  constexpr int W = NV * L + 8 * H;
  zero(acc);
  zero(tail);
  for (int64_t r = 0; r < R; ++r) {
    vL row[NV];
    for (int v = 0; v < NV; ++v) row[v] = ld(rows + r * W + v * L);
    const v8 row8 = H ? ld8(rows + r * W + NV * L) : v8{};
    for (int k = 0; k < KB; ++k) {
      const float sk = s[k][r];
      for (int v = 0; v < NV; ++v) acc[k][v] += sk * row[v];
      if (H) tail[k] += sk * row8;
    }
  }
}

template <int KB, int NV>
inline void combine_rows(vL (&acc)[KB][NV], const float* const* s, const float* __restrict rows, int64_t R) {
  v8 unused[KB];
  combine_rows<KB, NV, 0>(acc, unused, s, rows, R);
}

// F::go<NV, H>(args...) for the layout KernelChunks gives (NV 1-4, H 0-1, 16 NV + 8 H <= 64)
template <class F, typename... Args>
inline void by_chunks(const KernelChunks& ch, Args&&... args) {
  switch (ch.NV * 2 + ch.H) {
    case 2: F::template go<1, 0>(args...); break;
    case 3: F::template go<1, 1>(args...); break;
    case 4: F::template go<2, 0>(args...); break;
    case 5: F::template go<2, 1>(args...); break;
    case 6: F::template go<3, 0>(args...); break;
    case 7: F::template go<3, 1>(args...); break;
    default: F::template go<4, 0>(args...); break;
  }
}

// the lane kernels' arguments: float32 contiguous tensors, a basis of at most MAX_M kernels, a CSR support
inline void lanes_check(const torch::Tensor& x, const torch::Tensor& B, const torch::Tensor& coef,
                        const torch::Tensor& offs, const torch::Tensor& dst, const torch::Tensor& pos, int64_t n_out) {
  check(x, "x", at::kFloat, 3);
  check(B, "B", at::kFloat, 3);
  check(coef, "coef", at::kFloat, 2);
  TORCH_CHECK(B.size(1) == x.size(2), "B: expected ", x.size(2), " input channels");
  TORCH_CHECK(coef.size(1) == B.size(0), "coef: expected ", B.size(0), " columns");
  TORCH_CHECK(B.size(0) >= 1 && B.size(0) <= MAX_M, "B: 1 to ", MAX_M, " kernels");
  check_csr(offs, dst, x.size(0), n_out);
  check_coef(coef, torch::empty({0}, x.options()), pos, dst.size(0));
}

// a layer's bias: o floats, or none ((0,))
inline void check_bias(const torch::Tensor& bias, int64_t o) {
  check(bias, "bias", at::kFloat, 1);
  TORCH_CHECK(bias.size(0) == 0 || bias.size(0) == o, "bias: expected ", o, " entries or none");
}

// rows (b x w, row-major) of one vertex, batch entries [L g, L g + L), transposed: d[p][l] (zero past b)
inline void to_lanes(float* __restrict d, const float* __restrict x, int64_t b, int64_t w, int64_t g) {
  const int64_t l1 = std::min<int64_t>(L, b - g * L);
  for (int64_t p = 0; p < w; ++p)
    for (int64_t l = 0; l < L; ++l) d[p * L + l] = l < l1 ? x[(g * L + l) * w + p] : 0.f;
}

// back: x[(L g + l) w + p] = d[p][l] for the batch entries that exist
inline void from_lanes(float* __restrict x, const float* __restrict d, int64_t b, int64_t w, int64_t g) {
  const int64_t l1 = std::min<int64_t>(L, b - g * L);
  for (int64_t l = 0; l < l1; ++l)
    for (int64_t p = 0; p < w; ++p) x[(g * L + l) * w + p] = d[p * L + l];
}

// d[q][l] = bias[q] for q < w (zero without a bias): lanes that start at a layer's bias
inline void start_lanes(float* d, const float* bias, int64_t w) {
  for (int64_t q = 0; q < w; ++q) std::fill(d + q * L, d + (q + 1) * L, bias ? bias[q] : 0.f);
}

// the per-thread accumulators acc (nt, n, G, w, L) summed in thread order and taken out of lanes: (n, b, w), each
// row starting at bias (w floats) where one is given (a pass over the result saved: the layer's bias add)
inline torch::Tensor sum_out_of_lanes(const torch::Tensor& acc, int64_t b, const float* bias = nullptr) {
  const int nt = acc.size(0);
  const int64_t n = acc.size(1), G = acc.size(2), w = acc.size(3);
  auto out = torch::empty({n, b, w}, acc.options());
  const float* ap = acc.data_ptr<float>();
  float* op = out.data_ptr<float>();
  fwk_native::parallel_for(0, n, 64, [&](int64_t i0, int64_t i1) {
    std::vector<float> s(w * L);
    for (int64_t i = i0; i < i1; ++i)
      for (int64_t g = 0; g < G; ++g) {
        start_lanes(s.data(), bias, w);
        for (int t = 0; t < nt; ++t) {
          const float* a = ap + ((t * n + i) * G + g) * w * L;
          for (int64_t u = 0; u < w * L; ++u) s[u] += a[u];
        }
        from_lanes(op + i * b * w, s.data(), b, w, g);
      }
  });
  return out;
}

// x (n, b, c) in lanes: (n, G, c, L), zero past b. With ``sums`` (c floats), also the sum of x over its first two
// dimensions (a bias's gradient from its result's), made as x passes through: each thread adds its rows' lanes
// into c registers, their 16 lanes added at the end, the threads' sums in thread order (the same bits on every run
// with the same thread count). It spares a pass of its own over x (torch's sum over (11,248, 16, 3) floats took
// 0.17 ms of the chapter 5 width's step).
inline torch::Tensor all_to_lanes(const torch::Tensor& x, float* sums = nullptr) {
  const int64_t n = x.size(0), b = x.size(1), c = x.size(2), G = (b + L - 1) / L;
  auto xL = torch::empty({n, G, c, L}, x.options());
  const float* xp = x.data_ptr<float>();
  float* xLp = xL.data_ptr<float>();
  const int nt = at::get_num_threads();
  std::vector<float> part(sums ? nt * c * L : 0, 0.f);  // each thread's c registers
  fwk_native::parallel_for(0, n, 64, [&](int64_t j0, int64_t j1) {
    float* mine = sums ? thread_accumulator(part.data(), nt, c * L) : nullptr;
    for (int64_t j = j0; j < j1; ++j)
      for (int64_t g = 0; g < G; ++g) {
        float* d = xLp + (j * G + g) * c * L;
        to_lanes(d, xp + j * b * c, b, c, g);
        if (mine)
          for (int64_t p = 0; p < c; ++p) st(mine + p * L, ld(mine + p * L) + ld(d + p * L));
      }
  });
  if (sums)
    for (int64_t p = 0; p < c; ++p) {
      vL t = ld(part.data() + p * L);
      for (int th = 1; th < nt; ++th) t += ld(part.data() + (th * c + p) * L);
      sums[p] = lane_sum(t);
    }
  return xL;
}

// Z[r][l] = sum_p W[r][p] xT[p][l] for RB rows from r0 (W (R, c) row-major)
template <int RB>
inline void rows_times_lanes(float* __restrict Z, const float* __restrict W, const float* __restrict xT, int64_t c,
                             int64_t r0) {
  const float* w[RB];
  for (int r = 0; r < RB; ++r) w[r] = W + (r0 + r) * c;
  vL acc[RB][1];
  combine_rows(acc, w, xT, c);
  std::memcpy(Z + r0 * L, acc, sizeof acc);
}

// F<B>::run(p0, args...) over [0, w) in blocks of 8, then one block of the 1-7 left (not 1-wide blocks: each row
// or column of a block is its own chain of multiply-adds, and one chain alone waits on itself)
template <template <int> class F, typename... Args>
inline void by_blocks_of_8(int64_t w, Args... args) {
  int64_t p0 = 0;
  for (; p0 + 8 <= w; p0 += 8) F<8>::run(p0, args...);
  switch (w - p0) {
    case 7: F<7>::run(p0, args...); break;
    case 6: F<6>::run(p0, args...); break;
    case 5: F<5>::run(p0, args...); break;
    case 4: F<4>::run(p0, args...); break;
    case 3: F<3>::run(p0, args...); break;
    case 2: F<2>::run(p0, args...); break;
    case 1: F<1>::run(p0, args...); break;
    default: break;
  }
}

template <int RB>
struct RowsTimesLanes {
  static void run(int64_t r0, float* Z, const float* W, const float* xT, int64_t c) {
    rows_times_lanes<RB>(Z, W, xT, c, r0);
  }
};

// Z (R x L) = W (R x c) xT (c x L)
inline void matrix_times_lanes(float* Z, const float* W, const float* xT, int64_t R, int64_t c) {
  by_blocks_of_8<RowsTimesLanes>(R, Z, W, xT, c);
}

// out[k][q][l] += sum_m A[k][m] Z[m o + q][l] for KB rows k, q in [q0, q0 + QB)
template <int KB, int QB>
inline void y_block(float* const* out, const float* const* A, const float* __restrict Z, int64_t M, int64_t o,
                    int64_t q0) {
  vL acc[KB][QB];
  zero(acc);
  for (int64_t m = 0; m < M; ++m) {
    float a[KB];
    for (int k = 0; k < KB; ++k) a[k] = A[k][m];
    const float* z = Z + (m * o + q0) * L;
    for (int q = 0; q < QB; ++q) {
      const vL zq = ld(z + q * L);
      for (int k = 0; k < KB; ++k) acc[k][q] += a[k] * zq;
    }
  }
  for (int k = 0; k < KB; ++k)
    for (int q = 0; q < QB; ++q) {
      float* d = out[k] + (q0 + q) * L;
      st(d, ld(d) + acc[k][q]);
    }
}

template <int KB>
inline void y_rows(float* const* out, const float* const* A, const float* Z, int64_t M, int64_t o) {
  int64_t q0 = 0;
  for (; q0 + 4 <= o; q0 += 4) y_block<KB, 4>(out, A, Z, M, o, q0);
  switch (o - q0) {
    case 3: y_block<KB, 3>(out, A, Z, M, o, q0); break;
    case 2: y_block<KB, 2>(out, A, Z, M, o, q0); break;
    case 1: y_block<KB, 1>(out, A, Z, M, o, q0); break;
    default: break;
  }
}

// dZ[m o + q][l] = sum_k A[k][m] dY[k][q][l] for m in [m0, m0 + MB), q in [q0, q0 + QB)
template <int MB, int QB>
inline void dz_block(float* __restrict dZ, const float* const* A, const float* const* dY, int64_t K, int64_t o,
                     int64_t m0, int64_t q0) {
  vL acc[MB][QB];
  zero(acc);
  for (int64_t k = 0; k < K; ++k) {
    const float* a = A[k] + m0;
    const float* y = dY[k] + q0 * L;
    for (int q = 0; q < QB; ++q) {
      const vL yq = ld(y + q * L);
      for (int m = 0; m < MB; ++m) acc[m][q] += a[m] * yq;
    }
  }
  for (int m = 0; m < MB; ++m)
    for (int q = 0; q < QB; ++q) st(dZ + ((m0 + m) * o + q0 + q) * L, acc[m][q]);
}

template <int MB>
inline void dz_cols(float* dZ, const float* const* A, const float* const* dY, int64_t K, int64_t o, int64_t m0) {
  int64_t q0 = 0;
  for (; q0 + 3 <= o; q0 += 3) dz_block<MB, 3>(dZ, A, dY, K, o, m0, q0);
  switch (o - q0) {
    case 2: dz_block<MB, 2>(dZ, A, dY, K, o, m0, q0); break;
    case 1: dz_block<MB, 1>(dZ, A, dY, K, o, m0, q0); break;
    default: break;
  }
}

// Zm[ql][m] (m innermost, rows of W = NV L + 8 H: KernelChunks) = sum_p xT[p][l] Bq[p][q][m] for the (q, l) pairs
// [ql0, ql0 + ZB) (ZB divides L: one q, lanes l0 .. l0 + ZB - 1): Bq's row (p, q) loaded once for the ZB lanes (it was
// loaded for each)
template <int NV, int H, int ZB>
inline void zm_block(float* __restrict Zm, const float* __restrict Bq, const float* __restrict xT, int64_t c,
                     int64_t o, int64_t ql0) {
  static_assert(L % ZB == 0, "a block of lanes within one q");
  constexpr int W = NV * L + 8 * H;
  const int64_t q = ql0 / L, l0 = ql0 % L;
  vL acc[ZB][NV];
  v8 tail[ZB];
  zero(acc);
  zero(tail);
  for (int64_t p = 0; p < c; ++p) {
    const float* bq = Bq + (p * o + q) * W;
    vL bv[NV];
    for (int v = 0; v < NV; ++v) bv[v] = ld(bq + v * L);
    const v8 bt = H ? ld8(bq + NV * L) : v8{};
    const float* xs = xT + p * L + l0;
    for (int i = 0; i < ZB; ++i) {
      const float w = xs[i];
      for (int v = 0; v < NV; ++v) acc[i][v] += w * bv[v];
      if (H) tail[i] += w * bt;
    }
  }
  for (int i = 0; i < ZB; ++i) {
    for (int v = 0; v < NV; ++v) st(Zm + (ql0 + i) * W + v * L, acc[i][v]);
    if (H) st8(Zm + (ql0 + i) * W + NV * L, tail[i]);
  }
}

// d[m] (+)= a[m] for m < mn (mn <= L): masked where mn < L
inline void add_or_assign(float* d, vL a, int64_t mn, bool assign) {
  if (mn == L) st(d, assign ? a : ld(d) + a);
  else st_n(d, assign ? a : ld_n(d, mn) + a, mn);
}
inline void add_or_assign(float* d, v8 a, int64_t mn, bool assign) {  // (mn <= 8)
  if (mn == 8) st8(d, assign ? a : ld8(d) + a);
  else st8_n(d, assign ? a : ld8_n(d, mn) + a, mn);
}

// a row of M floats (+)= a row of kernels in KernelChunks' layout (NV vectors, and the half vector `tail` where H = 1;
// 16 (NV - 1) <= M <= 16 NV + 8): the coefficients' gradients (da_block) and T's rows (t_rows)
template <int NV, int H>
inline void put_row(float* d, const vL (&acc)[NV], v8 tail, int64_t M, bool assign) {
  for (int v = 0; v < NV; ++v) add_or_assign(d + v * L, acc[v], std::min<int64_t>(L, M - v * L), assign);
  if (H) add_or_assign(d + NV * L, tail, M - NV * L, assign);
}

// dA[k][m] += sum_ql dY[k][ql] Zm[ql][m] for KB rows, each slot's dY row read where it lies (one broadcast a
// multiply-add row, no packed copy); with `assign`, dA[k][m] = that sum (the row's first write: no zero-fill of dA
// before, no read of it here)
template <int KB, int NV, int H>
inline void da_block(float* const* dA, const float* const* dY, const float* __restrict Zm, int64_t QL, int64_t M,
                     bool assign) {
  vL acc[KB][NV];
  v8 tail[KB];
  combine_rows<KB, NV, H>(acc, tail, dY, Zm, QL);
  for (int k = 0; k < KB; ++k) put_row<NV, H>(dA[k], acc[k], tail[k], M, assign);  // L kernels a store
}

// da_block over K rows: 8 at a time, the rest (1-7) in one block of their own size
template <int NV, int H>
void da_all(float* const* dA, const float* const* dY, const float* Zm, int64_t K, int64_t QL, int64_t M, bool assign) {
  int64_t k0 = 0;
  for (; k0 + 8 <= K; k0 += 8) da_block<8, NV, H>(dA + k0, dY + k0, Zm, QL, M, assign);
  float* const* a = dA + k0;
  const float* const* y = dY + k0;
  switch (K - k0) {
    case 7: da_block<7, NV, H>(a, y, Zm, QL, M, assign); break;
    case 6: da_block<6, NV, H>(a, y, Zm, QL, M, assign); break;
    case 5: da_block<5, NV, H>(a, y, Zm, QL, M, assign); break;
    case 4: da_block<4, NV, H>(a, y, Zm, QL, M, assign); break;
    case 3: da_block<3, NV, H>(a, y, Zm, QL, M, assign); break;
    case 2: da_block<2, NV, H>(a, y, Zm, QL, M, assign); break;
    case 1: da_block<1, NV, H>(a, y, Zm, QL, M, assign); break;
    default: break;
  }
}

// Zm = the products of Bq with X (zm_block; X: contract x L, Zm's rows (q, l) for q < width) and then
// dA[k] += sum_ql rows[k][ql] Zm[ql] (da_all; = with `assign`), in the kernels' layout NV, H (KernelChunks)
struct ZmThenDa {
  template <int NV, int H>
  static void go(float* const* dA, const float* const* rows, float* Zm, const float* Bq, const float* X,
                 int64_t contract, int64_t width, int64_t K, int64_t M, bool assign) {
    constexpr int ZB = NV + H <= 3 ? 8 : 4;  // ZB (NV + H) accumulators (at most 24 of the 32 registers)
    for (int64_t ql0 = 0; ql0 < width * L; ql0 += ZB) zm_block<NV, H, ZB>(Zm, Bq, X, contract, width, ql0);
    da_all<NV, H>(dA, rows, Zm, K, width * L, M, assign);
  }
};

// dxT[p][l] = sum_r W[r][p] dZ[r][l] for PB columns p from p0 (W (R, c))
template <int PB>
inline void dx_block(float* __restrict dxT, const float* __restrict W, const float* __restrict dZ, int64_t R, int64_t c,
                     int64_t p0) {
  vL acc[PB];
  zero(acc);
  for (int64_t r = 0; r < R; ++r) {
    const vL z = ld(dZ + r * L);
    for (int p = 0; p < PB; ++p) acc[p] += W[r * c + p0 + p] * z;
  }
  std::memcpy(dxT + p0 * L, acc, sizeof acc);
}

template <int PB>
struct DxBlock {
  static void run(int64_t p0, float* dxT, const float* W, const float* dZ, int64_t R, int64_t c) {
    dx_block<PB>(dxT, W, dZ, R, c, p0);
  }
};

// the basis gradient's per-thread lanes dBv[r][p][l] (r = m o + q) take the products of DB_GROUP (vertex, batch group)
// pairs at once: one read and one write of dBv's line per DB_GROUP multiply-adds (a pair at a time, dBv (53 KB to
// 143 KB here) was read and written for each multiply-add)
constexpr int DB_GROUP = 8;

// dBv[r][p] += sum_v xTs[v][p] dZs[v][r] for PB columns p from p0: the group's x columns held while r runs
template <int PB>
inline void db_cols(float* __restrict dBv, const float* __restrict xTs, const float* __restrict dZs, int64_t R,
                    int64_t c, int64_t p0) {
  float xr[PB][DB_GROUP][L];
  for (int p = 0; p < PB; ++p)
    for (int v = 0; v < DB_GROUP; ++v) std::memcpy(xr[p][v], xTs + (v * c + p0 + p) * L, L * sizeof(float));
  for (int64_t r = 0; r < R; ++r) {
    float acc[PB][L];
    for (int p = 0; p < PB; ++p) std::memcpy(acc[p], dBv + (r * c + p0 + p) * L, L * sizeof(float));
    for (int v = 0; v < DB_GROUP; ++v) {
      const float* z = dZs + (v * R + r) * L;
      for (int p = 0; p < PB; ++p) {
#pragma omp simd
        for (int l = 0; l < L; ++l) acc[p][l] += xr[p][v][l] * z[l];
      }
    }
    for (int p = 0; p < PB; ++p) std::memcpy(dBv + (r * c + p0 + p) * L, acc[p], L * sizeof(float));
  }
}

// dBv[r][p] += sum_v xTs[v][p] dZs[v][r] over the group's DB_GROUP pairs (xTs (DB_GROUP, c, L), dZs (DB_GROUP, R, L))
inline void db_group(float* dBv, const float* xTs, const float* dZs, int64_t R, int64_t c) {
  int64_t p0 = 0;
  for (; p0 + 2 <= c; p0 += 2) db_cols<2>(dBv, xTs, dZs, R, c, p0);
  if (p0 < c) db_cols<1>(dBv, xTs, dZs, R, c, p0);
}
}  // namespace lanes

namespace lanes {
// acc[q][l] += sum_p W[p o + q] xs[p][l] for q < O (one slot's kernel W (c x o) applied to its input row in lanes)
template <int O>
inline void kernel_apply(float* __restrict acc, const float* __restrict W, const float* __restrict xs, int64_t c,
                         int64_t o, int64_t q0) {
  float a[O][L];
  for (int q = 0; q < O; ++q)
    for (int l = 0; l < L; ++l) a[q][l] = acc[(q0 + q) * L + l];
  for (int64_t p = 0; p < c; ++p) {
    const float* xv = xs + p * L;
    for (int q = 0; q < O; ++q) {
      const float w = W[p * o + q0 + q];
#pragma omp simd
      for (int l = 0; l < L; ++l) a[q][l] += w * xv[l];
    }
  }
  for (int q = 0; q < O; ++q)
    for (int l = 0; l < L; ++l) acc[(q0 + q) * L + l] = a[q][l];
}

template <int O>
struct KernelApply {
  static void run(int64_t q0, float* acc, const float* W, const float* xs, int64_t c, int64_t o) {
    kernel_apply<O>(acc, W, xs, c, o, q0);
  }
};
}  // namespace lanes

namespace lanes {
// W_k (NW L floats: the slot's kernel, row-major c x o, zero past c o) = sum_m A_k[m] Bf[m] for KB slots (Bf: M x NW L,
// the basis as (M, c o), zero past c o): each slot's kernel made in cache, its entries the vector
template <int KB, int NW>
inline void kernels_of_slots(float* __restrict W, const float* const* A, const float* __restrict Bf, int64_t M) {
  vL acc[KB][NW];
  combine_rows(acc, A, Bf, M);
  for (int k = 0; k < KB; ++k)
    for (int v = 0; v < NW; ++v) st(W + (k * NW + v) * L, acc[k][v]);
}

template <int KB>
inline void kernels_of_slots(float* W, const float* const* A, const float* Bf, int64_t M, int64_t NW) {
  switch (NW) {
    case 1: kernels_of_slots<KB, 1>(W, A, Bf, M); break;
    case 2: kernels_of_slots<KB, 2>(W, A, Bf, M); break;
    case 3: kernels_of_slots<KB, 3>(W, A, Bf, M); break;
    default: kernels_of_slots<KB, 4>(W, A, Bf, M); break;
  }
}
}  // namespace lanes

// basis order in lanes, forward. x (n_in, b, c), B the basis (M, c, o), coef (R, M) read at pos (slots), offs
// (n_in + 1), dst (slots). y (n_out, b, o) = bias (o, or none: (0,)) + the sum over input vertices j and their slots s
// of (A_s Z_j) at dst[s], by one of two routes (``route``, chosen by fwk_vcconv.native's cost model):
//   1. Z_j = B^T x_j made in cache (M o c L multiply-adds an input vertex), then A_s Z_j per slot (M o L);
//   2. each slot's kernel W_s = A_s B (c x o) made in cache (M c o), then x_j W_s (c o L): the kernel order's
//      products on the basis order's traversal, for layers of few input channels (c o <= 64; half route 1's
//      multiply-adds on the chapter 5 width's 8 -> 3 layer).
torch::Tensor lanes_forward(torch::Tensor x, torch::Tensor B, torch::Tensor coef, torch::Tensor offs, torch::Tensor dst,
                            torch::Tensor pos, int64_t n_out, torch::Tensor bias, int64_t route) {
  using namespace lanes;
  lanes_check(x, B, coef, offs, dst, pos, n_out);
  const int64_t n_in = x.size(0), b = x.size(1), c = x.size(2), M = B.size(0), o = B.size(2);
  check_bias(bias, o);
  const int64_t NW = (c * o + L - 1) / L;
  TORCH_CHECK(route == 1 || (route == 2 && NW <= 4), "route: 1 (through Z_j), or 2 (each slot's kernel; c o <= 64)");
  const bool via_w = route == 2;
  const int64_t G = (b + L - 1) / L;
  ThreadAccumulators acc({n_out, G, o, L}, x.options());
  torch::Tensor W;  // (M, o, c): row r = m o + q; or via W, the basis as (M, c o) rows of NW L floats
  if (via_w) {
    W = torch::zeros({M, NW * L}, x.options());
    W.narrow(1, 0, c * o).copy_(B.reshape({M, c * o}));
  } else {
    W = B.permute({0, 2, 1}).contiguous();
  }
  const float* xp = x.data_ptr<float>();
  const float* Wp = W.data_ptr<float>();
  const float* cp = coef.data_ptr<float>();
  const int64_t* op = offs.data_ptr<int64_t>();
  const int64_t* dp = dst.data_ptr<int64_t>();
  const int64_t* pp = pos.data_ptr<int64_t>();
  fwk_native::parallel_for(0, n_in, 1, [&](int64_t j0, int64_t j1) {
    float* mine = acc.mine();
    std::vector<float> xT(c * L), Z(via_w ? 4 * NW * L : o * M * L);
    for (int64_t j = j0; j < j1; ++j) {
      const int64_t s0 = op[j], K = op[j + 1] - s0;
      if (j + 1 < j1) {  // the next vertex's coefficient rows and output rows
        prefetch_rows<0>(cp, pp, op[j + 1], op[j + 2], M, M * sizeof(float));
        prefetch_rows<1>(mine, dp, op[j + 1], op[j + 2], G * o * L, G * o * L * sizeof(float));
      }
      if (K == 0) continue;
      for (int64_t g = 0; g < G; ++g) {
        to_lanes(xT.data(), xp + j * b * c, b, c, g);
        if (!via_w) matrix_times_lanes(Z.data(), Wp, xT.data(), M * o, c);
        for (int64_t k0 = 0; k0 < K; k0 += 4) {  // the slots 4 at a time (their rows of y, their coefficients)
          const int64_t kb = std::min<int64_t>(4, K - k0);
          float* out[4];
          const float* A[4];
          for (int64_t t = 0; t < kb; ++t) {
            out[t] = mine + (dp[s0 + k0 + t] * G + g) * o * L;
            A[t] = cp + pp[s0 + k0 + t] * M;
          }
          if (via_w) {  // the slots' kernels W_s = A_s B in cache, each applied to x_j's lanes
            if (kb == 4) kernels_of_slots<4>(Z.data(), A, Wp, M, NW);
            else
              for (int64_t t = 0; t < kb; ++t) kernels_of_slots<1>(Z.data() + t * NW * L, A + t, Wp, M, NW);
            for (int64_t t = 0; t < kb; ++t)
              by_blocks_of_8<KernelApply>(o, out[t], Z.data() + t * NW * L, xT.data(), c, o);
            continue;
          }
          if (kb == 4) y_rows<4>(out, A, Z.data(), M, o);
          else
            for (int64_t t = 0; t < kb; ++t) y_rows<1>(out + t, A + t, Z.data(), M, o);
        }
      }
    }
  });
  return sum_out_of_lanes(acc.done(), b, bias.size(0) ? bias.data_ptr<float>() : nullptr);
}

// its backward: dy (n_out, b, o); returns dx (n_in, b, c), dB (M, c, o), dcoef (R, M) (zero at the rows no slot
// reads) and the bias's gradient (o: dy summed over vertices and batch), each empty where not asked for
std::vector<torch::Tensor> lanes_backward(torch::Tensor dy, torch::Tensor x, torch::Tensor B, torch::Tensor coef,
                                          torch::Tensor offs, torch::Tensor dst, torch::Tensor pos, bool need_x,
                                          bool need_B, bool need_coef, bool need_bias) {
  using namespace lanes;
  check(dy, "dy", at::kFloat, 3);
  lanes_check(x, B, coef, offs, dst, pos, dy.size(0));
  const int64_t n_in = x.size(0), b = x.size(1), c = x.size(2), M = B.size(0), o = B.size(2), n_out = dy.size(0);
  TORCH_CHECK(dy.size(1) == b && dy.size(2) == o, "dy: expected (n_out, b, o)");
  const int64_t G = (b + L - 1) / L, QL = o * L;
  const KernelChunks ch = kernel_chunks(M);
  const int nt = at::get_num_threads();
  auto empty = torch::empty({0}, x.options());
  auto dbias = need_bias ? torch::empty({o}, x.options()) : empty;  // the sum of dy over vertices and batch
  auto dyT = all_to_lanes(dy, need_bias ? dbias.data_ptr<float>() : nullptr);  // (n_out, G, o, L)
  const float* dyTp = dyT.data_ptr<float>();
  auto dx = need_x ? torch::empty({n_in, b, c}, x.options()) : empty;
  // every coefficient row named by a slot: the first batch group writes each row's gradient, the others add to it
  const bool every_row = dst.size(0) == coef.size(0);
  auto dcoef = row_grad(need_coef, coef.size(0), M, dst.size(0), x.options());
  ThreadAccumulators dBv({need_B ? M * o : 0, c, L}, x.options());
  auto W = B.permute({0, 2, 1}).contiguous();  // (M, o, c)
  auto Bq = torch::zeros({c, o, ch.W}, x.options());  // (p, q, m), zero past M
  Bq.narrow(2, 0, M).copy_(B.permute({1, 2, 0}));
  const float* xp = x.data_ptr<float>();
  const float* Wp = W.data_ptr<float>();
  const float* Bqp = Bq.data_ptr<float>();
  const float* cp = coef.data_ptr<float>();
  const int64_t* op = offs.data_ptr<int64_t>();
  const int64_t* dp = dst.data_ptr<int64_t>();
  const int64_t* pp = pos.data_ptr<int64_t>();
  float* dxp = need_x ? dx.data_ptr<float>() : nullptr;
  float* dcp = need_coef ? dcoef.data_ptr<float>() : nullptr;
  const int64_t Kmax = max_run(op, n_in);
  fwk_native::parallel_for(0, n_in, 1, [&](int64_t j0, int64_t j1) {
    float* myB = need_B ? dBv.mine() : nullptr;
    // xT and dZ of the pairs (vertex, batch group) since db_group last ran: the next pair's are at `held`
    std::vector<float> xTs(DB_GROUP * c * L), Zm(QL * ch.W), dZs(DB_GROUP * o * M * L), dxT(c * L);
    int held = 0;
    std::vector<const float*> A(Kmax), dY(Kmax);
    std::vector<float*> dA(Kmax);
    for (int64_t j = j0; j < j1; ++j) {
      const int64_t s0 = op[j], K = op[j + 1] - s0;
      if (j + 1 < j1) {  // the next vertex's coefficient rows, their gradient's rows and its rows of dy
        prefetch_rows<0>(cp, pp, op[j + 1], op[j + 2], M, M * sizeof(float));
        if (need_coef) prefetch_rows<1>(dcp, pp, op[j + 1], op[j + 2], M, M * sizeof(float));
        prefetch_rows<0>(dyTp, dp, op[j + 1], op[j + 2], G * o * L, G * o * L * sizeof(float));
      }
      if (K == 0) {
        if (need_x) std::fill(dxp + j * b * c, dxp + (j + 1) * b * c, 0.f);
        continue;
      }
      for (int64_t k = 0; k < K; ++k) {
        A[k] = cp + pp[s0 + k] * M;
        if (need_coef) dA[k] = dcp + pp[s0 + k] * M;
      }
      for (int64_t g = 0; g < G; ++g) {
        float* xT = xTs.data() + held * c * L;
        float* dZ = dZs.data() + held * o * M * L;
        to_lanes(xT, xp + j * b * c, b, c, g);
        for (int64_t k = 0; k < K; ++k) dY[k] = dyTp + (dp[s0 + k] * G + g) * o * L;
        if (need_coef)
          by_chunks<ZmThenDa>(ch, dA.data(), dY.data(), Zm.data(), Bqp, xT, c, o, K, M, every_row && g == 0);
        if (!need_x && !need_B) continue;
        int64_t m0 = 0;
        for (; m0 + 4 <= M; m0 += 4) dz_cols<4>(dZ, A.data(), dY.data(), K, o, m0);
        for (; m0 < M; ++m0) dz_cols<1>(dZ, A.data(), dY.data(), K, o, m0);
        if (need_x) {
          by_blocks_of_8<DxBlock>(c, dxT.data(), Wp, dZ, M * o, c);
          from_lanes(dxp + j * b * c, dxT.data(), b, c, g);
        }
        if (need_B && ++held == DB_GROUP) {
          db_group(myB, xTs.data(), dZs.data(), M * o, c);
          held = 0;
        }
      }
    }
    if (need_B && held > 0) {  // the last pairs of this range, the group's other places zero
      std::fill(xTs.begin() + held * c * L, xTs.end(), 0.f);
      std::fill(dZs.begin() + held * o * M * L, dZs.end(), 0.f);
      db_group(myB, xTs.data(), dZs.data(), M * o, c);
    }
  });
  // dB[m][p][q] = sum over threads and lanes of dBv[(m o + q)][p] (the threads' vectors added in thread order, then
  // the 16 lanes: torch's sum over dimensions 0 and 3 took 0.44 ms for the 32 -> 16 layer's 2 x 560 x 32 x 16 floats)
  torch::Tensor dB = empty;
  if (need_B) {
    const float* dBvp = dBv.done().data_ptr<float>();
    dB = torch::empty({M, c, o}, x.options());
    float* dBp = dB.data_ptr<float>();
    const int64_t R = M * o;
    fwk_native::parallel_for(0, R, 16, [&](int64_t r0, int64_t r1) {
      for (int64_t r = r0; r < r1; ++r)
        for (int64_t p = 0; p < c; ++p) {
          vL t = ld(dBvp + (r * c + p) * L);
          for (int th = 1; th < nt; ++th) t += ld(dBvp + ((th * R + r) * c + p) * L);
          dBp[((r / o) * c + p) * o + r % o] = lane_sum(t);
        }
    });
  }
  return {dx, dB, dcoef, dbias};
}

namespace lanes {
// rows [r0, r0 + RB) and vectors [v0, v0 + CV) of C = A Bp + bias: each row's K scalars broadcast against Bp's rows
// (K x NP, op(B) zero-padded to NP = 16 NC columns), RB CV chains of multiply-adds, the last vector of a row stored
// masked (N - 16 v floats)
template <int RB, int CV>
inline void tall_block(float* __restrict C, const float* __restrict A, const float* __restrict Bp,
                       const float* __restrict biasp, int64_t K, int64_t N, int64_t NP, int64_t r0, int64_t v0) {
  vL acc[RB][CV];
  for (int v = 0; v < CV; ++v) {
    const vL b0 = ld(biasp + (v0 + v) * L);
    for (int r = 0; r < RB; ++r) acc[r][v] = b0;
  }
  const float* a = A + r0 * K;
  for (int64_t k = 0; k < K; ++k) {
    vL b[CV];
    for (int v = 0; v < CV; ++v) b[v] = ld(Bp + k * NP + (v0 + v) * L);
    for (int r = 0; r < RB; ++r) {
      const float ar = a[r * K + k];
      for (int v = 0; v < CV; ++v) acc[r][v] += ar * b[v];
    }
  }
  for (int r = 0; r < RB; ++r)
    for (int v = 0; v < CV; ++v) {
      const int64_t col = (v0 + v) * L, n = std::min<int64_t>(L, N - col);
      float* d = C + (r0 + r) * N + col;
      if (n == L) st(d, acc[r][v]);
      else st_n(d, acc[r][v], n);
    }
}

// rows [r0, r0 + RB) of C, every vector: 4 at a time (RB 4) or, for N <= 32, all at once (RB 8)
template <int RB, int CVMAX>
inline void tall_rows(float* C, const float* A, const float* Bp, const float* biasp, int64_t K, int64_t N, int64_t NP,
                      int64_t r0) {
  const int64_t NC = NP / L;
  int64_t v0 = 0;
  for (; v0 + CVMAX <= NC; v0 += CVMAX) tall_block<RB, CVMAX>(C, A, Bp, biasp, K, N, NP, r0, v0);
  switch (NC - v0) {
    case 3: tall_block<RB, 3>(C, A, Bp, biasp, K, N, NP, r0, v0); break;
    case 2: tall_block<RB, 2>(C, A, Bp, biasp, K, N, NP, r0, v0); break;
    case 1: tall_block<RB, 1>(C, A, Bp, biasp, K, N, NP, r0, v0); break;
    default: break;
  }
}
}  // namespace lanes

// the tall products in lanes: C (R x N) = A (R x K) op(B) + bias, rows in blocks of 8 (N <= 32) or 4, op(B)'s rows
// the vectors (zero-padded to whole registers, in L1 for the whole product). MKL's calls on the same row blocks
// (tall_mm) packed A and scaled C first: their copy and scaling routines were as many samples in perf as its
// products on the chapter 5 width's step.
void tall_lanes(const float* A, const float* B, bool bt, const float* bias, float* C, int64_t R, int64_t K,
                int64_t N) {
  using namespace lanes;
  const int64_t NP = (N + L - 1) / L * L;
  std::vector<float> Bp(K * NP, 0.f), biasp(NP, 0.f);
  for (int64_t k = 0; k < K; ++k)
    for (int64_t n = 0; n < N; ++n) Bp[k * NP + n] = bt ? B[n * K + k] : B[k * N + n];
  if (bias) std::copy(bias, bias + N, biasp.begin());
  const bool narrow = NP <= 2 * L;
  const int64_t RB = narrow ? 8 : 4;
  fwk_native::parallel_for(0, (R + RB - 1) / RB, 64, [&](int64_t q0, int64_t q1) {
    int64_t r0 = q0 * RB;
    const int64_t r1 = std::min(q1 * RB, R);
    for (; r0 + RB <= r1; r0 += RB) {
      if (narrow) tall_rows<8, 2>(C, A, Bp.data(), biasp.data(), K, N, NP, r0);
      else tall_rows<4, 4>(C, A, Bp.data(), biasp.data(), K, N, NP, r0);
    }
    for (; r0 < r1; ++r0) tall_rows<1, 4>(C, A, Bp.data(), biasp.data(), K, N, NP, r0);
  });
}

// kernel order in lanes, forward (kernel_forward's arguments, x as (n_in, b, c)): y_i = sum_s x_src[s] W_pos[s] and
// r_i = sum_s w_pos[s] x_src[s] per output vertex, 16 batch entries a register. Returns y (n_out, b, o) (plus bias (o),
// or none: (0,)) and r (n_out, b, c) (empty (0,) without w).
std::vector<torch::Tensor> kernel_lanes_forward(torch::Tensor x, torch::Tensor Wk, torch::Tensor w, torch::Tensor offs,
                                                torch::Tensor src, torch::Tensor pos, int64_t o, torch::Tensor bias) {
  using namespace lanes;
  check(x, "x", at::kFloat, 3);
  check(Wk, "Wk", at::kFloat, 2);
  const int64_t n_in = x.size(0), b = x.size(1), c = x.size(2), n_out = offs.size(0) - 1;
  TORCH_CHECK(o > 0 && Wk.size(1) == c * o, "Wk: expected c o = ", c * o, " columns");
  check_csr(offs, src, n_out, n_in);
  check_coef(Wk, w, pos, src.size(0));
  check_bias(bias, o);
  const float* biasp = bias.size(0) ? bias.data_ptr<float>() : nullptr;
  const bool res = w.size(0) > 0;
  const int64_t G = (b + L - 1) / L;
  auto xL = all_to_lanes(x);
  auto y = torch::empty({n_out, b, o}, x.options());
  auto r = res ? torch::empty({n_out, b, c}, x.options()) : torch::empty({0}, x.options());
  const float* xLp = xL.data_ptr<float>();
  const float* Wp = Wk.data_ptr<float>();
  const float* wp = res ? w.data_ptr<float>() : nullptr;
  const int64_t* op = offs.data_ptr<int64_t>();
  const int64_t* sp = src.data_ptr<int64_t>();
  const int64_t* pp = pos.data_ptr<int64_t>();
  float* yp = y.data_ptr<float>();
  float* rp = res ? r.data_ptr<float>() : nullptr;
  fwk_native::parallel_for(0, n_out, 1, [&](int64_t i0, int64_t i1) {
    std::vector<float> yL(o * L), rL(c * L);
    for (int64_t i = i0; i < i1; ++i) {
      const int64_t s0 = op[i], K = op[i + 1] - s0;
      if (i + 1 < i1) prefetch_rows(xLp, sp, op[i + 1], op[i + 2], G * c * L, G * c * L * sizeof(float));
      for (int64_t g = 0; g < G; ++g) {
        start_lanes(yL.data(), biasp, o);
        if (res) std::fill(rL.begin(), rL.end(), 0.f);
        for (int64_t k = 0; k < K; ++k) {
          const float* xs = xLp + (sp[s0 + k] * G + g) * c * L;
          by_blocks_of_8<KernelApply>(o, yL.data(), Wp + pp[s0 + k] * c * o, xs, c, o);
          if (res) {
            const float wk = wp[pp[s0 + k]];
#pragma omp simd
            for (int64_t t = 0; t < c * L; ++t) rL[t] += wk * xs[t];
          }
        }
        from_lanes(yp + i * b * o, yL.data(), b, o, g);
        if (res) from_lanes(rp + i * b * c, rL.data(), b, c, g);
      }
    }
  });
  return {y, r};
}

namespace lanes {
// a sum over the batch for S slots, rows [p0, p0 + PB) and columns [8 q0, 8 q0 + 8 QV) of
//     dW_s[p][q] = sum_beta X_s[beta][p] dY[beta][q]      (X_s: b x c row-major, dY: b x O8, zero past o)
// with 8 floats a vector (dY's row read once for the S slots and PB rows: S PB QV chains of multiply-adds): the
// kernel order's kernel gradients (X_s a slot's input rows, dY its output vertex's gradient)
template <int S, int PB, int QV>
inline void dw_block(float* const* dW, const float* const* X, const float* __restrict dY, int64_t b, int64_t c,
                     int64_t o, int64_t O8, int64_t p0, int64_t q0) {
  v8 acc[S][PB][QV];
  for (int s = 0; s < S; ++s)
    for (int p = 0; p < PB; ++p)
      for (int v = 0; v < QV; ++v) acc[s][p][v] = v8{};
  for (int64_t beta = 0; beta < b; ++beta) {
    v8 y[QV];
    for (int v = 0; v < QV; ++v) y[v] = ld8(dY + beta * O8 + (q0 + v) * 8);
    for (int s = 0; s < S; ++s)
      for (int p = 0; p < PB; ++p) {
        const float xv = X[s][beta * c + p0 + p];
        for (int v = 0; v < QV; ++v) acc[s][p][v] += xv * y[v];
      }
  }
  for (int s = 0; s < S; ++s)
    for (int p = 0; p < PB; ++p)
      for (int v = 0; v < QV; ++v) {
        const int64_t q = (q0 + v) * 8, n = std::min<int64_t>(8, o - q);
        if (n == 8) st8(dW[s] + (p0 + p) * o + q, acc[s][p][v]);
        else st8_n(dW[s] + (p0 + p) * o + q, acc[s][p][v], n);
      }
}

// dw_block over every row of S slots, for column vectors [q0, q0 + QV): rows in blocks of 4, then the 1-3 left
template <int S, int QV>
inline void dw_rows(float* const* dW, const float* const* X, const float* dY, int64_t b, int64_t c, int64_t o,
                    int64_t O8, int64_t q0) {
  int64_t p0 = 0;
  for (; p0 + 4 <= c; p0 += 4) dw_block<S, 4, QV>(dW, X, dY, b, c, o, O8, p0, q0);
  switch (c - p0) {
    case 3: dw_block<S, 3, QV>(dW, X, dY, b, c, o, O8, p0, q0); break;
    case 2: dw_block<S, 2, QV>(dW, X, dY, b, c, o, O8, p0, q0); break;
    case 1: dw_block<S, 1, QV>(dW, X, dY, b, c, o, O8, p0, q0); break;
    default: break;
  }
}

// dW_s (c x o, row-major) = X_s^T dY for S slots: column vectors two at a time, then the one left
template <int S>
inline void dw_slots(float* const* dW, const float* const* X, const float* dY, int64_t b, int64_t c, int64_t o,
                     int64_t O8) {
  const int64_t nv = O8 / 8;
  int64_t q0 = 0;
  for (; q0 + 2 <= nv; q0 += 2) dw_rows<S, 2>(dW, X, dY, b, c, o, O8, q0);
  if (q0 < nv) dw_rows<S, 1>(dW, X, dY, b, c, o, O8, q0);
}
}  // namespace lanes

// its backward: dy (n_out, b, o), dr (n_out, b, c) or empty; returns dx (n_in, b, c), dWk (R, c o) and dw (R) (zero
// at the rows no slot reads; empty where not asked for). dx in lanes (each slot's kernel transposed, applied to dy_i);
// the kernels' gradient dW_s = X_s^T dy_i, a sum over the batch for each slot, from x's and dy's own (batch-major)
// rows, 8 output channels a vector (dw_slots), two slots at a time: no lanes (a sum over lanes would end in a
// horizontal sum for each of the c o entries) and no BLAS call (kernel_backward's per-vertex product of (K c x b)
// by (b x o): 1.9-2.0 ms against 0.56 on the chapter 5 width's first layer, 2 threads); dw_s = <x_src[s], dr_i> from
// the same rows. The first layer's input needs no gradient: its backward never takes x into lanes.
std::vector<torch::Tensor> kernel_lanes_backward(torch::Tensor dy, torch::Tensor dr, torch::Tensor x, torch::Tensor Wk,
                                                 torch::Tensor w, torch::Tensor offs, torch::Tensor src,
                                                 torch::Tensor pos, bool need_x, bool need_W, bool need_w) {
  using namespace lanes;
  check(dy, "dy", at::kFloat, 3);
  check(x, "x", at::kFloat, 3);
  const int64_t n_in = x.size(0), b = x.size(1), c = x.size(2), o = dy.size(2), n_out = offs.size(0) - 1;
  TORCH_CHECK(dy.size(0) == n_out && dy.size(1) == b, "dy: expected (n_out, b, o)");
  check(Wk, "Wk", at::kFloat, 2);
  TORCH_CHECK(Wk.size(1) == c * o, "Wk: expected c o = ", c * o, " columns");
  check_csr(offs, src, n_out, n_in);
  check_coef(Wk, w, pos, src.size(0));  // the rows written below: in range and distinct
  const bool res = w.size(0) > 0;
  if (res) check(dr, "dr", at::kFloat, 3);
  need_w = need_w && res;
  const int64_t O8 = (o + 7) / 8 * 8;
  const int64_t G = (b + L - 1) / L;
  auto empty = torch::empty({0}, x.options());
  ThreadAccumulators acc({need_x ? n_in : 0, G, c, L}, x.options());
  auto dw = row_grad(need_w, w.size(0), 0, src.size(0), x.options());
  auto dWk = row_grad(need_W, Wk.size(0), c * o, src.size(0), x.options());
  const float* xp = x.data_ptr<float>();
  float* dWp = need_W ? dWk.data_ptr<float>() : nullptr;
  const float* Wp = Wk.data_ptr<float>();
  const float* wp = res ? w.data_ptr<float>() : nullptr;
  const float* dyp = dy.data_ptr<float>();
  const float* drp = res ? dr.data_ptr<float>() : nullptr;
  const int64_t* op = offs.data_ptr<int64_t>();
  const int64_t* sp = src.data_ptr<int64_t>();
  const int64_t* pp = pos.data_ptr<int64_t>();
  float* dwp = need_w ? dw.data_ptr<float>() : nullptr;
  // dx_src[p] += sum_q W[p o + q] dy[q]: kernel_apply with the slot's kernel transposed (o x c)
  fwk_native::parallel_for(0, n_out, 1, [&](int64_t i0, int64_t i1) {
    float* mine = need_x ? acc.mine() : nullptr;
    std::vector<float> dyL(o * L), drL(c * L), Wt(c * o), dyP(O8 != o && need_W ? b * O8 : 0);
    for (int64_t i = i0; i < i1; ++i) {
      const int64_t s0 = op[i], K = op[i + 1] - s0;
      if (i + 1 < i1) {  // the next vertex's rows of x (for dWk and dw) and of this thread's dx
        if (need_W || need_w) prefetch_rows(xp, sp, op[i + 1], op[i + 2], b * c, b * c * sizeof(float));
        if (need_x) prefetch_rows<1>(mine, sp, op[i + 1], op[i + 2], G * c * L, G * c * L * sizeof(float));
      }
      if (K == 0) continue;
      const float* dyi = dyp + i * b * o;
      if (need_W) {  // dW_s = X_s^T dy_i for the vertex's slots, two at a time; dy_i padded to O8 columns
        const float* dY = dyi;
        if (O8 != o) {
          for (int64_t beta = 0; beta < b; ++beta) {
            std::copy(dyi + beta * o, dyi + beta * o + o, dyP.begin() + beta * O8);
            std::fill(dyP.begin() + beta * O8 + o, dyP.begin() + beta * O8 + O8, 0.f);
          }
          dY = dyP.data();
        }
        int64_t k = 0;
        for (; k + 2 <= K; k += 2) {
          float* dW[2] = {dWp + pp[s0 + k] * c * o, dWp + pp[s0 + k + 1] * c * o};
          const float* X[2] = {xp + sp[s0 + k] * b * c, xp + sp[s0 + k + 1] * b * c};
          dw_slots<2>(dW, X, dY, b, c, o, O8);
        }
        if (k < K) {
          float* dW[1] = {dWp + pp[s0 + k] * c * o};
          const float* X[1] = {xp + sp[s0 + k] * b * c};
          dw_slots<1>(dW, X, dY, b, c, o, O8);
        }
      }
      if (need_w) {  // dw_s = <x_src[s], dr_i> over the b c floats of both rows
        const float* dri = drp + i * b * c;
        for (int64_t k = 0; k < K; ++k) {
          const float* xs = xp + sp[s0 + k] * b * c;
          float d = 0.f;
#pragma omp simd reduction(+ : d)
          for (int64_t t = 0; t < b * c; ++t) d += xs[t] * dri[t];
          dwp[pp[s0 + k]] = d;
        }
      }
      if (!need_x) continue;
      for (int64_t g = 0; g < G; ++g) {
        to_lanes(dyL.data(), dyi, b, o, g);
        if (res) to_lanes(drL.data(), drp + i * b * c, b, c, g);
        for (int64_t k = 0; k < K; ++k) {
          const int64_t j = sp[s0 + k], row = pp[s0 + k];
          float* dxs = mine + (j * G + g) * c * L;
          const float* W = Wp + row * c * o;
          for (int64_t p = 0; p < c; ++p)
            for (int64_t q = 0; q < o; ++q) Wt[q * c + p] = W[p * o + q];
          by_blocks_of_8<KernelApply>(c, dxs, Wt.data(), dyL.data(), o, c);
          if (res) {
            const float wk = wp[row];
#pragma omp simd
            for (int64_t t = 0; t < c * L; ++t) dxs[t] += wk * drL[t];
          }
        }
      }
    }
  });
  return {need_x ? sum_out_of_lanes(acc.done(), b) : empty, dWk, dw};
}

namespace lanes {
// T rows [beta0, beta0 + BB) of one output vertex: T[beta][m] = sum_k X_k[beta] A_k[m] for its K slots, the kernels
// (and the residual's weight, column M) as the vector: rows of W = NV L + 8 H (KernelChunks), A zero past Mx
template <int BB, int NV, int H>
inline void t_rows(float* __restrict T, float* __restrict r, const float* const* X, const float* __restrict A,
                   int64_t K, int64_t M, int64_t beta0) {
  constexpr int W = NV * L + 8 * H;
  vL acc[BB][NV];
  v8 tail[BB];
  zero(acc);
  zero(tail);
  for (int64_t k = 0; k < K; ++k) {
    const float* a = A + k * W;
    const float* xk = X[k] + beta0;
    vL av[NV];
    for (int v = 0; v < NV; ++v) av[v] = ld(a + v * L);
    const v8 at = H ? ld8(a + NV * L) : v8{};
    for (int t = 0; t < BB; ++t) {
      const float xv = xk[t];
      for (int v = 0; v < NV; ++v) acc[t][v] += xv * av[v];
      if (H) tail[t] += xv * at;
    }
  }
  for (int t = 0; t < BB; ++t) {  // T's row: M floats (masked past them); r: column M
    put_row<NV, H>(T + (beta0 + t) * M, acc[t], tail[t], M, true);
    if (r) r[beta0 + t] = M < NV * L ? acc[t][M / L][M % L] : tail[t][M - NV * L];
  }
}

template <int BB>
struct TRows {
  template <int NV, int H>
  static void go(float* T, float* r, const float* const* X, const float* A, int64_t K, int64_t M, int64_t beta0) {
    t_rows<BB, NV, H>(T, r, X, A, K, M, beta0);
  }
  static void run(int64_t beta0, float* T, float* r, const float* const* X, const float* A, int64_t K, int64_t M,
                  const KernelChunks& ch) {
    by_chunks<TRows>(ch, T, r, X, A, K, M, beta0);
  }
};
}  // namespace lanes

namespace lanes {
// dA rows of KB slots: dA_k[m] = sum_beta X_k[beta] dTx[beta][m], the kernels (and the residual's column M) as the
// vector: rows of W = NV L + 8 H (KernelChunks; dTx (B x W), zero past Mx)
template <int KB, int NV, int H>
inline void sum_da_block(float* __restrict dA, const float* const* X, const float* __restrict dTx, int64_t B,
                         int64_t k0) {
  constexpr int W = NV * L + 8 * H;
  vL acc[KB][NV];
  v8 tail[KB];
  combine_rows<KB, NV, H>(acc, tail, X + k0, dTx, B);
  for (int k = 0; k < KB; ++k) {
    for (int v = 0; v < NV; ++v) st(dA + (k0 + k) * W + v * L, acc[k][v]);
    if (H) st8(dA + (k0 + k) * W + NV * L, tail[k]);
  }
}

struct SumDaRows {
  template <int NV, int H>
  static void go(float* dA, const float* const* X, const float* dTx, int64_t B, int64_t K) {
    int64_t k0 = 0;
    for (; k0 + 4 <= K; k0 += 4) sum_da_block<4, NV, H>(dA, X, dTx, B, k0);
    switch (K - k0) {
      case 3: sum_da_block<3, NV, H>(dA, X, dTx, B, k0); break;
      case 2: sum_da_block<2, NV, H>(dA, X, dTx, B, k0); break;
      case 1: sum_da_block<1, NV, H>(dA, X, dTx, B, k0); break;
      default: break;
    }
  }
};
}  // namespace lanes

namespace lanes {
// r[0..16) := its transpose: r[j][t] = r[t][j] (16 x 16 floats; three rounds of shuffles within and across the
// 128-bit quarters)
#ifdef FWK_VCCONV_LANES
inline void transpose16(__m512 (&r)[16]) {
  __m512 t[16];
  for (int i = 0; i < 16; i += 2) {
    t[i] = _mm512_unpacklo_ps(r[i], r[i + 1]);
    t[i + 1] = _mm512_unpackhi_ps(r[i], r[i + 1]);
  }
  for (int i = 0; i < 16; i += 4) {
    r[i] = _mm512_shuffle_ps(t[i], t[i + 2], 0x44);
    r[i + 1] = _mm512_shuffle_ps(t[i], t[i + 2], 0xEE);
    r[i + 2] = _mm512_shuffle_ps(t[i + 1], t[i + 3], 0x44);
    r[i + 3] = _mm512_shuffle_ps(t[i + 1], t[i + 3], 0xEE);
  }
  for (int h = 0; h < 16; h += 8)
    for (int i = 0; i < 4; ++i) {
      t[h + i] = _mm512_shuffle_f32x4(r[h + i], r[h + i + 4], 0x88);
      t[h + i + 4] = _mm512_shuffle_f32x4(r[h + i], r[h + i + 4], 0xDD);
    }
  for (int i = 0; i < 8; ++i) {
    r[i] = _mm512_shuffle_f32x4(t[i], t[i + 8], 0x88);
    r[i + 8] = _mm512_shuffle_f32x4(t[i], t[i + 8], 0xDD);
  }
}
#endif

// dTt (M + 1 rows of Bp = round16(B) floats, zero past B) := dT_i^T (dT_i: B x M), with dr_i (B) as row M
inline void transpose_rows(float* __restrict dTt, const float* __restrict dTi, const float* __restrict dri, int64_t B,
                           int64_t M) {
  const int64_t Bp = round16(B);
  for (int64_t b0 = 0; b0 < B; b0 += L) {
    const int64_t nb = std::min<int64_t>(L, B - b0);
    for (int64_t m0 = 0; m0 < M; m0 += L) {
      const int64_t nm = std::min<int64_t>(L, M - m0);
#ifdef FWK_VCCONV_LANES
      __m512 r[16];
      for (int t = 0; t < 16; ++t) r[t] = t < nb ? (__m512)ld_n(dTi + (b0 + t) * M + m0, nm) : _mm512_setzero_ps();
      transpose16(r);
      for (int64_t j = 0; j < nm; ++j) st(dTt + (m0 + j) * Bp + b0, (vL)r[j]);
#else
      for (int64_t j = 0; j < nm; ++j)
        for (int64_t t = 0; t < L; ++t) dTt[(m0 + j) * Bp + b0 + t] = t < nb ? dTi[(b0 + t) * M + m0 + j] : 0.f;
#endif
    }
    if (dri) st(dTt + M * Bp + b0, ld_n(dri + b0, nb));
  }
}

// dX rows of SB slots, columns [b0, b0 + NB L): acc[s][v] = sum_m a_s[m] dTt[m][b0 + v L] over the Mx rows of dTt
// (a_s: the slot's coefficient row, and its residual weight for row M), added to the slot's row of out (B floats a
// row, masked past B). Each dTt vector is loaded once for the SB slots.
template <int SB, int NB>
inline void dx_block(float* __restrict out, const float* const* a, const float* wv, const float* __restrict dTt,
                     const int64_t* rows, int64_t M, int64_t B, int64_t Bp, int64_t b0) {
  vL acc[SB][NB];
  zero(acc);
  for (int64_t m = 0; m < M; ++m) {
    const float* t = dTt + m * Bp + b0;
    vL tv[NB];
    for (int v = 0; v < NB; ++v) tv[v] = ld(t + v * L);
    for (int s = 0; s < SB; ++s) {
      const float as = a[s][m];
      for (int v = 0; v < NB; ++v) acc[s][v] += as * tv[v];
    }
  }
  if (wv) {
    const float* t = dTt + M * Bp + b0;
    for (int v = 0; v < NB; ++v) {
      const vL tv = ld(t + v * L);
      for (int s = 0; s < SB; ++s) acc[s][v] += wv[s] * tv;
    }
  }
  for (int s = 0; s < SB; ++s) {
    float* o = out + rows[s] * B + b0;
    for (int v = 0; v < NB; ++v) {
      const int64_t n = B - b0 - v * L;
      if (n >= L) st(o + v * L, ld(o + v * L) + acc[s][v]);
      else st_n(o + v * L, ld_n(o + v * L, n) + acc[s][v], n);
    }
  }
}

// the slots [k0, k0 + SB) over every column block: NB = 4 vectors at a time, then the 1-3 left
template <int SB>
inline void dx_slots(float* out, const float* const* a, const float* wv, const float* dTt, const int64_t* rows,
                     int64_t M, int64_t B) {
  const int64_t Bp = round16(B), nv = Bp / L;
  int64_t v0 = 0;
  for (; v0 + 4 <= nv; v0 += 4) dx_block<SB, 4>(out, a, wv, dTt, rows, M, B, Bp, v0 * L);
  const int64_t b0 = v0 * L;
  switch (nv - v0) {
    case 3: dx_block<SB, 3>(out, a, wv, dTt, rows, M, B, Bp, b0); break;
    case 2: dx_block<SB, 2>(out, a, wv, dTt, rows, M, B, Bp, b0); break;
    case 1: dx_block<SB, 1>(out, a, wv, dTt, rows, M, B, Bp, b0); break;
    default: break;
  }
}
}  // namespace lanes

// sum_backward's x gradient in lanes: dT_i (B x M) and dr_i transposed into dTt (the batch as the vector, 16 x 16
// blocks in registers), then each slot's dX_k = sum_m A_k[m] dTt[m] (+ a_k dTt[M]) six slots by four vectors at a
// time (24 accumulators, the four dTt vectors and a broadcast in registers: each dTt vector loaded once for six
// slots; three slots by eight vectors left the eight in memory, one load a multiply-add, and was 0.71-1.03x the BLAS
// call), the coefficients read in place, and added to the slot's row of acc.
constexpr int DX_SLOTS = 6;  // slots a block: 6 x 4 accumulators, 4 vectors of dTt and a broadcast in registers
void sum_vertex_lanes_dx(float* acc, const float* dTi, const float* dri, const float* coef, const float* w,
                         const int64_t* src, const int64_t* pos, int64_t s0, int64_t K, int64_t M, int64_t B,
                         float* dTt) {
  using namespace lanes;
  transpose_rows(dTt, dTi, dri, B, M);
  const float* a[DX_SLOTS];
  float wv[DX_SLOTS];
  for (int64_t k = 0; k < K; k += DX_SLOTS) {
    const int n = static_cast<int>(std::min<int64_t>(DX_SLOTS, K - k));
    for (int s = 0; s < n; ++s) {
      a[s] = coef + pos[s0 + k + s] * M;
      if (w) wv[s] = w[pos[s0 + k + s]];
    }
    const float* wp = w ? wv : nullptr;
    const int64_t* rows = src + s0 + k;
    switch (n) {
      case 6: dx_slots<6>(acc, a, wp, dTt, rows, M, B); break;
      case 5: dx_slots<5>(acc, a, wp, dTt, rows, M, B); break;
      case 4: dx_slots<4>(acc, a, wp, dTt, rows, M, B); break;
      case 3: dx_slots<3>(acc, a, wp, dTt, rows, M, B); break;
      case 2: dx_slots<2>(acc, a, wp, dTt, rows, M, B); break;
      default: dx_slots<1>(acc, a, wp, dTt, rows, M, B); break;
    }
  }
}

// sum_backward's coefficient gradients in lanes: dT_i (B x M) and dr_i (B, or null) copied into dTx (B x W: dr_i
// in column M, zero past it), then dA_k[m] = sum_beta X_k[beta] dTx[beta][m] for the vertex's K slots, the kernels
// as the vector (dA: K rows of W floats; W = KernelChunks' row), and each slot's row written to its row of dcoef (M
// floats) and of dw (column M). The input's gradient is sum_vertex_lanes_dx's.
void sum_vertex_lanes_backward(float* dcoef, float* dw, const float* x, const int64_t* src, const int64_t* pos,
                               int64_t s0, int64_t K, const float* dTi, const float* dri, int64_t M, int64_t B,
                               KernelChunks ch, std::vector<float>& work, float* dA, const float** X) {
  using namespace lanes;
  if (static_cast<int64_t>(work.size()) < B * ch.W) work.resize(B * ch.W);
  float* dTx = work.data();
  for (int64_t beta = 0; beta < B; ++beta) {
    float* row = dTx + beta * ch.W;
    copy_padded(row, dTi + beta * M, M, ch.W);
    if (dri) row[M] = dri[beta];
  }
  for (int64_t k = 0; k < K; ++k) X[k] = x + src[s0 + k] * B;
  by_chunks<SumDaRows>(ch, dA, X, dTx, B, K);
  for (int64_t k = 0; k < K; ++k) {
    if (dcoef) copy_n(dcoef + pos[s0 + k] * M, dA + k * ch.W, M);
    if (dw) dw[pos[s0 + k]] = dA[k * ch.W + M];
  }
}

// sum_forward's per-vertex T_i and r_i with the kernels as the vector (rows of 8, the kernels in KernelChunks' layout,
// the residual's weight in column M): 1.2-2.0x the BLAS call on the encoders' layers. Each slot's coefficient row (and
// w in column M) is copied into A, zero-padded to W; the x rows are read in place.
void sum_vertex_lanes(float* Ti, float* ri, const float* x, const float* coef, const float* w, const int64_t* src,
                      const int64_t* pos, int64_t s0, int64_t K, int64_t M, int64_t B, KernelChunks ch, float* A,
                      const float** X) {
  using namespace lanes;
  for (int64_t k = 0; k < K; ++k) {
    copy_padded(A + k * ch.W, coef + pos[s0 + k] * M, M, ch.W);
    if (w) A[k * ch.W + M] = w[pos[s0 + k]];
    X[k] = x + src[s0 + k] * B;
  }
  by_blocks_of_8<TRows>(B, Ti, ri, X, A, K, M, ch);
}

// ---- the residual block's activation and mix: out = res + a f(t) (res empty: f(t)), f = ELU or (a network's last
// layer) the identity, and its gradient dt = a' g f'(t) (a' = a, or 1 without res; ELU'(t) = 1 for t > 0, e^t
// otherwise; res's gradient is g itself). torch runs ELU, the add and their gradients as four passes, and its ELU's
// e^t - 1 (Sleef's expm1, 1 ulp) at about 70 cycles a register: ELU alone was 1.2 ms of the chapter 5 width's step.
// Here e^t comes from Cephes' expf polynomial (Moshier; about 1 ulp on [-88, 0]) and AVX-512's scalef, 16 floats at
// a time. With the identity the mix is res + a t as one multiply-add (torch's add with alpha, vectorised, is the same
// fmadd). The result can be laid out batch-major (`batch_major`: (n, b, c) with strides (c, n c, 1), so that its
// (b, n, c) transpose, which the conv hands on, is contiguous) and the gradient read in that layout: a network's last
// layer then needs no copy of its result into the loss's layout and none of the loss's gradient back. On the chapter
// 5 width's (11,248, 16, 3) floats, alone: 0.13 ms each way against 0.29-0.30 ms for torch's add and copy (and, back,
// the copy and the product); in the step, caches cold: 0.33 and 0.29 ms against 0.81 ms for the four operators.
namespace lanes {
#ifdef FWK_VCCONV_LANES
// em1 = e^x - 1 and ex = e^x for 16 floats x <= 0 (x below -88 taken as -88: e^x is then under 1e-38; NaN stays NaN):
// x = k ln2 + r with |r| <= ln2 / 2, e^r - 1 = r + r^2 P(r), e^x = 2^k e^r; where k = 0 (|x| < ln2 / 2) e^x - 1 is
// r + r^2 P(r) itself, without the cancellation of subtracting 1
inline void expm1_exp(__m512 x, __m512& em1, __m512& ex) {
  x = _mm512_max_ps(_mm512_set1_ps(-88.f), x);  // max_ps returns its second operand where one is NaN: x
  const __m512 k = _mm512_roundscale_ps(_mm512_mul_ps(x, _mm512_set1_ps(1.44269504088896341f)),
                                        _MM_FROUND_TO_NEAREST_INT | _MM_FROUND_NO_EXC);
  __m512 r = _mm512_fnmadd_ps(k, _mm512_set1_ps(0.693359375f), x);  // ln2 in two parts (Cephes' C1, C2)
  r = _mm512_fnmadd_ps(k, _mm512_set1_ps(-2.12194440e-4f), r);
  __m512 P = _mm512_set1_ps(1.9875691500e-4f);
  P = _mm512_fmadd_ps(P, r, _mm512_set1_ps(1.3981999507e-3f));
  P = _mm512_fmadd_ps(P, r, _mm512_set1_ps(8.3334519073e-3f));
  P = _mm512_fmadd_ps(P, r, _mm512_set1_ps(4.1665795894e-2f));
  P = _mm512_fmadd_ps(P, r, _mm512_set1_ps(1.6666665459e-1f));
  P = _mm512_fmadd_ps(P, r, _mm512_set1_ps(5.0000001201e-1f));
  const __m512 q = _mm512_fmadd_ps(_mm512_mul_ps(r, r), P, r);  // e^r - 1
  const __m512 one = _mm512_set1_ps(1.f);
  ex = _mm512_scalef_ps(_mm512_add_ps(q, one), k);
  const __mmask16 k0 = _mm512_cmp_ps_mask(k, _mm512_setzero_ps(), _CMP_EQ_OQ);
  em1 = _mm512_mask_mov_ps(_mm512_sub_ps(ex, one), k0, q);
}

// out[i] = res[i] + a f(t[i]) (or f(t[i]) without res) for i in [0, len)
template <bool ELU>
inline void mix_run(float* out, const float* t, const float* res, float a, int64_t len) {
  const __m512 av = _mm512_set1_ps(a), zero = _mm512_setzero_ps();
  for (int64_t i = 0; i < len; i += L) {
    const int64_t n = std::min<int64_t>(L, len - i);
    const __m512 x = (__m512)ld_n(t + i, n);
    __m512 e = x;
    if (ELU) {
      __m512 em1, ex;
      expm1_exp(x, em1, ex);
      const __mmask16 neg = _mm512_cmp_ps_mask(x, zero, _CMP_LE_OQ);  // torch's test: t <= 0 (false at a NaN)
      e = _mm512_mask_mov_ps(x, neg, em1);  // ELU(t)
    }
    st_n(out + i, (vL)(res ? _mm512_fmadd_ps(av, e, (__m512)ld_n(res + i, n)) : e), n);
  }
}

// dt[i] = a g[i] f'(t[i]) for i in [0, len) (t unread for the identity)
template <bool ELU>
inline void mix_grad_run(float* dt, const float* g, const float* t, float a, int64_t len) {
  const __m512 av = _mm512_set1_ps(a), zero = _mm512_setzero_ps(), one = _mm512_set1_ps(1.f);
  for (int64_t i = 0; i < len; i += L) {
    const int64_t n = std::min<int64_t>(L, len - i);
    const __m512 ag = _mm512_mul_ps(av, (__m512)ld_n(g + i, n));
    if (ELU) {
      const __m512 x = (__m512)ld_n(t + i, n);
      __m512 em1, ex;
      expm1_exp(x, em1, ex);
      const __mmask16 neg = _mm512_cmp_ps_mask(x, zero, _CMP_LE_OQ);
      st_n(dt + i, (vL)_mm512_mul_ps(ag, _mm512_mask_mov_ps(one, neg, ex)), n);  // ELU'(t): 1 at a NaN, as torch's
    } else {
      st_n(dt + i, (vL)ag, n);
    }
  }
}
#else  // lanes_supported() is false here and fwk_vcconv does not call these: plain loops, for a complete build
template <bool ELU>
inline void mix_run(float* out, const float* t, const float* res, float a, int64_t len) {
  for (int64_t i = 0; i < len; ++i) {
    const float e = ELU && t[i] <= 0.f ? std::expm1(t[i]) : t[i];
    out[i] = res ? res[i] + a * e : e;
  }
}
template <bool ELU>
inline void mix_grad_run(float* dt, const float* g, const float* t, float a, int64_t len) {
  for (int64_t i = 0; i < len; ++i) dt[i] = a * g[i] * (ELU && t[i] <= 0.f ? std::exp(t[i]) : 1.f);
}
#endif
}  // namespace lanes

// the c floats of one vertex and batch entry between the two layouts: scalar moves for 3 (the coordinates) or fewer,
// masked vectors for more (the chapter 5 width's last layer, forward alone, 2 threads: a masked store a row 0.24 ms, a
// loop over c 0.17 ms, these 0.13 ms)
inline void copy_row(float* dst, const float* src, int64_t c) {
  if (c == 3) {
    dst[0] = src[0], dst[1] = src[1], dst[2] = src[2];
  } else if (c < 3) {
    for (int64_t q = 0; q < c; ++q) dst[q] = src[q];
  } else {
    lanes::copy_n(dst, src, c);
  }
}

// out = res + a f(t) (f = ELU, or the identity where `elu` is false), or f(t) where res is empty (0 floats); t and
// res of one shape. With `batch_major` (t of 3 dimensions (n, b, c)), out has t's shape laid out as (b, n, c):
// vertex v's b rows of c floats made in a buffer, then stored at (beta n + v) c.
torch::Tensor elu_mix_forward(torch::Tensor t, torch::Tensor res, double a, bool elu, bool batch_major) {
  check(t, "t", at::kFloat, t.dim());
  const bool has_res = res.numel() > 0;
  if (has_res) {
    check(res, "res", at::kFloat, res.dim());
    TORCH_CHECK(res.sizes() == t.sizes(), "res: expected t's shape ", t.sizes(), ", got ", res.sizes());
  }
  const float* tp = t.data_ptr<float>();
  const float* rp = has_res ? res.data_ptr<float>() : nullptr;
  const float af = static_cast<float>(a);
  const auto run = elu ? lanes::mix_run<true> : lanes::mix_run<false>;
  if (batch_major) {
    TORCH_CHECK(t.dim() == 3, "elu_mix: a batch-major result needs t as (n, b, c), got ", t.sizes());
    const int64_t n = t.size(0), b = t.size(1), c = t.size(2), R = b * c;
    auto out = torch::empty_strided({n, b, c}, {c, n * c, 1}, t.options());
    float* op = out.data_ptr<float>();
    fwk_native::parallel_for(0, n, 256, [&](int64_t v0, int64_t v1) {
      std::vector<float> buf(R);
      for (int64_t v = v0; v < v1; ++v) {
        run(buf.data(), tp + v * R, rp ? rp + v * R : nullptr, af, R);
        for (int64_t beta = 0; beta < b; ++beta) copy_row(op + (beta * n + v) * c, buf.data() + beta * c, c);
      }
    });
    return out;
  }
  auto out = torch::empty_like(t);
  float* op = out.data_ptr<float>();
  const int64_t n = t.numel(), V = (n + lanes::L - 1) / lanes::L;
  fwk_native::parallel_for(0, V, 1024, [&](int64_t v0, int64_t v1) {
    const int64_t i0 = v0 * lanes::L, i1 = std::min(n, v1 * lanes::L);
    run(op + i0, tp + i0, rp ? rp + i0 : nullptr, af, i1 - i0);
  });
  return out;
}

// the gradients: dt = a g f'(t) (a: the mix's weight, 1 where there was no res; t unread and may be empty for the
// identity) and, where g is not laid out as t (contiguous), res's gradient g in t's layout (else empty (0,): it is g
// itself). g is read in t's layout or batch-major (the transpose of a contiguous (b, n, c), as elu_mix_forward's
// batch-major result's gradient arrives from the loss), other layouts made contiguous first. Each empty (0,) where
// not asked for.
std::vector<torch::Tensor> elu_mix_backward(torch::Tensor g, torch::Tensor t, double a, bool elu, bool need_t,
                                            bool need_res) {
  TORCH_CHECK(g.scalar_type() == at::kFloat && g.device().is_cpu(), "g: expected float32 on the CPU");
  if (elu) {
    check(t, "t", at::kFloat, t.dim());
    TORCH_CHECK(g.sizes() == t.sizes(), "g: expected t's shape ", t.sizes(), ", got ", g.sizes());
  }
  const bool bm = g.dim() == 3 && !g.is_contiguous() && g.transpose(0, 1).is_contiguous();
  if (!bm) g = g.contiguous();
  auto empty = torch::empty({0}, g.options());
  auto dt = need_t ? torch::empty(g.sizes(), g.options()) : empty;
  auto dres = need_res && bm ? torch::empty(g.sizes(), g.options()) : empty;
  const float* gp = g.data_ptr<float>();
  const float* tp = elu ? t.data_ptr<float>() : nullptr;
  float* dp = need_t ? dt.data_ptr<float>() : nullptr;
  float* rp = dres.numel() ? dres.data_ptr<float>() : nullptr;
  const float af = static_cast<float>(a);
  const auto run = elu ? lanes::mix_grad_run<true> : lanes::mix_grad_run<false>;
  if (bm) {
    const int64_t n = g.size(0), b = g.size(1), c = g.size(2), R = b * c;
    fwk_native::parallel_for(0, n, 256, [&](int64_t v0, int64_t v1) {
      std::vector<float> buf(R);
      for (int64_t v = v0; v < v1; ++v) {
        float* gv = rp ? rp + v * R : buf.data();  // g's rows of vertex v in t's layout
        for (int64_t beta = 0; beta < b; ++beta) copy_row(gv + beta * c, gp + (beta * n + v) * c, c);
        if (dp) run(dp + v * R, gv, tp ? tp + v * R : nullptr, af, R);
      }
    });
  } else if (dp) {
    const int64_t n = g.numel(), V = (n + lanes::L - 1) / lanes::L;
    fwk_native::parallel_for(0, V, 1024, [&](int64_t v0, int64_t v1) {
      const int64_t i0 = v0 * lanes::L, i1 = std::min(n, v1 * lanes::L);
      run(dp + i0, gp + i0, tp ? tp + i0 : nullptr, af, i1 - i0);
    });
  }
  return {dt, dres};
}

#ifdef FWK_VCCONV_LANES
#pragma GCC pop_options
#endif

// whether this build and CPU run the lane kernels (AVX-512F)
bool lanes_supported() {
#ifdef FWK_VCCONV_LANES
  __builtin_cpu_init();
  return __builtin_cpu_supports("avx512f");
#else
  return false;
#endif
}

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
  m.def("lanes_supported", &lanes_supported);
  m.def("elu_mix_forward", &elu_mix_forward);
  m.def("elu_mix_backward", &elu_mix_backward);
  m.def("lanes_forward", &lanes_forward);
  m.def("lanes_backward", &lanes_backward);
  m.def("kernel_lanes_forward", &kernel_lanes_forward);
  m.def("kernel_lanes_backward", &kernel_lanes_backward);
  m.def("kernel_forward", &kernel_forward);
  m.def("kernel_backward", &kernel_backward);
  m.def("tall_forward", &tall_forward);
  m.def("tall_backward", &tall_backward);
  m.def("sum_forward", &sum_forward);
  m.def("sum_backward", &sum_backward);
  m.def("basis_forward", &basis_forward);
  m.def("basis_backward", &basis_backward);
  m.def("weighted_forward", &weighted_forward);
  m.def("norm_weights_forward", &norm_weights_forward);
  m.def("norm_weights_backward", &norm_weights_backward);
  m.def("weighted_backward", &weighted_backward);
}
