// The window losses' per-frame squared errors, forward and backward, in one pass each (CPU),
// read straight from the roll-out's vertex-major frames.
//
// frames: n tensors (V, C, R), the roll-out's steps as it made them (R = B forward chains, then,
// when R = 2B, B backward chains in their own order); windows (B, n, D): the ground truth,
// D = V x C. For each window b and frame i (j = n - 1 - i), f = the forward chains' lanes,
// g = the backward chains' lanes, x = the truth:
//
//   e[0, b, i] = ||f_i - x_i||^2                                            (L_rec, forward chain)
//   e[1, b, i] = ||g_i - x_j||^2                                            (L_rec, backward chain)
//   e[2, b, i] = ||f_i - g_j||^2                                            (L_bd)
//
// (rows 1 and 2 only with the backward chains), and with `steps` the step sizes of L_motion:
//
//   e[3, b, i] = ||f_i - f_{i-1}||^2,  e[4, b, i] = ||g_i - g_{i-1}||^2,  e[5, b, i] = ||x_i - x_{i-1}||^2
//
// (zero at i = 0; row 4 only with the backward chains). The backward writes each frame's
// gradient in the frame's own layout (V, C, R), the one the roll-out's backward adds it to:
//
//   d f_i = 2 ge[0, b, i] (f_i - x_i) + 2 ge[2, b, i] (f_i - g_j)
//   d g_i = 2 ge[1, b, i] (g_i - x_j) - 2 ge[2, b, j] (f_j - g_i)
//
// plus, with `steps`, 2 ge[3, b, i] (f_i - f_{i-1}) - 2 ge[3, b, i+1] (f_{i+1} - f_i) (and the
// same with row 4 for g); the windows get no gradient (row 5's is ignored).
//
// Why this layout: the loss used to read the frames stacked chain-major (R, n, V, C): a stack
// of all frames forward (155 MB on the horse) and a transposing copy of each frame's gradient
// backward (together about 40 ms an iteration). Here the work goes by chunks of K values of
// every frame: within a chunk all n frames' slices (and the truth's, transposed to lanes) stay
// in cache, so each frame is read once from memory however many terms use it, and the per-chain
// sums fall out lane by lane (lanes = chains).
//
// Sums: per chunk (fixed size, whatever the thread count) in float, the chunks added in double
// in order: the same bits with any number of threads.

#include <torch/extension.h>
#include <ATen/Parallel.h>

#include <cstdint>
#ifdef __AVX__
#include <immintrin.h>
#endif
#include <vector>

#include "simd.h"

