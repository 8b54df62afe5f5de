// Band attention of the windowed Transformer cell (cells.py, WindowAttentionLayer), forward and backward.
//
// Query t of a sequence reads the w positions t .. t + w - 1 of its keys and values (P = T + w - 1 positions per
// sequence: the w - 1 cached ones, then the chunk's own), slot j = p - t, where allowed[b, t, j]; its score is
// q . k * scale + bias[head, j]. PyTorch computes all T x P scores of a chunk and masks all but w per row (plus
// about twenty small ops); here each query touches only its w slots, one pass per query, batch rows in parallel.
//
// Layouts (row-major): q (B, T, H*d); kv (B, P, >= 2*H*d) with rows `kv_row` apart and sequences `kv_batch` apart
// (key of head h at h*d, value at H*d + h*d), so the rollout's cache of [key | value | valid] slots is read in
// place; allowed (B, T, w) bool; bias (H, w). The forward writes out (B, T, H*d) and probs (B, T, H, w), which the
// backward reads (a slot that is not allowed has probability 0, so it gets no gradient). Every query allows its
// own position (slot w - 1), so no row is empty.
#include "common.h"

#include <algorithm>
#include <limits>

namespace fastrnn {

template <typename T>
void band_forward_impl(const T* q, const T* kv, const bool* allowed, const T* bias, T* out, T* probs, int64_t B,
                       int64_t steps, int64_t H, int64_t d, int64_t w, int64_t kv_row, int64_t kv_batch, T scale) {
  const int64_t W = H * d;
  at::parallel_for(0, B * steps, 64, [&](int64_t begin, int64_t end) {
    std::vector<T> s(w);
    for (int64_t i = begin; i < end; ++i) {
      const int64_t b = i / steps, t = i % steps;
      const T* kvt = kv + b * kv_batch + t * kv_row;  // slot 0 of query t
      const bool* ai = allowed + i * w;
      for (int64_t h = 0; h < H; ++h) {
        const T* qh = q + i * W + h * d;
        T top = -std::numeric_limits<T>::infinity();
        for (int64_t j = 0; j < w; ++j) {
          if (!ai[j]) continue;
          const T* k = kvt + j * kv_row + h * d;
          T dot = 0;
#pragma omp simd reduction(+ : dot)
          for (int64_t e = 0; e < d; ++e) dot += qh[e] * k[e];
          s[j] = dot * scale + bias[h * w + j];
          top = std::max(top, s[j]);
        }
        T* ph = probs + (i * H + h) * w;
        T total = 0;
        for (int64_t j = 0; j < w; ++j) {
          ph[j] = ai[j] ? std::exp(s[j] - top) : T(0);
          total += ph[j];
        }
        T* oh = out + i * W + h * d;
        std::fill(oh, oh + d, T(0));
        for (int64_t j = 0; j < w; ++j) {
          ph[j] /= total;
          if (ph[j] == T(0)) continue;
          const T a = ph[j];
          const T* v = kvt + j * kv_row + W + h * d;
#pragma omp simd
          for (int64_t e = 0; e < d; ++e) oh[e] += a * v[e];
        }
      }
    }
  });
}

// Gradients of band_forward: dq (B, T, H*d), dkv (B, P, 2*H*d) (zeroed here, contiguous) and dscores (B, T, H, w),
// whose sum over (B, T) the caller takes as the bias gradient. Batch rows in parallel: the queries of one
// sequence add into overlapping key/value rows, so a sequence stays on one thread.
template <typename T>
void band_backward_impl(const T* grad, const T* q, const T* kv, const T* probs, T* dq, T* dkv, T* dscores, int64_t B,
                        int64_t steps, int64_t H, int64_t d, int64_t w, int64_t kv_row, int64_t kv_batch, T scale) {
  const int64_t W = H * d, P = steps + w - 1;
  at::parallel_for(0, B, 1, [&](int64_t b0, int64_t b1) {
    std::vector<T> dp(w);
    for (int64_t b = b0; b < b1; ++b) {
      T* dkvb = dkv + b * P * 2 * W;
      std::fill(dkvb, dkvb + P * 2 * W, T(0));
      for (int64_t t = 0; t < steps; ++t) {
        const int64_t i = b * steps + t;
        const T* kvt = kv + b * kv_batch + t * kv_row;
        T* dkvt = dkvb + t * 2 * W;
        for (int64_t h = 0; h < H; ++h) {
          const T* gh = grad + i * W + h * d;
          const T* qh = q + i * W + h * d;
          const T* ph = probs + (i * H + h) * w;
          T* dsh = dscores + (i * H + h) * w;
          T weighted = 0;  // sum_j p_j * dp_j
          for (int64_t j = 0; j < w; ++j) {
            dp[j] = 0;
            if (ph[j] == T(0)) continue;
            const T* v = kvt + j * kv_row + W + h * d;
            T* dv = dkvt + j * 2 * W + W + h * d;
            const T a = ph[j];
            T dot = 0;
#pragma omp simd reduction(+ : dot)
            for (int64_t e = 0; e < d; ++e) {
              dot += gh[e] * v[e];
              dv[e] += a * gh[e];
            }
            dp[j] = dot;
            weighted += a * dot;
          }
          T* dqh = dq + i * W + h * d;
          std::fill(dqh, dqh + d, T(0));
          for (int64_t j = 0; j < w; ++j) {
            const T ds = ph[j] * (dp[j] - weighted);
            dsh[j] = ds;
            if (ph[j] == T(0)) continue;
            const T c = ds * scale;
            const T* k = kvt + j * kv_row + h * d;
            T* dk = dkvt + j * 2 * W + h * d;
#pragma omp simd
            for (int64_t e = 0; e < d; ++e) {
              dqh[e] += c * k[e];
              dk[e] += c * qh[e];
            }
          }
        }
      }
    }
  });
}

}  // namespace fastrnn

