// Helpers shared by fwk's native kernels (fwk.native; each plugin's native.cpp includes this).
//
// Layout: row-major tensors; BLAS is column-major, so a row-major (r x c) matrix is handed over as
// the column-major (c x r) matrix with leading dimension c, and every product is written for the
// transposes (the comment at each call gives the row-major product it computes).
//
// Scatters into a shared result go to one private accumulator per thread (``ThreadAccumulators``, each zeroed by its
// own thread; ``thread_accumulator`` for a caller's own buffer),
// summed in thread order at the end (``reduce``): no atomics, and the same bits on every run with
// the same thread count, because at::parallel_for splits a range statically.
#pragma once

#include <torch/extension.h>
#include <ATen/Parallel.h>

#include <algorithm>
#include <cstdint>
#include <mutex>
#include <vector>

extern "C" void sgemm_(const char* transa, const char* transb, const int* m, const int* n, const int* k,
                       const float* alpha, const float* a, const int* lda, const float* b, const int* ldb,
                       const float* beta, float* c, const int* ldc);
// MKL's C interface (by value; the lower-case name is its Fortran one, by pointer). Weak: a libtorch
// built with another BLAS does not have it, and then nothing is set.
extern "C" int MKL_Set_Num_Threads_Local(int nt) __attribute__((weak));

// Loops compiled for AVX-512 as well as for the baseline (GCC's target_clones: the CPU's version is picked when the
// library loads); plain -O3 vectorises them for SSE2 only, 4 floats a multiply-add. "avx512f", not "arch=x86-64-v4":
// GCCs before 11 do not know the x86-64-v levels, and then the whole extension would not build.
#if defined(__GNUC__) && defined(__x86_64__) && !defined(__clang__)
#define FWK_CLONES __attribute__((target_clones("avx512f", "default")))
#else
#define FWK_CLONES
#endif

namespace fwk_native {

// One BLAS thread for the calling thread while it lives (MKL's thread-local setting; the previous one
// back after, 0 being "the global one"). Without it, MKL called from the threads of an at::parallel_for
// region runs each small product with torch's thread count: libgomp allows nested teams here (its
// max-active-levels is unlimited), so every per-vertex product forked a team of its own. Measured
// 2026-12-07 (3,089 products of 57 x 16 by 16 x 8, the first vcconv layer's kernel gradients, in one
// region): 1.2-1.9 ms on 1 thread, 3.8-4.4 ms on 2 threads, 1.0 ms on 2 with this guard; with nesting off
// (OMP_MAX_ACTIVE_LEVELS=1) still 2.6 ms on 2 threads.
struct OneBlasThread {
  int prev = 0;
  bool set = false;
  OneBlasThread() {
    if (MKL_Set_Num_Threads_Local) {
      prev = MKL_Set_Num_Threads_Local(1);
      set = true;
    }
  }
  ~OneBlasThread() {
    if (set) MKL_Set_Num_Threads_Local(prev);
  }
  OneBlasThread(const OneBlasThread&) = delete;
  OneBlasThread& operator=(const OneBlasThread&) = delete;
};

// at::parallel_for with one BLAS thread in each of its threads (``OneBlasThread``): every native kernel's
// parallel loop, whether or not its body calls BLAS today.
template <class F>
inline void parallel_for(int64_t begin, int64_t end, int64_t grain, const F& f) {
  at::parallel_for(begin, end, grain, [&](int64_t a, int64_t b) {
    OneBlasThread one;
    f(a, b);
  });
}

// column-major C (m x n) = alpha op(A) op(B) + beta C (MKL's sgemm_, which libtorch exports)
inline void gemm(char ta, char tb, int64_t m, int64_t n, int64_t k, float alpha, const float* a, int64_t lda,
                 const float* b, int64_t ldb, float beta, float* c, int64_t ldc) {
  if (m == 0 || n == 0) return;
  if (k == 0) {
    for (int64_t j = 0; j < n; ++j)
      for (int64_t i = 0; i < m; ++i) c[j * ldc + i] = beta == 0.f ? 0.f : beta * c[j * ldc + i];
    return;
  }
  const int M = (int)m, N = (int)n, K = (int)k, LDA = (int)lda, LDB = (int)ldb, LDC = (int)ldc;
  sgemm_(&ta, &tb, &M, &N, &K, &alpha, a, &LDA, b, &LDB, &beta, c, &LDC);
}

inline void add_row(float* __restrict dst, const float* __restrict src, int64_t n) {
#pragma omp simd
  for (int64_t t = 0; t < n; ++t) dst[t] += src[t];
}

// dst = a src (``first``) or dst += a src, n floats
inline void axpy_row(float* __restrict dst, const float* __restrict src, float a, int64_t n, bool first) {
  if (first) {
#pragma omp simd
    for (int64_t t = 0; t < n; ++t) dst[t] = a * src[t];
  } else {
#pragma omp simd
    for (int64_t t = 0; t < n; ++t) dst[t] += a * src[t];
  }
}

inline void check(const torch::Tensor& t, const char* name, at::ScalarType dtype, int64_t dim) {
  TORCH_CHECK(t.device().is_cpu(), name, ": expected a CPU tensor");
  TORCH_CHECK(t.scalar_type() == dtype, name, ": expected ", dtype, ", got ", t.scalar_type());
  TORCH_CHECK(t.dim() == dim, name, ": expected ", dim, " dimensions, got ", t.dim());
  TORCH_CHECK(t.is_contiguous(), name, ": expected a contiguous tensor");
}

// Checks that passed, remembered while their tensors stay as they were. The kernels check every index they will
// read (in range, offsets ordered, positions distinct) before reading: loops over every slot on every call (the
// chapter 5 width's vcconv training step is 1.01-1.02x faster without them, 2026-12-07), for supports that are the
// same buffers step after step. A passed check is remembered with its arguments and, for each tensor, a weak reference to its
// TensorImpl (a live object; a freed tensor whose address is taken by another no longer matches, its reference has
// expired), its data pointer, element count and version counter (every in-place write through torch bumps it). Not
// seen: writes that bypass torch (through a numpy array or another tensor sharing the memory, or raw pointers); fwk
// makes its index buffers once, each owning its memory (spiral++ copies the memoised spirals it is given), and
// writes them only through torch; tensors read from received files are fresh objects, checked on first use. Sets whose tensors are gone are forgotten when the next is added, and at most CAPACITY are
// remembered (the oldest forgotten first).
class PassedChecks {
 public:
  static constexpr size_t CAPACITY = 512;

