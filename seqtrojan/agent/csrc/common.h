// Helpers shared by the fused recurrent-cell kernels (fast_lstm.cpp: LSTM and peephole LSTM; gru.cpp: GRU):
// the BLAS GEMM, the activations and the argument checks.  See fast_lstm.cpp for the design.
#pragma once

// ATen only (about a third of the compile time of torch/extension.h, which only fast_lstm.cpp needs: it binds
// the module)
#include <ATen/ATen.h>
#include <ATen/Parallel.h>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <vector>

// BLAS (MKL inside libtorch_cpu, LP64 Fortran interface; at::native::cpublas::gemm is not exported).
extern "C" {
void sgemm_(const char* ta, const char* tb, const int* m, const int* n, const int* k, const float* alpha,
            const float* a, const int* lda, const float* b, const int* ldb, const float* beta, float* c,
            const int* ldc);
void dgemm_(const char* ta, const char* tb, const int* m, const int* n, const int* k, const double* alpha,
            const double* a, const int* lda, const double* b, const int* ldb, const double* beta, double* c,
            const int* ldc);
int MKL_Set_Num_Threads_Local(int nt);  // per-thread MKL thread count (0 = back to global setting); C API
// (the lowercase symbol exported by libtorch_cpu is the Fortran interface taking int*)
}

namespace fastrnn {

// column-major C(m x n) = alpha * op(A) op(B) + beta * C
inline void gemm(char ta, char tb, int m, int n, int k, float alpha, const float* a, int lda,
                 const float* b, int ldb, float beta, float* c, int ldc) {
  sgemm_(&ta, &tb, &m, &n, &k, &alpha, a, &lda, b, &ldb, &beta, c, &ldc);
}
inline void gemm(char ta, char tb, int m, int n, int k, double alpha, const double* a, int lda,
                 const double* b, int ldb, double beta, double* c, int ldc) {
  dgemm_(&ta, &tb, &m, &n, &k, &alpha, a, &lda, b, &ldb, &beta, c, &ldc);
}

// ---- activations.  float: inline, vectorisable approximations (no libm calls inside the SIMD loops);
// double (used by gradcheck): std::exp / std::tanh.
inline float fexp(float x) {
  // Cody-Waite range reduction + Cephes degree-6 polynomial: max rel. error ~1e-7 on [-87.3, 88.3]
  x = std::fmin(std::fmax(x, -87.3f), 88.3f);
  const float n = std::nearbyint(x * 1.44269504088896341f);
  float r = std::fma(n, -0.693359375f, x);
  r = std::fma(n, 2.12194440e-4f, r);
  float p = 1.9875691500E-4f;
  p = std::fma(p, r, 1.3981999507E-3f);
  p = std::fma(p, r, 8.3334519073E-3f);
  p = std::fma(p, r, 4.1665795894E-2f);
  p = std::fma(p, r, 1.6666665459E-1f);
  p = std::fma(p, r, 5.0000001201E-1f);
  p = std::fma(p, r * r, r) + 1.0f;
  const int32_t e = (static_cast<int32_t>(n) + 127) << 23;  // 2^n
  float s;
  std::memcpy(&s, &e, 4);
  return p * s;
}
inline float ftanh(float x) {
  // odd rational approximation (Eigen's fast tanh); max abs/rel error ~3e-7 (float tanhf: ~1e-7)
  const float c = 7.90531110763549805f;
  x = std::fmin(std::fmax(x, -c), c);
  const float x2 = x * x;
  float p = -2.76076847742355e-16f;
  p = std::fma(x2, p, 2.00018790482477e-13f);
  p = std::fma(x2, p, -8.60467152213735e-11f);
  p = std::fma(x2, p, 5.12229709037114e-08f);
  p = std::fma(x2, p, 1.48572235717979e-05f);
  p = std::fma(x2, p, 6.37261928875436e-04f);
  p = std::fma(x2, p, 4.89352455891786e-03f);
  p = x * p;
  float q = 1.19825839466702e-06f;
  q = std::fma(x2, q, 1.18534705686654e-04f);
  q = std::fma(x2, q, 2.26843463243900e-03f);
  q = std::fma(x2, q, 4.89352518554385e-03f);
  return p / q;
}
inline float sigm(float x) { return 1.0f / (1.0f + fexp(-x)); }
inline float tanh_(float x) { return ftanh(x); }
inline double sigm(double x) { return 1.0 / (1.0 + std::exp(-x)); }
inline float exp_(float x) { return fexp(x); }  // inline, no libm call inside the loops
inline double exp_(double x) { return std::exp(x); }
inline double tanh_(double x) { return std::tanh(x); }

// y = layer norm of one row x of W (biased variance, as torch.layer_norm); its mean and 1 / std are stored
template <typename T>
inline void norm_row(const T* x, T* y, int64_t W, const T* gamma, const T* beta, T eps, T& mean, T& rstd) {
  T sum = 0;
  for (int64_t e = 0; e < W; ++e) sum += x[e];
  const T mu = sum / W;
  T squares = 0;
  for (int64_t e = 0; e < W; ++e) squares += (x[e] - mu) * (x[e] - mu);
  const T r = T(1) / std::sqrt(squares / W + eps);
#pragma omp simd
  for (int64_t e = 0; e < W; ++e) y[e] = (x[e] - mu) * r * gamma[e] + beta[e];
  mean = mu;
  rstd = r;
}

inline void check(const at::Tensor& t, const char* name) {
  TORCH_CHECK(t.is_contiguous(), name, " must be contiguous");
  TORCH_CHECK(t.device().is_cpu(), name, " must be on CPU");
}

}  // namespace fastrnn

