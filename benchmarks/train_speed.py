"""Benchmark: BD-LSTM training speed at the paper's configuration.

Trains the shared-weight BD-LSTM (latent = LSTM width 128, 3 LSTM layers, 3 mesh-conv layers) on
ACAP features of ../shared/data/horse-gallop.npz (8431 vertices), 8 windows x 32 frames per
iteration (both chains: 16 roll-outs of 31 steps), Adam, exactly the step ``meshseq train`` runs,
and prints:

* seconds per iteration (median and best of the measured iterations) and the projected time of
  the paper's 7000 iterations (the paper: about 8 h on a Tesla K40c);
* achieved GFLOP/s next to a large float32 matmul's GFLOP/s measured in the same run (the
  practical limit of this machine);
* the 1-ring mean by sparse matrix vs padded gather (forward + backward), which decides the
  default ``--conv``, and the fast path's ``embedding_bag`` ring mean (forward + transpose);
* the cores' multiply-add rate with vectors in registers and fed from the L1 cache
  (``core_limits.py``): the units' peak, which the matmul and the kernels are measured against
  when the VM's memory path, not its arithmetic, is what changed from one day to the next;
* a large copy's memory bandwidth (GB/s) measured in the same run, and the bytes an iteration
  must move (the FC weight read 4 times per step, the activations saved for the backward pass,
  the banked FC inputs), as time floors next to the FLOP floor: which limit binds;
* the variants side by side, measured in turn, iteration by iteration (A/B on a busy machine):
  ``fast`` (the default float32 fast path, ``meshseq.kernels``), ``bf16`` (``--precision bf16``),
  ``reference`` (the plain ops of ``MeshConv.forward``); wall and CPU seconds per iteration (CPU
  seconds of this process are less disturbed by other processes on a shared machine);
* with --scaling, seconds per iteration vs vertices (pcow 2.9k, horse 8.4k, crane 10k, the
  horse subdivided once, 33.7k; random features: the speed does not depend on the values) and vs
  windows per iteration (4, 8, 16);
* with --profile, the operators that take the time (torch.profiler, one iteration).

FLOPs are counted analytically from the layer shapes (``meshseq.model.count_step_flops``: 2 per
multiply-add; conv channel maps, ring means, the FC and its tied transpose, VAE head, LSTM
gates), forward per step times 31 steps times 16 rows; forward + backward = 3 x forward (the
backward of a matmul is two matmuls of the same size: input and weight gradients).

    python benchmarks/train_speed.py [DATA.npz] [--iterations 5] [--variants fast,bf16,reference]
        [--conv sparse|gather|both] [--scaling] [--device cuda] [--profile]
"""

from __future__ import annotations

import argparse
import gc
import json
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import torch

from meshseq import acap
from meshseq.data.windows import WindowSampler, split_frames
from meshseq.io import load_sequence
from meshseq.mesh import Topology
from meshseq import kernels
from meshseq.kernels import MeshConvFused, keep_freed_memory, ring_mean
from meshseq.model import BDLSTM, ModelConfig, NeighborMean, count_step_flops
from meshseq.train import (TrainConfig, WindowLoss, autocast, freeze_setup_objects, fused_adam, gather_frames,
                           resolve_device)

sys.path.insert(0, str(Path(__file__).resolve().parent))  # core_limits.py beside this script

DEFAULT = Path(__file__).resolve().parent.parent.parent / "shared" / "data" / "horse-gallop.npz"


def sync(device):
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def timed(fn, device, repeat):
    times = []
    for _ in range(repeat):
        sync(device)
        t0 = time.perf_counter()
        fn()
        sync(device)
        times.append(time.perf_counter() - t0)
    return times


def matmul_gflops(device, n=4096, repeat=5) -> float:
    a = torch.randn(n, n, device=device)
    b = torch.randn(n, n, device=device)
    a @ b
    return 2 * n**3 / min(timed(lambda: a @ b, device, repeat)) / 1e9