  static PassedChecks& instance() {
    static PassedChecks one;
    return one;
  }

  bool contains(std::initializer_list<const torch::Tensor*> ts, std::initializer_list<int64_t> args) {
    std::lock_guard<std::mutex> lock(mu_);
    for (const Entry& e : entries_)
      if (matches(e, ts, args)) return true;
    return false;
  }

  void add(std::initializer_list<const torch::Tensor*> ts, std::initializer_list<int64_t> args) {
    Entry e;
    for (const torch::Tensor* t : ts) {
      e.refs.emplace_back(t->getIntrusivePtr());
      e.state.push_back(state_of(*t));
    }
    e.args.assign(args.begin(), args.end());
    std::lock_guard<std::mutex> lock(mu_);
    // entries whose tensors are gone first (a fresh index each call, as a pooling's selected rows, leaves one a call)
    entries_.erase(std::remove_if(entries_.begin(), entries_.end(),
                                  [](const Entry& x) {
                                    return std::any_of(x.refs.begin(), x.refs.end(),
                                                       [](const Weak& r) { return r.expired(); });
                                  }),
                   entries_.end());
    if (entries_.size() >= CAPACITY) entries_.erase(entries_.begin());
    entries_.push_back(std::move(e));
  }

 private:
  using Weak = c10::weak_intrusive_ptr<c10::TensorImpl, c10::UndefinedTensorImpl>;
  struct State {
    intptr_t data;
    int64_t numel, version;
    bool operator==(const State& o) const { return data == o.data && numel == o.numel && version == o.version; }
  };
  static State state_of(const torch::Tensor& t) {
    return {reinterpret_cast<intptr_t>(t.data_ptr()), t.numel(), int64_t(t._version())};
  }
  struct Entry {
    std::vector<Weak> refs;
    std::vector<State> state;
    std::vector<int64_t> args;
  };

  static bool matches(const Entry& e, std::initializer_list<const torch::Tensor*> ts,
                      std::initializer_list<int64_t> args) {
    if (e.refs.size() != ts.size() || !std::equal(args.begin(), args.end(), e.args.begin(), e.args.end())) return false;
    size_t k = 0;
    for (const torch::Tensor* t : ts) {
      if (e.refs[k].expired() || e.refs[k]._unsafe_get_target() != t->unsafeGetTensorImpl()) return false;
      if (!(e.state[k] == state_of(*t))) return false;
      ++k;
    }
    return true;
  }