namespace {

constexpr int64_t K = 256;  // values of each frame per chunk
constexpr int ROWS = 6;     // error rows kept per chunk

struct FrameSet {
  std::vector<const float*> frame;  // n pointers to (D, R)
  int64_t n, D, R, B;
  bool both;
};

FrameSet frame_set(const std::vector<torch::Tensor>& frames, const torch::Tensor& windows) {
  TORCH_CHECK(windows.dim() == 3 && windows.is_contiguous() && windows.scalar_type() == torch::kFloat &&
                  windows.device().is_cpu(),
              "frame_errors: windows must be a contiguous float32 CPU tensor (B, n, D)");
  const int64_t B = windows.size(0), n = windows.size(1), D = windows.size(2);
  TORCH_CHECK(int64_t(frames.size()) == n && n > 0, "frame_errors: ", frames.size(), " frames for windows of ", n);
  const int64_t R = frames[0].size(-1);
  TORCH_CHECK(R == B || R == 2 * B, "frame_errors: frames must have B or 2B chains (last dimension)");
  FrameSet fs{{}, n, D, R, B, R == 2 * B};
  for (const auto& f : frames) {
    TORCH_CHECK(f.is_contiguous() && f.scalar_type() == torch::kFloat && f.device().is_cpu() && f.numel() == D * R &&
                    f.size(-1) == R,
                "frame_errors: every frame must be a contiguous float32 CPU tensor (V, C, R) of D x R values");
    fs.frame.push_back(f.data_ptr<float>());
  }
  return fs;
}

#ifdef __AVX__
// r[q] (8 floats each) -> their transpose, in place: r[q][l] becomes r[l][q]
inline void transpose8(__m256 r[8]) {
  __m256 t[8], u[8];
  for (int q = 0; q < 8; q += 2) {
    t[q] = _mm256_unpacklo_ps(r[q], r[q + 1]);
    t[q + 1] = _mm256_unpackhi_ps(r[q], r[q + 1]);
  }
  for (int q = 0; q < 8; q += 4) {
    u[q] = _mm256_shuffle_ps(t[q], t[q + 2], _MM_SHUFFLE(1, 0, 1, 0));
    u[q + 1] = _mm256_shuffle_ps(t[q], t[q + 2], _MM_SHUFFLE(3, 2, 3, 2));
    u[q + 2] = _mm256_shuffle_ps(t[q + 1], t[q + 3], _MM_SHUFFLE(1, 0, 1, 0));
    u[q + 3] = _mm256_shuffle_ps(t[q + 1], t[q + 3], _MM_SHUFFLE(3, 2, 3, 2));
  }
  for (int q = 0; q < 4; ++q) {
    r[q] = _mm256_permute2f128_ps(u[q], u[q + 4], 0x20);
    r[q + 4] = _mm256_permute2f128_ps(u[q], u[q + 4], 0x31);
  }
}
#endif

// The truth of values [k0, k0 + kn) of every frame, lanes = windows: tb[(i K + k) B + b]
// (8 windows by 8 values at a time as an 8 x 8 transpose in registers where AVX is there: one
// float at a time, this copy was a fifth of the forward's time)
void truth_lanes(const float* w, const FrameSet& fs, int64_t k0, int64_t kn, float* tb) {
  const int64_t n = fs.n, B = fs.B;
  for (int64_t i = 0; i < n; ++i) {
    int64_t b = 0;
#ifdef __AVX__
    for (; b + 8 <= B; b += 8) {
      int64_t k = 0;
      for (; k + 8 <= kn; k += 8) {
        __m256 r[8];
        for (int q = 0; q < 8; ++q) {
          const float* src = w + ((b + q) * n + i) * fs.D + k0 + k;
          r[q] = _mm256_loadu_ps(src);
          if ((k & 15) == 0) __builtin_prefetch(src + K);  // the next chunk's line (a thread's next chunk)
        }
        transpose8(r);
        for (int q = 0; q < 8; ++q) _mm256_storeu_ps(tb + (i * K + k + q) * B + b, r[q]);
      }
      for (; k < kn; ++k)
        for (int q = 0; q < 8; ++q) tb[(i * K + k) * B + b + q] = w[((b + q) * n + i) * fs.D + k0 + k];
    }
#endif
    for (; b < B; ++b) {
      const float* src = w + (b * n + i) * fs.D + k0;
      float* dst = tb + i * K * B + b;
      for (int64_t k = 0; k < kn; ++k) dst[k * B] = src[k];
    }
  }
}

// G lanes as one value: 8 as a SIMD vector (simd.h's unaligned loads; streaming stores, see below), 1 as a float
template <int G> struct Lanes;
template <> struct Lanes<8> {
  typedef v8 T;
  static T load(const float* p) { return ::load<v8>(p); }
  static T splat(float s) { return ::splat<v8>(s); }
  // The gradients (310 MB on the horse) are read only when the roll-out's backward reaches their
  // frame, long after: written past the cache when aligned (no read of the lines first)
  static void store(float* p, T v) {
#ifdef __AVX__
    if ((reinterpret_cast<uintptr_t>(p) & 31) == 0) return _mm256_stream_ps(p, reinterpret_cast<__m256>(v));
#endif
    ::store(p, v);
  }
  static void put(float* p, T v) { ::store(p, v); }
};
template <> struct Lanes<1> {
  typedef float T;
  static T load(const float* p) { return *p; }
  static T splat(float s) { return s; }
  static void store(float* p, T v) { *p = v; }
  static void put(float* p, T v) { *p = v; }
};

// Error sums of lanes [b0, b0 + G) over one chunk: part[(i ROWS + row) B + b]. Each lane sums
// its own values in order, so a group of 8 as one vector (explicit: the compiler had left the
// lane loops scalar, with the sums on the stack) gives every lane the same bits as one at a time.
template <int G, bool BOTH, bool STEPS>
void chunk_errors(const FrameSet& fs, const float* tb, int64_t b0, int64_t k0, int64_t kn, float* part) {
  typedef Lanes<G> L;
  typedef typename L::T T;
  const int64_t n = fs.n, R = fs.R, B = fs.B;
  for (int64_t i = 0; i < n; ++i) {
    const int64_t j = n - 1 - i, ip = i > 0 ? i - 1 : 0;
    const float* fi = fs.frame[i] + k0 * R;
    const float* fj = fs.frame[j] + k0 * R;
    const float* fp = fs.frame[ip] + k0 * R;
    const float *xi = tb + i * K * B, *xj = tb + j * K * B, *xp = tb + ip * K * B;
    T s0{}, s1{}, s2{}, s3{}, s4{}, s5{};
    for (int64_t k = 0; k < kn; ++k) {
      const float *f = fi + k * R + b0, *x = xi + k * B + b0;
      const T fv = L::load(f), xv = L::load(x);
      const T d0 = fv - xv;
      s0 += d0 * d0;
      if (BOTH) {
        const T gv = L::load(f + B);
        const T d1 = gv - L::load(xj + k * B + b0), d2 = fv - L::load(fj + k * R + B + b0);
        s1 += d1 * d1;
        s2 += d2 * d2;
      }
      if (STEPS) {
        const float* f0 = fp + k * R + b0;
        const T d3 = fv - L::load(f0), d5 = xv - L::load(xp + k * B + b0);
        s3 += d3 * d3;
        s5 += d5 * d5;
        if (BOTH) {
          const T d4 = L::load(f + B) - L::load(f0 + B);
          s4 += d4 * d4;
        }
      }
    }
    float* out = part + i * ROWS * B + b0;
    L::put(out + 0 * B, s0);
    L::put(out + 1 * B, s1);
    L::put(out + 2 * B, s2);
    L::put(out + 3 * B, s3);  // frame 0 against itself: 0
    L::put(out + 4 * B, s4);
    L::put(out + 5 * B, s5);
  }
}

// Frame i's gradient, lanes [b0, b0 + G) (and B + b0 ...), values [k0, k0 + kn): into out (D, R)
template <int G, bool BOTH, bool STEPS>
void chunk_gradient(const FrameSet& fs, const float* tb, const float* ge, int64_t i, int64_t b0, int64_t k0,
                    int64_t kn, float* out) {
  typedef Lanes<G> L;
  typedef typename L::T T;
  const int64_t n = fs.n, R = fs.R, B = fs.B, j = n - 1 - i;
  const int64_t ip = i > 0 ? i - 1 : i, in = i < n - 1 ? i + 1 : i;
  float c[8][G];  // the coefficients per lane: 2 ge[row, b, frame]
  for (int l = 0; l < G; ++l) {
    auto coef = [&](int row, int64_t t, bool used) { return used ? 2.f * ge[(row * B + b0 + l) * n + t] : 0.f; };
    c[0][l] = coef(0, i, true);
    c[1][l] = coef(1, i, BOTH);
    c[2][l] = coef(2, i, BOTH);
    c[3][l] = coef(2, j, BOTH);
    c[4][l] = coef(3, i, STEPS && i > 0);  // the step into frame i
    c[5][l] = coef(3, i + 1, STEPS && i < n - 1);  // the step out of it
    c[6][l] = coef(4, i, STEPS && BOTH && i > 0);
    c[7][l] = coef(4, i + 1, STEPS && BOTH && i < n - 1);
  }
  T a[8];
  for (int r = 0; r < 8; ++r) a[r] = G == 1 ? L::splat(c[r][0]) : L::load(c[r]);
  const float* fi = fs.frame[i] + k0 * R;
  const float* fj = fs.frame[j] + k0 * R;
  const float* fp = fs.frame[ip] + k0 * R;
  const float* fn = fs.frame[in] + k0 * R;
  const float *xi = tb + i * K * B, *xj = tb + j * K * B;
  out += k0 * R;
  for (int64_t k = 0; k < kn; ++k) {
    const int64_t o = k * R + b0;
    const T f = L::load(fi + o), x = L::load(xi + k * B + b0);
    T gf = a[0] * (f - x);
    if (BOTH) gf += a[2] * (f - L::load(fj + o + B));
    if (STEPS) gf += a[4] * (f - L::load(fp + o)) - a[5] * (L::load(fn + o) - f);
    L::store(out + o, gf);
    if (BOTH) {
      const T g = L::load(fi + o + B);
      T gg = a[1] * (g - L::load(xj + k * B + b0)) - a[3] * (L::load(fj + o) - g);
      if (STEPS) gg += a[6] * (g - L::load(fp + o + B)) - a[7] * (L::load(fn + o + B) - g);
      L::store(out + o + B, gg);
    }
  }
}

// every lane group of B: 8 lanes at a time (vectorised), then one at a time
template <template <int, bool, bool> class Op, typename... Args>
void by_lanes(const FrameSet& fs, bool steps, Args... args) {
  int64_t b0 = 0;
  auto run = [&](auto g) {
    constexpr int G = decltype(g)::value;
    if (fs.both && steps) Op<G, true, true>::run(fs, b0, args...);
    else if (fs.both) Op<G, true, false>::run(fs, b0, args...);
    else if (steps) Op<G, false, true>::run(fs, b0, args...);
    else Op<G, false, false>::run(fs, b0, args...);
  };
  for (; b0 + 8 <= fs.B; b0 += 8) run(std::integral_constant<int, 8>{});
  for (; b0 < fs.B; ++b0) run(std::integral_constant<int, 1>{});
}

template <int G, bool BOTH, bool STEPS> struct ErrorsOp {
  static void run(const FrameSet& fs, int64_t b0, const float* tb, int64_t k0, int64_t kn, float* part) {
    chunk_errors<G, BOTH, STEPS>(fs, tb, b0, k0, kn, part);
  }
};
template <int G, bool BOTH, bool STEPS> struct GradientOp {
  static void run(const FrameSet& fs, int64_t b0, const float* tb, const float* ge, int64_t i, int64_t k0, int64_t kn,
                  float* out) {
    chunk_gradient<G, BOTH, STEPS>(fs, tb, ge, i, b0, k0, kn, out);
  }
};

// f(c, k0, kn, tb) for every chunk c: values [k0, k0 + kn) of each frame, tb their truth in lanes
// (truth_lanes); threads over chunks. STREAMED: f writes with streaming stores
template <bool STREAMED, typename F>
void for_chunks(const FrameSet& fs, const float* w, const F& f) {
  const int64_t chunks = (fs.D + K - 1) / K;
  at::parallel_for(0, chunks, 1, [&](int64_t c0, int64_t c1) {
    std::vector<float> tb(fs.n * K * fs.B);
    for (int64_t c = c0; c < c1; ++c) {
      const int64_t k0 = c * K, kn = std::min(K, fs.D - k0);
      truth_lanes(w, fs, k0, kn, tb.data());
      f(c, k0, kn, (const float*)tb.data());
    }
#ifdef __AVX__
    if (STREAMED) _mm_sfence();  // this thread's streaming stores visible before the results are handed on
#endif
  });
}

}  // namespace