def copy_gbps(device, mib=256, repeat=5) -> float:
    """Memory bandwidth: bytes read + written per second by a large tensor copy."""
    a = torch.randn(mib * 2**20 // 4, device=device)
    b = torch.empty_like(a)
    b.copy_(a)
    return 2 * a.numel() * 4 / min(timed(lambda: b.copy_(a), device, repeat)) / 1e9


def core_rates(device, matmul: float) -> dict:
    """The CPU cores' multiply-add rate in registers and fed from L1 (``core_limits.py``), printed
    beside the matmul: on a shared VM the matmul moves by 3x from day to day, these tell whether the
    units or the path that feeds them changed. Empty on a GPU or without a C compiler."""
    if device.type != "cpu":
        return {}
    try:
        import core_limits
        threads = torch.get_num_threads()
        rates = {"registers": core_limits.fma_gflops(threads),
                 "from_l1": core_limits.fma_gflops(threads, from_l1=True)}
    except (RuntimeError, OSError, subprocess.CalledProcessError) as e:
        print(f"cores' multiply-add rate: not measured ({e})")
        return {}
    print(f"cores' multiply-adds, {threads} threads, {core_limits.vector_lanes()}-float vectors: "
          f"{rates['registers']:.1f} GFLOP/s in registers, {rates['from_l1']:.1f} fed from L1 "
          f"(the matmul reaches {100 * matmul / rates['registers']:.0f}% of the first)")
    return rates


def duration(seconds: float) -> str:
    """``0.35 s`` or, below a tenth of a second (a GPU's floors), ``1.9 ms``."""
    return f"{seconds:.2f} s" if seconds >= 0.1 else f"{seconds * 1e3:.1f} ms"


def bytes_per_iteration(cfg: ModelConfig, rows: int, steps: int, weight_bytes: int = 4) -> dict:
    """Bytes an iteration must move between memory and the cores, by part (a floor, not a count).

    fc: the FC weight (L x 9V) read 4 times per step (encoder and decoder products, forward and
    backward) plus once for its gradient; saved: every conv layer's output written in the forward
    pass and it and its input read in the backward pass (float32); bank: the FC inputs and output
    gradients kept for the one weight-gradient matmul, written and read once.
    """
    V, C, L, K = cfg.n_vertices, cfg.channels, cfg.latent, cfg.conv_layers
    act = C * V * rows * 4
    return {"fc": (4 * steps + 2) * L * C * V * weight_bytes,
            "saved": steps * 2 * K * 3 * act,
            "bank": 2 * 2 * steps * rows * C * V * weight_bytes}


def subdivide(faces: np.ndarray, n_vertices: int) -> tuple[np.ndarray, int]:
    """One midpoint subdivision (each triangle -> 4): the connectivity of a finer mesh."""
    e = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), 1)
    edges, inv = np.unique(e, axis=0, return_inverse=True)
    m = n_vertices + inv.reshape(3, -1).T  # midpoints of (01, 12, 20) per face
    a, b, c = faces.T
    new = np.concatenate([np.stack([a, m[:, 0], m[:, 2]], 1), np.stack([m[:, 0], b, m[:, 1]], 1),
                          np.stack([m[:, 2], m[:, 1], c], 1), m])
    return new, n_vertices + len(edges)


def ring_benchmark(topo, device, rows=16, repeat=20) -> dict:
    """Milliseconds of the 1-ring mean (forward + backward) by sparse matrix, by padded gather and by
    ``embedding_bag`` (forward + transpose), and of one fused conv layer (forward + backward) with
    the C++ CPU kernel and with the torch-op path, on vertex-major ``(V, 9, rows)``."""
    out = {}
    for impl in ("sparse", "gather"):
        ring = NeighborMean(topo, impl).to(device)
        x = torch.randn(topo.n_vertices, 9, rows, device=device, requires_grad=True)  # (V, C, B)

        def fwd_bwd():
            ring(x).square().sum().backward()

        fwd_bwd()
        out[impl] = statistics.median(timed(fwd_bwd, device, repeat)) * 1e3
        if impl == "sparse":  # the fast path's ring mean (forward + the transposed one)
            z = x.detach()
            out["embedding_bag"] = statistics.median(timed(
                lambda: (ring_mean(ring, z), ring_mean(ring, z, transpose=True)), device, repeat)) * 1e3
            w = [torch.randn(9, 9, device=device, requires_grad=True) * 0.3 for _ in range(2)]
            bias, gy = torch.zeros(9, device=device, requires_grad=True), torch.randn_like(z)

            def layer():
                y = MeshConvFused.apply(x, w[0], w[1], bias, ring, True, None)
                torch.autograd.grad(y, [x, bias], gy)

            paths = {"torch-op": False}
            if device.type == "cpu" and kernels.cpu_kernels_available():
                paths = {"C++": True, "torch-op": False}
            for name, cpp in paths.items():
                saved, kernels._cpu_kernels = kernels._cpu_kernels, cpp if cpp else False
                try:
                    layer()
                    out[f"fused layer, {name}"] = statistics.median(timed(layer, device, repeat)) * 1e3
                finally:
                    kernels._cpu_kernels = saved
    return out


