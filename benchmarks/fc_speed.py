"""The big FC's products of a roll-out step, each way: the compiled streams over the weight (the
inference library's ``fc_wx``, the training kernels' ``fc_wx`` / ``fc_wtx``) against numpy's BLAS,
at a crane-sized model (latent 128, 10,002 vertices x 9 channels, 16 chains), beside the machine's
copy rate: each product reads the 46 MB weight once, so its floor is the weight's bytes over the
read rate (half the copy rate counted read + write).

    python benchmarks/fc_speed.py [--repeat 20]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from synthesis_speed import machine_rates  # noqa: E402

L, N, B = 128, 10002 * 9, 16


def best_ms(f, repeat: int) -> float:
    f()
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        f()
        times.append(time.perf_counter() - t0)
    return float(np.min(times) * 1e3)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--repeat", type=int, default=20)
    args = p.parse_args()
    from meshseq import kernels, native

    gflops, gbs = machine_rates(3)
    floor = 4 * L * N / (gbs / 2 * 1e9) * 1e3
    print(f"machine: float32 matmul {gflops:.1f} GFLOP/s, copy {gbs:.1f} GB/s (read + write); torch threads "
          f"{torch.get_num_threads()}; floor of a product (the weight read once) {floor:.2f} ms")
    rng = np.random.default_rng(0)
    w = rng.standard_normal((L, N)).astype(np.float32)
    x = rng.standard_normal((N, B)).astype(np.float32)
    h = rng.standard_normal((L, B)).astype(np.float32)
    zeros_l, zeros_n = np.zeros(L, np.float32), np.zeros(N, np.float32)
    wt, xt, ht = (torch.from_numpy(a) for a in (w, x, h))
    lib, threads = native.conv_library(), torch.get_num_threads()
    rows = []
    if lib is not None:
        rows.append(("W x, inference library", lambda: native.fc_wx(lib, w, x, zeros_l, threads)))
    if kernels.cpu_kernels_available():
        rows += [("W x, training kernel", lambda: torch.ops.meshseq.fc_wx(wt, xt, None)),
                 ("W^T h, training kernel", lambda: torch.ops.meshseq.fc_wtx(wt, ht, None))]
    rows += [("W x, numpy", lambda: w @ x), ("W^T h, numpy (h^T W)", lambda: h.T @ w)]
    for name, f in rows:
        t = best_ms(f, args.repeat)
        print(f"{name:26s} {t:6.2f} ms ({t / floor:4.2f}x floor)")


if __name__ == "__main__":
    main()
