// Band attention of the windowed Transformer cell (cells.py, WindowAttentionLayer), forward and backward.
//
// Query t of a sequence reads the w positions t .. t + w - 1 of its keys and values (P = T + w - 1 positions per
// sequence: the w - 1 cached ones, then the chunk's own), slot j = p - t, where allowed[b, t, j]; its score is
// q . k * scale + bias[head, j]. PyTorch computes all T x P scores of a chunk and masks all but w per row (plus
// about twenty small ops and the copies that assemble q, k and v); here each query touches only its w slots, read
// where they lie, one pass per query, batch rows in parallel.
//
// Layouts (row-major, unit inner stride, other strides as given): qkv (B, T, 3*H*d), the layer's projection
// [q | k | v] of the chunk (head h at h*d within each part); prefix (B, w - 1, >= 2*H*d), the cached positions
// [k | v | ...] (the rollout's cache slots [k | v | valid] are read in place); allowed (B, T, w) bool; bias (H, w).
// The forward writes out (B, T, H*d) and probs (B, T, H, w), which the backward reads (a slot that is not allowed
// has probability 0, so it gets no gradient); the backward writes d qkv (B, T, 3*H*d), d prefix (the prefix's shape;
// zero after the keys and values) and d scores (B, T, H, w), all contiguous. Every query allows its own position (slot w - 1): no row is empty.
#include "common.h"

#include <algorithm>
#include <type_traits>
#include <limits>

namespace fastrnn {

// Where position p of sequence b lies: a pointer to its key (its value follows W further on), in the prefix for
// p < w - 1, else in the chunk's qkv (key at column W).
template <typename T>
struct Positions {
  T* qkv;
  int64_t qkv_batch, qkv_row;
  T* prefix;
  int64_t prefix_batch, prefix_row;
  int64_t cached, W;  // w - 1, H * d

