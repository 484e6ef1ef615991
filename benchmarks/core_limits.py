"""The cores' own arithmetic limits, measured beside the matmul and copy figures of a benchmark.

A large float32 matmul's GFLOP/s is the practical limit the training benchmarks compare with, but
on a shared VM it moves by 3x from day to day (the AVX2 machine, 2026-12-04/05: 38-63 GFLOP/s
against 137-190) while the cores' multiply-add units do not. Two probes, compiled here with the
system's C compiler (``cc``) and called through ctypes (which releases the GIL, so one Python
thread a core runs them side by side):

* ``fma_gflops(threads)``: multiply-adds on vectors held in registers, 10 independent chains
  (more than the units' latency x count), the widest vectors the compiler targets (AVX-512: 16
  floats, AVX2: 8): the cores' peak, nothing read from memory;
* ``fma_gflops(threads, from_l1=True)``: the same with one operand loaded per multiply-add from a
  16 KB buffer (the L1 cache): the rate at which the cache can feed the units. A matmul's inner
  loop needs fewer loads per multiply-add than this, the mesh-conv and FC kernels about as many.

Neither probe is a timed test: they print figures. ``python benchmarks/core_limits.py`` runs
both on 1 and on all threads.
"""

from __future__ import annotations

import ctypes
import os
import shutil
import subprocess
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

SOURCE = r"""
#ifdef __AVX512F__
#define LANES 16
#else
#define LANES 8
#endif
typedef float vec __attribute__((vector_size(LANES * 4)));
/* 16 KB cycled through, plus the 10 vectors read past its last offset */
static float buffer[4096 + 10 * 16] __attribute__((aligned(64)));

int lanes(void) { return LANES; }

/* once, before the probes run (on several threads at once: they only read the buffer) */
void fill_buffer(void) {
    for (int i = 0; i < 4096 + 10 * 16; i++) buffer[i] = 1e-7f;
}

/* 10 chains of n multiply-adds each, in named variables (registers); returns a sum so the
   compiler keeps them */
#define CHAINS(OPERAND) \
    x0 = x0 * m + OPERAND(0); x1 = x1 * m + OPERAND(1); x2 = x2 * m + OPERAND(2); \
    x3 = x3 * m + OPERAND(3); x4 = x4 * m + OPERAND(4); x5 = x5 * m + OPERAND(5); \
    x6 = x6 * m + OPERAND(6); x7 = x7 * m + OPERAND(7); x8 = x8 * m + OPERAND(8); \
    x9 = x9 * m + OPERAND(9);
#define CONSTANT(k) c
#define LOADED(k) p[k]
float fma_chains(long n, int from_l1) {
    vec m, c;
    for (int i = 0; i < LANES; i++) { m[i] = 0.999999f; c[i] = 1e-7f; }
    vec x0 = m, x1 = m, x2 = m, x3 = m, x4 = m, x5 = m, x6 = m, x7 = m, x8 = m, x9 = m;
    if (from_l1) {
        for (long i = 0; i < n; i++) {
            const vec *p = (const vec *)(buffer + ((i * 10 * LANES) & (4096 - 1)));
            CHAINS(LOADED)
        }
    } else {
        for (long i = 0; i < n; i++) { CHAINS(CONSTANT) }
    }
    vec s = x0 + x1 + x2 + x3 + x4 + x5 + x6 + x7 + x8 + x9;
    float t = 0;
    for (int i = 0; i < LANES; i++) t += s[i];
    return t;
}
"""

_library: ctypes.CDLL | None = None


def _compile() -> ctypes.CDLL:
    global _library
    if _library is None:
        cc = os.environ.get("CC") or shutil.which("cc") or shutil.which("gcc")
        if cc is None:
            raise RuntimeError("no C compiler (cc) on PATH")
        with tempfile.TemporaryDirectory(prefix="meshseq-core-limits-") as folder:
            build = Path(folder)
            (build / "probe.c").write_text(SOURCE)
            # -ffp-contract=fast: x * m + c as one fused multiply-add instruction
            subprocess.run([cc, "-O2", "-march=native", "-ffp-contract=fast", "-shared", "-fPIC",
                            str(build / "probe.c"), "-o", str(build / "probe.so")], check=True,
                           capture_output=True)
            lib = ctypes.CDLL(str(build / "probe.so"))  # stays mapped once the folder is gone
        lib.fma_chains.argtypes = (ctypes.c_long, ctypes.c_int)
        lib.fma_chains.restype = ctypes.c_float
        lib.lanes.restype = ctypes.c_int
        lib.fill_buffer()
        _library = lib
    return _library


def vector_lanes() -> int:
    """Floats a vector of the probes holds (16 with AVX-512, 8 with AVX2)."""
    return _compile().lanes()


def fma_gflops(threads: int = 1, from_l1: bool = False, seconds: float = 0.3) -> float:
    """GFLOP/s (2 per multiply-add) of ``threads`` cores running the probe at once (best of 3)."""
    lib = _compile()
    lanes = lib.lanes()
    lib.fma_chains(100_000, from_l1)  # page in, warm up
    t0 = time.perf_counter()
    lib.fma_chains(1_000_000, from_l1)
    n = max(100_000, int(1_000_000 * seconds / max(time.perf_counter() - t0, 1e-6)))

    def one(_):
        t = time.perf_counter()
        lib.fma_chains(n, from_l1)
        return time.perf_counter() - t

    best = 0.0
    with ThreadPoolExecutor(threads) as pool:
        for _ in range(3):
            elapsed = list(pool.map(one, range(threads)))
            best = max(best, sum(2 * 10 * lanes * n / t for t in elapsed) / 1e9)
    return best


def main() -> None:
    print(f"vectors of {vector_lanes()} floats")
    for threads in sorted({1, os.cpu_count() or 1}):
        print(f"{threads} thread(s): multiply-adds in registers {fma_gflops(threads):.1f} GFLOP/s, "
              f"fed from L1 {fma_gflops(threads, from_l1=True):.1f} GFLOP/s")


if __name__ == "__main__":
    main()