  std::mutex mu_;
  std::vector<Entry> entries_;
};

// what a remembered check was (PassedChecks' first argument), so that one kind's pass does not stand for another's
enum CheckKind : int64_t { RANGE = 1, CSR = 2, DISTINCT = 3 };

// every entry of an int64 tensor in [0, n)
inline void check_range(const torch::Tensor& idx, const char* name, int64_t n) {
  check(idx, name, at::kLong, idx.dim());
  if (PassedChecks::instance().contains({&idx}, {RANGE, n})) return;
  const int64_t* s = idx.data_ptr<int64_t>();
  for (int64_t t = 0; t < idx.numel(); ++t) TORCH_CHECK(s[t] >= 0 && s[t] < n, name, ": entry out of range");
  PassedChecks::instance().add({&idx}, {RANGE, n});
}

// every entry of an int64 tensor in [0, n), none twice (positions a kernel writes in place)
inline void check_distinct(const torch::Tensor& idx, const char* name, int64_t n) {
  check(idx, name, at::kLong, 1);
  if (PassedChecks::instance().contains({&idx}, {DISTINCT, n})) return;
  const int64_t* p = idx.data_ptr<int64_t>();
  std::vector<char> seen(n, 0);
  for (int64_t t = 0; t < idx.numel(); ++t) {
    TORCH_CHECK(p[t] >= 0 && p[t] < n, name, ": entry out of range");
    TORCH_CHECK(!seen[p[t]], name, ": a row is named twice");
    seen[p[t]] = 1;
  }
  PassedChecks::instance().add({&idx}, {DISTINCT, n});
}

// a CSR structure: offs (n_rows + 1) running from 0 to idx's length without decreasing, every idx entry in
// [0, n_target)
inline void check_csr(const torch::Tensor& offs, const torch::Tensor& idx, int64_t n_rows, int64_t n_target,
                      const char* offs_name = "offs", const char* idx_name = "index") {
  check(offs, offs_name, at::kLong, 1);
  check(idx, idx_name, at::kLong, 1);
  TORCH_CHECK(n_rows >= 0 && offs.size(0) == n_rows + 1, offs_name, ": expected ", n_rows + 1, " entries (at least 1)");
  if (PassedChecks::instance().contains({&offs, &idx}, {CSR, n_rows, n_target})) return;
  const int64_t* o = offs.data_ptr<int64_t>();
  TORCH_CHECK(o[0] == 0 && o[n_rows] == idx.size(0), offs_name, ": must run from 0 to the slot count");
  for (int64_t i = 0; i < n_rows; ++i) TORCH_CHECK(o[i + 1] >= o[i], offs_name, ": must not decrease");
  check_range(idx, idx_name, n_target);
  PassedChecks::instance().add({&offs, &idx}, {CSR, n_rows, n_target});
}

// this thread's accumulator in acc (nt, size...): at::parallel_for splits the range statically
inline float* thread_accumulator(float* acc, int nt, int64_t size) {
  const int tid = at::get_thread_num();
  TORCH_CHECK(tid < nt, "more threads than accumulators");
  return acc + tid * size;
}

// Per-thread accumulators (nt, shape...) zeroed by their own threads: torch::empty, and each thread zeroes its
// accumulator as its part of the parallel loop starts (``mine``), in its own cache, instead of a fill of the whole
// tensor beforehand (a pass and a parallel region of their own: 0.06-0.15 ms each for the chapter 5 width's
// largest, 2026-12-08). ``done`` (after the loop) zeroes those of threads given no part (at::parallel_for gives a short
// range fewer threads) and returns the (nt, shape...) tensor, for ``reduce`` or a kernel's own sum.
class ThreadAccumulators {
 public:
  ThreadAccumulators(std::vector<int64_t> shape, const torch::TensorOptions& options)
      : nt_(at::get_num_threads()), zeroed_(nt_, 0) {
    size_ = 1;
    for (int64_t d : shape) size_ *= d;
    shape.insert(shape.begin(), nt_);
    acc_ = torch::empty(shape, options);
    p_ = acc_.data_ptr<float>();
  }
  // this thread's accumulator, zeroed on its first call in this thread (called inside the parallel loop)
  float* mine() {
    float* m = thread_accumulator(p_, nt_, size_);
    char& z = zeroed_[at::get_thread_num()];
    if (!z) {
      std::fill(m, m + size_, 0.f);
      z = 1;
    }
    return m;
  }
  // after the loop: every accumulator zeroed or written; the (nt, shape...) tensor
  const torch::Tensor& done() {
    for (int t = 0; t < nt_; ++t)
      if (!zeroed_[t]) {
        std::fill(p_ + t * size_, p_ + (t + 1) * size_, 0.f);
        zeroed_[t] = 1;
      }
    return acc_;
  }