// -> (3, B, n) float32, (6, B, n) with steps (rows 1, 2, 4 zero without backward chains)
torch::Tensor frame_errors(std::vector<torch::Tensor> frames, torch::Tensor windows, bool steps) {
  const FrameSet fs = frame_set(frames, windows);
  const int64_t n = fs.n, B = fs.B, chunks = (fs.D + K - 1) / K;
  std::vector<float> part(chunks * n * ROWS * B);
  for_chunks<false>(fs, windows.data_ptr<float>(), [&](int64_t c, int64_t k0, int64_t kn, const float* tb) {
    by_lanes<ErrorsOp>(fs, steps, tb, k0, kn, part.data() + c * n * ROWS * B);
  });
  const int rows = steps ? 6 : 3;
  auto e = torch::empty({rows, B, n}, windows.options());
  float* out = e.data_ptr<float>();
  // each sum over the chunks in order (part read in its own order: it is 3 MB on the horse)
  std::vector<double> total(size_t(rows) * B * n, 0.0);
  for (int64_t c = 0; c < chunks; ++c)
    for (int64_t i = 0; i < n; ++i)
      for (int r = 0; r < rows; ++r)
        for (int64_t b = 0; b < B; ++b) total[(r * B + b) * n + i] += part[((c * n + i) * ROWS + r) * B + b];
  for (size_t q = 0; q < total.size(); ++q) out[q] = float(total[q]);
  return e;
}

