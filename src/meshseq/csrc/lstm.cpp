// One time step of a stacked LSTM, all layers in one call, forward and backward (CPU, float32).
//
//   gates = x W_ih^T + h W_hh^T + b_ih + b_hh        (B, 4H), torch's order: i, f, g, o
//   c' = sigmoid(f) c + sigmoid(i) tanh(g),  h' = sigmoid(o) tanh(c')
//
// layer by layer (layer k's x is layer k-1's h'; layer 0's is z). The roll-out runs 31 such steps
// of 3 layers for 16 chains of 128: torch's lstm_cell is a dozen operators a layer on CPU, and its
// (16, 128) x (128, 512) products went through MKL, which repacked the (512, 128) weight at every
// call (its copy routines took more of the loop than its multiply-adds): 22 ms forward + 46 ms
// backward a roll-out. Here each product is a register-tiled loop over the small matrices (4 rows
// x 4 vectors of 16 columns of sums in registers; 2 x 2 with AVX2) and the gate arithmetic one
// vectorised pass.
//
// The backward returns the input, state and weight gradients of the step; the weight gradients
// per step (autograd sums them over the steps). The columns of every product are split between
// threads in fixed groups, and each sum is made by one thread in a fixed order: the same bits with
// any number of threads. Sizes: the input and hidden widths multiples of 16 (kernels.py checks).

#include <torch/extension.h>
#include <ATen/Parallel.h>

#include <vector>

#include "simd.h"

namespace {

// rows of the product and vectors of 16 columns per register tile: with AVX-512 4 x 4 (16 of the 32
// registers hold sums); with AVX2 a vector of 16 is two registers, and 4 x 4 would be 32 of its 16
// (spilled): 2 x 2 there (8 registers of sums, 4 of the row of M, a broadcast). AMD EPYC with AVX2,
// 2 threads, 3 layers of 128 at 16 chains, p10 of 200 alternated calls (ms, forward / backward):
// 4 x 4 0.74 / 1.89, 2 x 2 0.54 / 1.30, 3 x 2 0.47 / 1.28, 1 x 4 0.55 / 1.25, 4 x 1 0.49 / 1.39
#if defined(__AVX512F__)
constexpr int MM_ROWS = 4, MM_VECS = 4;
#else
constexpr int MM_ROWS = 2, MM_VECS = 2;
#endif

// out[r0 .. r0 + RB, n0 .. n0 + 16 NV] (+)= A M, A[r, k] = A[r sr + k sk], M (K, N) and out (., N) row-major
template <int RB, int NV>
inline void mm_tile(const float* A, int64_t sr, int64_t sk, const float* M, int64_t K, int64_t N, float* out,
                    int64_t r0, int64_t n0, bool accumulate) {
  v16 acc[RB][NV];
  for (int i = 0; i < RB; ++i)
    for (int j = 0; j < NV; ++j) acc[i][j] = accumulate ? load<v16>(out + (r0 + i) * N + n0 + 16 * j) : v16{};
  for (int64_t k = 0; k < K; ++k) {
    v16 m[NV];
    for (int j = 0; j < NV; ++j) {
      m[j] = load<v16>(M + k * N + n0 + 16 * j);
#if defined(__AVX512F__)
      __asm__("" : "+v"(m[j]));  // one load into a register for the RB multiply-adds, not RB memory operands
#endif
    }
    for (int i = 0; i < RB; ++i) {
      const v16 a = splat<v16>(A[(r0 + i) * sr + k * sk]);
      for (int j = 0; j < NV; ++j) acc[i][j] += a * m[j];
    }
  }
  for (int i = 0; i < RB; ++i)
    for (int j = 0; j < NV; ++j) store(out + (r0 + i) * N + n0 + 16 * j, acc[i][j]);
}

// out (R, N) (+)= A (R, K) M (K, N); N a multiple of 16
void small_mm(const float* A, int64_t sr, int64_t sk, const float* M, int64_t R, int64_t K, int64_t N, float* out,
              bool accumulate) {
  constexpr int64_t GROUP = 16 * MM_VECS;
  at::parallel_for(0, (N + GROUP - 1) / GROUP, 1, [&](int64_t g0, int64_t g1) {
    for (int64_t g = g0; g < g1; ++g) {
      const int64_t n0 = g * GROUP;
      const bool whole = n0 + GROUP <= N;
      int64_t r0 = 0;
      for (; r0 + MM_ROWS <= R; r0 += MM_ROWS) {
        if (whole) mm_tile<MM_ROWS, MM_VECS>(A, sr, sk, M, K, N, out, r0, n0, accumulate);
        else
          for (int64_t n = n0; n < N; n += 16) mm_tile<MM_ROWS, 1>(A, sr, sk, M, K, N, out, r0, n, accumulate);
      }
      for (; r0 < R; ++r0) {
        if (whole) mm_tile<1, MM_VECS>(A, sr, sk, M, K, N, out, r0, n0, accumulate);
        else
          for (int64_t n = n0; n < N; n += 16) mm_tile<1, 1>(A, sr, sk, M, K, N, out, r0, n, accumulate);
      }
    }
  });
}

inline v16 sigmoid(v16 x) { return 0.5f + 0.5f * tanh_rational(0.5f * x); }

void check(const torch::Tensor& t, const char* name) {
  TORCH_CHECK(t.is_contiguous() && t.scalar_type() == torch::kFloat && t.device().is_cpu(),
              "lstm: ", name, " must be a contiguous float32 CPU tensor");
}

}  // namespace

