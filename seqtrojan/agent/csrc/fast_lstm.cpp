// Fused CPU kernels for a masked (episode-start resetting) LSTM layer, plain or with peephole
// connections: forward unroll and BPTT.  The GRU kernels (gru.cpp) follow the same design; the shared
// helpers are in common.h; this file holds the one Python module of all cells.
// Used by seqtrojan/agent/fast_lstm.py (JIT-compiled once per machine with torch.utils.cpp_extension).
//
// Layout (all row-major, contiguous, time-major; gate order i, f, g, o as in nn.LSTMCell):
//   X   (T,B,I)     layer input
//   M   (T,B)       mask = 1 - episode_start; the state is multiplied by M[t] BEFORE step t
//   Wc  (4H,K)      [W_ih | W_hh | b_ih + b_hh],  K = I + H + 1
//   P   (3,H)       peephole weights [p_i; p_f; p_o] (peephole cell only)
//   XH  (T,B,K)     row (t,b) = [x_t | h_{t-1} * M[t] | 1]  (the GEMM input of step t; saved for dW)
//   S   (T,B,4H)    gate activations [i, f, g, o] (after sigmoid/tanh), saved for backward
//   Hs  (T,B,H)     h_t (unmasked output), C (T,B,H) c_t (unmasked), CP (T,B,H) c_{t-1} * M[t]
//   G   (T,B,4H)    optional: the input projection computed elsewhere (sparse_input.cpp, for one-hot inputs),
//                   added to the GEMM's result; the layer is then called with I = 0 (X is (T,B,0)), and the
//                   backward writes dZ (T,B,4H), the pre-activation gradients, for that projection's weights.
//
// Forward, step t:  S[t] = XH[t] Wc^T  (ONE GEMM: input projection + recurrence + bias), then the
//                   fused gate math, which also writes the next step's masked h into XH[t+1].
//                   Peephole: i = sig(z_i + p_i*cp), f = sig(z_f + p_f*cp), o = sig(z_o + p_o*c),
//                   with cp = c_{t-1}*M[t] (so a reset state reaches no gate).
// Backward, t = T-1..0:
//                   dZ[t] (gradient of the pre-activations) from the fused gate math, then
//                   [dx_t | dh_{t-1}] = dZ[t] Wc[:, :I+H]  (ONE GEMM); dh_{t-1} is masked with M[t]
//                   and dc_{t-1} = dc_t * f_t * M[t]  (no gradient flows into a reset state;
//                   peephole: + (dz_i p_i + dz_f p_f) * M[t]).
//                   and, also per step while dZ[t] and XH[t] are in cache, dWc += dZ[t]^T XH[t]
//                   (-> dW_ih, dW_hh, db), accumulated per batch block; dZ is never stored.
//                   Peephole: dP (3,H) is accumulated per batch block in the gate loop.
//
// Parallelisation: the batch is split into `nchunks` contiguous row blocks (normally one per
// thread); each block runs the WHOLE time loop on its own thread (at::parallel_for over blocks).
// Environments are independent, so there is no synchronisation inside the time loop (no OpenMP
// fork/join per small op).  Each block's per-step GEMM is a single-threaded MKL call (sgemm_ from
// libtorch_cpu, thread-local MKL thread count forced to 1).  Must be compiled with -fopenmp
// (at::parallel_for is an inline OpenMP template) -- otherwise the blocks run serially.
//
// The peephole variant is the template parameter PEEP: with PEEP = false every peephole term is
// compiled out (`if constexpr`), so the plain LSTM runs exactly the code it ran before.
//
// Activations (float): inline vectorisable exp / rational tanh approximations (max error ~3e-7,
// comparable to float32 rounding); double (gradcheck): std::exp / std::tanh.

#include <torch/extension.h>  // the Python module (PYBIND11_MODULE below)

#include "common.h"

