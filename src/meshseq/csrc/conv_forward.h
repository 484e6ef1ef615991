// The forward of one mesh-convolution layer over vertex-major frames (V, C, B): the arithmetic
// shared by the training kernel (mesh_conv.cpp, with torch) and the inference one (inference.cpp,
// without). See mesh_conv.cpp for what it computes and why it is laid out so.
//
// The including file defines, before including this, in an anonymous namespace:
//   template <class F> void parallel_for(int64_t begin, int64_t end, int64_t grain, const F& f);
// calling f(v0, v1) over chunks of [begin, end) (at::parallel_for, or OpenMP).
#pragma once

#include <cstdint>

#include "simd.h"

namespace {

constexpr int CMAX = 16;  // most channels a layer may have

struct Csr {
  const int64_t* rowptr;
  const int64_t* col;
  const float* weight;
};

// One tile of vertex v of vertex-major `a` (V, C, B): its own channels `own[c]` and the ring
// sum `ring[c] = sum_k M.weight[k] a[M.col[k], c]` over row v of M (A, or A^T in the backward).
template <typename T>
inline void own_and_ring(const float* a, Csr M, int64_t v, int C, int B, int b0, T* own, T* ring) {
  const int64_t stride = int64_t(C) * B;
  for (int c = 0; c < C; ++c) {
    ring[c] = T{};
    own[c] = load<T>(a + v * stride + c * B + b0);
  }
  for (int64_t k = M.rowptr[v]; k < M.rowptr[v + 1]; ++k) {
    const T w = splat<T>(M.weight[k]);
    const float* au = a + M.col[k] * stride + b0;
    for (int c = 0; c < C; ++c) ring[c] += w * load<T>(au + c * B);
  }
}

#if !defined(__AVX512F__)
// Without AVX-512 a tile of 16 windows is two 8-float registers (simd.h), and a whole tile's ring
// sums (2 C registers, 18 for ACAP's 9 channels) spill on AVX2's 16: a store and a reload per
// neighbour and spilled channel, in the sums' dependency chains. Summing the ring by halves of 8
// windows (the whole-tile form above on each 8-float half) keeps each half's C sums in registers;
// each lane's sum is the same as with the whole tile (the same bits).
template <>
inline void own_and_ring<v16>(const float* a, Csr M, int64_t v, int C, int B, int b0, v16* own, v16* ring) {
  v8 own_half[CMAX], ring_half[CMAX];
  for (int h = 0; h < 16; h += 8) {
    own_and_ring(a, M, v, C, B, b0 + h, own_half, ring_half);
    for (int c = 0; c < C; ++c) {
      (h ? own[c].hi : own[c].lo) = own_half[c];
      (h ? ring[c].hi : ring[c].lo) = ring_half[c];
    }
  }
}
#endif

// T: a tile of W windows
// CI, CO: the channel counts when known at compile time (0: at run time, ci and co); BT: the number
// of windows when known (a training batch of 16 chains: one tile; 0: at run time, b_rt)
// bias_stride: 0 for a bias per output channel (Co), Co for one per vertex and channel (V, Co)
template <typename T, int W, int CI, int CO, int BT = 0>
void forward_tiles(const float* X, float* Y, const float* Ws, const float* Wr, const float* bias,
                   Csr A, const float* R, int64_t V, int ci, int co, int b_rt, bool act, int64_t bias_stride) {
  const int Ci = CI ? CI : ci, Co = CO ? CO : co, B = BT ? BT : b_rt;
  const int64_t ys = int64_t(Co) * B;
  parallel_for(0, V, 128, [&](int64_t v0, int64_t v1) {
    T ax[CMAX], xv[CMAX];
    for (int64_t v = v0; v < v1; ++v) {
      for (int b0 = 0; b0 < B; b0 += W) {
        own_and_ring(X, A, v, Ci, B, b0, xv, ax);
        // the self and ring sums as two chains of multiply-adds (`acc += ws * x + wr * a`, as this
        // was, compiled to a multiply, a multiply-add and an add per channel; likewise gx below)
        for (int o = 0; o < Co; ++o) {
          T acc = splat<T>(bias[v * bias_stride + o]), acc_ring = T{};
          for (int c = 0; c < Ci; ++c) {
            acc += Ws[o * Ci + c] * xv[c];
            acc_ring += Wr[o * Ci + c] * ax[c];
          }
          acc += acc_ring;
          if (act) acc = tanh_rational(acc);
          if (R) acc += load<T>(R + v * ys + o * B + b0);
          store(Y + v * ys + o * B + b0, acc);
        }
      }
    }
  });
}


}  // namespace
