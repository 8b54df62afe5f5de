// Fused CPU kernels for a masked (episode-start resetting) GRU layer: forward unroll, BPTT and the
// no-grad stack step.  Same design as the LSTM kernels (fast_lstm.cpp, which also holds the Python
// bindings): one batch block per thread runs the whole time loop, one GEMM per step.
//
// Layout (row-major, contiguous, time-major; gate order r, z, n as in nn.GRUCell):
//   X   (T,B,I)     layer input
//   M   (T,B)       mask = 1 - episode_start; the state is multiplied by M[t] BEFORE step t
//   Wc  (4H,K)      K = I + H + 1, rows   r:   [W_ir | W_hr | b_ir + b_hr]
//                                         z:   [W_iz | W_hz | b_iz + b_hz]
//                                         n_x: [W_in |  0   | b_in       ]
//                                         n_h: [ 0   | W_hn | b_hn       ]
//                   (n needs its input and hidden parts apart: n = tanh(n_x + r * n_h))
//   XH  (T,B,K)     row (t,b) = [x_t | hp_t | 1], hp_t = h_{t-1} * M[t]  (GEMM input; saved for dW)
//   S   (T,B,4H)    [r, z, n, n_h] (activations, and n_h before the reset gate), saved for backward
//   Hs  (T,B,H)     h_t = (1 - z) n + z hp_t  (unmasked output)
//
// Forward, step t:  G = XH[t] Wc^T (ONE GEMM), then the fused gate math, which also writes the
//                   next step's masked h into XH[t+1].
// Backward, t = T-1..0, with dh = dHs[t] + M[t+1] * dhp_{t+1}:
//   dG_z = dh (hp - n) z (1 - z),  dG_nx = dh (1 - z) (1 - n^2),  dG_nh = dG_nx r,
//   dG_r = dG_nx n_h r (1 - r),    dhp_t = dh z + (dG Wc)[:, I:I+H]   (direct path + ONE GEMM,
//   which also gives dx_t = (dG Wc)[:, :I]),  dWc += dG^T XH[t] per batch block.  The zero blocks
//   of Wc receive gradients too; fast_lstm.py reads dW_ih, dW_hh, db_ih, db_hh from the others.

#include "common.h"