namespace {

using namespace fastrnn;

// ======================================================================================
// "cat" kernels: the input projection is fused into the per-step GEMM.
//   XH (T,B,K), K = I+H+1: row (t,b) = [ x_t | h_{t-1}*m_t | 1 ]  (x part copied in the loop,
//                                        h part written by the previous step, 1 -> bias)
//   Wc (4H,K) = [ W_ih | W_hh | b_ih+b_hh ]
//   fwd: S[t] = XH[t] Wc^T (one GEMM per step and batch block, K = I+H+1), then the gate math.
//   bwd: dZ[t] from the gate math, then [dx_t | dh_{t-1}] = dZ[t] Wc[:, :I+H] and
//        dWc += dZ[t]^T XH[t] (two GEMMs per step and batch block).
// ======================================================================================
template <typename T, bool PEEP>
void fwd_cat_impl(const at::Tensor& X, const at::Tensor& M, const at::Tensor& h0, const at::Tensor& c0,
                  const at::Tensor& Wc, const T* p_, at::Tensor XH, at::Tensor S, at::Tensor Hs, at::Tensor C,
                  at::Tensor CP, int64_t nchunks, const T* g_) {
  const int64_t TT = X.size(0), B = X.size(1), I = X.size(2), H4 = Wc.size(0), H = H4 / 4, K = I + H + 1;
  const T* x_ = X.data_ptr<T>();
  const T* m_ = M.data_ptr<T>();
  const T* h0_ = h0.data_ptr<T>();
  const T* c0_ = c0.data_ptr<T>();
  const T* w_ = Wc.data_ptr<T>();
  T* xh_ = XH.data_ptr<T>();
  T* s_ = S.data_ptr<T>();
  T* hs_ = Hs.data_ptr<T>();
  T* c_ = C.data_ptr<T>();
  T* cp_ = CP.data_ptr<T>();
  const T* pi = p_;  // peephole rows (unused unless PEEP)
  const T* pf = PEEP ? p_ + H : nullptr;
  const T* po = PEEP ? p_ + 2 * H : nullptr;
  nchunks = std::max<int64_t>(1, std::min(nchunks, B));
  at::parallel_for(0, nchunks, 1, [&](int64_t k0, int64_t k1) {
    const int prev_mkl = MKL_Set_Num_Threads_Local(1);
    for (int64_t k = k0; k < k1; ++k) {
      const int64_t b0 = B * k / nchunks, b1 = B * (k + 1) / nchunks, nb = b1 - b0;
      for (int64_t b = b0; b < b1; ++b) {  // masked initial state into XH[0] / CP[0]
        const T m = m_[b];
        for (int64_t j = 0; j < H; ++j) {
          xh_[b * K + I + j] = h0_[b * H + j] * m;
          cp_[b * H + j] = c0_[b * H + j] * m;
        }
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
        const int64_t so = (t * B + b0) * H;
        const bool has_next = t + 1 < TT;
        for (int64_t r = 0; r < nb; ++r) {
          T* gr = st + r * H4;
          const T* cpr = cp_ + so + r * H;
          T* cr = c_ + so + r * H;
          T* hr = hs_ + so + r * H;
          const T mn = has_next ? m_[(t + 1) * B + b0 + r] : T(0);
          // next step's recurrent input (masked); for the last step write to a dummy place
          T* hpn = has_next ? xht + B * K + r * K + I : nullptr;
          T* cpn = has_next ? cp_ + so + B * H + r * H : nullptr;
#pragma omp simd
          for (int64_t j = 0; j < H; ++j) {
            T i, f, gg, o, c;
            if constexpr (PEEP) {
              i = sigm(gr[j] + pi[j] * cpr[j]);
              f = sigm(gr[H + j] + pf[j] * cpr[j]);
              gg = tanh_(gr[2 * H + j]);
              c = f * cpr[j] + i * gg;
              o = sigm(gr[3 * H + j] + po[j] * c);
            } else {
              i = sigm(gr[j]);
              f = sigm(gr[H + j]);
              gg = tanh_(gr[2 * H + j]);
              o = sigm(gr[3 * H + j]);
              c = f * cpr[j] + i * gg;
            }
            const T h = o * tanh_(c);
            gr[j] = i; gr[H + j] = f; gr[2 * H + j] = gg; gr[3 * H + j] = o;
            cr[j] = c; hr[j] = h;
          }
          if (has_next) {
#pragma omp simd
            for (int64_t j = 0; j < H; ++j) { hpn[j] = hr[j] * mn; cpn[j] = cr[j] * mn; }
          }
        }
      }
    }
    MKL_Set_Num_Threads_Local(prev_mkl);
  });
}

template <typename T, bool PEEP>
void bwd_cat_impl(const at::Tensor& S, const at::Tensor& C, const at::Tensor& CP, const at::Tensor& M,
                  const at::Tensor& Wc, const T* p_, const at::Tensor& XH, int64_t I, const at::Tensor& dHs,
                  const c10::optional<at::Tensor>& dCs, const at::Tensor& dcT,
                  c10::optional<at::Tensor> dX, at::Tensor dWparts, T* dpp_, at::Tensor dh0, at::Tensor dc0,
                  int64_t nchunks, T* dz_out) {
  const int64_t TT = S.size(0), B = S.size(1), H4 = S.size(2), H = H4 / 4, K = I + H + 1;
  const T* s_ = S.data_ptr<T>();
  const T* c_ = C.data_ptr<T>();
  const T* cp_ = CP.data_ptr<T>();
  const T* m_ = M.data_ptr<T>();
  const T* w_ = Wc.data_ptr<T>();
  const T* xh_ = XH.data_ptr<T>();
  const T* dhs_ = dHs.data_ptr<T>();
  const T* dcs_ = dCs.has_value() ? dCs->data_ptr<T>() : nullptr;
  const T* dcT_ = dcT.data_ptr<T>();
  T* dx_ = dX.has_value() ? dX->data_ptr<T>() : nullptr;
  T* dwp_ = dWparts.data_ptr<T>();   // (nchunks, 4H, K): per-block partial weight gradients
  T* dh0_ = dh0.data_ptr<T>();
  T* dc0_ = dc0.data_ptr<T>();
  const T* pi = p_;  // peephole rows and their per-block gradients dpp_ (nchunks, 3, H) (unused unless PEEP)
  const T* pf = PEEP ? p_ + H : nullptr;
  const T* po = PEEP ? p_ + 2 * H : nullptr;
  // per-step GEMM output columns: [dx | dh] (I+H) if dX is wanted, else only dh (H)
  const int64_t N = dx_ ? I + H : H;
  const T* wsrc = dx_ ? w_ : w_ + I;
  at::parallel_for(0, nchunks, 1, [&](int64_t k0, int64_t k1) {
    const int prev_mkl = MKL_Set_Num_Threads_Local(1);
    for (int64_t k = k0; k < k1; ++k) {
      const int64_t b0 = B * k / nchunks, b1 = B * (k + 1) / nchunks, nb = b1 - b0;
      T* dw = dwp_ + k * H4 * K;
      std::fill(dw, dw + H4 * K, T(0));
      T* dpi = PEEP ? dpp_ + k * 3 * H : nullptr;
      T* dpf = PEEP ? dpi + H : nullptr;
      T* dpo = PEEP ? dpi + 2 * H : nullptr;
      if constexpr (PEEP) std::fill(dpi, dpi + 3 * H, T(0));
      // out: [dx | dh] of the step just processed (dh = grad w.r.t. the masked h_{t-1});
      // dz: gradient of the pre-activations of the current step (stays in cache);
      // dcr: grad w.r.t. c_{t} from step t+1 (already masked).
      std::vector<T> out(nb * N, T(0)), dz(nb * H4), dcr(nb * H);
      for (int64_t r = 0; r < nb * H; ++r) dcr[r] = dcT_[b0 * H + r];
      T* dhr_base = out.data() + (N - H);
      for (int64_t t = TT - 1; t >= 0; --t) {
        const int64_t so = (t * B + b0) * H;
        const T* st = s_ + (t * B + b0) * H4;
        for (int64_t r = 0; r < nb; ++r) {
          const T mn = (t + 1 < TT) ? m_[(t + 1) * B + b0 + r] : T(0);
          const T mt = m_[t * B + b0 + r];
          const T* sr = st + r * H4;
          T* dzr = dz.data() + r * H4;
          const T* cr = c_ + so + r * H;
          const T* cpr = cp_ + so + r * H;
          const T* dhsr = dhs_ + so + r * H;
          const T* dhrr = dhr_base + r * N;
          T* dcrr = dcr.data() + r * H;
          if (dcs_) {
            const T* dcsr = dcs_ + so + r * H;
#pragma omp simd
            for (int64_t j = 0; j < H; ++j) dcrr[j] += dcsr[j];
          }
#pragma omp simd
          for (int64_t j = 0; j < H; ++j) {
            const T i = sr[j], f = sr[H + j], gg = sr[2 * H + j], o = sr[3 * H + j];
            const T tc = tanh_(cr[j]);
            const T dh = dhsr[j] + mn * dhrr[j];
            T dc = dcrr[j] + dh * o * (T(1) - tc * tc);
            const T dzo = dh * tc * o * (T(1) - o);
            if constexpr (PEEP) dc += dzo * po[j];  // c_t reaches h_t also through o_t
            const T dzi = dc * gg * i * (T(1) - i);
            const T dzf = dc * cpr[j] * f * (T(1) - f);
            dzr[j] = dzi;
            dzr[H + j] = dzf;
            dzr[2 * H + j] = dc * i * (T(1) - gg * gg);
            dzr[3 * H + j] = dzo;
            if constexpr (PEEP) {
              dcrr[j] = (dc * f + dzi * pi[j] + dzf * pf[j]) * mt;
              dpi[j] += dzi * cpr[j];
              dpf[j] += dzf * cpr[j];
              dpo[j] += dzo * cr[j];
            } else {
              dcrr[j] = dc * f * mt;
            }
          }
        }
        if (dz_out) std::memcpy(dz_out + (t * B + b0) * H4, dz.data(), sizeof(T) * nb * H4);
        // [dx_t | dh_{t-1}] = dZ_t @ Wc[:, cols]   (row-major out(nb x N) = dZ(nb x 4H) W(4H x N), ld K)
        gemm('N', 'N', (int)N, (int)nb, (int)H4, T(1), wsrc, (int)K, dz.data(), (int)H4, T(0),
             out.data(), (int)N);
        // dWc += dZ_t^T @ XH_t   (row-major (4H x K); column-major view: (K x 4H) += XH_t^T dZ_t)
        gemm('N', 'T', (int)K, (int)H4, (int)nb, T(1), xh_ + (t * B + b0) * K, (int)K, dz.data(),
             (int)H4, T(1), dw, (int)K);
        if (dx_) {
          T* dxt = dx_ + (t * B + b0) * I;
          for (int64_t r = 0; r < nb; ++r) std::memcpy(dxt + r * I, out.data() + r * N, sizeof(T) * I);
        }
      }
      for (int64_t r = 0; r < nb; ++r) {
        const T m0 = m_[b0 + r];
        for (int64_t j = 0; j < H; ++j) {
          dh0_[(b0 + r) * H + j] = dhr_base[r * N + j] * m0;
          dc0_[(b0 + r) * H + j] = dcr[r * H + j];
        }
      }
    }
    MKL_Set_Num_Threads_Local(prev_mkl);
  });
}

// ======================================================================================
// Inference: one time step of the whole stack (no autograd, nothing saved), one call for all
// layers.  x (B,I0), M (B) mask, hs[l]/cs[l] (B,H_l) current states, Wcs[l] (4H_l, K_l),
// Ps[l] (3,H_l) peepholes (PEEP only); writes the new states to hs_out[l], cs_out[l] (may alias
// hs/cs: rows are processed in place).
// ======================================================================================
template <typename T, bool PEEP>
void step_impl(const at::Tensor& X, const at::Tensor& M, const std::vector<at::Tensor>& hs,
               const std::vector<at::Tensor>& cs, const std::vector<at::Tensor>& Wcs,
               const std::vector<at::Tensor>& Ps, std::vector<at::Tensor>& hs_out,
               std::vector<at::Tensor>& cs_out, int64_t nchunks, const T* g0_) {
  const int64_t B = X.size(0), I0 = X.size(1), L = (int64_t)Wcs.size();
  const T* m_ = M.data_ptr<T>();
  at::parallel_for(0, nchunks, 1, [&](int64_t k0, int64_t k1) {
    const int prev_mkl = MKL_Set_Num_Threads_Local(1);
    std::vector<T> xh, g;
    for (int64_t k = k0; k < k1; ++k) {
      const int64_t b0 = B * k / nchunks, b1 = B * (k + 1) / nchunks, nb = b1 - b0;
      const T* in = X.data_ptr<T>() + b0 * I0;
      int64_t I = I0, ld_in = I0;
      for (int64_t l = 0; l < L; ++l) {
        const int64_t H4 = Wcs[l].size(0), H = H4 / 4, K = I + H + 1;
        xh.resize(nb * K);
        g.resize(nb * H4);
        const T* h_ = hs[l].data_ptr<T>() + b0 * H;
        const T* c_ = cs[l].data_ptr<T>() + b0 * H;
        const T* pi = PEEP ? Ps[l].data_ptr<T>() : nullptr;
        const T* pf = PEEP ? pi + H : nullptr;
        const T* po = PEEP ? pi + 2 * H : nullptr;
        for (int64_t r = 0; r < nb; ++r) {
          const T m = m_[b0 + r];
          T* row = xh.data() + r * K;
          if (I > 0) std::memcpy(row, in + r * ld_in, sizeof(T) * I);
          for (int64_t j = 0; j < H; ++j) row[I + j] = h_[r * H + j] * m;
          row[K - 1] = T(1);
        }
        const bool projected = l == 0 && g0_ != nullptr;  // the first layer's input projection, computed elsewhere
        if (projected) std::memcpy(g.data(), g0_ + b0 * H4, sizeof(T) * nb * H4);
        gemm('T', 'N', (int)H4, (int)nb, (int)K, T(1), Wcs[l].data_ptr<T>(), (int)K, xh.data(), (int)K,
             projected ? T(1) : T(0), g.data(), (int)H4);
        T* ho = hs_out[l].data_ptr<T>() + b0 * H;
        T* co = cs_out[l].data_ptr<T>() + b0 * H;
        for (int64_t r = 0; r < nb; ++r) {
          const T m = m_[b0 + r];
          const T* gr = g.data() + r * H4;
          const T* cr = c_ + r * H;
          T* hor = ho + r * H;
          T* cor = co + r * H;
#pragma omp simd
          for (int64_t j = 0; j < H; ++j) {
            if constexpr (PEEP) {
              const T cp = cr[j] * m;
              const T i = sigm(gr[j] + pi[j] * cp), f = sigm(gr[H + j] + pf[j] * cp), gg = tanh_(gr[2 * H + j]);
              const T c = f * cp + i * gg;
              const T o = sigm(gr[3 * H + j] + po[j] * c);
              cor[j] = c;
              hor[j] = o * tanh_(c);
            } else {
              const T i = sigm(gr[j]), f = sigm(gr[H + j]), gg = tanh_(gr[2 * H + j]), o = sigm(gr[3 * H + j]);
              const T c = f * (cr[j] * m) + i * gg;
              cor[j] = c;
              hor[j] = o * tanh_(c);
            }
          }
        }
        in = ho; I = H; ld_in = H;   // next layer's input = this layer's new h (rows b0..b1)
      }
    }
    MKL_Set_Num_Threads_Local(prev_mkl);
  });
}

// The peephole weights P (3,H) of a layer with H units: contiguous CPU, the layer's dtype.
void check_peephole(const at::Tensor& P, int64_t H, const at::Tensor& like) {
  check(P, "peephole");
  TORCH_CHECK(P.dim() == 2 && P.size(0) == 3 && P.size(1) == H, "peephole must be (3, H)");
  TORCH_CHECK(P.scalar_type() == like.scalar_type(), "dtype mismatch");
}

}  // namespace