// ge (3 or 6, B, n): the gradient of frame_errors' output -> the gradients of frames[need[0]],
// frames[need[1]], ... (each (V, C, R) like its frame)
std::vector<torch::Tensor> frame_errors_backward(torch::Tensor ge, std::vector<torch::Tensor> frames,
                                                 torch::Tensor windows, std::vector<int64_t> need) {
  const FrameSet fs = frame_set(frames, windows);
  const int64_t n = fs.n, B = fs.B;
  auto gec = ge.to(torch::kFloat).contiguous();
  TORCH_CHECK(gec.dim() == 3 && (gec.size(0) == 3 || gec.size(0) == 6) && gec.size(1) == B && gec.size(2) == n,
              "frame_errors_backward: the gradient must be (3, B, n) or (6, B, n)");
  const bool steps = gec.size(0) == 6;
  std::vector<torch::Tensor> grads;
  std::vector<float*> out;
  for (int64_t i : need) {
    TORCH_CHECK(i >= 0 && i < n, "frame_errors_backward: frame ", i, " out of range");
    grads.push_back(torch::empty_like(frames[i]));
    out.push_back(grads.back().data_ptr<float>());
  }
  const float* G = gec.data_ptr<float>();
  for_chunks<true>(fs, windows.data_ptr<float>(), [&](int64_t, int64_t k0, int64_t kn, const float* tb) {
    for (size_t q = 0; q < need.size(); ++q) by_lanes<GradientOp>(fs, steps, tb, G, need[q], k0, kn, out[q]);
  });
  return grads;
}

TORCH_LIBRARY_FRAGMENT(meshseq, m) {
  m.def("frame_errors", &frame_errors);
  m.def("frame_errors_backward", &frame_errors_backward);
}
