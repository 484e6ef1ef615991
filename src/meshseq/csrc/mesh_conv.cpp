// One mesh-convolution layer, forward and backward, over vertex-major frames (CPU).
//
//   y = act(Ws x + Wr (A x) + b) [+ r]        x (V, Ci, B), y (V, Co, B), float32, contiguous
//
// Ws, Wr (Co, Ci) are the self and ring channel maps, A the row-normalised 1-ring mean (CSR:
// rowptr (V + 1), col, weight), b the bias, per output channel (Co) or per vertex and channel
// (V, Co: the encoder's first layer with the input normalisation folded in), act tanh or nothing,
// r an optional residual (the decoder's last layer adds the current frame). The ring mean is linear and acts on vertices only, so
// A (Wr x) = Wr (A x): each vertex gathers its neighbours' (Ci, B) blocks (contiguous rows of the
// vertex-major layout), and the two 9 x 9 maps, the bias, tanh and the residual follow while
// the block is in registers: x is read once (plus neighbour reads from cache), y written once.
//
// Backward, with g = act ? gy (1 - y^2) : gy and A^T as CSR:
//   gx = Ws^T g + Wr^T (A^T g),  gWs = sum g x^T,  gWr = sum (A^T g) x^T,  gb = sum g
// (sum over vertices and windows) in one pass over vertices (two over each block of 16: gx, then
// the weight-gradient sums in registers); optionally gx times 1 - x^2 when x is a tanh output
// (the layer below's pre-activation gradient: kernels.MeshConvStack). The weight gradients are
// summed per fixed chunk of vertices (NCHUNK, whatever the thread count) and the chunks in order,
// so the result has the same bits with any number of threads (bit-exact resume).
//
// Sizes: ACAP's 9 channels and a batch of 16 windows are compiled as constants (offsets in the
// instructions, accumulators in registers: `perf annotate` showed the run-time versions reloading
// offsets and keeping accumulators on the stack); other sizes run the same code with run-time
// sizes.
//
// Vectorised over the windows B: a tile of 16 windows of one channel (8 when B <= 8) is one SIMD
// vector (GCC/Clang vector extensions; the compiler maps them to AVX-512, AVX2 or SSE). Other
// window counts are padded with zeros to whole tiles (a copy: far cheaper than scalar code). Threads:
// at::parallel_for over vertices (torch's intra-op thread count).
// tanh: Eigen's rational approximation (what torch's vectorised CPU tanh uses), to ~1 ulp.

#include <torch/extension.h>
#include <ATen/Parallel.h>

#include <optional>
#include <vector>

namespace {

// at::parallel_for over vertices (torch's intra-op thread count), for conv_forward.h
template <class F>
void parallel_for(int64_t begin, int64_t end, int64_t grain, const F& f) {
  at::parallel_for(begin, end, grain, f);
}

}  // namespace

#include "conv_forward.h"