  T* key(int64_t b, int64_t p) const {
    return p < cached ? prefix + b * prefix_batch + p * prefix_row
                      : qkv + b * qkv_batch + (p - cached) * qkv_row + W;
  }
  T* query(int64_t b, int64_t t) const { return qkv + b * qkv_batch + t * qkv_row; }
};

// D > 0: the head width d known at compile time (the loops over it unroll and vectorise fully); D = 0: any d.
template <typename T, int D>
void band_forward_impl(const Positions<T>& at, const bool* allowed, const T* bias, T* out, T* probs, int64_t B,
                       int64_t steps, int64_t H, int64_t d_any, int64_t w, T scale) {
  const int64_t d = D > 0 ? D : d_any, W = H * d;
  at::parallel_for(0, B * steps, 64, [&](int64_t begin, int64_t end) {
    std::vector<T> s(w);
    std::vector<const T*> keys(w);
    for (int64_t i = begin; i < end; ++i) {
      const int64_t b = i / steps, t = i % steps;
      const bool* ai = allowed + i * w;
      const T* q = at.query(b, t);
      for (int64_t j = 0; j < w; ++j) keys[j] = ai[j] ? at.key(b, t + j) : nullptr;
      for (int64_t h = 0; h < H; ++h) {
        const T* qh = q + h * d;
        T top = -std::numeric_limits<T>::infinity();
        for (int64_t j = 0; j < w; ++j) {
          if (!keys[j]) continue;
          const T* k = keys[j] + h * d;
          T dot = 0;
          for (int64_t e = 0; e < d; ++e) dot += qh[e] * k[e];
          s[j] = dot * scale + bias[h * w + j];
          top = std::max(top, s[j]);
        }
        T* ph = probs + (i * H + h) * w;
        T total = 0;
        for (int64_t j = 0; j < w; ++j) {
          ph[j] = keys[j] ? exp_(s[j] - top) : T(0);
          total += ph[j];
        }
        const T inverse = T(1) / total;
        T* oh = out + i * W + h * d;
        T acc[D > 0 ? D : 1];
        T* o = D > 0 ? acc : oh;  // a known width accumulates in registers
        std::fill(o, o + d, T(0));
        for (int64_t j = 0; j < w; ++j) {
          ph[j] *= inverse;
          if (!keys[j]) continue;
          const T a = ph[j];
          const T* v = keys[j] + W + h * d;
#pragma omp simd
          for (int64_t e = 0; e < d; ++e) o[e] += a * v[e];
        }
        if (D > 0) std::copy(acc, acc + d, oh);
      }
    }
  });
}

// Batch rows in parallel: the queries of one sequence add into overlapping key/value rows, so a sequence stays on
// one thread. The gradients go to the same layout as the inputs: d qkv (B, T, 3W) and d prefix (B, w - 1, 2W).
template <typename T, int D>
void band_backward_impl(const Positions<T>& at, const Positions<T>& grads, const T* grad, const T* probs,
                        T* dscores, int64_t B, int64_t steps, int64_t H, int64_t d_any, int64_t w, T scale) {
  const int64_t d = D > 0 ? D : d_any, W = H * d, cached = w - 1;
  at::parallel_for(0, B, 1, [&](int64_t b0, int64_t b1) {
    std::vector<T> dp(w);
    for (int64_t b = b0; b < b1; ++b) {
      std::fill(grads.query(b, 0), grads.query(b, 0) + steps * 3 * W, T(0));
      // whole rows of d prefix, its columns after the keys and values (the cache's validity flags) included
      if (cached) std::fill(grads.key(b, 0), grads.key(b, 0) + cached * grads.prefix_row, T(0));
      for (int64_t t = 0; t < steps; ++t) {
        const int64_t i = b * steps + t;
        const T* q = at.query(b, t);
        T* dq = grads.query(b, t);
        for (int64_t h = 0; h < H; ++h) {
          const T* gh = grad + i * W + h * d;
          const T* qh = q + h * d;
          const T* ph = probs + (i * H + h) * w;
          T* dsh = dscores + (i * H + h) * w;
          T weighted = 0;  // sum_j p_j * dp_j
          for (int64_t j = 0; j < w; ++j) {
            dp[j] = 0;
            if (ph[j] == T(0)) continue;
            const T* v = at.key(b, t + j) + W + h * d;
            T* dv = grads.key(b, t + j) + W + h * d;
            const T a = ph[j];
            T dot = 0;
            for (int64_t e = 0; e < d; ++e) {
              dot += gh[e] * v[e];
              dv[e] += a * gh[e];
            }
            dp[j] = dot;
            weighted += a * dot;
          }
          T acc[D > 0 ? D : 1];
          T* dqh = D > 0 ? acc : dq + h * d;  // a known width accumulates in registers (dq starts at 0)
          if (D > 0) std::fill(acc, acc + d, T(0));
          for (int64_t j = 0; j < w; ++j) {
            const T ds = ph[j] * (dp[j] - weighted);
            dsh[j] = ds;
            if (ph[j] == T(0)) continue;
            const T c = ds * scale;
            const T* k = at.key(b, t + j) + h * d;
            T* dk = grads.key(b, t + j) + h * d;
#pragma omp simd
            for (int64_t e = 0; e < d; ++e) {
              dqh[e] += c * k[e];
              dk[e] += c * qh[e];
            }
          }
          if (D > 0) std::copy(acc, acc + d, dq + h * d);
        }
      }
    }
  });
}

// Calls f with the head width as a compile-time constant where it is a usual one (0: any other).
template <typename F>
void with_head_width(int64_t d, F&& f) {
  switch (d) {
    case 16: f(std::integral_constant<int, 16>{}); break;
    case 32: f(std::integral_constant<int, 32>{}); break;
    case 64: f(std::integral_constant<int, 64>{}); break;
    default: f(std::integral_constant<int, 0>{});
  }
}

}  // namespace fastrnn

using namespace fastrnn;

