// One no-grad step of a windowed Transformer layer (cells.py, WindowAttentionLayer.step) in one call.
//
// A rollout step of the PyTorch path is about twenty ops per layer at a batch of a few hundred envs (five linears,
// three layer norms, the cache's copy and masking, the attention), each a dispatch and a pass over memory. Here the
// batch is split into one block per thread and each block runs the whole layer: the five products as BLAS calls on
// the block's rows, the norms, and per row the new cache written and attended over while it is in cache.
//
// Per row: e = W_in x + b_in; [q | k | v] = W_qkv norm_a(e) + b_qkv; the new slots are [cache * keep | k v 1]; the
// query attends over the slots whose validity flag is > 0 (scores q . k * scale + bias[head, slot]);
// y = e + W_out a + b_out; y += W_2 relu(W_1 norm_m(y) + b_1) + b_2; h = norm_o(y).
//
// Layouts (row-major): x (B, I) contiguous; keep (B); cache (B, (w - 1) * S) with unit inner stride and any row
// stride, S = 2H + 1 (key, value, validity flag per slot, oldest first); h_out (B, H) and slots_out (B, w * S)
// contiguous (the next state is slots_out's last w - 1 slots). params: the layer's 17 tensors in the order of
// window_step_params (fast_attention.py).
#include "common.h"

#include <algorithm>
#include <limits>

namespace fastrnn {

template <typename T>
struct WindowWeights {
  const T *w_in, *b_in, *g_a, *n_a, *w_qkv, *b_qkv, *w_out, *b_out, *g_m, *n_m, *w_1, *b_1, *w_2, *b_2, *g_o, *n_o,
      *bias;
};

// y rows = layer norm of x rows (n rows of W)
template <typename T>
void norm_rows(const T* x, T* y, int64_t n, int64_t W, const T* gamma, const T* beta, T eps) {
  T mean, rstd;
  for (int64_t r = 0; r < n; ++r) norm_row(x + r * W, y + r * W, W, gamma, beta, eps, mean, rstd);
}

// c (n x m, row-major) += a (n x k, row-major, row stride lda) w^T, w (m x k) row-major: a linear layer on n rows
template <typename T>
void linear_add(const T* a, int64_t lda, const T* w, int64_t m, int64_t k, int64_t n, T* c) {
  gemm('T', 'N', (int)m, (int)n, (int)k, T(1), w, (int)k, a, (int)lda, T(1), c, (int)m);
}

template <typename T>
void fill_rows(T* c, const T* bias, int64_t n, int64_t m) {
  for (int64_t r = 0; r < n; ++r) std::copy(bias, bias + m, c + r * m);
}

// out rows = x rows + bias (n rows of m; out may be x). Row by row: an index i % m would cost an integer division
// per element and keep the loop scalar.
template <typename T>
void add_rows(const T* x, const T* bias, int64_t n, int64_t m, T* out) {
  for (int64_t r = 0; r < n; ++r) {
#pragma omp simd
    for (int64_t i = 0; i < m; ++i) out[r * m + i] = x[r * m + i] + bias[i];
  }
}

template <typename T>
void window_step_impl(const T* x, int64_t I, const T* keep, const T* cache, int64_t cache_row, const WindowWeights<T>& p,
                      T eps_a, T eps_m, T eps_o, T* h_out, T* slots_out, int64_t B, int64_t H, int64_t heads,
                      int64_t w, T scale, int64_t nchunks) {
  const int64_t S = 2 * H + 1, d = H / heads, cached = (w - 1) * S;
  at::parallel_for(0, nchunks, 1, [&](int64_t k0, int64_t k1) {
    const int prev_mkl = MKL_Set_Num_Threads_Local(1);
    std::vector<T> e, n, qkv, a, y, m, s(w), prob(w);
    for (int64_t k = k0; k < k1; ++k) {
      const int64_t b0 = B * k / nchunks, b1 = B * (k + 1) / nchunks, nb = b1 - b0;
      e.resize(nb * H);
      n.resize(nb * H);
      qkv.resize(nb * 3 * H);
      a.resize(nb * H);
      y.resize(nb * H);
      m.resize(nb * H);
      fill_rows(e.data(), p.b_in, nb, H);
      linear_add(x + b0 * I, I, p.w_in, H, I, nb, e.data());
      norm_rows(e.data(), n.data(), nb, H, p.g_a, p.n_a, eps_a);
      fill_rows(qkv.data(), p.b_qkv, nb, 3 * H);
      linear_add(n.data(), H, p.w_qkv, 3 * H, H, nb, qkv.data());
      for (int64_t r = 0; r < nb; ++r) {
        const int64_t b = b0 + r;
        T* slots = slots_out + b * w * S;
        const T* old = cache + b * cache_row;
        const T kb = keep[b];
#pragma omp simd
        for (int64_t i = 0; i < cached; ++i) slots[i] = old[i] * kb;
        const T* qr = qkv.data() + r * 3 * H;
        std::copy(qr + H, qr + 3 * H, slots + cached);
        slots[cached + 2 * H] = T(1);
        for (int64_t h = 0; h < heads; ++h) {
          const T* qh = qr + h * d;
          T top = -std::numeric_limits<T>::infinity();
          for (int64_t j = 0; j < w; ++j) {
            const T* slot = slots + j * S;
            if (!(slot[2 * H] > T(0))) continue;
            const T* kh = slot + h * d;
            T dot = 0;
            for (int64_t i = 0; i < d; ++i) dot += qh[i] * kh[i];
            s[j] = dot * scale + p.bias[h * w + j];
            top = std::max(top, s[j]);
          }
          T total = 0;
          for (int64_t j = 0; j < w; ++j) {
            prob[j] = slots[j * S + 2 * H] > T(0) ? exp_(s[j] - top) : T(0);
            total += prob[j];
          }
          T* ah = a.data() + r * H + h * d;
          std::fill(ah, ah + d, T(0));
          for (int64_t j = 0; j < w; ++j) {
            if (prob[j] == T(0)) continue;
            const T pj = prob[j] / total;
            const T* vh = slots + j * S + H + h * d;
#pragma omp simd
            for (int64_t i = 0; i < d; ++i) ah[i] += pj * vh[i];
          }
        }
      }
      // y = e + W_out a + b_out
      add_rows(e.data(), p.b_out, nb, H, y.data());
      linear_add(a.data(), H, p.w_out, H, H, nb, y.data());
      // y += W_2 relu(W_1 norm_m(y) + b_1) + b_2
      norm_rows(y.data(), n.data(), nb, H, p.g_m, p.n_m, eps_m);
      fill_rows(m.data(), p.b_1, nb, H);
      linear_add(n.data(), H, p.w_1, H, H, nb, m.data());
      for (int64_t i = 0; i < nb * H; ++i) m[i] = std::max(m[i], T(0));
      add_rows(y.data(), p.b_2, nb, H, y.data());
      linear_add(m.data(), H, p.w_2, H, H, nb, y.data());
      norm_rows(y.data(), h_out + b0 * H, nb, H, p.g_o, p.n_o, eps_o);
    }
    MKL_Set_Num_Threads_Local(prev_mkl);
  });
}

}  // namespace fastrnn

