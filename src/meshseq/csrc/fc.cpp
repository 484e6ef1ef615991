// The big FC's per-step products on CPU, for a few columns (the windows of a training batch).
//
//   fc_wx:   out (L, B) = W (L, N) X (N, B)  [+ bias (L)]     the encoder; the decoder's backward
//   fc_wtx:  out (N, B) = W^T H  [+ bias (N)], H (L, B)        the decoder; the encoder's backward
//
// W is the FC weight (L = 128 latent rows, N = V x 9 columns: 39 MB on the horse), read as it is
// stored (row-major, no transposed copy); X, H and out are float32 with B columns, B a multiple
// of 8 (a training batch: 16 chains). With so few columns a product is a stream over W: one
// multiply-add per weight and column, W read once from memory. BLAS treats these shapes as
// general matrix products (packing panels of W, blocking for a large third dimension) and ran
// them at 60-88 GFLOP/s on 2 cores; here each weight is loaded once, broadcast, and multiplied
// with a SIMD vector of B columns (16 windows: one AVX-512 register, or two AVX2 registers, simd.h).
//
// fc_wx: WX_ROWS rows of W at a time against one vector of X (that many independent accumulators and
// sequential streams of W; X's chunk stays in the L2 cache across the row blocks); the N columns are
// cut into fixed chunks (NCHUNK_COLS), each chunk's partial sums stored, and the chunks summed in
// order afterwards: the same bits with any number of threads (bit-exact resume). fc_wtx: blocks of
// WTX_BLOCK columns of W (16 with AVX-512: one cache line of each row), all L rows, WTX_SUB
// accumulators a pass; each output row is written once, so no reduction is needed.
// Measured with AVX-512 (AMD Zen 4; horse, N = 75879, B = 16, 2 threads, 10th percentile of 60):
// fc_wx 1.96 ms, fc_wtx 2.04 ms, about the time to read W's 39 MB from memory (27 GB/s measured by a
// read-only sum); with W in the L3 cache (N = 20000) 0.39 and 0.37 ms, 6.6 G multiply-adds of 16
// lanes a second, above a 4096^3 float32 matmul's rate on this machine. (torch.addmm/mm: 3.98 and
// 5.18 ms, 2026-12-02.) With AVX2 (AMD Zen 3, 2026-12-03): fc_wx 2.6-3.7 ms, fc_wtx 3.2-3.4 ms
// (torch.mm 3.5-5 and 4.5-9 ms); 21 ms each before v16 became a register pair there.

#include <torch/extension.h>
#include <ATen/Parallel.h>

#include <optional>

namespace {

// at::parallel_for (torch's intra-op thread count), for fc_forward.h
template <class F>
void parallel_for(int64_t begin, int64_t end, int64_t grain, const F& f) {
  at::parallel_for(begin, end, grain, f);
}

}  // namespace

#include "fc_forward.h"