namespace {

using namespace fastrnn;

template <typename T>
void gru_fwd_impl(const at::Tensor& X, const at::Tensor& M, const at::Tensor& h0, const at::Tensor& Wc,
                  at::Tensor XH, at::Tensor S, at::Tensor Hs, int64_t nchunks, const T* g_) {
  const int64_t TT = X.size(0), B = X.size(1), I = X.size(2), H4 = Wc.size(0), H = H4 / 4, K = I + H + 1;
  const T* x_ = X.data_ptr<T>();
  const T* m_ = M.data_ptr<T>();
  const T* h0_ = h0.data_ptr<T>();
  const T* w_ = Wc.data_ptr<T>();
  T* xh_ = XH.data_ptr<T>();
  T* s_ = S.data_ptr<T>();
  T* hs_ = Hs.data_ptr<T>();
  at::parallel_for(0, nchunks, 1, [&](int64_t k0, int64_t k1) {
    const int prev_mkl = MKL_Set_Num_Threads_Local(1);
    for (int64_t k = k0; k < k1; ++k) {
      const int64_t b0 = B * k / nchunks, b1 = B * (k + 1) / nchunks, nb = b1 - b0;
      for (int64_t b = b0; b < b1; ++b) {  // masked initial state into XH[0]
        const T m = m_[b];
        for (int64_t j = 0; j < H; ++j) xh_[b * K + I + j] = h0_[b * H + j] * m;
      }
      for (int64_t t = 0; t < TT; ++t) {
        T* xht = xh_ + (t * B + b0) * K;
        const T* xt = x_ + (t * B + b0) * I;
        for (int64_t r = 0; r < nb; ++r) {  // [x_t | . | 1]
          if (I > 0) std::memcpy(xht + r * K, xt + r * I, sizeof(T) * I);
          xht[r * K + K - 1] = T(1);
        }
        T* st = s_ + (t * B + b0) * H4;
        if (g_) std::memcpy(st, g_ + (t * B + b0) * H4, sizeof(T) * nb * H4);  // a projected input: added
        gemm('T', 'N', (int)H4, (int)nb, (int)K, T(1), w_, (int)K, xht, (int)K, g_ ? T(1) : T(0), st, (int)H4);
        const bool has_next = t + 1 < TT;
        for (int64_t r = 0; r < nb; ++r) {
          T* gr = st + r * H4;
          const T* hpr = xht + r * K + I;
          T* hr = hs_ + (t * B + b0 + r) * H;
#pragma omp simd
          for (int64_t j = 0; j < H; ++j) {
            const T rg = sigm(gr[j]);
            const T z = sigm(gr[H + j]);
            const T nh = gr[3 * H + j];
            const T n = tanh_(gr[2 * H + j] + rg * nh);
            hr[j] = n + z * (hpr[j] - n);
            gr[j] = rg; gr[H + j] = z; gr[2 * H + j] = n;  // gr[3H + j] keeps n_h
          }
          if (has_next) {
            const T mn = m_[(t + 1) * B + b0 + r];
            T* hpn = xht + B * K + r * K + I;
#pragma omp simd
            for (int64_t j = 0; j < H; ++j) hpn[j] = hr[j] * mn;
          }
        }
      }
    }
    MKL_Set_Num_Threads_Local(prev_mkl);
  });
}

template <typename T>
void gru_bwd_impl(const at::Tensor& S, const at::Tensor& M, const at::Tensor& Wc, const at::Tensor& XH, int64_t I,
                  const at::Tensor& dHs, c10::optional<at::Tensor> dX, at::Tensor dWparts, at::Tensor dh0,
                  int64_t nchunks, T* dz_out) {
  const int64_t TT = S.size(0), B = S.size(1), H4 = S.size(2), H = H4 / 4, K = I + H + 1;
  const T* s_ = S.data_ptr<T>();
  const T* m_ = M.data_ptr<T>();
  const T* w_ = Wc.data_ptr<T>();
  const T* xh_ = XH.data_ptr<T>();
  const T* dhs_ = dHs.data_ptr<T>();
  T* dx_ = dX.has_value() ? dX->data_ptr<T>() : nullptr;
  T* dwp_ = dWparts.data_ptr<T>();  // (nchunks, 4H, K): per-block partial gradients of Wc
  T* dh0_ = dh0.data_ptr<T>();
  // per-step GEMM output columns: [dx | dhp] (I+H) if dX is wanted, else only dhp (H)
  const int64_t N = dx_ ? I + H : H;
  const T* wsrc = dx_ ? w_ : w_ + I;
  at::parallel_for(0, nchunks, 1, [&](int64_t k0, int64_t k1) {
    const int prev_mkl = MKL_Set_Num_Threads_Local(1);
    for (int64_t k = k0; k < k1; ++k) {
      const int64_t b0 = B * k / nchunks, b1 = B * (k + 1) / nchunks, nb = b1 - b0;
      T* dw = dwp_ + k * H4 * K;
      std::fill(dw, dw + H4 * K, T(0));
      // out: [dx | dhp] of the step just processed (dhp = grad w.r.t. its masked input state, both paths);
      // dz: gradient of the GEMM outputs of the current step (stays in cache).
      std::vector<T> out(nb * N, T(0)), dz(nb * H4);
      T* dhp_base = out.data() + (N - H);
      for (int64_t t = TT - 1; t >= 0; --t) {
        const T* st = s_ + (t * B + b0) * H4;
        const T* xht = xh_ + (t * B + b0) * K;
        for (int64_t r = 0; r < nb; ++r) {
          const T mn = (t + 1 < TT) ? m_[(t + 1) * B + b0 + r] : T(0);
          const T* sr = st + r * H4;
          const T* hpr = xht + r * K + I;
          const T* dhsr = dhs_ + (t * B + b0 + r) * H;
          T* dzr = dz.data() + r * H4;
          T* dhpr = dhp_base + r * N;  // in: dhp of step t+1; out: the direct part of step t's dhp
          if (dx_) std::fill(out.data() + r * N, out.data() + r * N + I, T(0));
#pragma omp simd
          for (int64_t j = 0; j < H; ++j) {
            const T rg = sr[j], z = sr[H + j], n = sr[2 * H + j], nh = sr[3 * H + j];
            const T dh = dhsr[j] + mn * dhpr[j];
            const T dnx = dh * (T(1) - z) * (T(1) - n * n);
            dzr[j] = dnx * nh * rg * (T(1) - rg);
            dzr[H + j] = dh * (hpr[j] - n) * z * (T(1) - z);
            dzr[2 * H + j] = dnx;
            dzr[3 * H + j] = dnx * rg;
            dhpr[j] = dh * z;
          }
        }
        if (dz_out) std::memcpy(dz_out + (t * B + b0) * H4, dz.data(), sizeof(T) * nb * H4);
        // [dx_t | dhp_t] += dZ_t @ Wc[:, cols]   (row-major out(nb x N) += dZ(nb x 4H) W(4H x N), ld K)
        gemm('N', 'N', (int)N, (int)nb, (int)H4, T(1), wsrc, (int)K, dz.data(), (int)H4, T(1),
             out.data(), (int)N);
        // dWc += dZ_t^T @ XH_t   (row-major (4H x K); column-major view: (K x 4H) += XH_t^T dZ_t)
        gemm('N', 'T', (int)K, (int)H4, (int)nb, T(1), xht, (int)K, dz.data(), (int)H4, T(1), dw, (int)K);
        if (dx_) {
          T* dxt = dx_ + (t * B + b0) * I;
          for (int64_t r = 0; r < nb; ++r) std::memcpy(dxt + r * I, out.data() + r * N, sizeof(T) * I);
        }
      }
      for (int64_t r = 0; r < nb; ++r) {
        const T m0 = m_[b0 + r];
        for (int64_t j = 0; j < H; ++j) dh0_[(b0 + r) * H + j] = dhp_base[r * N + j] * m0;
      }
    }
    MKL_Set_Num_Threads_Local(prev_mkl);
  });
}

// One no-grad step of a GRU stack; as the LSTM's step_impl, hs_out may alias hs.
template <typename T>
void gru_step_impl(const at::Tensor& X, const at::Tensor& M, const std::vector<at::Tensor>& hs,
                   const std::vector<at::Tensor>& Wcs, std::vector<at::Tensor>& hs_out, int64_t nchunks,
                   const T* g0_) {
  const int64_t B = X.size(0), I0 = X.size(1), L = (int64_t)Wcs.size();
  const T* m_ = M.data_ptr<T>();
  at::parallel_for(0, nchunks, 1, [&](int64_t k0, int64_t k1) {
    const int prev_mkl = MKL_Set_Num_Threads_Local(1);
    std::vector<T> xh, g;
    for (int64_t k = k0; k < k1; ++k) {
      const int64_t b0 = B * k / nchunks, b1 = B * (k + 1) / nchunks, nb = b1 - b0;
      const T* in = X.data_ptr<T>() + b0 * I0;
      int64_t I = I0;
      for (int64_t l = 0; l < L; ++l) {
        const int64_t H4 = Wcs[l].size(0), H = H4 / 4, K = I + H + 1;
        xh.resize(nb * K);
        g.resize(nb * H4);
        const T* h_ = hs[l].data_ptr<T>() + b0 * H;
        for (int64_t r = 0; r < nb; ++r) {
          const T m = m_[b0 + r];
          T* row = xh.data() + r * K;
          if (I > 0) std::memcpy(row, in + r * I, sizeof(T) * I);
          for (int64_t j = 0; j < H; ++j) row[I + j] = h_[r * H + j] * m;
          row[K - 1] = T(1);
        }
        const bool projected = l == 0 && g0_ != nullptr;  // the first layer's input projection, computed elsewhere
        if (projected) std::memcpy(g.data(), g0_ + b0 * H4, sizeof(T) * nb * H4);
        gemm('T', 'N', (int)H4, (int)nb, (int)K, T(1), Wcs[l].data_ptr<T>(), (int)K, xh.data(), (int)K,
             projected ? T(1) : T(0), g.data(), (int)H4);
        T* ho = hs_out[l].data_ptr<T>() + b0 * H;
        for (int64_t r = 0; r < nb; ++r) {
          const T* gr = g.data() + r * H4;
          const T* hpr = xh.data() + r * K + I;
          T* hor = ho + r * H;
#pragma omp simd
          for (int64_t j = 0; j < H; ++j) {
            const T rg = sigm(gr[j]), z = sigm(gr[H + j]);
            const T n = tanh_(gr[2 * H + j] + rg * gr[3 * H + j]);
            hor[j] = n + z * (hpr[j] - n);
          }
        }
        in = ho; I = H;  // next layer's input = this layer's new h (rows b0..b1)
      }
    }
    MKL_Set_Num_Threads_Local(prev_mkl);
  });
}

}  // namespace