def make_iteration(cfg, topo, frames, sampler, rng, device, batch, precision="float32", fast=True):
    """One training iteration (exactly the step ``meshseq train`` runs) of a fresh model."""
    torch.manual_seed(0)
    model = BDLSTM(cfg, topo).to(device)
    model.fast_path = fast
    # the model's training step as issue 10 measures it: L_vertex (default recipe since 2026-12-02,
    # a sparse solve per picked frame, about +15% per iteration on horse-gallop) is left out
    objective = WindowLoss(model, TrainConfig(w_vertex=0.0))
    opt = torch.optim.Adam(model.parameters(), lr=1e-3, fused=fused_adam(device))  # as meshseq train

    def iteration():
        rows = sampler.sample(rng, batch)
        w = gather_frames(frames, torch.from_numpy(rows).to(device))
        opt.zero_grad(set_to_none=True)
        with autocast(device, precision):
            total, _ = objective(w)
        total.backward()
        opt.step()

    return iteration


VARIANTS = {"fast": ("float32", True), "bf16": ("bf16", True), "reference": ("float32", False)}


def measure_ab(iterations: dict, device, repeat: int) -> dict:
    """Wall and CPU seconds of each variant, measured in turn (A, B, C, A, B, C, ...)."""
    for fn in iterations.values():
        fn()  # warm-up
    out = {k: ([], []) for k in iterations}
    for _ in range(repeat):
        for k, fn in iterations.items():
            sync(device)
            t0, c0 = time.perf_counter(), time.process_time()
            fn()
            sync(device)
            out[k][0].append(time.perf_counter() - t0)
            out[k][1].append(time.process_time() - c0)
    return out