// P: peephole weights (3,H), or None for the plain LSTM.
void lstm_fwd_cat(at::Tensor X, at::Tensor M, at::Tensor h0, at::Tensor c0, at::Tensor Wc,
                  c10::optional<at::Tensor> P, at::Tensor XH, at::Tensor S, at::Tensor Hs, at::Tensor C,
                  at::Tensor CP, int64_t nchunks, c10::optional<at::Tensor> G) {
  for (auto* p : {&X, &M, &h0, &c0, &Wc, &XH, &S, &Hs, &C, &CP}) check(*p, "tensor");
  TORCH_CHECK(X.dim() == 3 && Wc.dim() == 2 && Wc.size(0) % 4 == 0);
  const int64_t TT = X.size(0), B = X.size(1), I = X.size(2), H = Wc.size(0) / 4, K = I + H + 1;
  TORCH_CHECK(Wc.size(1) == K, "Wc must be (4H, I+H+1)");
  TORCH_CHECK(M.numel() == TT * B && h0.numel() == B * H && c0.numel() == B * H);
  TORCH_CHECK(XH.numel() == TT * B * K && S.numel() == TT * B * 4 * H && Hs.numel() == TT * B * H &&
              C.numel() == TT * B * H && CP.numel() == TT * B * H);
  for (auto* p : {&M, &h0, &c0, &Wc, &XH, &S, &Hs, &C, &CP})
    TORCH_CHECK(p->scalar_type() == X.scalar_type(), "dtype mismatch");
  if (P.has_value()) check_peephole(*P, H, X);
  if (G.has_value()) {
    check(*G, "G");
    TORCH_CHECK(G->numel() == TT * B * 4 * H && G->scalar_type() == X.scalar_type(), "G must be (T,B,4H)");
  }
  AT_DISPATCH_FLOATING_TYPES(X.scalar_type(), "lstm_fwd_cat", [&] {
    const scalar_t* g = G.has_value() ? G->data_ptr<scalar_t>() : nullptr;
    if (P.has_value())
      fwd_cat_impl<scalar_t, true>(X, M, h0, c0, Wc, P->data_ptr<scalar_t>(), XH, S, Hs, C, CP, nchunks, g);
    else
      fwd_cat_impl<scalar_t, false>(X, M, h0, c0, Wc, nullptr, XH, S, Hs, C, CP, nchunks, g);
  });
}