// G (optional, T,B,4H): the input projection computed elsewhere, added (rows r, z, n_x; n_h zero); X is (T,B,0)
void gru_fwd_cat(at::Tensor X, at::Tensor M, at::Tensor h0, at::Tensor Wc, at::Tensor XH, at::Tensor S,
                 at::Tensor Hs, int64_t nchunks, c10::optional<at::Tensor> G) {
  for (auto* p : {&X, &M, &h0, &Wc, &XH, &S, &Hs}) {
    check(*p, "tensor");
    TORCH_CHECK(p->scalar_type() == X.scalar_type(), "dtype mismatch");
  }
  TORCH_CHECK(X.dim() == 3 && Wc.dim() == 2 && Wc.size(0) % 4 == 0);
  const int64_t TT = X.size(0), B = X.size(1), I = X.size(2), H = Wc.size(0) / 4, K = I + H + 1;
  TORCH_CHECK(Wc.size(1) == K, "Wc must be (4H, I+H+1)");
  TORCH_CHECK(M.numel() == TT * B && h0.numel() == B * H);
  TORCH_CHECK(XH.numel() == TT * B * K && S.numel() == TT * B * 4 * H && Hs.numel() == TT * B * H);
  if (G.has_value()) {
    check(*G, "G");
    TORCH_CHECK(G->numel() == TT * B * 4 * H && G->scalar_type() == X.scalar_type(), "G must be (T,B,4H)");
  }
  nchunks = std::max<int64_t>(1, std::min(nchunks, B));
  AT_DISPATCH_FLOATING_TYPES(X.scalar_type(), "gru_fwd_cat", [&] {
    gru_fwd_impl<scalar_t>(X, M, h0, Wc, XH, S, Hs, nchunks, G.has_value() ? G->data_ptr<scalar_t>() : nullptr);
  });
}

