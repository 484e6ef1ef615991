// The window losses' per-frame squared errors, forward and backward, in one pass each (CPU).
//
// chains (R, n, D): the roll-out's frames, R = B (forward chains only) or 2B (forward chains,
// then backward chains in their own order); windows (B, n, D): the ground truth; D = V x C.
// For each window b and frame i (j = n - 1 - i):
//
//   e[0, b, i] = ||f_i - x_i||^2        f = chains[b], x = windows[b]       (L_rec, forward chain)
//   e[1, b, i] = ||g_i - x_j||^2        g = chains[B + b]                   (L_rec, backward chain)
//   e[2, b, i] = ||f_i - g_j||^2                                            (L_bd)
//
// (rows 1 and 2 only with the backward chains), and with `steps` the step sizes of L_motion:
//
//   e[3, b, i] = ||f_i - f_{i-1}||^2,  e[4, b, i] = ||g_i - g_{i-1}||^2,  e[5, b, i] = ||x_i - x_{i-1}||^2
//
// (zero at i = 0; row 4 only with the backward chains). Written with torch operators, these terms
// cost about 25 passes over (B, n, V, C) tensors forward and backward (differences, squares,
// flipped copies, zero-filled slice gradients, accumulations; 78 MB each on the horse); here the
// forward reads each frame once and the backward reads them once and writes the two gradients:
//
//   d chains[b, i]     = 2 ge[0, b, i] (f_i - x_i) + 2 ge[2, b, i] (f_i - g_j)
//   d chains[B + b, j] = 2 ge[1, b, j] (g_j - x_i) - 2 ge[2, b, i] (f_i - g_j)
//
// plus, with `steps`, 2 ge[3, b, i] (f_i - f_{i-1}) - 2 ge[3, b, i+1] (f_{i+1} - f_i) (and the
// same with row 4 for g); the windows get no gradient (row 5's is ignored).
//
// Sums: float SIMD partial sums over blocks of BLOCK values, the blocks added in double, in a
// fixed order (the same bits with any number of threads).

#include <torch/extension.h>
#include <ATen/Parallel.h>

#include <vector>

namespace {

typedef float v16 __attribute__((vector_size(64)));

inline v16 load(const float* p) { v16 r; __builtin_memcpy(&r, p, sizeof(v16)); return r; }
inline void store(float* p, v16 v) { __builtin_memcpy(p, &v, sizeof(v16)); }
inline float lanes_sum(v16 v) {
  float s = 0.f;
  for (int l = 0; l < 16; ++l) s += v[l];
  return s;
}
constexpr int64_t BLOCK = 1024;  // values per float partial sum

// sum ||a - b||^2 over D values
double squared_distance(const float* a, const float* b, int64_t D) {
  double total = 0.0;
  for (int64_t k0 = 0; k0 < D; k0 += BLOCK) {
    const int64_t k1 = std::min(D, k0 + BLOCK);
    v16 acc = v16{};
    int64_t k = k0;
    for (; k + 16 <= k1; k += 16) {
      const v16 d = load(a + k) - load(b + k);
      acc += d * d;
    }
    float s = lanes_sum(acc);
    for (; k < k1; ++k) s += (a[k] - b[k]) * (a[k] - b[k]);
    total += s;
  }
  return total;
}

void check(const torch::Tensor& chains, const torch::Tensor& windows) {
  TORCH_CHECK(chains.dim() == 3 && windows.dim() == 3 && chains.is_contiguous() && windows.is_contiguous() &&
                  chains.scalar_type() == torch::kFloat && windows.scalar_type() == torch::kFloat &&
                  chains.device().is_cpu() && windows.device().is_cpu(),
              "frame_errors: chains and windows must be contiguous float32 CPU tensors (R, n, D), (B, n, D)");
  const int64_t B = windows.size(0);
  TORCH_CHECK(chains.size(0) == B || chains.size(0) == 2 * B, "frame_errors: chains must have B or 2B rows");
  TORCH_CHECK(chains.size(1) == windows.size(1) && chains.size(2) == windows.size(2),
              "frame_errors: chains and windows differ in frames or values per frame");
}

}  // namespace

// -> (3, B, n) float32, (6, B, n) with steps (rows 1, 2, 4 zero without backward chains)
torch::Tensor frame_errors(torch::Tensor chains, torch::Tensor windows, bool steps) {
  check(chains, windows);
  const int64_t B = windows.size(0), n = windows.size(1), D = windows.size(2);
  const bool both = chains.size(0) == 2 * B;
  auto e = torch::zeros({steps ? 6 : 3, B, n}, windows.options());
  const float* c = chains.data_ptr<float>();
  const float* x = windows.data_ptr<float>();
  float* out = e.data_ptr<float>();
  at::parallel_for(0, B * n, 1, [&](int64_t t0, int64_t t1) {
    for (int64_t t = t0; t < t1; ++t) {
      const int64_t b = t / n, i = t % n, j = n - 1 - i;
      const float* f = c + (b * n + i) * D;
      out[b * n + i] = float(squared_distance(f, x + (b * n + i) * D, D));
      if (both) {
        const float* g = c + ((B + b) * n + j) * D;
        out[(B + b) * n + j] = float(squared_distance(g, x + (b * n + i) * D, D));
        out[(2 * B + b) * n + i] = float(squared_distance(f, g, D));
        if (steps && j > 0) out[(4 * B + b) * n + j] = float(squared_distance(g, g - D, D));
      }
      if (steps && i > 0) {
        out[(3 * B + b) * n + i] = float(squared_distance(f, f - D, D));
        out[(5 * B + b) * n + i] = float(squared_distance(x + (b * n + i) * D, x + (b * n + i - 1) * D, D));
      }
    }
  });
  return e;
}

