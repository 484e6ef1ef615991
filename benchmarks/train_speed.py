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
  default ``--conv``;
* with --profile, the operators that take the time (torch.profiler, one iteration).

FLOPs are counted analytically from the layer shapes (``meshseq.model.count_step_flops``: 2 per
multiply-add; conv channel maps, ring means, the FC and its tied transpose, VAE head, LSTM
gates), forward per step times 31 steps times 16 rows; forward + backward = 3 x forward (the
backward of a matmul is two matmuls of the same size: input and weight gradients).

    python benchmarks/train_speed.py [DATA.npz] [--iterations 5] [--conv both] [--profile]
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import time
from pathlib import Path

import numpy as np
import torch

from meshseq import acap
from meshseq.data.windows import WindowSampler, split_frames
from meshseq.io import load_sequence
from meshseq.mesh import Topology
from meshseq.model import BDLSTM, ModelConfig, NeighborMean, count_step_flops
from meshseq.train import TrainConfig, WindowLoss, resolve_device

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


def ring_benchmark(topo, device, rows=16, repeat=20) -> dict:
    out = {}
    for impl in ("sparse", "gather"):
        ring = NeighborMean(topo, impl).to(device)
        x = torch.randn(9, topo.n_vertices, rows, device=device, requires_grad=True)  # (C, V, B)

        def fwd_bwd():
            ring(x).square().sum().backward()

        fwd_bwd()
        out[impl] = statistics.median(timed(fwd_bwd, device, repeat)) * 1e3
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("data", nargs="?", default=str(DEFAULT))
    ap.add_argument("--iterations", type=int, default=5, help="measured iterations (after one warm-up)")
    ap.add_argument("--window", type=int, default=32)
    ap.add_argument("--batch", type=int, default=8)
    ap.add_argument("--conv", choices=("sparse", "gather", "both"), default="both")
    ap.add_argument("--gather-iterations", type=int, default=2, help="measured iterations of the gather variant")
    ap.add_argument("--device", default="auto")
    ap.add_argument("--threads", type=int, default=None)
    ap.add_argument("--profile", action="store_true", help="profile one iteration (default conv)")
    ap.add_argument("--json", help="also write the figures to this JSON file")
    args = ap.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    device = resolve_device(args.device)
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
    print(f"float32 matmul 4096^3: {peak:.1f} GFLOP/s (this machine's practical limit)")
    ring = ring_benchmark(topo, device, rows=2 * args.batch)
    faster = min(ring, key=ring.get)
    print("1-ring mean, forward+backward on (9, V, 16): "
          + ", ".join(f"{k} {v:.2f} ms" for k, v in ring.items()) + f" -> {faster} is faster")

    results = {"device": str(device), "threads": torch.get_num_threads(), "matmul_gflops": peak,
               "ring_ms": ring, "extract_s": t_extract, "variants": {}}
    impls = ("sparse", "gather") if args.conv == "both" else (args.conv,)
    for impl in impls:
        torch.manual_seed(0)
        cfg = ModelConfig(n_vertices=seq.n_vertices, variant="bd", conv_impl=impl)
        model = BDLSTM(cfg, topo).to(device)
        objective = WindowLoss(model, TrainConfig())
        opt = torch.optim.Adam(model.parameters(), lr=1e-3)

        def iteration():
            rows = sampler.sample(rng, args.batch)
            w = frames[torch.from_numpy(rows).to(device)]
            opt.zero_grad(set_to_none=True)
            total, _ = objective(w)
            total.backward()
            opt.step()

        iteration()  # warm-up
        times = timed(iteration, device, args.iterations if impl == impls[0] else args.gather_iterations)
        steps, rows = args.window - 1, 2 * args.batch
        fwd = sum(count_step_flops(cfg, topo, rows).values()) * steps
        flops = 3 * fwd
        med, best = statistics.median(times), min(times)
        achieved = flops / med / 1e9
        print(f"\n[{impl}] {args.batch} windows x {args.window} frames, bd: "
              f"{med:.2f} s/iteration (median of {len(times)}; best {best:.2f})")
        print(f"[{impl}] FLOPs per iteration: {flops / 1e9:.1f} GFLOP (forward {fwd / 1e9:.1f}); "
              f"achieved {achieved:.1f} GFLOP/s = {100 * achieved / peak:.0f}% of the matmul limit "
              f"({flops / best / 1e9:.1f} GFLOP/s at the best iteration)")
        print(f"[{impl}] projected 7000 iterations: {7000 * med / 3600:.1f} h (paper: ~8 h on a Tesla K40c)")
        parts = count_step_flops(cfg, topo, rows)
        share = {k: v / sum(parts.values()) for k, v in parts.items()}
        results["variants"][impl] = {"seconds_per_iteration": med, "best": best, "times": times,
                                     "gflop_per_iteration": flops / 1e9, "achieved_gflops": achieved,
                                     "fraction_of_matmul": achieved / peak,
                                     "projected_7000_hours": 7000 * med / 3600, "flop_share": share}
        print(f"[{impl}] FLOP share: " + ", ".join(f"{k} {100 * v:.0f}%" for k, v in share.items()))

        if args.profile and impl == impls[0]:
            from torch.profiler import ProfilerActivity, profile

            acts = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if device.type == "cuda" else [])
            with profile(activities=acts) as prof:
                iteration()
                sync(device)
            key = "self_cuda_time_total" if device.type == "cuda" else "self_cpu_time_total"
            print(prof.key_averages().table(sort_by=key, row_limit=15))

    print(f"\nload average at the end: {os.getloadavg()[0]:.1f}")
    if args.json:
        Path(args.json).write_text(json.dumps(results, indent=1))


if __name__ == "__main__":
    main()