 private:
  int nt_;
  std::vector<char> zeroed_;
  int64_t size_;
  torch::Tensor acc_;
  float* p_;
};

// floats [i0, i1) of the sum of nt accumulators of n floats each (acc: nt x n), added in thread order
FWK_CLONES static void add_accumulators(float* __restrict out, const float* __restrict acc, int64_t nt, int64_t n,
                                        int64_t i0, int64_t i1) {
#pragma omp simd
  for (int64_t i = i0; i < i1; ++i) out[i] = acc[i] + acc[n + i];
  for (int64_t t = 2; t < nt; ++t) {
#pragma omp simd
    for (int64_t i = i0; i < i1; ++i) out[i] += acc[t * n + i];
  }
}

// the per-thread accumulators (nt, ...) summed in thread order: ((a_0 + a_1) + a_2) ..., as torch's sum over
// dimension 0 adds them (the same floats; a sum of zeros may keep the sign of -0), in one parallel pass. torch's sum
// took 0.07-0.18 ms for the (2, n, b c) accumulators of the chapter 5 width's sum-order gradients (2026-12-08)
inline torch::Tensor reduce(const torch::Tensor& acc) {
  if (acc.size(0) == 1) return acc[0];
  TORCH_CHECK(acc.scalar_type() == at::kFloat && acc.is_contiguous(), "reduce: expected contiguous float32");
  const int64_t nt = acc.size(0), n = acc.numel() / nt;
  auto out = torch::empty(acc.sizes().slice(1), acc.options());
  const float* a = acc.data_ptr<float>();
  float* o = out.data_ptr<float>();
  at::parallel_for(0, n, 16384, [&](int64_t i0, int64_t i1) { add_accumulators(o, a, nt, n, i0, i1); });
  return out;
}

// Asks the cache for rows that a kernel will read soon: base + idx[s] * stride, row_bytes each, for the slots
// [s0, s1). The kernels gather rows scattered over megabytes (a vertex's neighbours' rows, its slots' coefficient
// rows); the next vertex's rows, asked for while this vertex is computed, are in cache when it starts. Only a row's
// first PREFETCH_ROW_BYTES are asked for: the hardware's own prefetcher follows a row once it is read, and whole
// rows of the wide layers (8 KB a row, 75 rows a vertex) would push this vertex's data out of cache. RW: 1 where the
// rows will be written. A hint only: no effect on any result.
constexpr int64_t PREFETCH_ROW_BYTES = 256;

template <int RW = 0>
inline void prefetch_rows(const float* base, const int64_t* idx, int64_t s0, int64_t s1, int64_t stride,
                          int64_t row_bytes) {
#if defined(__GNUC__)
  row_bytes = std::min(row_bytes, PREFETCH_ROW_BYTES);
  for (int64_t s = s0; s < s1; ++s) {
    const uintptr_t r = reinterpret_cast<uintptr_t>(base + idx[s] * stride);
    for (uintptr_t at = r & ~uintptr_t(63); at < r + row_bytes; at += 64)
      __builtin_prefetch(reinterpret_cast<const void*>(at), RW, 3);
  }
#endif
}

// Asks the level-2 cache for a contiguous block a kernel reads next (e.g. the next vertex's dT_i, 18 KB at the
// chapter 5 width's second layer, read once from memory). A hint only: no effect on any result.
inline void prefetch_block(const float* p, int64_t n) {
#if defined(__GNUC__)
  const uintptr_t r = reinterpret_cast<uintptr_t>(p), end = r + static_cast<uintptr_t>(n) * sizeof(float);
  for (uintptr_t at = r & ~uintptr_t(63); at < end; at += 64) __builtin_prefetch(reinterpret_cast<const void*>(at), 0, 2);
#endif
}

// Row-major products with a narrow result. BLAS vectorises along the first dimension of its
// (column-major) result; a row-major C (r x N) handed over as its transpose puts N first, which for
// N < 16 (an output of 3-9 channels) leaves most of each vector register empty. There, C is
// computed column-major (r first) into ``tmp`` and transposed back while in cache.
constexpr int64_t NARROW = 16;

// row-major C (r x N) = A (r x K) op(B) + beta C: op(B) = B (row-major K x N) or, with ``bt``, B^T for
// B row-major (N x K). ``tmp``: scratch, resized as needed.
inline void rows_gemm(int64_t r, int64_t N, int64_t K, const float* a, int64_t lda, const float* b, bool bt,
                      float beta, float* c, int64_t ldc, std::vector<float>& tmp) {
  if (N >= NARROW) {  // column-major C^T (N x r) = op(B)^T (N x K) A^T (K x r)
    gemm(bt ? 'T' : 'N', 'N', N, r, K, 1.f, b, bt ? K : N, a, lda, beta, c, ldc);
    return;
  }
  if (tmp.size() < size_t(r * N)) tmp.resize(r * N);
  // column-major tmp (r x N) = A (r x K) op(B) (K x N)
  gemm('T', bt ? 'N' : 'T', r, N, K, 1.f, a, lda, b, bt ? K : N, 0.f, tmp.data(), r);
  for (int64_t i = 0; i < r; ++i)
    for (int64_t n = 0; n < N; ++n) c[i * ldc + n] = tmp[n * r + i] + (beta == 0.f ? 0.f : beta * c[i * ldc + n]);
}

// Tall products: (R x K) @ (K x N) with R in the thousands to hundreds of thousands and K, N small
// (vcconv's products with its basis: 49,424 x 8 @ 8 x 105 in the chapter 5 width's last layer;
// spiral++'s up-sampling products). MKL runs these shapes at 6-25 GFLOP/s on 2 threads, and 2-6x
// faster or slower by orientation alone (A^T dC (105 x 8) took 13 ms, (dC^T A)^T 2 ms); cut into
// blocks of rows that stay in cache, one single-threaded BLAS call per block (``rows_gemm``),
// blocks in parallel, they run at 40-60. A block's rows fit about 128 KB of A's and C's floats.
inline int64_t tall_block_rows(int64_t K, int64_t N) {
  return std::max<int64_t>(8, int64_t(32768) / std::max<int64_t>(K + N, 1));
}

// row-major C (R x N) = A (R x K) op(B) + bias (N; none when null), or, with ``accumulate`` (and no bias),
// C += A op(B); op(B) as in rows_gemm. Every row block is one BLAS call and the blocks do not depend on
// the thread count: the same bits on any number of threads.
inline void tall_mm(const float* a, const float* b, bool bt, const float* bias, float* c, int64_t R, int64_t K,
                    int64_t N, bool accumulate = false) {
  TORCH_CHECK(!(bias && accumulate), "tall_mm: a bias or accumulate, not both");
  const int64_t rb = tall_block_rows(K, N);
  parallel_for(0, (R + rb - 1) / rb, 1, [&](int64_t q0, int64_t q1) {
    std::vector<float> tmp;
    for (int64_t q = q0; q < q1; ++q) {
      const int64_t r0 = q * rb, r = std::min(rb, R - r0);
      float* cb = c + r0 * N;
      if (bias)
        for (int64_t i = 0; i < r; ++i) std::copy(bias, bias + N, cb + i * N);
      rows_gemm(r, N, K, a + r0 * K, K, b, bt, bias || accumulate ? 1.f : 0.f, cb, N, tmp);
    }
  });
}

// row-major D (K x N) = A^T (K x R) C (R x N): each thread sums its row blocks' products (in its
// accumulator, ``ThreadAccumulators``), and the sums are added in thread order.
inline torch::Tensor tall_tn(const float* a, const float* c, int64_t R, int64_t K, int64_t N,
                             const torch::TensorOptions& options) {
  const int64_t rb = tall_block_rows(K, N);
  ThreadAccumulators acc({K, N}, options);  // K x N, or N x K when N < K (below)
  parallel_for(0, (R + rb - 1) / rb, 1, [&](int64_t q0, int64_t q1) {
    float* mine = acc.mine();
    for (int64_t q = q0; q < q1; ++q) {
      const int64_t r0 = q * rb, r = std::min(rb, R - r0);
      if (N >= K)  // column-major D^T (N x K) += C_b^T (N x r) A_b (r x K)
        gemm('N', 'T', N, K, r, 1.f, c + r0 * N, N, a + r0 * K, K, 1.f, mine, N);
      else  // the long side first again: column-major D (K x N) += A_b^T (K x r) C_b (r x N)
        gemm('N', 'T', K, N, r, 1.f, a + r0 * K, K, c + r0 * N, N, 1.f, mine, K);
    }
  });
  auto d = reduce(acc.done());
  return N >= K ? d : d.reshape({N, K}).t().contiguous();
}

}  // namespace fwk_native