namespace {

constexpr int NCHUNK = 64;  // vertex chunks of the weight-gradient sums

template <typename T, int W>
void tanh_grad_tiles(const float* gy, const float* y, float* g, int64_t n) {
  at::parallel_for(0, n / W, 4096, [&](int64_t i0, int64_t i1) {
    for (int64_t i = i0; i < i1; ++i) {
      const T yi = load<T>(y + i * W);
      store(g + i * W, load<T>(gy + i * W) * (1.0f - yi * yi));
    }
  });
}

// partial: (NCHUNK, 2 Co Ci + Co) sums of gWs, gWr, gb per vertex chunk. A few vertices (SUB) at a
// time: pass 1 forms gx and keeps their A^T g in a small buffer; pass 2 forms their weight-gradient
// sums with register accumulators (OG output channels x Ci inputs at a time), instead of a
// read-modify-write of all 2 Co Ci + Co sums in memory per vertex (store-bound: a 64-byte store
// takes two cycles on AMD Zen 4). Each sum still adds the vertices in order within a chunk.
// CI, CO, BT: as in forward_tiles.
// input_tanh: x is a tanh output and gx is returned times tanh's derivative 1 - x^2 (the gradient of
// the layer below's pre-activation, which then needs no pass of its own)
template <typename T, int W, int CI, int CO, int BT = 0>
void backward_tiles(const float* G, const float* X, float* GX, const float* Ws, const float* Wr,
                    Csr At, float* partial, int64_t V, int ci, int co, int b_rt, bool input_tanh) {
  const int B = BT ? BT : b_rt;
  constexpr int SUB = 16, OG = (CO > 0 && CO % 3 == 0) ? 3 : 1, CIN = CI > 0 ? CI : CMAX;
  // pass 2's vectors (PT, PW lanes) and input channels a pass (CG): with AVX-512 a whole tile and all
  // inputs (3 x 9 sums in registers); with AVX2 (16 registers) half a tile and 3 inputs (3 x 3 sums)
#if defined(__AVX512F__)
  typedef T PT;
  constexpr int PW = W, CG = CIN;
#else
  typedef v8 PT;
  constexpr int PW = 8, CG = (CI > 0 && CI % 3 == 0) ? 3 : 1;
#endif
  const int Ci = CI ? CI : ci, Co = CO ? CO : co;
  const int64_t xs = int64_t(Ci) * B, gs = int64_t(Co) * B;
  const int n_sums = 2 * Co * Ci + Co;
  at::parallel_for(0, NCHUNK, 1, [&](int64_t k0, int64_t k1) {
    // the sums and A^T g of the SUB vertices as floats (W lanes each): pass 2 reads them in PT vectors
    alignas(64) float sums[(2 * CMAX * CMAX + CMAX) * W];
    alignas(64) float atgbuf[SUB * CMAX * W];
    for (int64_t chunk = k0; chunk < k1; ++chunk) {
      for (int i = 0; i < n_sums * W; ++i) sums[i] = 0.f;
      const int64_t v0 = V * chunk / NCHUNK, v1 = V * (chunk + 1) / NCHUNK;
      for (int b0 = 0; b0 < B; b0 += W) {
        for (int64_t vs = v0; vs < v1; vs += SUB) {
          const int n = int(std::min<int64_t>(SUB, v1 - vs));
          for (int i = 0; i < n; ++i) {  // pass 1: gx = Ws^T g + Wr^T (A^T g)
            const int64_t v = vs + i;
            T gv[CMAX], atg[CMAX];
            own_and_ring(G, At, v, Co, B, b0, gv, atg);
            for (int c = 0; c < Ci; ++c) {
              T s = T{}, s_ring = T{};
              for (int o = 0; o < Co; ++o) {
                s += Ws[o * Ci + c] * gv[o];
                s_ring += Wr[o * Ci + c] * atg[o];
              }
              s += s_ring;
              if (input_tanh) {
                const T xc = load<T>(X + v * xs + c * B + b0);
                s *= 1.0f - xc * xc;
              }
              store(GX + v * xs + c * B + b0, s);
            }
            for (int o = 0; o < Co; ++o) store(atgbuf + (i * Co + o) * W, atg[o]);
          }
          // pass 2: gWs += g x^T, gWr += (A^T g) x^T, OG output channels x CG inputs of PT lanes at a time
          for (int ring = 0; ring < 2; ++ring) {
            float* S = sums + ring * Co * Ci * W;
            for (int h = 0; h < W; h += PW)
              for (int o0 = 0; o0 < Co; o0 += OG) {
                const int og = CO > 0 ? OG : std::min(OG, Co - o0);  // a constant when CO is: registers
                for (int c0 = 0; c0 < Ci; c0 += CG) {
                  const int cg = CI > 0 ? CG : std::min(CG, Ci - c0);
                  PT acc[OG][CG];
                  for (int j = 0; j < og; ++j)
                    for (int c = 0; c < cg; ++c) acc[j][c] = load<PT>(S + ((o0 + j) * Ci + c0 + c) * W + h);
                  for (int i = 0; i < n; ++i) {
                    const int64_t v = vs + i;
                    PT gj[OG];
                    for (int j = 0; j < og; ++j)
                      gj[j] = ring ? load<PT>(atgbuf + (i * Co + o0 + j) * W + h)
                                   : load<PT>(G + v * gs + (o0 + j) * B + b0 + h);
                    for (int c = 0; c < cg; ++c) {
                      const PT xc = load<PT>(X + v * xs + (c0 + c) * B + b0 + h);
                      for (int j = 0; j < og; ++j) acc[j][c] += gj[j] * xc;
                    }
                  }
                  for (int j = 0; j < og; ++j)
                    for (int c = 0; c < cg; ++c) store(S + ((o0 + j) * Ci + c0 + c) * W + h, acc[j][c]);
                }
              }
          }
          float* gb = sums + 2 * Co * Ci * W;  // gb += g
          for (int i = 0; i < n; ++i)
            for (int o = 0; o < Co; ++o)
              store(gb + o * W, load<T>(gb + o * W) + load<T>(G + (vs + i) * gs + o * B + b0));
        }
      }
      for (int i = 0; i < n_sums; ++i) partial[chunk * n_sums + i] = lanes_sum(load<T>(sums + i * W));
    }
  });
}

Csr csr(const torch::Tensor& rowptr, const torch::Tensor& col, const torch::Tensor& weight) {
  return {rowptr.data_ptr<int64_t>(), col.data_ptr<int64_t>(), weight.data_ptr<float>()};
}

// windows per tile for B windows, and B padded to whole tiles
int tile(int B) { return B > 8 ? 16 : 8; }
torch::Tensor pad_windows(const torch::Tensor& t, int Bp) {
  return t.size(2) == Bp ? t.contiguous() : torch::constant_pad_nd(t, {0, Bp - t.size(2)}).contiguous();
}

void check(const torch::Tensor& x, const torch::Tensor& w_self, int64_t V) {
  TORCH_CHECK(x.dim() == 3 && x.is_contiguous() && x.scalar_type() == torch::kFloat && x.device().is_cpu(),
              "mesh_conv: x must be a contiguous float32 CPU tensor (V, C, B)");
  TORCH_CHECK(x.size(1) <= CMAX && w_self.size(0) <= CMAX, "mesh_conv: at most 16 channels");
  TORCH_CHECK(x.size(0) == V, "mesh_conv: x has ", x.size(0), " vertices, the ring ", V);
}

}  // namespace

