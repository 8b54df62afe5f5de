// A linear layer's bias, the residual add and the layer norm after it (the windowed Transformer's three norms per
// block), forward and backward.
//
// PyTorch's CPU layer norm costs about as much as a matrix product of the same rows when rows are as short as a
// policy's (32 or 64 units): per-row dispatch and a separate reduction pass for the weight gradients. Here a row is
// one pass forward and one backward, rows in parallel, and the weight and bias gradients are summed per fixed block
// of rows and then over the blocks in order, so that the result does not depend on the number of threads.
//
// x = g + bias (+ residual), written over g (g a linear layer's product without its bias), and y = layer norm of x:
// y = (x - mean) * rstd * gamma + beta, rstd = 1 / sqrt(var + eps), var the biased variance (as torch.layer_norm).
// Backward, x's gradient is the norm's plus the one x gets from its other uses (dx_extra), and the bias gradient is
// its column sum. This saves the bias copy of a linear layer, the residual add and, backward, the gradient sums and
// the bias reduction. x, y, dy, dx: (N, W) contiguous; bias, gamma, beta and their gradients: (W); mean, rstd: (N).
#include "common.h"

#include <algorithm>

namespace fastrnn {

constexpr int64_t kRowsPerBlock = 128;  // of the weight-gradient partial sums (fixed: thread-count independent)

// x = x + bias (+ residual) in place first; then y = layer norm of x
template <typename T>
void layer_norm_forward_impl(T* x, const T* bias, const T* residual, const T* gamma, const T* beta, T eps, T* y,
                             T* mean, T* rstd, int64_t N, int64_t W) {
  at::parallel_for(0, N, 256, [&](int64_t begin, int64_t end) {
    for (int64_t i = begin; i < end; ++i) {
      T* __restrict xi = x + i * W;
      if (residual) {
        const T* __restrict ri = residual + i * W;
#pragma omp simd
        for (int64_t e = 0; e < W; ++e) xi[e] += bias[e] + ri[e];
      } else {
#pragma omp simd
        for (int64_t e = 0; e < W; ++e) xi[e] += bias[e];
      }
      norm_row(xi, y + i * W, W, gamma, beta, eps, mean[i], rstd[i]);
    }
  });
}

// dx = the norm's input gradient (+ dx_extra where given); dbias = column sums of dx
template <typename T>
void layer_norm_backward_impl(const T* dy, const T* dx_extra, const T* x, const T* mean, const T* rstd,
                              const T* gamma, T* dx, T* dgamma, T* dbeta, T* dbias, int64_t N, int64_t W) {
  const int64_t blocks = (N + kRowsPerBlock - 1) / kRowsPerBlock;
  std::vector<T> partial(blocks * 3 * W, T(0));  // per block: [d gamma | d beta | d bias]
  at::parallel_for(0, blocks, 1, [&](int64_t b0, int64_t b1) {
    for (int64_t blk = b0; blk < b1; ++blk) {
      T* __restrict pg = partial.data() + blk * 3 * W;
      T* __restrict pb = pg + W;
      T* __restrict pbias = pg + 2 * W;
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
        if (dx_extra) {
          const T* __restrict ei = dx_extra + i * W;
#pragma omp simd
          for (int64_t e = 0; e < W; ++e) di[e] += ei[e];
        }
#pragma omp simd
        for (int64_t e = 0; e < W; ++e) pbias[e] += di[e];
      }
    }
  });
  std::fill(dgamma, dgamma + W, T(0));
  std::fill(dbeta, dbeta + W, T(0));
  std::fill(dbias, dbias + W, T(0));
  for (int64_t blk = 0; blk < blocks; ++blk) {
    const T* pg = partial.data() + blk * 3 * W;
    for (int64_t e = 0; e < W; ++e) {
      dgamma[e] += pg[e];
      dbeta[e] += pg[W + e];
      dbias[e] += pg[2 * W + e];
    }
  }
}

}  // namespace fastrnn

using namespace fastrnn;

