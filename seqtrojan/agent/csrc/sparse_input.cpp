// A linear map of a mostly-zero input (one-hot observations such as MiniGrid's view: 500 numbers, 75 of them 1)
// that reads only the nonzero entries: forward out = X W^T and the weight gradient dW^T = X^T dOut.
// The dense product costs N * I * G multiply-adds whatever X holds; these cost N * I reads plus nnz * G.
//   X (N, I) dense input (no gradient is computed for it), Wt (I, G) = W^T contiguous, out (N, G),
//   dOut (N, G), dWt (I, G).
// Both are deterministic whatever the thread count: the forward splits rows (each row is summed over its
// nonzero entries in column order), the gradient splits the I rows of dWt, each summed over X's rows in order.
#include "common.h"

#include <algorithm>

namespace fastrnn {

namespace {

// acc[0..n) += v * w[0..n).  A full block (n == kBlock) of floats is summed in eight 8-wide vector registers
// (GCC/Clang vector extensions): written as a plain loop over a stack array, the compiler loads and stores the
// accumulator for every product, which made the sparse product no faster than the dense GEMM it replaces.
constexpr int64_t kBlock = 64;

template <typename T>
inline void add_scaled(T* __restrict acc, const T* __restrict w, T v, int64_t n) {
  for (int64_t e = 0; e < n; ++e) acc[e] += v * w[e];
}

typedef float float8 __attribute__((vector_size(32)));

// sum_k vals[k] * rows[k][0..kBlock) into out[0..kBlock), for float: the accumulators stay in registers
inline void block_sum(const float* const* rows, const float* vals, int64_t count, float* out) {
  float8 a0 = {}, a1 = {}, a2 = {}, a3 = {}, a4 = {}, a5 = {}, a6 = {}, a7 = {};
  for (int64_t k = 0; k < count; ++k) {
    const float* w = rows[k];
    float8 v;
    for (int q = 0; q < 8; ++q) v[q] = vals[k];
    float8 w0, w1, w2, w3, w4, w5, w6, w7;
    std::memcpy(&w0, w, 32); std::memcpy(&w1, w + 8, 32); std::memcpy(&w2, w + 16, 32);
    std::memcpy(&w3, w + 24, 32); std::memcpy(&w4, w + 32, 32); std::memcpy(&w5, w + 40, 32);
    std::memcpy(&w6, w + 48, 32); std::memcpy(&w7, w + 56, 32);
    a0 += v * w0; a1 += v * w1; a2 += v * w2; a3 += v * w3;
    a4 += v * w4; a5 += v * w5; a6 += v * w6; a7 += v * w7;
  }
  std::memcpy(out, &a0, 32); std::memcpy(out + 8, &a1, 32); std::memcpy(out + 16, &a2, 32);
  std::memcpy(out + 24, &a3, 32); std::memcpy(out + 32, &a4, 32); std::memcpy(out + 40, &a5, 32);
  std::memcpy(out + 48, &a6, 32); std::memcpy(out + 56, &a7, 32);
}

// the same for double (the gradient checks' dtype): plain loops
inline void block_sum(const double* const* rows, const double* vals, int64_t count, double* out) {
  std::fill(out, out + kBlock, 0.0);
  for (int64_t k = 0; k < count; ++k) add_scaled(out, rows[k], vals[k], kBlock);
}

// out[0..n) = sum_k vals[k] * rows[k][0..n), any n <= kBlock
template <typename T>
inline void gather_sum(const T* const* rows, const T* vals, int64_t count, int64_t n, T* out) {
  if (n == kBlock) {
    block_sum(rows, vals, count, out);
    return;
  }
  std::fill(out, out + n, T(0));
  for (int64_t k = 0; k < count; ++k) add_scaled(out, rows[k], vals[k], n);
}

// out rows: each row's nonzero entries (in column order) gathered once, then per block of kBlock outputs a sum
// held in registers over those entries' rows of Wt (one load per product, one store per output)
template <typename T>
void project_impl(const T* x, const T* wt, T* out, int64_t N, int64_t I, int64_t G) {
  at::parallel_for(0, N, 16, [&](int64_t r0, int64_t r1) {
    std::vector<const T*> rows(I);
    std::vector<T> vals(I);
    for (int64_t r = r0; r < r1; ++r) {
      const T* xr = x + r * I;
      int64_t nnz = 0;
      for (int64_t j = 0; j < I; ++j) {  // branch-free: a random one-hot pattern defeats branch prediction
        rows[nnz] = wt + j * G;
        vals[nnz] = xr[j];
        nnz += xr[j] != T(0);
      }
      for (int64_t e0 = 0; e0 < G; e0 += kBlock) {
        for (int64_t k = 0; k < nnz; ++k) rows[k] += (e0 ? kBlock : 0);
        gather_sum(rows.data(), vals.data(), nnz, std::min(kBlock, G - e0), out + r * G + e0);
      }
    }
  });
}

// dWt rows (one per input column j): the rows of X where column j is nonzero are listed in row order (a counting
// sort), then per block of kBlock outputs a sum held in registers over those rows of dOut; columns split among
// threads, each element summed in row order whatever the thread count
template <typename T>
void project_grad_impl(const T* x, const T* dout, T* dwt, int64_t N, int64_t I, int64_t G) {
  // X's nonzero entries row by row, then regrouped by column in row order (a counting sort). The writes are
  // branch-free, as in project_impl: a zero entry's write lands where the next nonzero one (or the slack slot)
  // goes, rows being filled in order.
  std::vector<int64_t> row_starts(N + 1, 0);
  for (int64_t r = 0; r < N; ++r) {
    const T* xr = x + r * I;
    int64_t count = 0;
    for (int64_t j = 0; j < I; ++j) count += xr[j] != T(0);
    row_starts[r + 1] = row_starts[r] + count;
  }
  const int64_t nnz = row_starts[N];
  std::vector<int32_t> csr_cols(nnz + 1);
  std::vector<T> csr_vals(nnz + 1);
  std::vector<int64_t> starts(I + 1, 0);
  for (int64_t r = 0, k = 0; r < N; ++r) {
    const T* xr = x + r * I;
    for (int64_t j = 0; j < I; ++j) {
      csr_cols[k] = (int32_t)j;
      csr_vals[k] = xr[j];
      k += xr[j] != T(0);
    }
  }
  for (int64_t k = 0; k < nnz; ++k) ++starts[csr_cols[k] + 1];
  for (int64_t j = 0; j < I; ++j) starts[j + 1] += starts[j];
  std::vector<int64_t> rows(nnz), next(starts.begin(), starts.end() - 1);
  std::vector<T> vals(nnz);
  for (int64_t r = 0; r < N; ++r) {
    for (int64_t k = row_starts[r]; k < row_starts[r + 1]; ++k) {
      const int64_t slot = next[csr_cols[k]]++;
      rows[slot] = r;
      vals[slot] = csr_vals[k];
    }
  }
  at::parallel_for(0, I, 8, [&](int64_t j0, int64_t j1) {
    std::vector<const T*> src;
    for (int64_t j = j0; j < j1; ++j) {
      const int64_t count = starts[j + 1] - starts[j];
      src.resize(count);
      for (int64_t e0 = 0; e0 < G; e0 += kBlock) {
        for (int64_t k = 0; k < count; ++k) src[k] = dout + rows[starts[j] + k] * G + e0;
        gather_sum(src.data(), vals.data() + starts[j], count, std::min(kBlock, G - e0), dwt + j * G + e0);
      }
    }
  });
}

void check_shapes(const at::Tensor& X, const at::Tensor& A, const at::Tensor& B, const char* a, const char* b) {
  check(X, "X");
  check(A, a);
  check(B, b);
  TORCH_CHECK(X.dim() == 2 && A.dim() == 2 && B.dim() == 2, "X, ", a, " and ", b, " must be matrices");
  TORCH_CHECK(A.scalar_type() == X.scalar_type() && B.scalar_type() == X.scalar_type(), "dtype mismatch");
}

}  // namespace

}  // namespace fastrnn

