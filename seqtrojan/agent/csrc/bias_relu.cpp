// A linear layer's bias and a ReLU on its matrix product, in place, and the backward with the bias gradient
// (the windowed Transformer's MLP, cells.py): one pass each way instead of PyTorch's bias copy, ReLU, ReLU backward
// and bias reduction. The bias gradient is summed per fixed block of rows, then over the blocks in order (the
// result does not depend on the number of threads). x, y, dy, dx: (N, W) contiguous; bias, dbias: (W).
#include "common.h"

#include <algorithm>

namespace fastrnn {

constexpr int64_t kReluRowsPerBlock = 128;

template <typename T>
void bias_relu_forward_impl(T* x, const T* bias, int64_t N, int64_t W) {
  at::parallel_for(0, N, 256, [&](int64_t begin, int64_t end) {
    for (int64_t i = begin; i < end; ++i) {
      T* __restrict xi = x + i * W;
#pragma omp simd
      for (int64_t e = 0; e < W; ++e) xi[e] = std::max(xi[e] + bias[e], T(0));
    }
  });
}

template <typename T>
void bias_relu_backward_impl(const T* dy, const T* y, T* dx, T* dbias, int64_t N, int64_t W) {
  const int64_t blocks = (N + kReluRowsPerBlock - 1) / kReluRowsPerBlock;
  std::vector<T> partial(blocks * W, T(0));
  at::parallel_for(0, blocks, 1, [&](int64_t b0, int64_t b1) {
    for (int64_t blk = b0; blk < b1; ++blk) {
      T* __restrict pb = partial.data() + blk * W;
      for (int64_t i = blk * kReluRowsPerBlock; i < std::min(N, (blk + 1) * kReluRowsPerBlock); ++i) {
        const T* __restrict gi = dy + i * W;
        const T* __restrict yi = y + i * W;
        T* __restrict di = dx + i * W;
#pragma omp simd
        for (int64_t e = 0; e < W; ++e) {
          di[e] = yi[e] > T(0) ? gi[e] : T(0);
          pb[e] += di[e];
        }
      }
    }
  });
  std::fill(dbias, dbias + W, T(0));
  for (int64_t blk = 0; blk < blocks; ++blk)
    for (int64_t e = 0; e < W; ++e) dbias[e] += partial[blk * W + e];
}

}  // namespace fastrnn

using namespace fastrnn;

void bias_relu_fwd(at::Tensor& x, const at::Tensor& bias) {
  check(x, "bias relu: x");
  const int64_t W = x.size(-1), N = x.numel() / std::max<int64_t>(W, 1);
  TORCH_CHECK(bias.is_contiguous() && bias.numel() == W && bias.scalar_type() == x.scalar_type(),
              "bias relu: the bias must be a contiguous vector of the rows' width and dtype");
  AT_DISPATCH_FLOATING_TYPES(x.scalar_type(), "bias_relu_fwd", [&] {
    bias_relu_forward_impl<scalar_t>(x.data_ptr<scalar_t>(), bias.data_ptr<scalar_t>(), N, W);
  });
}

void bias_relu_bwd(const at::Tensor& dy, const at::Tensor& y, at::Tensor& dx, at::Tensor& dbias) {
  check(dy, "bias relu backward: dy");
  check(y, "bias relu backward: y");
  check(dx, "bias relu backward: dx");
  const int64_t W = y.size(-1), N = y.numel() / std::max<int64_t>(W, 1);
  TORCH_CHECK(dy.numel() == y.numel() && dx.numel() == y.numel() && dbias.numel() == W && dbias.is_contiguous(),
              "bias relu backward: buffers do not match");
  AT_DISPATCH_FLOATING_TYPES(y.scalar_type(), "bias_relu_bwd", [&] {
    bias_relu_backward_impl<scalar_t>(dy.data_ptr<scalar_t>(), y.data_ptr<scalar_t>(), dx.data_ptr<scalar_t>(),
                                      dbias.data_ptr<scalar_t>(), N, W);
  });
}