static void check_band(const at::Tensor& qkv, const at::Tensor& prefix, const at::Tensor& allowed,
                       const at::Tensor& bias) {
  TORCH_CHECK(bias.dim() == 2 && bias.is_contiguous(), "band attention: bias must be a contiguous (H, w) tensor");
  const int64_t w = bias.size(1);
  TORCH_CHECK(qkv.dim() == 3 && qkv.stride(2) == 1 && qkv.size(2) % 3 == 0,
              "band attention: qkv must be (B, T, 3*H*d) with unit inner stride");
  const int64_t B = qkv.size(0), steps = qkv.size(1), W = qkv.size(2) / 3;
  TORCH_CHECK(W % bias.size(0) == 0, "band attention: the width is not a multiple of the heads");
  TORCH_CHECK(prefix.dim() == 3 && prefix.stride(2) == 1 && prefix.size(0) == B && prefix.size(1) == w - 1 &&
                  prefix.size(2) >= 2 * W,
              "band attention: the prefix does not match qkv and the window");
  TORCH_CHECK(allowed.dim() == 3 && allowed.is_contiguous() && allowed.scalar_type() == at::kBool &&
                  allowed.size(0) == B && allowed.size(1) == steps && allowed.size(2) == w,
              "band attention: allowed must be a contiguous (B, T, w) bool tensor");
  TORCH_CHECK(prefix.scalar_type() == qkv.scalar_type() && bias.scalar_type() == qkv.scalar_type(),
              "band attention: qkv, prefix and bias must have one dtype");
}

template <typename T>
static Positions<T> positions(const at::Tensor& qkv, const at::Tensor& prefix, int64_t w) {
  return Positions<T>{qkv.data_ptr<T>(), qkv.stride(0), qkv.stride(1), prefix.data_ptr<T>(), prefix.stride(0),
                      prefix.stride(1), w - 1, qkv.size(2) / 3};
}

void band_attention_fwd(const at::Tensor& qkv, const at::Tensor& prefix, const at::Tensor& allowed,
                        const at::Tensor& bias, at::Tensor& out, at::Tensor& probs, double scale) {
  check_band(qkv, prefix, allowed, bias);
  const int64_t B = qkv.size(0), steps = qkv.size(1), H = bias.size(0), w = bias.size(1), d = qkv.size(2) / 3 / H;
  TORCH_CHECK(out.is_contiguous() && probs.is_contiguous(), "band attention: out and probs must be contiguous");
  AT_DISPATCH_FLOATING_TYPES(qkv.scalar_type(), "band_attention_fwd", [&] {
    with_head_width(d, [&](auto D) {
      band_forward_impl<scalar_t, decltype(D)::value>(positions<scalar_t>(qkv, prefix, w), allowed.data_ptr<bool>(),
                                                      bias.data_ptr<scalar_t>(), out.data_ptr<scalar_t>(),
                                                      probs.data_ptr<scalar_t>(), B, steps, H, d, w,
                                                      static_cast<scalar_t>(scale));
    });
  });
}

void band_attention_bwd(const at::Tensor& grad, const at::Tensor& qkv, const at::Tensor& prefix,
                        const at::Tensor& probs, at::Tensor& dqkv, at::Tensor& dprefix, at::Tensor& dscores,
                        double scale) {
  const int64_t B = qkv.size(0), steps = qkv.size(1), H = probs.size(2), w = probs.size(3), d = qkv.size(2) / 3 / H;
  TORCH_CHECK(grad.is_contiguous() && dqkv.is_contiguous() && dprefix.is_contiguous() && dscores.is_contiguous() &&
                  probs.is_contiguous(),
              "band attention backward: contiguous tensors expected");
  TORCH_CHECK(dqkv.sizes() == qkv.sizes() && dprefix.sizes() == prefix.sizes(),
              "band attention backward: gradient buffers do not match");
  AT_DISPATCH_FLOATING_TYPES(qkv.scalar_type(), "band_attention_bwd", [&] {
    with_head_width(d, [&](auto D) {
      band_backward_impl<scalar_t, decltype(D)::value>(
          positions<scalar_t>(qkv, prefix, w), positions<scalar_t>(dqkv, dprefix, w), grad.data_ptr<scalar_t>(),
          probs.data_ptr<scalar_t>(), dscores.data_ptr<scalar_t>(), B, steps, H, d, w, static_cast<scalar_t>(scale));
    });
  });
}