// P / dPparts: peephole weights (3,H) and their per-block gradients (nchunks,3,H), both None for the plain LSTM.
void lstm_bwd_cat(at::Tensor S, at::Tensor C, at::Tensor CP, at::Tensor M, at::Tensor Wc,
                  c10::optional<at::Tensor> P, at::Tensor XH, int64_t I, at::Tensor dHs,
                  c10::optional<at::Tensor> dCs, at::Tensor dcT, c10::optional<at::Tensor> dX,
                  at::Tensor dWparts, c10::optional<at::Tensor> dPparts, at::Tensor dh0, at::Tensor dc0,
                  c10::optional<at::Tensor> dZ) {
  for (auto* p : {&S, &C, &CP, &M, &Wc, &XH, &dHs, &dcT, &dWparts, &dh0, &dc0}) check(*p, "tensor");
  if (dCs.has_value()) check(*dCs, "dCs");
  if (dX.has_value()) check(*dX, "dX");
  const int64_t TT = S.size(0), B = S.size(1), H = S.size(2) / 4, K = I + H + 1;
  TORCH_CHECK(Wc.size(0) == 4 * H && Wc.size(1) == K);
  TORCH_CHECK(XH.numel() == TT * B * K && dHs.numel() == TT * B * H && dcT.numel() == B * H);
  TORCH_CHECK(dWparts.dim() == 3 && dWparts.size(1) == 4 * H && dWparts.size(2) == K &&
              dWparts.size(0) >= 1 && dWparts.size(0) <= B, "dWparts must be (nchunks, 4H, K)");
  if (dCs.has_value()) TORCH_CHECK(dCs->numel() == TT * B * H);
  if (dX.has_value()) TORCH_CHECK(dX->numel() == TT * B * I);
  TORCH_CHECK(P.has_value() == dPparts.has_value(), "P and dPparts go together");
  if (P.has_value()) {
    check_peephole(*P, H, S);
    check(*dPparts, "dPparts");
    TORCH_CHECK(dPparts->dim() == 3 && dPparts->size(0) == dWparts.size(0) && dPparts->size(1) == 3 &&
                dPparts->size(2) == H && dPparts->scalar_type() == S.scalar_type(),
                "dPparts must be (nchunks, 3, H)");
  }
  if (dZ.has_value()) {
    check(*dZ, "dZ");
    TORCH_CHECK(dZ->numel() == TT * B * 4 * H && dZ->scalar_type() == S.scalar_type(), "dZ must be (T,B,4H)");
  }
  AT_DISPATCH_FLOATING_TYPES(S.scalar_type(), "lstm_bwd_cat", [&] {
    scalar_t* dz = dZ.has_value() ? dZ->data_ptr<scalar_t>() : nullptr;
    if (P.has_value())
      bwd_cat_impl<scalar_t, true>(S, C, CP, M, Wc, P->data_ptr<scalar_t>(), XH, I, dHs, dCs, dcT, dX, dWparts,
                                   dPparts->data_ptr<scalar_t>(), dh0, dc0, dWparts.size(0), dz);
    else
      bwd_cat_impl<scalar_t, false>(S, C, CP, M, Wc, nullptr, XH, I, dHs, dCs, dcT, dX, dWparts, nullptr, dh0,
                                    dc0, dWparts.size(0), dz);
  });
}