using namespace fastrnn;

static void check_band(const at::Tensor& q, const at::Tensor& kv, const at::Tensor& allowed, const at::Tensor& bias) {
  TORCH_CHECK(q.dim() == 3 && q.is_contiguous(), "band attention: q must be a contiguous (B, T, H*d) tensor");
  TORCH_CHECK(kv.dim() == 3 && kv.stride(2) == 1, "band attention: kv must be (B, P, >= 2*H*d) with unit inner stride");
  TORCH_CHECK(allowed.dim() == 3 && allowed.is_contiguous() && allowed.scalar_type() == at::kBool,
              "band attention: allowed must be a contiguous (B, T, w) bool tensor");
  TORCH_CHECK(bias.dim() == 2 && bias.is_contiguous(), "band attention: bias must be a contiguous (H, w) tensor");
  const int64_t B = q.size(0), steps = q.size(1), H = bias.size(0), w = bias.size(1);
  TORCH_CHECK(q.size(2) % H == 0, "band attention: the query width is not a multiple of the heads");
  TORCH_CHECK(kv.size(0) == B && kv.size(1) == steps + w - 1 && kv.size(2) >= 2 * q.size(2),
              "band attention: kv does not match q and the window");
  TORCH_CHECK(allowed.size(0) == B && allowed.size(1) == steps && allowed.size(2) == w,
              "band attention: allowed does not match q and the window");
  TORCH_CHECK(kv.scalar_type() == q.scalar_type() && bias.scalar_type() == q.scalar_type(),
              "band attention: q, kv and bias must have one dtype");
}

void band_attention_fwd(const at::Tensor& q, const at::Tensor& kv, const at::Tensor& allowed, const at::Tensor& bias,
                        at::Tensor& out, at::Tensor& probs, double scale) {
  check_band(q, kv, allowed, bias);
  const int64_t B = q.size(0), steps = q.size(1), H = bias.size(0), w = bias.size(1), d = q.size(2) / H;
  AT_DISPATCH_FLOATING_TYPES(q.scalar_type(), "band_attention_fwd", [&] {
    band_forward_impl<scalar_t>(q.data_ptr<scalar_t>(), kv.data_ptr<scalar_t>(), allowed.data_ptr<bool>(),
                                bias.data_ptr<scalar_t>(), out.data_ptr<scalar_t>(), probs.data_ptr<scalar_t>(), B,
                                steps, H, d, w, kv.stride(1), kv.stride(0), static_cast<scalar_t>(scale));
  });
}

void band_attention_bwd(const at::Tensor& grad, const at::Tensor& q, const at::Tensor& kv, const at::Tensor& probs,
                        at::Tensor& dq, at::Tensor& dkv, at::Tensor& dscores, double scale) {
  const int64_t B = q.size(0), steps = q.size(1), H = probs.size(2), w = probs.size(3), d = q.size(2) / H;
  TORCH_CHECK(grad.is_contiguous() && dq.is_contiguous() && dkv.is_contiguous() && dscores.is_contiguous(),
              "band attention backward: contiguous tensors expected");
  AT_DISPATCH_FLOATING_TYPES(q.scalar_type(), "band_attention_bwd", [&] {
    band_backward_impl<scalar_t>(grad.data_ptr<scalar_t>(), q.data_ptr<scalar_t>(), kv.data_ptr<scalar_t>(),
                                 probs.data_ptr<scalar_t>(), dq.data_ptr<scalar_t>(), dkv.data_ptr<scalar_t>(),
                                 dscores.data_ptr<scalar_t>(), B, steps, H, d, w, kv.stride(1), kv.stride(0),
                                 static_cast<scalar_t>(scale));
  });
}