using namespace fastrnn;

void sparse_project(const at::Tensor& X, const at::Tensor& Wt, at::Tensor& out) {
  check_shapes(X, Wt, out, "Wt", "out");
  const int64_t N = X.size(0), I = X.size(1), G = Wt.size(1);
  TORCH_CHECK(Wt.size(0) == I && out.size(0) == N && out.size(1) == G, "Wt must be (I, G) and out (N, G)");
  AT_DISPATCH_FLOATING_TYPES(X.scalar_type(), "sparse_project", [&] {
    project_impl<scalar_t>(X.data_ptr<scalar_t>(), Wt.data_ptr<scalar_t>(), out.data_ptr<scalar_t>(), N, I, G);
  });
}

void sparse_project_grad(const at::Tensor& X, const at::Tensor& dOut, at::Tensor& dWt) {
  check_shapes(X, dOut, dWt, "dOut", "dWt");
  const int64_t N = X.size(0), I = X.size(1), G = dOut.size(1);
  TORCH_CHECK(dOut.size(0) == N && dWt.size(0) == I && dWt.size(1) == G, "dOut must be (N, G) and dWt (I, G)");
  AT_DISPATCH_FLOATING_TYPES(X.scalar_type(), "sparse_project_grad", [&] {
    project_grad_impl<scalar_t>(X.data_ptr<scalar_t>(), dOut.data_ptr<scalar_t>(), dWt.data_ptr<scalar_t>(), N,
                                I, G);
  });
}