// Ps: one peephole (3,H_l) per layer, or empty for the plain LSTM.
// G0: optional (B, 4H_0), the first layer's input projection computed elsewhere (X is then (B, 0)).
void lstm_stack_step(at::Tensor X, at::Tensor M, std::vector<at::Tensor> hs, std::vector<at::Tensor> cs,
                     std::vector<at::Tensor> Wcs, std::vector<at::Tensor> Ps, std::vector<at::Tensor> hs_out,
                     std::vector<at::Tensor> cs_out, int64_t nchunks, c10::optional<at::Tensor> G0) {
  check(X, "X"); check(M, "M");
  const int64_t B = X.size(0), L = (int64_t)Wcs.size();
  TORCH_CHECK(L >= 1 && (int64_t)hs.size() == L && (int64_t)cs.size() == L && (int64_t)hs_out.size() == L &&
              (int64_t)cs_out.size() == L);
  TORCH_CHECK(Ps.empty() || (int64_t)Ps.size() == L, "one peephole per layer, or none");
  TORCH_CHECK(M.numel() == B && M.scalar_type() == X.scalar_type());
  int64_t I = X.size(1);
  for (int64_t l = 0; l < L; ++l) {
    for (auto* p : {&hs[l], &cs[l], &Wcs[l], &hs_out[l], &cs_out[l]}) {
      check(*p, "tensor");
      TORCH_CHECK(p->scalar_type() == X.scalar_type(), "dtype mismatch");
    }
    const int64_t H = Wcs[l].size(0) / 4;
    TORCH_CHECK(Wcs[l].size(1) == I + H + 1, "Wc must be (4H, I+H+1)");
    TORCH_CHECK(hs[l].numel() == B * H && cs[l].numel() == B * H && hs_out[l].numel() == B * H &&
                cs_out[l].numel() == B * H);
    if (!Ps.empty()) check_peephole(Ps[l], H, X);
    I = H;
  }
  if (G0.has_value()) {
    check(*G0, "G0");
    TORCH_CHECK(G0->numel() == B * Wcs[0].size(0) && G0->scalar_type() == X.scalar_type(), "G0 must be (B, 4H_0)");
  }
  nchunks = std::max<int64_t>(1, std::min(nchunks, B));
  AT_DISPATCH_FLOATING_TYPES(X.scalar_type(), "lstm_stack_step", [&] {
    const scalar_t* g0 = G0.has_value() ? G0->data_ptr<scalar_t>() : nullptr;
    if (Ps.empty())
      step_impl<scalar_t, false>(X, M, hs, cs, Wcs, Ps, hs_out, cs_out, nchunks, g0);
    else
      step_impl<scalar_t, true>(X, M, hs, cs, Wcs, Ps, hs_out, cs_out, nchunks, g0);
  });
}

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
  m.def("lstm_stack_step", &lstm_stack_step, "one no-grad step of a masked (peephole) LSTM stack (all layers)");
  m.def("lstm_fwd_cat", &lstm_fwd_cat, "masked (peephole) LSTM layer forward, input projection fused per step");
  m.def("lstm_bwd_cat", &lstm_bwd_cat, "masked (peephole) LSTM layer BPTT, dx fused per step");
  m.def("gru_stack_step", &gru_stack_step, "one no-grad step of a masked GRU stack (all layers)");
  m.def("gru_fwd_cat", &gru_fwd_cat, "masked GRU layer forward, input projection fused per step");
  m.def("gru_bwd_cat", &gru_bwd_cat, "masked GRU layer BPTT, dx fused per step");
  m.def("band_attention_fwd", &band_attention_fwd, "the windowed Transformer's band attention, forward");
  m.def("band_attention_bwd", &band_attention_bwd, "the windowed Transformer's band attention, backward");
  m.def("layer_norm_fwd", &layer_norm_fwd, "bias (+ residual) and layer norm over the last dimension, forward");
  m.def("layer_norm_bwd", &layer_norm_bwd, "bias (+ residual) and layer norm over the last dimension, backward");
  m.def("bias_relu_fwd", &bias_relu_fwd, "a linear layer's bias and a ReLU on its product, in place");
  m.def("bias_relu_bwd", &bias_relu_bwd, "the backward of bias_relu_fwd, with the bias gradient");
  m.def("window_layer_step", &window_layer_step, "one no-grad step of a windowed Transformer layer");
  m.def("sparse_project", &sparse_project, "X W^T reading only X's nonzero entries (one-hot inputs)");
  m.def("sparse_project_grad", &sparse_project_grad, "the weight gradient X^T dOut of sparse_project");
}
