// Small SIMD helpers shared by the CPU kernels (mesh_conv.cpp, lstm.cpp, frame_errors.cpp): GCC/Clang vector types
// of 16 and 8 floats (AVX-512 / AVX2 registers with -march=native), a broadcast, unaligned loads
// and stores, a lane sum and a vectorised tanh. (kernels.py hashes this file into the build flags,
// so changing it rebuilds the kernels.)
#pragma once

namespace {

typedef float v8 __attribute__((vector_size(32)));
#if defined(__AVX512F__)
typedef float v16 __attribute__((vector_size(64)));
#else
// Without AVX-512 a tile of 16 floats is a pair of 8-float vectors (two AVX2 registers). GCC
// expands a 64-byte vector type "piecewise" there, through the stack and general registers: the
// FC products took 21 ms instead of about 3 (AMD EPYC with AVX2, 2026-12-03). Each lane is computed
// as with the 64-byte type, so the results have the same bits.
struct v16 {
  v8 lo, hi;
  float operator[](int i) const { return i < 8 ? lo[i] : hi[i - 8]; }
};
#define MESHSEQ_V16_OP(op)                                                                              \
  inline v16 operator op(v16 a, v16 b) { return {a.lo op b.lo, a.hi op b.hi}; }                         \
  inline v16 operator op(float a, v16 b) { return {a op b.lo, a op b.hi}; }                             \
  inline v16 operator op(v16 a, float b) { return {a.lo op b, a.hi op b}; }                             \
  inline v16& operator op##=(v16& a, v16 b) { a.lo op## = b.lo; a.hi op## = b.hi; return a; }          \
  inline v16& operator op##=(v16& a, float b) { a.lo op## = b; a.hi op## = b; return a; }
MESHSEQ_V16_OP(+)
MESHSEQ_V16_OP(-)
MESHSEQ_V16_OP(*)
MESHSEQ_V16_OP(/)
#undef MESHSEQ_V16_OP
inline v16 operator-(v16 a) { return {-a.lo, -a.hi}; }
#endif

// s in every lane: one broadcast. (`T{} + s`, as this was, compiled to an add and a broadcast:
// 0 + s cannot be folded to s, because of s = -0; in the FC products that tripled the instructions
// per multiply-add. s - 0 is s for every s; a lane-by-lane loop compiled to 16 masked broadcasts.)
template <typename T> inline T splat(float s) { return s - T{}; }
// unaligned vectors of floats: loads and stores typed as float data (a memcpy store may alias
// anything, so the compiler reloaded every captured pointer and flag after each store)
typedef float v16u __attribute__((vector_size(64), aligned(4)));
typedef float v8u __attribute__((vector_size(32), aligned(4)));
template <typename T> struct unaligned;
template <> struct unaligned<v16> { typedef v16u type; };  // (not used for the pair without AVX-512)
template <> struct unaligned<v8> { typedef v8u type; };
template <typename T> inline T load(const float* p) { return *reinterpret_cast<const typename unaligned<T>::type*>(p); }
template <typename T> inline void store(float* p, T v) { *reinterpret_cast<typename unaligned<T>::type*>(p) = v; }
#if !defined(__AVX512F__)
template <> inline v16 load<v16>(const float* p) { return {load<v8>(p), load<v8>(p + 8)}; }
template <> inline void store<v16>(float* p, v16 v) { store(p, v.lo); store(p + 8, v.hi); }
#endif
template <typename T> inline float lanes_sum(T v) {
  float s = 0.f;
  for (int l = 0; l < int(sizeof(T) / sizeof(float)); ++l) s += v[l];
  return s;
}

template <typename T> inline T tanh_rational(T x) {
  const T c = splat<T>(7.90531110763549805f);
  x = x < -c ? -c : (x > c ? c : x);
  const T x2 = x * x;
  T p = splat<T>(-2.76076847742355e-16f);
  p = p * x2 + 2.00018790482477e-13f;
  p = p * x2 + -8.60467152213735e-11f;
  p = p * x2 + 5.12229709037114e-08f;
  p = p * x2 + 1.48572235717979e-05f;
  p = p * x2 + 6.37261928875436e-04f;
  p = p * x2 + 4.89352455891786e-03f;
  p = p * x;
  T q = splat<T>(1.19825839466702e-06f);
  q = q * x2 + 1.18534705686654e-04f;
  q = q * x2 + 2.26843463243900e-03f;
  q = q * x2 + 4.89352518554385e-03f;
  return p / q;
}

#if !defined(__AVX512F__)
template <> inline v16 tanh_rational<v16>(v16 x) { return {tanh_rational(x.lo), tanh_rational(x.hi)}; }
#endif

}  // namespace