// ---- GRU entry points (gru.cpp), bound to Python in fast_lstm.cpp's PYBIND11_MODULE (one module for all cells)
void gru_fwd_cat(at::Tensor X, at::Tensor M, at::Tensor h0, at::Tensor Wc, at::Tensor XH, at::Tensor S,
                 at::Tensor Hs, int64_t nchunks, c10::optional<at::Tensor> G);
void gru_bwd_cat(at::Tensor S, at::Tensor M, at::Tensor Wc, at::Tensor XH, int64_t I, at::Tensor dHs,
                 c10::optional<at::Tensor> dX, at::Tensor dWparts, at::Tensor dh0, c10::optional<at::Tensor> dZ);
void gru_stack_step(at::Tensor X, at::Tensor M, std::vector<at::Tensor> hs, std::vector<at::Tensor> Wcs,
                    std::vector<at::Tensor> hs_out, int64_t nchunks, c10::optional<at::Tensor> G0);

// ---- band attention of the windowed Transformer (band_attention.cpp), bound in the same module
void band_attention_fwd(const at::Tensor& qkv, const at::Tensor& prefix, const at::Tensor& allowed,
                        const at::Tensor& bias, at::Tensor& out, at::Tensor& probs, double scale);
void band_attention_bwd(const at::Tensor& grad, const at::Tensor& qkv, const at::Tensor& prefix,
                        const at::Tensor& probs, at::Tensor& dqkv, at::Tensor& dprefix, at::Tensor& dscores,
                        double scale);

// ---- bias + residual + layer norm of the windowed Transformer (layer_norm.cpp), bound in the same module
void layer_norm_fwd(at::Tensor& x, const at::Tensor& bias, const c10::optional<at::Tensor>& residual,
                    const at::Tensor& gamma, const at::Tensor& beta, double eps, at::Tensor& y, at::Tensor& mean,
                    at::Tensor& rstd);
void layer_norm_bwd(const at::Tensor& dy, const c10::optional<at::Tensor>& dx_extra, const at::Tensor& x,
                    const at::Tensor& mean, const at::Tensor& rstd, const at::Tensor& gamma, at::Tensor& dx,
                    at::Tensor& dgamma, at::Tensor& dbeta, at::Tensor& dbias);

// ---- a linear layer's bias and a ReLU, in place (bias_relu.cpp), bound in the same module
void bias_relu_fwd(at::Tensor& x, const at::Tensor& bias);
void bias_relu_bwd(const at::Tensor& dy, const at::Tensor& y, at::Tensor& dx, at::Tensor& dbias);

// ---- one no-grad step of a windowed Transformer layer (window_step.cpp), bound in the same module
void window_layer_step(const at::Tensor& x, const at::Tensor& keep, const at::Tensor& cache,
                       const std::vector<at::Tensor>& params, const std::vector<double>& eps, at::Tensor& h_out,
                       at::Tensor& slots_out, int64_t nchunks);

// ---- a linear map that reads only the nonzero entries of its input (sparse_input.cpp), bound in the same module
void sparse_project(const at::Tensor& X, const at::Tensor& Wt, at::Tensor& out);
void sparse_project_grad(const at::Tensor& X, const at::Tensor& dOut, at::Tensor& dWt);