namespace {

int64_t rows_of(const at::Tensor& x) { return x.numel() / std::max<int64_t>(x.size(-1), 1); }

void check_vector(const c10::optional<at::Tensor>& t, int64_t W, const at::Tensor& x, const char* what) {
  if (!t) return;
  TORCH_CHECK(t->is_contiguous() && t->numel() == W && t->scalar_type() == x.scalar_type(), "layer norm: ", what,
              " must be a contiguous vector of the rows' width and dtype");
}

void check_like(const c10::optional<at::Tensor>& t, const at::Tensor& x, const char* what) {
  if (!t) return;
  TORCH_CHECK(t->is_contiguous() && t->numel() == x.numel() && t->scalar_type() == x.scalar_type(), "layer norm: ",
              what, " must be contiguous and match x");
}

template <typename T>
T* ptr(const c10::optional<at::Tensor>& t) {
  return t ? t->data_ptr<T>() : nullptr;
}

}  // namespace

// x = x + bias (+ residual) in place; y = layer norm of x
void layer_norm_fwd(at::Tensor& x, const at::Tensor& bias, const c10::optional<at::Tensor>& residual,
                    const at::Tensor& gamma, const at::Tensor& beta, double eps, at::Tensor& y, at::Tensor& mean,
                    at::Tensor& rstd) {
  check(x, "layer norm: x");
  const int64_t W = x.size(-1), N = rows_of(x);
  check_vector(gamma, W, x, "gamma");
  check_vector(beta, W, x, "beta");
  check_vector(bias, W, x, "bias");
  check_like(residual, x, "the residual");
  TORCH_CHECK(y.is_contiguous() && y.numel() == x.numel() && mean.numel() == N && rstd.numel() == N,
              "layer norm: output buffers do not match");
  AT_DISPATCH_FLOATING_TYPES(x.scalar_type(), "layer_norm_fwd", [&] {
    layer_norm_forward_impl<scalar_t>(x.data_ptr<scalar_t>(), bias.data_ptr<scalar_t>(), ptr<scalar_t>(residual),
                                      gamma.data_ptr<scalar_t>(), beta.data_ptr<scalar_t>(),
                                      static_cast<scalar_t>(eps), y.data_ptr<scalar_t>(), mean.data_ptr<scalar_t>(),
                                      rstd.data_ptr<scalar_t>(), N, W);
  });
}

// dx = the norm's input gradient (+ dx_extra); dbias = column sums of dx
void layer_norm_bwd(const at::Tensor& dy, const c10::optional<at::Tensor>& dx_extra, const at::Tensor& x,
                    const at::Tensor& mean, const at::Tensor& rstd, const at::Tensor& gamma, at::Tensor& dx,
                    at::Tensor& dgamma, at::Tensor& dbeta, at::Tensor& dbias) {
  check(dy, "layer norm backward: dy");
  check(x, "layer norm backward: x");
  const int64_t W = x.size(-1), N = rows_of(x);
  check_like(dx_extra, x, "the extra gradient");
  check_vector(gamma, W, x, "gamma");
  check_vector(dgamma, W, x, "d gamma");
  check_vector(dbeta, W, x, "d beta");
  check_vector(dbias, W, x, "d bias");
  TORCH_CHECK(dy.numel() == x.numel() && dx.is_contiguous() && dx.numel() == x.numel() && mean.numel() == N &&
                  rstd.numel() == N,
              "layer norm backward: buffers do not match");
  AT_DISPATCH_FLOATING_TYPES(x.scalar_type(), "layer_norm_bwd", [&] {
    layer_norm_backward_impl<scalar_t>(dy.data_ptr<scalar_t>(), ptr<scalar_t>(dx_extra), x.data_ptr<scalar_t>(),
                                       mean.data_ptr<scalar_t>(), rstd.data_ptr<scalar_t>(),
                                       gamma.data_ptr<scalar_t>(), dx.data_ptr<scalar_t>(),
                                       dgamma.data_ptr<scalar_t>(), dbeta.data_ptr<scalar_t>(),
                                       dbias.data_ptr<scalar_t>(), N, W);
  });
}
