// Layer norm over the last dimension (the windowed Transformer's three norms per block), forward and backward.
//
// PyTorch's CPU layer norm costs about as much as a matrix product of the same rows when rows are as short as a
// policy's (32 or 64 units): per-row dispatch and a separate reduction pass for the weight gradients. Here a row is
// one pass forward and one backward, rows in parallel, and the weight and bias gradients are summed per fixed block
// of rows and then over the blocks in order, so that the result does not depend on the number of threads.
//
// y = (x - mean) * rstd * gamma + beta, rstd = 1 / sqrt(var + eps), var the biased variance (as torch.layer_norm).
// x, y, dy, dx: (N, W) contiguous; gamma, beta, dgamma, dbeta: (W); mean, rstd: (N).
#include "common.h"

#include <algorithm>

namespace fastrnn {

constexpr int64_t kRowsPerBlock = 128;  // of the weight-gradient partial sums (fixed: thread-count independent)

template <typename T>
void layer_norm_forward_impl(const T* x, const T* gamma, const T* beta, T eps, T* y, T* mean, T* rstd, int64_t N,
                             int64_t W) {
  at::parallel_for(0, N, 256, [&](int64_t begin, int64_t end) {
    for (int64_t i = begin; i < end; ++i) {
      const T* xi = x + i * W;
      T sum = 0;
      for (int64_t e = 0; e < W; ++e) sum += xi[e];
      const T mu = sum / W;
      T squares = 0;
      for (int64_t e = 0; e < W; ++e) squares += (xi[e] - mu) * (xi[e] - mu);
      const T r = T(1) / std::sqrt(squares / W + eps);
      T* yi = y + i * W;
#pragma omp simd
      for (int64_t e = 0; e < W; ++e) yi[e] = (xi[e] - mu) * r * gamma[e] + beta[e];
      mean[i] = mu;
      rstd[i] = r;
    }
  });
}

template <typename T>
void layer_norm_backward_impl(const T* dy, const T* x, const T* mean, const T* rstd, const T* gamma, T* dx,
                              T* dgamma, T* dbeta, int64_t N, int64_t W) {
  const int64_t blocks = (N + kRowsPerBlock - 1) / kRowsPerBlock;
  std::vector<T> partial(blocks * 2 * W, T(0));  // per block: [d gamma | d beta]
  at::parallel_for(0, blocks, 1, [&](int64_t b0, int64_t b1) {
    for (int64_t blk = b0; blk < b1; ++blk) {
      T* __restrict pg = partial.data() + blk * 2 * W;
      T* __restrict pb = pg + W;
      for (int64_t i = blk * kRowsPerBlock; i < std::min(N, (blk + 1) * kRowsPerBlock); ++i) {
        const T* __restrict xi = x + i * W;
        const T* __restrict gi = dy + i * W;
        const T mu = mean[i], r = rstd[i];
        T sum_g = 0, sum_gx = 0;  // sums over the row of dxhat = dy * gamma and of dxhat * (x - mean)
        for (int64_t e = 0; e < W; ++e) {
          const T g = gi[e] * gamma[e];
          sum_g += g;
          sum_gx += g * (xi[e] - mu);
        }
        const T a = sum_g / W, c = sum_gx * r * r / W;
        T* __restrict di = dx + i * W;
#pragma omp simd
        for (int64_t e = 0; e < W; ++e) {
          const T centred = xi[e] - mu;
          di[e] = r * (gi[e] * gamma[e] - a - centred * c);
          pg[e] += gi[e] * centred * r;
          pb[e] += gi[e];
        }
      }
    }
  });
  std::fill(dgamma, dgamma + W, T(0));
  std::fill(dbeta, dbeta + W, T(0));
  for (int64_t blk = 0; blk < blocks; ++blk) {
    const T* pg = partial.data() + blk * 2 * W;
    for (int64_t e = 0; e < W; ++e) {
      dgamma[e] += pg[e];
      dbeta[e] += pg[W + e];
    }
  }
}

}  // namespace fastrnn

using namespace fastrnn;

void layer_norm_fwd(const at::Tensor& x, const at::Tensor& gamma, const at::Tensor& beta, double eps, at::Tensor& y,
                    at::Tensor& mean, at::Tensor& rstd) {
  check(x, "layer norm: x");
  const int64_t W = x.size(-1), N = x.numel() / std::max<int64_t>(W, 1);
  TORCH_CHECK(gamma.numel() == W && beta.numel() == W && gamma.is_contiguous() && beta.is_contiguous(),
              "layer norm: gamma and beta must be contiguous with the rows' width");
  TORCH_CHECK(y.is_contiguous() && y.numel() == x.numel() && mean.numel() == N && rstd.numel() == N,
              "layer norm: output buffers do not match");
  TORCH_CHECK(gamma.scalar_type() == x.scalar_type() && beta.scalar_type() == x.scalar_type(),
              "layer norm: x, gamma and beta must have one dtype");
  AT_DISPATCH_FLOATING_TYPES(x.scalar_type(), "layer_norm_fwd", [&] {
    layer_norm_forward_impl<scalar_t>(x.data_ptr<scalar_t>(), gamma.data_ptr<scalar_t>(), beta.data_ptr<scalar_t>(),
                                      static_cast<scalar_t>(eps), y.data_ptr<scalar_t>(), mean.data_ptr<scalar_t>(),
                                      rstd.data_ptr<scalar_t>(), N, W);
  });
}

void layer_norm_bwd(const at::Tensor& dy, const at::Tensor& x, const at::Tensor& mean, const at::Tensor& rstd,
                    const at::Tensor& gamma, at::Tensor& dx, at::Tensor& dgamma, at::Tensor& dbeta) {
  check(dy, "layer norm backward: dy");
  check(x, "layer norm backward: x");
  const int64_t W = x.size(-1), N = x.numel() / std::max<int64_t>(W, 1);
  TORCH_CHECK(dy.numel() == x.numel() && dx.is_contiguous() && dx.numel() == x.numel() && mean.numel() == N &&
                  rstd.numel() == N && gamma.numel() == W && dgamma.numel() == W && dbeta.numel() == W,
              "layer norm backward: buffers do not match");
  AT_DISPATCH_FLOATING_TYPES(x.scalar_type(), "layer_norm_bwd", [&] {
    layer_norm_backward_impl<scalar_t>(dy.data_ptr<scalar_t>(), x.data_ptr<scalar_t>(), mean.data_ptr<scalar_t>(),
                                       rstd.data_ptr<scalar_t>(), gamma.data_ptr<scalar_t>(),
                                       dx.data_ptr<scalar_t>(), dgamma.data_ptr<scalar_t>(),
                                       dbeta.data_ptr<scalar_t>(), N, W);
  });
}