// z (B, I), h, c (K, B, H); per layer k: w_ih_t (I_k, 4H) and w_hh_t (H, 4H) (the weights
// transposed), bias (4H) = b_ih + b_hh -> (h' (K, B, H), c' (K, B, H), gates (K, B, 4H): i, f, g, o
// after their sigmoid / tanh, what the backward reads)
std::vector<torch::Tensor> lstm_forward(torch::Tensor z, torch::Tensor h, torch::Tensor c,
                                        std::vector<torch::Tensor> w_ih_t, std::vector<torch::Tensor> w_hh_t,
                                        std::vector<torch::Tensor> bias) {
  const int64_t K = int64_t(w_ih_t.size()), B = z.size(0), H = h.size(2), G = 4 * H;
  TORCH_CHECK(h.size(0) == K && c.sizes() == h.sizes() && h.size(1) == B && H % 16 == 0, "lstm_forward: shapes");
  for (const auto* t : {&z, &h, &c}) check(*t, "an input");
  auto h_out = torch::empty({K, B, H}, z.options()), c_out = torch::empty({K, B, H}, z.options());
  auto gates = torch::empty({K, B, G}, z.options());
  const float* x = z.data_ptr<float>();
  int64_t I = z.size(1);
  for (int64_t k = 0; k < K; ++k) {
    check(w_ih_t[k], "w_ih_t");
    check(w_hh_t[k], "w_hh_t");
    check(bias[k], "bias");
    TORCH_CHECK(w_ih_t[k].size(0) == I && w_ih_t[k].size(1) == G && w_hh_t[k].size(0) == H && I % 16 == 0,
                "lstm_forward: layer ", k, " weights do not match");
    float* gk = gates.data_ptr<float>() + k * B * G;
    const float* b = bias[k].data_ptr<float>();
    for (int64_t r = 0; r < B; ++r)
      for (int64_t j = 0; j < G; ++j) gk[r * G + j] = b[j];
    small_mm(x, I, 1, w_ih_t[k].data_ptr<float>(), B, I, G, gk, true);
    small_mm(h.data_ptr<float>() + k * B * H, H, 1, w_hh_t[k].data_ptr<float>(), B, H, G, gk, true);
    const float* cp = c.data_ptr<float>() + k * B * H;
    float* hn = h_out.data_ptr<float>() + k * B * H;
    float* cn = c_out.data_ptr<float>() + k * B * H;
    for (int64_t r = 0; r < B; ++r)
      for (int64_t j = 0; j < H; j += 16) {
        float* q = gk + r * G + j;
        const v16 i = sigmoid(load<v16>(q)), f = sigmoid(load<v16>(q + H));
        const v16 g = tanh_rational(load<v16>(q + 2 * H)), o = sigmoid(load<v16>(q + 3 * H));
        store(q, i);
        store(q + H, f);
        store(q + 2 * H, g);
        store(q + 3 * H, o);
        const v16 cv = f * load<v16>(cp + r * H + j) + i * g;
        store(cn + r * H + j, cv);
        store(hn + r * H + j, o * tanh_rational(cv));
      }
    x = hn;
    I = H;
  }
  return {h_out, c_out, gates};
}