namespace {

void check(const torch::Tensor& t, const char* name, int64_t rows, int64_t cols) {
  TORCH_CHECK(t.dim() == 2 && t.size(0) == rows && t.size(1) == cols, "fc: ", name, " must be (", rows, ", ", cols,
              "), got ", t.sizes());
  TORCH_CHECK(t.is_contiguous() && t.scalar_type() == torch::kFloat && t.device().is_cpu(),
              "fc: ", name, " must be a contiguous float32 CPU tensor");
}

void check_bias(const std::optional<torch::Tensor>& bias, int64_t n) {
  if (!bias.has_value()) return;
  TORCH_CHECK(bias->dim() == 1 && bias->size(0) == n && bias->is_contiguous() && bias->scalar_type() == torch::kFloat,
              "fc: bias must be a contiguous float32 vector of ", n);
}

int tile_width(int64_t B) {
  TORCH_CHECK(B > 0 && B % 8 == 0, "fc: the number of columns must be a multiple of 8, got ", B);
  return B % 16 == 0 ? 16 : 8;
}

// ---- the banked weight gradient: g (L, N) = sum_t left_t^T right_t^T ----
//
// g[l, n] = sum_t sum_r left_t[r, l] right_t[n, r], over the roll-out's (left (B_t, L), right (N, B_t))
// pairs: the FC's inputs or output gradients (N = V x 9 rows, B_t = 16 chains) and the matching
// (B_t, L) gradients or LSTM outputs, 62 pairs an iteration on the horse. As one matmul this
// needed the rights concatenated into one (N, sum B_t) matrix (301 MB written and read again)
// and its (N, L) product transposed into the weight's layout block by block; here each thread
// takes NR = 3 rows n at a time, reads their B_t values straight from every right (one cache
// line each), broadcasts them against the left rows' 8 vectors of 16 l, and keeps the 3 x 8
// sums in registers over all pairs; the sums are written to g's columns n (the weight's own
// layout). Every g[l, n] is summed by one thread in a fixed order (pairs, then r): the same bits
// with any number of threads.
constexpr int GRAD_AHEAD = 4;  // tiles ahead whose right rows are prefetched

// rows n .. n + NR of g's columns, latent rows 16 j0 .. 16 (j0 + LP) of L = 16 LV
template <int NR, int LP, int LV>
inline void grad_tile(const float* const* rights, const int64_t* widths, int64_t T, const float* left,
                      int64_t n, int64_t N, int j0, float* g) {
  v16 acc[NR][LP];
  for (int i = 0; i < NR; ++i)
    for (int j = 0; j < LP; ++j) acc[i][j] = v16{};
  const float* lrow = left + 16 * j0;
  for (int64_t t = 0; t < T; ++t) {
    const int64_t B = widths[t];
    const float* r = rights[t] + n * B;
    if (j0 == 0 && n + (GRAD_AHEAD + 1) * NR <= N)  // the rows GRAD_AHEAD tiles ahead (a row of 16 values: one line)
      for (int i = 0; i < NR; ++i) __builtin_prefetch(r + (GRAD_AHEAD * NR + i) * B, 0, 0);
    for (int64_t b = 0; b < B; ++b, lrow += LV * 16) {
      float s[NR];
      for (int i = 0; i < NR; ++i) s[i] = r[i * B + b];
      for (int j = 0; j < LP; ++j) {
        v16 w = load<v16>(lrow + 16 * j);
#if defined(__AVX512F__)
        __asm__("" : "+v"(w));  // one load into a register for the NR multiply-adds, not NR memory operands
#endif
        for (int i = 0; i < NR; ++i) acc[i][j] += s[i] * w;
      }
    }
  }
  // through a buffer: reading the accumulators' lanes directly made the compiler keep them on the stack
  float buf[NR][LP * 16];
  for (int i = 0; i < NR; ++i)
    for (int j = 0; j < LP; ++j) store(buf[i] + 16 * j, acc[i][j]);
  for (int l = 0; l < LP * 16; ++l)
    for (int i = 0; i < NR; ++i) g[(16 * j0 + l) * N + n + i] = buf[i][l];
}

// NR rows x LP latent vectors of sums in registers, and the NR broadcasts. AVX-512 (32 registers): all L
// at once, NR x LV <= 24. AVX2 (16 registers, a v16 two of them): one latent vector a pass over the
// same NR = 6 rows (12 registers of sums; each vector of left read from the L2 cache serves 6 rows).
// L = 128 on the horse (AMD EPYC, Zen 3, 2 threads): 211 ms against 291 at 3 rows x 2 vectors, 339 at
// 2 x 2, 432 at 1 x 4, and 446 for torch's concatenation, matmul and transpose.
#if defined(__AVX512F__)
template <int LV> constexpr int grad_rows() { return LV >= 16 ? 1 : LV == 8 ? 3 : LV == 4 ? 6 : 8; }
template <int LV> constexpr int grad_pass() { return LV; }
#else
template <int LV> constexpr int grad_rows() { return 6; }
template <int LV> constexpr int grad_pass() { return 1; }
#endif

template <int NR, int LV>
inline void grad_rows_all_passes(const float* const* rights, const int64_t* widths, int64_t T, const float* left,
                                 int64_t n, int64_t N, float* g) {
  constexpr int LP = grad_pass<LV>();
  for (int j0 = 0; j0 < LV; j0 += LP) grad_tile<NR, LP, LV>(rights, widths, T, left, n, N, j0, g);
}

template <int LV>
void grad_tiles(const float* const* rights, const int64_t* widths, int64_t T, const float* left, int64_t N, float* g) {
  constexpr int NR = grad_rows<LV>();
  const int64_t tiles = N / NR;
  at::parallel_for(0, tiles, 64, [&](int64_t k0, int64_t k1) {
    for (int64_t k = k0; k < k1; ++k) grad_rows_all_passes<NR, LV>(rights, widths, T, left, k * NR, N, g);
  });
  for (int64_t n = tiles * NR; n < N; ++n) grad_rows_all_passes<1, LV>(rights, widths, T, left, n, N, g);
}

// whether fc_weight_grad has a kernel for L latent rows: L = 16, 32, 64, 128 or 256
bool fc_weight_grad_supports(int64_t L) { return L == 16 || L == 32 || L == 64 || L == 128 || L == 256; }

}  // namespace

