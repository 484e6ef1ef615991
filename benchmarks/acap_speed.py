"""Benchmark: ACAP feature extraction and reconstruction speed on real data.

Prints frames per second of extract (frame chunks on ``frame_threads()`` threads: one per CPU, or
``MESHSEQ_THREADS``) and reconstruct (default least-squares and exact encoding) on
../shared/data/crane.npz (10002 vertices, 175 frames) or a file given as the first argument, next
to this machine's limits measured in the same run: a large float64 matmul's GFLOP/s and a
streaming copy's GB/s (the feature pipeline is memory-bound elementwise work on 3x3 matrices).

    python benchmarks/acap_speed.py [DATA.npz] [--repeat 3]
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from meshseq.acap import Reconstructor, extract
from meshseq.acap.features import FRAME_CHUNK, frame_threads
from meshseq.align import per_vertex_error
from meshseq.mesh import bounding_box_diagonal

DEFAULT = Path(__file__).resolve().parent.parent.parent / "shared" / "data" / "crane.npz"


def best_of(repeat: int, fn):
    times, result = [], None
    for _ in range(repeat):
        t0 = time.perf_counter()
        result = fn()
        times.append(time.perf_counter() - t0)
    return min(times), result


def machine_limits(repeat: int) -> tuple[float, float]:
    n = 2048
    a, b = np.random.rand(n, n), np.random.rand(n, n)
    t, _ = best_of(repeat, lambda: a @ b)
    gflops = 2 * n**3 / t / 1e9
    x = np.random.rand(1 << 25)  # 256 MB
    y = np.empty_like(x)
    t, _ = best_of(repeat, lambda: np.copyto(y, x))
    gbs = 2 * x.nbytes / t / 1e9
    return gflops, gbs


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("data", nargs="?", default=str(DEFAULT))
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()
    d = np.load(args.data)
    v, f = d["vertices"].astype(np.float64), d["faces"]
    t_frames, n_vertices = v.shape[:2]
    print(f"data: {args.data}: {t_frames} frames, {n_vertices} vertices; frame chunk {FRAME_CHUNK}, "
          f"{frame_threads()} threads (MESHSEQ_THREADS)")
    gflops, gbs = machine_limits(args.repeat)
    print(f"machine: float64 matmul {gflops:.1f} GFLOP/s, streaming copy {gbs:.1f} GB/s")
    diag = bounding_box_diagonal(v)
    for exact in (False, True):
        t_ex, feats = best_of(args.repeat, lambda: extract(v, f, exact=exact))
        t_fac, rec = best_of(args.repeat, lambda: Reconstructor(v[0], f))
        t_sol, out = best_of(args.repeat, lambda: rec.solve(feats, target=v))
        err = per_vertex_error(out, v) / diag
        label = "exact  " if exact else "default"
        # bytes the pipeline must at least touch per frame: vertices in, 9 features out, (V,3,3) gradients
        gb_frame = n_vertices * (3 + 9 + 9) * 8 / 1e9
        print(f"{label}: extract {t_frames / t_ex:7.1f} frames/s ({t_frames * n_vertices / t_ex / 1e6:.2f} M vertex-frames/s,"
              f" {gb_frame * t_frames / t_ex:.2f} GB/s of minimum traffic = {100 * gb_frame * t_frames / t_ex / gbs:.0f}% of copy)"
              f" | factor {t_fac * 1e3:.0f} ms | reconstruct {t_frames / t_sol:7.1f} frames/s"
              f" | mean error {err.mean():.3g} of diag")


if __name__ == "__main__":
    main()