def scaling_table(data_dir: Path, device, repeat: int) -> list[dict]:
    """s/iteration (fast float32) vs vertices and vs windows per iteration; random features."""
    meshes = []
    for name in ("pcow", "horse-gallop", "crane"):
        path = data_dir / f"{name}.npz"
        if path.is_file():
            seq = load_sequence(str(path))
            meshes.append((name, seq.faces, seq.n_vertices))
    horse = [m for m in meshes if m[0] == "horse-gallop"]
    if horse:
        faces, n = subdivide(horse[0][1], horse[0][2])
        meshes.append(("horse subdivided", faces, n))
    cases = [(name, f, n, 8) for name, f, n in meshes] + [(name, f, n, b) for name, f, n in horse for b in (4, 16)]
    rows = []
    for name, faces, n, batch in cases:
        topo = Topology.from_faces(faces, n)
        frames = (0.1 * torch.randn(64, n, 9)).to(device)
        sampler = WindowSampler([split_frames(64, 0.0)], [name], 32)
        cfg = ModelConfig(n_vertices=n, variant="bd")
        it = make_iteration(cfg, topo, frames, sampler, np.random.default_rng(0), device, batch)
        (wall, cpu), = measure_ab({"fast": it}, device, repeat).values()
        peak = matmul_gflops(device, repeat=2)
        flops = 3 * sum(count_step_flops(cfg, topo, 2 * batch).values()) * 31
        rows.append({"mesh": name, "vertices": n, "windows": batch, "s_per_iteration": statistics.median(wall),
                     "cpu_s": statistics.median(cpu), "gflop": flops / 1e9, "matmul_gflops": peak})
        r = rows[-1]
        print(f"  {name:17s} {n:7d} {batch:4d}   {r['s_per_iteration']:7.2f} {r['cpu_s']:7.2f} "
              f"{r['gflop']:7.1f} {r['gflop'] / r['s_per_iteration']:8.1f} {peak:8.1f} "
              f"{r['s_per_iteration'] * peak:8.0f}", flush=True)
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("data", nargs="?", default=str(DEFAULT))
    ap.add_argument("--iterations", type=int, default=5, help="measured iterations (after one warm-up)")
    ap.add_argument("--window", type=int, default=32)
    ap.add_argument("--batch", type=int, default=8)
    ap.add_argument("--variants", default="fast,bf16",
                    help="comma-separated, measured in turn: fast (float32), bf16, reference (plain ops)")
    ap.add_argument("--conv", choices=("sparse", "gather", "both"), default="sparse",
                    help="ring mean of the measured model (gather: the reference conv, slow)")
    ap.add_argument("--device", default="auto")
    ap.add_argument("--threads", type=int, default=None)
    ap.add_argument("--scaling", action="store_true", help="also the table of s/iteration vs vertices and windows")
    ap.add_argument("--scaling-iterations", type=int, default=1)
    ap.add_argument("--profile", action="store_true", help="profile one iteration (first variant)")
    ap.add_argument("--json", help="also write the figures to this JSON file")
    args = ap.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    device = resolve_device(args.device)
    if device.type == "cpu":
        keep_freed_memory()  # as meshseq train does
    variants = [v.strip() for v in args.variants.split(",") if v.strip()]
    for v in variants:
        if v not in VARIANTS:
            ap.error(f"--variants: unknown {v!r} (expected {', '.join(VARIANTS)})")
    seq = load_sequence(args.data)
    topo = Topology.from_faces(seq.faces, seq.n_vertices)
    t0 = time.perf_counter()
    feats = acap.extract(seq.vertices, seq.faces)
    t_extract = time.perf_counter() - t0
    split = split_frames(len(feats), 0.2)
    scaling = acap.Scaling.fit(feats[split.train_frames()])
    frames = torch.from_numpy(scaling.apply(feats).astype(np.float32)).to(device)
    sampler = WindowSampler([split], [seq.name], args.window)
    rng = np.random.default_rng(0)
    print(f"data: {args.data}: {seq.n_frames} frames, {seq.n_vertices} vertices (ACAP features in {t_extract:.1f} s)")
    print(f"device: {device}, torch {torch.__version__}, {torch.get_num_threads()} CPU threads, "
          f"{os.cpu_count()} CPUs, load average {os.getloadavg()[0]:.1f} (other processes skew CPU timings)")

    peak = matmul_gflops(device)
    bw = copy_gbps(device)
    print(f"float32 matmul 4096^3: {peak:.1f} GFLOP/s (this machine's practical limit)")
    print(f"memory bandwidth (256 MiB copy, read + write): {bw:.1f} GB/s")
    cores = core_rates(device, peak)
    ring = ring_benchmark(topo, device, rows=2 * args.batch)
    print(f"ring mean and fused layer, forward+backward on (V, 9, {2 * args.batch}): "
          + ", ".join(f"{k} {v:.2f} ms" for k, v in ring.items()))

    steps, rows = args.window - 1, 2 * args.batch
    results = {"device": str(device), "threads": torch.get_num_threads(), "matmul_gflops": peak,
               "copy_gbps": bw, "core_gflops": cores, "ring_ms": ring, "extract_s": t_extract, "variants": {}}
    impls = ("sparse", "gather") if args.conv == "both" else (args.conv,)
    for impl in impls:
        cfg = ModelConfig(n_vertices=seq.n_vertices, variant="bd", conv_impl=impl)
        fwd = sum(count_step_flops(cfg, topo, rows).values()) * steps
        flops = 3 * fwd
        parts = count_step_flops(cfg, topo, rows)
        share = {k: v / sum(parts.values()) for k, v in parts.items()}
        print(f"\n[{impl}] {args.batch} windows x {args.window} frames, bd, {seq.n_vertices} vertices: "
              f"{flops / 1e9:.1f} GFLOP per iteration (forward {fwd / 1e9:.1f}; "
              + ", ".join(f"{k} {100 * v:.0f}%" for k, v in share.items()) + ")")
        its = {v: make_iteration(cfg, topo, frames, sampler, rng, device, args.batch, *VARIANTS[v]) for v in variants}
        frozen = freeze_setup_objects()  # as meshseq train does before its first iteration
        try:
            timings = measure_ab(its, device, args.iterations)
        finally:
            if frozen:
                gc.unfreeze()
        peak_after, bw_after = matmul_gflops(device, repeat=3), copy_gbps(device)
        # both limits again, after: this VM's speed moves from minute to minute (its neighbours' load),
        # and neither figure alone predicts the iterations' (2026-12-03: 0.86-0.88 s at 29.6-30.2
        # GB/s before, 1.09 s at 20.7, 1.05 s at 29.0 before and 38.9 after)
        print(f"[{impl}] after the iterations: float32 matmul {peak_after:.1f} GFLOP/s, copy {bw_after:.1f} GB/s; "
              f"load average {os.getloadavg()[0]:.1f}")
        results.update(matmul_gflops_after=peak_after, copy_gbps_after=bw_after)
        print(f"[{impl}] {'variant':10s} {'s/it':>6s} {'best':>6s} {'CPU s':>6s} {'GFLOP/s':>8s} "
              f"{'of mm':>6s} {'s x mm':>7s} {'7000 it':>8s}   floors: FLOP, bytes")
        for v in variants:
            wall, cpu = timings[v]
            med, best = statistics.median(wall), min(wall)
            achieved = flops / med / 1e9
            nbytes = bytes_per_iteration(cfg, rows, steps, 2 if v == "bf16" else 4)
            t_flop = flops / (peak * (2 if v == "bf16" else 1)) / 1e9
            t_bytes = sum(nbytes.values()) / (bw * 1e9)
            print(f"[{impl}] {v:10s} {med:6.2f} {best:6.2f} {statistics.median(cpu):6.2f} {achieved:8.1f} "
                  f"{100 * achieved / peak:5.0f}% {med * peak:7.0f} {7000 * med / 3600:7.1f}h   "
                  f"{duration(t_flop)}, {duration(t_bytes)} ({sum(nbytes.values()) / 1e9:.1f} GB: "
                  + ", ".join(f"{k} {b / 1e9:.1f}" for k, b in nbytes.items()) + ")")
            results["variants"][f"{impl}/{v}"] = {
                "seconds_per_iteration": med, "best": best, "times": wall, "cpu_times": cpu,
                "gflop_per_iteration": flops / 1e9, "achieved_gflops": achieved,
                "fraction_of_matmul": achieved / peak, "seconds_x_matmul_gflops": med * peak,
                "projected_7000_hours": 7000 * med / 3600, "flop_share": share, "bytes": nbytes}
        print(f"[{impl}] (s x mm: seconds per iteration x matmul GFLOP/s; the issue's target is <= 153, "
              "i.e. 0.9 s at 170 GFLOP/s)")

        if args.profile and impl == impls[0]:
            from torch.profiler import ProfilerActivity, profile

            acts = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if device.type == "cuda" else [])
            with profile(activities=acts) as prof:
                its[variants[0]]()
                sync(device)
            key = "self_cuda_time_total" if device.type == "cuda" else "self_cpu_time_total"
            print(prof.key_averages().table(sort_by=key, row_limit=40))

    if args.scaling:
        print(f"\nscaling (fast path, float32, {args.scaling_iterations} measured iteration(s) each after a warm-up):")
        print(f"  {'mesh':17s} {'V':>7s} {'win':>4s}   {'s/it':>7s} {'CPU s':>7s} {'GFLOP':>7s} "
              f"{'GFLOP/s':>8s} {'mm GF/s':>8s} {'s x mm':>8s}")
        results["scaling"] = scaling_table(Path(args.data).resolve().parent, device, args.scaling_iterations)

    print(f"\nload average at the end: {os.getloadavg()[0]:.1f}")
    if args.json:
        Path(args.json).write_text(json.dumps(results, indent=1))


if __name__ == "__main__":
    main()