// left (sum B_t, L) (the pairs' lefts stacked in order), rights: T tensors (N, B_t) -> g (L, N)
torch::Tensor fc_weight_grad(torch::Tensor left, std::vector<torch::Tensor> rights) {
  TORCH_CHECK(!rights.empty(), "fc_weight_grad: no pairs");
  const int64_t N = rights[0].size(0), L = left.size(1), T = int64_t(rights.size());
  TORCH_CHECK(fc_weight_grad_supports(L), "fc_weight_grad: no kernel for L = ", L);
  std::vector<const float*> ptrs(T);
  std::vector<int64_t> widths(T);
  int64_t rows = 0;
  for (int64_t t = 0; t < T; ++t) {
    check(rights[t], "right", N, rights[t].size(1));
    ptrs[t] = rights[t].data_ptr<float>();
    widths[t] = rights[t].size(1);
    rows += widths[t];
  }
  check(left, "left", rows, L);
  auto g = torch::empty({L, N}, left.options());
  float* gp = g.data_ptr<float>();
  const float* lp = left.data_ptr<float>();
  switch (L / 16) {
    case 1: grad_tiles<1>(ptrs.data(), widths.data(), T, lp, N, gp); break;
    case 2: grad_tiles<2>(ptrs.data(), widths.data(), T, lp, N, gp); break;
    case 4: grad_tiles<4>(ptrs.data(), widths.data(), T, lp, N, gp); break;
    case 8: grad_tiles<8>(ptrs.data(), widths.data(), T, lp, N, gp); break;
    default: grad_tiles<16>(ptrs.data(), widths.data(), T, lp, N, gp); break;
  }
  return g;
}

namespace {

// W (L, N), X (N, B) -> (L, B); x_sums: X's row sums (N) into it when defined
torch::Tensor wx_product(torch::Tensor weight, torch::Tensor x, std::optional<torch::Tensor> bias, float* x_sums) {
  const int64_t L = weight.size(0), N = weight.size(1), B = x.size(1);
  check(weight, "weight", L, N);
  check(x, "x", N, B);
  check_bias(bias, L);
  const int W_ = tile_width(B);
  const int64_t nchunks = (N + NCHUNK_COLS - 1) / NCHUNK_COLS;
  auto partial = torch::empty({nchunks, L, B}, x.options());
  if (W_ == 16) wx<v16, 16>(weight.data_ptr<float>(), x.data_ptr<float>(), partial.data_ptr<float>(), x_sums, L, N, B);
  else wx<v8, 8>(weight.data_ptr<float>(), x.data_ptr<float>(), partial.data_ptr<float>(), x_sums, L, N, B);
  auto out = torch::empty({L, B}, x.options());
  const float* p = partial.data_ptr<float>();
  float* o = out.data_ptr<float>();
  const float* b = bias.has_value() ? bias->data_ptr<float>() : nullptr;
  // the chunks' partial sums in chunk order (the same bits with any thread count), chunk by
  // chunk over all L x B outputs: contiguous, vectorised rows instead of a strided scalar sum
  for (int64_t i = 0; i < L * B; ++i) o[i] = 0.f;
  for (int64_t k = 0; k < nchunks; ++k) {
    const float* pk = p + k * L * B;
    for (int64_t i = 0; i < L * B; ++i) o[i] += pk[i];
  }
  if (b)
    for (int64_t i = 0; i < L * B; ++i) o[i] += b[i / B];
  return out;
}

}  // namespace

// W (L, N), X (N, B) -> (L, B)
torch::Tensor fc_wx(torch::Tensor weight, torch::Tensor x, std::optional<torch::Tensor> bias) {
  return wx_product(weight, x, bias, nullptr);
}

// W (L, N), X (N, B) -> (W X (L, B), X's row sums (N)): the decoder's backward, where X is the
// gradient of the decoder's FC output and its row sums the decoder bias's gradient (a separate
// torch sum read the 4.9 MB X once more per step)
std::vector<torch::Tensor> fc_wx_row_sums(torch::Tensor weight, torch::Tensor x) {
  auto sums = torch::empty({x.size(0)}, x.options());
  auto out = wx_product(weight, x, std::nullopt, sums.data_ptr<float>());
  return {out, sums};
}

// W (L, N), H (L, B) -> (N, B)
torch::Tensor fc_wtx(torch::Tensor weight, torch::Tensor h, std::optional<torch::Tensor> bias) {
  const int64_t L = weight.size(0), N = weight.size(1), B = h.size(1);
  check(weight, "weight", L, N);
  check(h, "h", L, B);
  check_bias(bias, N);
  const int W_ = tile_width(B);
  auto out = torch::empty({N, B}, h.options());
  const float* b = bias.has_value() ? bias->data_ptr<float>() : nullptr;
  if (W_ == 16) wtx<v16, 16>(weight.data_ptr<float>(), h.data_ptr<float>(), b, out.data_ptr<float>(), L, N, B);
  else wtx<v8, 8>(weight.data_ptr<float>(), h.data_ptr<float>(), b, out.data_ptr<float>(), L, N, B);
  return out;
}

TORCH_LIBRARY_FRAGMENT(meshseq, m) {
  m.def("fc_wx", &fc_wx);
  m.def("fc_wx_row_sums", &fc_wx_row_sums);
  m.def("fc_wtx", &fc_wtx);
  m.def("fc_weight_grad", &fc_weight_grad);
  m.def("fc_weight_grad_supports", &fc_weight_grad_supports);
}