// the gradients of one step from those of its outputs dh' and dc' (K, B, H) and what the forward
// saved -> (dz (B, I), dh (K, B, H), dc (K, B, H), then per layer dW_ih (4H, I_k), dW_hh (4H, H),
// db (4H), the gradient of b_ih and of b_hh alike); w_ih (4H, I_k), w_hh (4H, H) as stored
std::vector<torch::Tensor> lstm_backward(torch::Tensor dh_out, torch::Tensor dc_out, torch::Tensor z, torch::Tensor h,
                                         torch::Tensor c, torch::Tensor h_out, torch::Tensor c_out, torch::Tensor gates,
                                         std::vector<torch::Tensor> w_ih, std::vector<torch::Tensor> w_hh) {
  const int64_t K = int64_t(w_ih.size()), B = z.size(0), H = h.size(2), G = 4 * H;
  for (const auto* t : {&dh_out, &dc_out, &z, &h, &c, &h_out, &c_out, &gates}) check(*t, "a saved tensor or gradient");
  auto dh = torch::empty({K, B, H}, z.options()), dc = torch::empty({K, B, H}, z.options());
  auto dG = torch::empty({B, G}, z.options());
  float* dg = dG.data_ptr<float>();
  std::vector<torch::Tensor> out(3 + 3 * K);
  torch::Tensor carry;  // the gradient of layer k's h' from layer k + 1's input
  for (int64_t k = K - 1; k >= 0; --k) {
    check(w_ih[k], "w_ih");
    check(w_hh[k], "w_hh");
    const int64_t I = w_ih[k].size(1);
    const float* gk = gates.data_ptr<float>() + k * B * G;
    const float* cp = c.data_ptr<float>() + k * B * H;
    const float* cn = c_out.data_ptr<float>() + k * B * H;
    const float* dhn = dh_out.data_ptr<float>() + k * B * H;
    const float* dcn = dc_out.data_ptr<float>() + k * B * H;
    const float* up = carry.defined() ? carry.data_ptr<float>() : nullptr;
    float* dcp = dc.data_ptr<float>() + k * B * H;
    for (int64_t r = 0; r < B; ++r)
      for (int64_t j = 0; j < H; j += 16) {
        const int64_t e = r * H + j;
        const float* q = gk + r * G + j;
        const v16 i = load<v16>(q), f = load<v16>(q + H), g = load<v16>(q + 2 * H), o = load<v16>(q + 3 * H);
        const v16 tc = tanh_rational(load<v16>(cn + e));
        v16 dhv = load<v16>(dhn + e);
        if (up) dhv += load<v16>(up + e);
        const v16 dct = load<v16>(dcn + e) + dhv * o * (1.0f - tc * tc);
        store(dcp + e, dct * f);
        float* p = dg + r * G + j;
        store(p, dct * g * i * (1.0f - i));
        store(p + H, dct * load<v16>(cp + e) * f * (1.0f - f));
        store(p + 2 * H, dct * i * (1.0f - g * g));
        store(p + 3 * H, dhv * tc * o * (1.0f - o));
      }
    const float* x = k == 0 ? z.data_ptr<float>() : h_out.data_ptr<float>() + (k - 1) * B * H;
    auto dx = torch::empty({B, I}, z.options());
    small_mm(dg, G, 1, w_ih[k].data_ptr<float>(), B, G, I, dx.data_ptr<float>(), false);
    small_mm(dg, G, 1, w_hh[k].data_ptr<float>(), B, G, H, dh.data_ptr<float>() + k * B * H, false);
    auto dwi = torch::empty({G, I}, z.options()), dwh = torch::empty({G, H}, z.options());
    small_mm(dg, 1, G, x, G, B, I, dwi.data_ptr<float>(), false);  // dG^T x
    small_mm(dg, 1, G, h.data_ptr<float>() + k * B * H, G, B, H, dwh.data_ptr<float>(), false);
    auto db = torch::zeros({G}, z.options());
    float* dbp = db.data_ptr<float>();
    for (int64_t r = 0; r < B; ++r)
      for (int64_t j = 0; j < G; ++j) dbp[j] += dg[r * G + j];
    out[3 + 3 * k] = dwi;
    out[4 + 3 * k] = dwh;
    out[5 + 3 * k] = db;
    carry = dx;
  }
  out[0] = carry;
  out[1] = dh;
  out[2] = dc;
  return out;
}

TORCH_LIBRARY_FRAGMENT(meshseq, m) {
  m.def("lstm_forward", &lstm_forward);
  m.def("lstm_backward", &lstm_backward);
}