using namespace fastrnn;

void window_layer_step(const at::Tensor& x, const at::Tensor& keep, const at::Tensor& cache,
                       const std::vector<at::Tensor>& params, const std::vector<double>& eps, at::Tensor& h_out,
                       at::Tensor& slots_out, int64_t nchunks) {
  check(x, "window step: x");
  check(keep, "window step: keep");
  check(h_out, "window step: h_out");
  check(slots_out, "window step: slots_out");
  TORCH_CHECK(params.size() == 17 && eps.size() == 3, "window step: expected 17 parameter tensors and 3 norm eps");
  for (const auto& t : params) {
    check(t, "window step: a parameter");
    TORCH_CHECK(t.scalar_type() == x.scalar_type(), "window step: parameters and x must have one dtype");
  }
  const int64_t B = x.size(0), I = x.size(1), H = params[0].size(0);
  const at::Tensor& bias = params[16];
  TORCH_CHECK(bias.dim() == 2 && H % bias.size(0) == 0, "window step: position bias must be (heads, w)");
  const int64_t heads = bias.size(0), w = bias.size(1), S = 2 * H + 1;
  TORCH_CHECK(params[0].size(1) == I && params[4].size(0) == 3 * H && params[4].size(1) == H,
              "window step: the layer's weights do not match x");
  TORCH_CHECK(keep.numel() == B && keep.scalar_type() == x.scalar_type(), "window step: keep must be (B,)");
  TORCH_CHECK(cache.dim() == 2 && cache.size(0) == B && cache.size(1) == (w - 1) * S &&
                  (cache.size(1) == 0 || cache.stride(1) == 1) && cache.scalar_type() == x.scalar_type(),
              "window step: the cache must be (B, (w - 1) * (2H + 1)) with unit inner stride");
  TORCH_CHECK(h_out.numel() == B * H && slots_out.numel() == B * w * S, "window step: output buffers do not match");
  nchunks = std::max<int64_t>(1, std::min(nchunks, B));
  AT_DISPATCH_FLOATING_TYPES(x.scalar_type(), "window_layer_step", [&] {
    auto ptr = [&](int i) { return params[i].data_ptr<scalar_t>(); };
    const WindowWeights<scalar_t> p{ptr(0), ptr(1), ptr(2),  ptr(3),  ptr(4),  ptr(5),  ptr(6),  ptr(7), ptr(8),
                                    ptr(9), ptr(10), ptr(11), ptr(12), ptr(13), ptr(14), ptr(15), ptr(16)};
    window_step_impl<scalar_t>(x.data_ptr<scalar_t>(), I, keep.data_ptr<scalar_t>(), cache.data_ptr<scalar_t>(),
                               cache.size(1) ? cache.stride(0) : 0, p, static_cast<scalar_t>(eps[0]),
                               static_cast<scalar_t>(eps[1]), static_cast<scalar_t>(eps[2]),
                               h_out.data_ptr<scalar_t>(), slots_out.data_ptr<scalar_t>(), B, H, heads, w,
                               static_cast<scalar_t>(1.0 / std::sqrt(static_cast<double>(H / heads))), nchunks);
  });
}