// dZ (optional, T,B,4H): the GEMM outputs' gradients, for the weights of a projection computed elsewhere
void gru_bwd_cat(at::Tensor S, at::Tensor M, at::Tensor Wc, at::Tensor XH, int64_t I, at::Tensor dHs,
                 c10::optional<at::Tensor> dX, at::Tensor dWparts, at::Tensor dh0, c10::optional<at::Tensor> dZ) {
  for (auto* p : {&S, &M, &Wc, &XH, &dHs, &dWparts, &dh0}) {
    check(*p, "tensor");
    TORCH_CHECK(p->scalar_type() == S.scalar_type(), "dtype mismatch");
  }
  if (dX.has_value()) {
    check(*dX, "dX");
    TORCH_CHECK(dX->scalar_type() == S.scalar_type(), "dtype mismatch");
  }
  const int64_t TT = S.size(0), B = S.size(1), H = S.size(2) / 4, K = I + H + 1;
  TORCH_CHECK(Wc.size(0) == 4 * H && Wc.size(1) == K);
  TORCH_CHECK(M.numel() == TT * B && XH.numel() == TT * B * K && dHs.numel() == TT * B * H && dh0.numel() == B * H);
  TORCH_CHECK(dWparts.dim() == 3 && dWparts.size(1) == 4 * H && dWparts.size(2) == K &&
              dWparts.size(0) >= 1 && dWparts.size(0) <= B, "dWparts must be (nchunks, 4H, K)");
  if (dX.has_value()) TORCH_CHECK(dX->numel() == TT * B * I);
  if (dZ.has_value()) {
    check(*dZ, "dZ");
    TORCH_CHECK(dZ->numel() == TT * B * 4 * H && dZ->scalar_type() == S.scalar_type(), "dZ must be (T,B,4H)");
  }
  AT_DISPATCH_FLOATING_TYPES(S.scalar_type(), "gru_bwd_cat", [&] {
    gru_bwd_impl<scalar_t>(S, M, Wc, XH, I, dHs, dX, dWparts, dh0, dWparts.size(0),
                           dZ.has_value() ? dZ->data_ptr<scalar_t>() : nullptr);
  });
}

// G0 (optional, B,4H_0): the first layer's input projection computed elsewhere; X is then (B,0)
void gru_stack_step(at::Tensor X, at::Tensor M, std::vector<at::Tensor> hs, std::vector<at::Tensor> Wcs,
                    std::vector<at::Tensor> hs_out, int64_t nchunks, c10::optional<at::Tensor> G0) {
  check(X, "X"); check(M, "M");
  const int64_t B = X.size(0), L = (int64_t)Wcs.size();
  TORCH_CHECK(L >= 1 && (int64_t)hs.size() == L && (int64_t)hs_out.size() == L);
  TORCH_CHECK(M.numel() == B && M.scalar_type() == X.scalar_type());
  int64_t I = X.size(1);
  for (int64_t l = 0; l < L; ++l) {
    for (auto* p : {&hs[l], &Wcs[l], &hs_out[l]}) {
      check(*p, "tensor");
      TORCH_CHECK(p->scalar_type() == X.scalar_type(), "dtype mismatch");
    }
    const int64_t H = Wcs[l].size(0) / 4;
    TORCH_CHECK(Wcs[l].size(1) == I + H + 1, "Wc must be (4H, I+H+1)");
    TORCH_CHECK(hs[l].numel() == B * H && hs_out[l].numel() == B * H);
    I = H;
  }
  if (G0.has_value()) {
    check(*G0, "G0");
    TORCH_CHECK(G0->numel() == B * Wcs[0].size(0) && G0->scalar_type() == X.scalar_type(), "G0 must be (B, 4H_0)");
  }
  nchunks = std::max<int64_t>(1, std::min(nchunks, B));
  AT_DISPATCH_FLOATING_TYPES(X.scalar_type(), "gru_stack_step", [&] {
    gru_step_impl<scalar_t>(X, M, hs, Wcs, hs_out, nchunks, G0.has_value() ? G0->data_ptr<scalar_t>() : nullptr);
  });
}