namespace {

// grad[k] += a_prev (y_k - y_{k-1}) - a_next (y_{k+1} - y_k) over D values (the step-size terms
// of frame k; a_prev = 0 at the first frame, a_next = 0 at the last, where the neighbour is unused)
void add_step_gradient(float* grad, const float* y, int64_t D, float a_prev, float a_next, bool first, bool last) {
  const float* prev = first ? y : y - D;
  const float* next = last ? y : y + D;
  const v16 ap = v16{} + a_prev, an = v16{} + a_next;
  int64_t k = 0;
  for (; k + 16 <= D; k += 16) {
    const v16 yv = load(y + k);
    store(grad + k, load(grad + k) + ap * (yv - load(prev + k)) - an * (load(next + k) - yv));
  }
  for (; k < D; ++k) grad[k] += a_prev * (y[k] - prev[k]) - a_next * (next[k] - y[k]);
}

}  // namespace

// ge (3 or 6, B, n): the gradient of frame_errors' output -> the gradient of chains (R, n, D)
torch::Tensor frame_errors_backward(torch::Tensor ge, torch::Tensor chains, torch::Tensor windows) {
  check(chains, windows);
  const int64_t B = windows.size(0), n = windows.size(1), D = windows.size(2);
  const bool both = chains.size(0) == 2 * B;
  auto gec = ge.to(torch::kFloat).contiguous();
  TORCH_CHECK(gec.dim() == 3 && (gec.size(0) == 3 || gec.size(0) == 6) && gec.size(1) == B && gec.size(2) == n,
              "frame_errors_backward: the gradient must be (3, B, n) or (6, B, n)");
  const bool steps = gec.size(0) == 6;
  auto grad = torch::empty_like(chains);
  const float* c = chains.data_ptr<float>();
  const float* x = windows.data_ptr<float>();
  const float* G = gec.data_ptr<float>();
  float* out = grad.data_ptr<float>();
  at::parallel_for(0, B * n, 1, [&](int64_t t0, int64_t t1) {
    for (int64_t t = t0; t < t1; ++t) {
      const int64_t b = t / n, i = t % n, j = n - 1 - i;
      const float* f = c + (b * n + i) * D;
      const float* xi = x + (b * n + i) * D;
      float* gf = out + (b * n + i) * D;
      const float a_rec = 2.f * G[b * n + i];
      if (both) {
        const float* g = c + ((B + b) * n + j) * D;
        float* gg = out + ((B + b) * n + j) * D;
        const float a_bd = 2.f * G[(2 * B + b) * n + i], a_back = 2.f * G[(B + b) * n + j];
        const v16 ar = v16{} + a_rec, ab = v16{} + a_bd, ak = v16{} + a_back;
        int64_t k = 0;
        for (; k + 16 <= D; k += 16) {
          const v16 fv = load(f + k), gv = load(g + k), xv = load(xi + k);
          const v16 dfg = fv - gv;
          store(gf + k, ar * (fv - xv) + ab * dfg);
          store(gg + k, ak * (gv - xv) - ab * dfg);
        }
        for (; k < D; ++k) {
          const float dfg = f[k] - g[k];
          gf[k] = a_rec * (f[k] - xi[k]) + a_bd * dfg;
          gg[k] = a_back * (g[k] - xi[k]) - a_bd * dfg;
        }
        if (steps)
          add_step_gradient(gg, g, D, j > 0 ? 2.f * G[(4 * B + b) * n + j] : 0.f,
                            j < n - 1 ? 2.f * G[(4 * B + b) * n + j + 1] : 0.f, j == 0, j == n - 1);
      } else {
        const v16 a = v16{} + a_rec;
        int64_t k = 0;
        for (; k + 16 <= D; k += 16) store(gf + k, a * (load(f + k) - load(xi + k)));
        for (; k < D; ++k) gf[k] = a_rec * (f[k] - xi[k]);
      }
      if (steps)
        add_step_gradient(gf, f, D, i > 0 ? 2.f * G[(3 * B + b) * n + i] : 0.f,
                          i < n - 1 ? 2.f * G[(3 * B + b) * n + i + 1] : 0.f, i == 0, i == n - 1);
    }
  });
  return grad;
}

TORCH_LIBRARY_FRAGMENT(meshseq, m) {
  m.def("frame_errors", &frame_errors);
  m.def("frame_errors_backward", &frame_errors_backward);
}