torch::Tensor conv_forward(torch::Tensor x_in, torch::Tensor w_self, torch::Tensor w_ring, torch::Tensor bias,
                           torch::Tensor rowptr, torch::Tensor col, torch::Tensor weight, bool act,
                           std::optional<torch::Tensor> residual) {
  const int64_t V = rowptr.size(0) - 1;
  check(x_in, w_self, V);
  const int B_in = x_in.size(2), W = tile(B_in), B = (B_in + W - 1) / W * W;
  auto x = pad_windows(x_in, B);
  const int Ci = x.size(1), Co = w_self.size(0);
  auto ws = w_self.contiguous(), wr = w_ring.contiguous(), b = bias.contiguous();
  auto y = torch::empty({V, Co, B}, x.options());
  torch::Tensor r;
  if (residual.has_value()) r = pad_windows(*residual, B);
  const float* R = residual.has_value() ? r.data_ptr<float>() : nullptr;
  // a bias per vertex and channel (V, Co): the encoder's first layer reading the raw frame of a model
  // with input normalisation (kernels.MeshConvStack)
  TORCH_CHECK(b.scalar_type() == torch::kFloat && ((b.dim() == 1 && b.size(0) == Co) ||
                                                   (b.dim() == 2 && b.size(0) == V && b.size(1) == Co)),
              "mesh_conv: the bias must be (C_out,) or (V, C_out) float32");
  const int64_t bias_stride = b.dim() == 2 ? Co : 0;
  auto run = [&](auto tiles) {
    tiles(x.data_ptr<float>(), y.data_ptr<float>(), ws.data_ptr<float>(), wr.data_ptr<float>(), b.data_ptr<float>(),
          csr(rowptr, col, weight), R, V, Ci, Co, B, act, bias_stride);
  };
  // ACAP's 9 channels, and 16 windows: sizes known to the compiler (constant offsets, fewer registers)
  const bool nine = Ci == 9 && Co == 9;
  if (W == 16 && nine && B == 16) run(forward_tiles<v16, 16, 9, 9, 16>);
  else if (W == 16) nine ? run(forward_tiles<v16, 16, 9, 9>) : run(forward_tiles<v16, 16, 0, 0>);
  else nine ? run(forward_tiles<v8, 8, 9, 9>) : run(forward_tiles<v8, 8, 0, 0>);
  return B == B_in ? y : y.narrow(2, 0, B_in).contiguous();
}

