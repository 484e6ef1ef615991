// The numpy roll-out's compiled pieces (CPU, float32), without torch: plain C functions that
// numpy_net calls through ctypes (meshseq/native.py builds this file with the system's C++ compiler
// on first use). Their arithmetic is the training kernels' forward (conv_forward.h, fc_forward.h).
//
// meshseq_conv_vcb: one mesh-convolution layer on vertex-major (V, C, B) frames (see mesh_conv.cpp):
//
//   y = act(Ws x + Wr (A x) + b)        x (V, Ci, B), y (V, Co, B)
//
// Ws, Wr (Co, Ci), A the row-normalised 1-ring mean (CSR: rowptr (V + 1), col, weight), b per
// output channel (Co) or per vertex and channel (V, Co: a first layer with the input
// normalisation folded in), act tanh or nothing. B must be a whole number of tiles: a multiple of
// 16, or 8 (the caller pads). numpy took about ten passes over the frames for a layer (a sparse
// product, two GEMMs of 9 columns, the bias, tanh); this reads x once and writes y once.
// Threads: `threads` runs of vertices, on plain threads joined at the end of the layer.

#include <algorithm>
#include <cstdint>
#include <thread>
#include <vector>

namespace {

thread_local int n_threads = 1;  // set by each call (meshseq_conv_vcb's `threads`)

// [begin, end) in n_threads contiguous runs of whole grains: n_threads - 1 new threads and the caller.
// Plain threads, joined at the end: nothing spins after the layer (OpenMP's waiting workers took a
// core from the numpy work that follows each layer, on 2 cores).
template <class F>
void parallel_for(int64_t begin, int64_t end, int64_t grain, const F& f) {
  const int64_t grains = (end - begin + grain - 1) / grain;
  const int n = int(std::max<int64_t>(1, std::min<int64_t>(n_threads, grains)));
  auto run = [&](int i) {
    const int64_t a = begin + grains * i / n * grain, b = std::min(end, begin + grains * (i + 1) / n * grain);
    if (a < b) f(a, b);
  };
  std::vector<std::thread> pool;
  for (int i = 1; i < n; ++i) pool.emplace_back(run, i);
  run(0);
  for (auto& t : pool) t.join();
}

}  // namespace

#include "conv_forward.h"
#include "fc_forward.h"

extern "C" {

// 0 on success; 1 when a size is out of range (over CMAX channels, or B not 8 or a multiple of 16)
int meshseq_conv_vcb(const float* x, float* y, const float* w_self, const float* w_ring, const float* bias,
                     int64_t bias_stride, const int64_t* rowptr, const int64_t* col, const float* weight, int64_t V,
                     int B, int Ci, int Co, int act, int threads) {
  if (Ci < 1 || Ci > CMAX || Co < 1 || Co > CMAX || !(B == 8 || (B > 0 && B % 16 == 0))) return 1;
  n_threads = threads > 0 ? threads : 1;
  const Csr A{rowptr, col, weight};
  const bool nine = Ci == 9 && Co == 9;
  auto run = [&](auto tiles) { tiles(x, y, w_self, w_ring, bias, A, nullptr, V, Ci, Co, B, act != 0, bias_stride); };
  if (B == 16 && nine) run(forward_tiles<v16, 16, 9, 9, 16>);
  else if (B >= 16) nine ? run(forward_tiles<v16, 16, 9, 9>) : run(forward_tiles<v16, 16, 0, 0>);
  else nine ? run(forward_tiles<v8, 8, 9, 9>) : run(forward_tiles<v8, 8, 0, 0>);
  return 0;
}

// b[j * ldb + i] = a[i * lda + j] for i < rows, j < cols: the roll-out's frames between the
// channel-major (V*C, Bp) layout and batch-major (B, V*C) rows (numpy copies a transposed view
// element by element, at a tenth of this). Tiles of 16 x 16, `threads` runs of tile rows.
void meshseq_transpose(const float* a, int64_t lda, float* b, int64_t ldb, int64_t rows, int64_t cols, int threads) {
  constexpr int64_t TILE = 16;
  n_threads = threads > 0 ? threads : 1;
  parallel_for(0, (rows + TILE - 1) / TILE, 64, [&](int64_t t0, int64_t t1) {
    for (int64_t i0 = t0 * TILE; i0 < std::min(rows, t1 * TILE); i0 += TILE)
      for (int64_t j0 = 0; j0 < cols; j0 += TILE)
        for (int64_t j = j0; j < std::min(cols, j0 + TILE); ++j)
          for (int64_t i = i0; i < std::min(rows, i0 + TILE); ++i) b[j * ldb + i] = a[i * lda + j];
  });
}

// out (L, B) = W (L, N) X (N, B) + bias (L); partial: (ceil(N / NCHUNK_COLS), L, B) scratch. B a multiple
// of 8. The chunks' partial sums are added in order (fc.cpp's wx_product).
void meshseq_fc_wx(const float* w, const float* x, const float* bias, float* out, float* partial, int64_t L, int64_t N,
                   int B, int threads) {
  n_threads = threads > 0 ? threads : 1;
  if (B % 16 == 0) wx<v16, 16>(w, x, partial, nullptr, L, N, B);
  else wx<v8, 8>(w, x, partial, nullptr, L, N, B);
  const int64_t nchunks = (N + NCHUNK_COLS - 1) / NCHUNK_COLS;
  for (int64_t i = 0; i < L * B; ++i) out[i] = bias[i / B];
  for (int64_t k = 0; k < nchunks; ++k) {
    const float* pk = partial + k * L * B;
    for (int64_t i = 0; i < L * B; ++i) out[i] += pk[i];
  }
}

}  // extern "C"
