// The big FC's forward products over a few columns (fc_wx: W X, fc_wtx: W^T H), shared by the training
// kernels (fc.cpp, with torch) and the inference ones (inference.cpp, without). See fc.cpp for what
// they compute, why they are laid out so, and their measured speed.
//
// The including file defines, before including this, in an anonymous namespace:
//   template <class F> void parallel_for(int64_t begin, int64_t end, int64_t grain, const F& f);
#pragma once

#include <algorithm>
#include <cstdint>

#include "simd.h"

namespace {

typedef float v4 __attribute__((vector_size(16)));

// the lanes' sum by halves (a pairwise tree: 4 vector adds, not 15 dependent scalar ones)
inline float pairwise_sum(v4 v) { return (v[0] + v[2]) + (v[1] + v[3]); }
inline float pairwise_sum(v8 v) {
  v4 lo, hi;
  __builtin_memcpy(&lo, &v, sizeof(v4));
  __builtin_memcpy(&hi, reinterpret_cast<const char*>(&v) + sizeof(v4), sizeof(v4));
  return pairwise_sum(lo + hi);
}
inline float pairwise_sum(v16 v) {
#if defined(__AVX512F__)
  v8 lo, hi;
  __builtin_memcpy(&lo, &v, sizeof(v8));
  __builtin_memcpy(&hi, reinterpret_cast<const char*>(&v) + sizeof(v8), sizeof(v8));
  return pairwise_sum(lo + hi);
#else
  return pairwise_sum(v.lo + v.hi);
#endif
}

constexpr int64_t NCHUNK_COLS = 2048;  // columns of W per partial sum of fc_wx (X's chunk: 128 KB at B = 16)
// fc_wtx reads one cache line from each of L rows in turn: more streams than the hardware
// prefetcher follows, so it asks for the line PREFETCH floats (4 lines) ahead in the same row
// (a prefetch past the end of W is harmless: it never faults). Measured on the horse, 2 threads:
// 12.9 ms a product without, 2.45 ms at 64 floats (2.57 at 32, 2.95 at 96).
constexpr int PREFETCH = 64;

// accumulators per pass: fc_wx's rows of W (WX_ROWS), fc_wtx's columns (WTX_SUB of its WTX_BLOCK-column
// blocks). AVX-512's 32 vector registers hold 8 and 16 tiles of 16 windows. With AVX2's 16 a tile is two
// registers: 6 rows (12 sums) and 6 columns (12 sums) measured best on an AMD EPYC (Zen 3, 2 threads,
// p10 of 60 alternated calls): fc_wx 2.68 ms at 6 rows against 3.30 at 8 (spilled) and 3.68 at 4;
// fc_wtx 3.37 at 6 columns against 4.8 at 4 and 3.8 at 8 (blocks of 16).
#if defined(__AVX512F__)
constexpr int WX_ROWS = 8, WTX_BLOCK = 16, WTX_SUB = 16;
#else
constexpr int WX_ROWS = 6, WTX_BLOCK = 12, WTX_SUB = 6;
#endif

// partial (LB, B) rows l0.. of one column chunk [n0, n1): sum_n W[l, n] X[n, :]
template <typename T, int W_, int LB>
inline void wx_rows(const float* Wm, int64_t N, const float* X, int64_t l0, int64_t n0, int64_t n1, int B,
                    float* partial) {
  for (int b0 = 0; b0 < B; b0 += W_) {
    T acc[LB];
    for (int i = 0; i < LB; ++i) acc[i] = T{};
    const float* w[LB];
    for (int i = 0; i < LB; ++i) w[i] = Wm + (l0 + i) * N;
    for (int64_t n = n0; n < n1; ++n) {
      const T xv = load<T>(X + n * B + b0);
      // scalar * vector: the weight broadcast inside the multiply-add (one instruction; a separate
      // broadcast of `T{} + w` compiled to an add, a broadcast and the multiply-add)
      for (int i = 0; i < LB; ++i) acc[i] += w[i][n] * xv;
    }
    for (int i = 0; i < LB; ++i) store(partial + (l0 + i) * B + b0, acc[i]);
  }
}

// x_sums (optional, N): each row of X summed over its B columns, from the chunk while it is in cache
template <typename T, int W_>
void wx(const float* Wm, const float* X, float* partial, float* x_sums, int64_t L, int64_t N, int B) {
  const int64_t nchunks = (N + NCHUNK_COLS - 1) / NCHUNK_COLS;
  parallel_for(0, nchunks, 1, [&](int64_t k0, int64_t k1) {
    for (int64_t k = k0; k < k1; ++k) {
      const int64_t n0 = k * NCHUNK_COLS, n1 = std::min(N, n0 + NCHUNK_COLS);
      float* p = partial + k * L * B;
      int64_t l0 = 0;
      for (; l0 + WX_ROWS <= L; l0 += WX_ROWS) wx_rows<T, W_, WX_ROWS>(Wm, N, X, l0, n0, n1, B, p);
      for (; l0 < L; ++l0) wx_rows<T, W_, 1>(Wm, N, X, l0, n0, n1, B, p);
      if (x_sums)
        for (int64_t n = n0; n < n1; ++n) {
          T acc = load<T>(X + n * B);
          for (int b0 = W_; b0 < B; b0 += W_) acc += load<T>(X + n * B + b0);
          x_sums[n] = pairwise_sum(acc);
        }
    }
  });
}

// out rows [n0, n0 + NB) = W[:, n0:n0+NB]^T H (+ bias)
// NS columns at a time (NS accumulators in registers); the first tile of windows prefetches W's lines
template <typename T, int W_, int NB, int NS = NB>
inline void wtx_cols(const float* Wm, int64_t L, int64_t N, const float* H, const float* bias, int64_t n0, int B,
                     float* out) {
  for (int b0 = 0; b0 < B; b0 += W_) {
    for (int s0 = 0; s0 < NB; s0 += NS) {
      T acc[NS];
      for (int j = 0; j < NS; ++j) acc[j] = T{};
      for (int64_t l = 0; l < L; ++l) {
        const T hv = load<T>(H + l * B + b0);
        const float* w = Wm + l * N + n0 + s0;
        if (b0 == 0) __builtin_prefetch(w + PREFETCH, 0, 0);
        for (int j = 0; j < NS; ++j) acc[j] += w[j] * hv;
      }
      for (int j = 0; j < NS; ++j) {
        if (bias) acc[j] += bias[n0 + s0 + j];
        store(out + (n0 + s0 + j) * B + b0, acc[j]);
      }
    }
  }
}

template <typename T, int W_>
void wtx(const float* Wm, const float* H, const float* bias, float* out, int64_t L, int64_t N, int B) {
  constexpr int NB = WTX_BLOCK;
  const int64_t nblocks = N / NB;
  parallel_for(0, nblocks, 16, [&](int64_t j0, int64_t j1) {
    for (int64_t j = j0; j < j1; ++j) wtx_cols<T, W_, NB, WTX_SUB>(Wm, L, N, H, bias, j * NB, B, out);
  });
  for (int64_t n0 = nblocks * NB; n0 < N; ++n0) wtx_cols<T, W_, 1>(Wm, L, N, H, bias, n0, B, out);
}

}  // namespace