// returns (gx, gWs, gWr, gb); y: the layer's output when act (tanh) and gy is the gradient of that
// output, else None (no activation, or gy already the pre-activation's gradient); input_tanh: x is
// a tanh output, and gx comes back times 1 - x^2
std::vector<torch::Tensor> conv_backward(torch::Tensor gy, std::optional<torch::Tensor> y, torch::Tensor x_in,
                                         torch::Tensor w_self, torch::Tensor w_ring,
                                         torch::Tensor rowptr_t, torch::Tensor col_t, torch::Tensor weight_t,
                                         bool input_tanh) {
  const int64_t V = rowptr_t.size(0) - 1;
  check(x_in, w_self, V);
  const int B_in = x_in.size(2), W = tile(B_in), B = (B_in + W - 1) / W * W;
  auto x = pad_windows(x_in, B);  // padded windows: x = 0 and g = 0 there, so they add nothing
  const int Ci = x.size(1), Co = w_self.size(0);
  auto ws = w_self.contiguous(), wr = w_ring.contiguous();
  torch::Tensor g = pad_windows(gy, B);
  if (y.has_value()) {
    auto out = pad_windows(*y, B);
    auto gt = torch::empty_like(g);
    const int64_t n = g.numel();  // a multiple of 8 (B is)
    if (n % 16 == 0) tanh_grad_tiles<v16, 16>(g.data_ptr<float>(), out.data_ptr<float>(), gt.data_ptr<float>(), n);
    else tanh_grad_tiles<v8, 8>(g.data_ptr<float>(), out.data_ptr<float>(), gt.data_ptr<float>(), n);
    g = gt;
  }
  auto gx = torch::empty({V, Ci, B}, x.options());
  const int n_sums = 2 * Co * Ci + Co;
  std::vector<float> partial(size_t(NCHUNK) * n_sums);
  auto run = [&](auto tiles) {
    tiles(g.data_ptr<float>(), x.data_ptr<float>(), gx.data_ptr<float>(), ws.data_ptr<float>(), wr.data_ptr<float>(),
          csr(rowptr_t, col_t, weight_t), partial.data(), V, Ci, Co, B, input_tanh);
  };
  const bool nine = Ci == 9 && Co == 9;
  if (W == 16 && nine && B == 16) run(backward_tiles<v16, 16, 9, 9, 16>);
  else if (W == 16) nine ? run(backward_tiles<v16, 16, 9, 9>) : run(backward_tiles<v16, 16, 0, 0>);
  else nine ? run(backward_tiles<v8, 8, 9, 9>) : run(backward_tiles<v8, 8, 0, 0>);
  auto sums = torch::empty({n_sums}, x.options());
  float* s = sums.data_ptr<float>();
  for (int i = 0; i < n_sums; ++i) {
    double acc = 0.0;
    for (int k = 0; k < NCHUNK; ++k) acc += partial[size_t(k) * n_sums + i];
    s[i] = float(acc);
  }
  if (B != B_in) gx = gx.narrow(2, 0, B_in).contiguous();
  return {gx, sums.slice(0, 0, Co * Ci).view({Co, Ci}), sums.slice(0, Co * Ci, 2 * Co * Ci).view({Co, Ci}),
          sums.slice(0, 2 * Co * Ci, n_sums)};
}

TORCH_LIBRARY(meshseq, m) {
  m.def("conv_forward", &conv_forward);
  m.def("conv_backward", &conv_backward);
}
