"""Benchmark: whole training iterations of this checkout against another git revision, in one process.

Copies ``src/meshseq`` as it is at ``--against REV`` into a temporary folder as the package
``meshseq_rev`` (``revision.py``: its imports, its C++ operators' namespace and its build folder
renamed, so both versions and both kernel builds load into one process), builds the same model on both (horse-gallop,
bd, 8 windows x 32 frames, the paper's losses: ``benchmarks/train_speed.py``'s iteration) and
alternates their iterations, A B B A ..., ``--pairs`` times. Prints each side's median and the
mean of the paired differences with its standard error.

Why this way: this machine's speed drifts by 20-50% from one minute to the next, so two runs
measured apart cannot show a 5% lever; alternated in one process, each pair sees the same moment.
And why many pairs: on this 2-core VM the pairs' differences scatter by about 0.1 s, so 16 pairs
leave a standard error of about 25 ms, as large as most levers left (docs/performance.md,
"Measuring a change"); 40 pairs bring it to about 15 ms. A lever is shown when the mean
difference is several standard errors from 0.

    python benchmarks/iteration_ab.py --against HEAD~3 [--pairs 40] [--threads 2] [--batch 8]
"""

from __future__ import annotations

import argparse
import importlib
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from revision import copy_revision

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data" / "horse-gallop.npz"


def make_iteration(package: str, batch: int, threads: int):
    """One training iteration of a fresh model built with ``package``'s code (its own API only)."""
    def mod(name):
        return importlib.import_module(f"{package}.{name}")

    kernels, acap, data_io, mesh = mod("kernels"), mod("acap"), mod("io"), mod("mesh")
    windows, model, train = mod("data.windows"), mod("model"), mod("train")
    torch.set_num_threads(threads)
    kernels.keep_freed_memory()
    if not kernels.cpu_kernels_available():
        raise SystemExit(f"{package}: the C++ kernels could not be built here")
    seq = data_io.load_sequence(str(DATA))
    topo = mesh.Topology.from_faces(seq.faces, seq.n_vertices)
    feats = acap.extract(seq.vertices, seq.faces)
    split = windows.split_frames(len(feats), 0.2)
    scaling = acap.Scaling.fit(feats[split.train_frames()])
    frames = torch.from_numpy(scaling.apply(feats).astype(np.float32))
    sampler = windows.WindowSampler([split], [seq.name], 32)
    torch.manual_seed(0)
    net = model.BDLSTM(model.ModelConfig(n_vertices=seq.n_vertices, variant="bd"), topo)
    objective = train.WindowLoss(net, train.TrainConfig(w_vertex=0.0))
    fused = getattr(train, "fused_adam", lambda device: False)(torch.device("cpu"))
    opt = torch.optim.Adam(net.parameters(), lr=1e-3, fused=fused)
    rng = np.random.default_rng(0)

    def iteration():
        rows = torch.from_numpy(sampler.sample(rng, batch))
        w = frames.index_select(0, rows.reshape(-1)).view(*rows.shape, *frames.shape[1:])
        opt.zero_grad(set_to_none=True)
        total, _ = objective(w)
        total.backward()
        opt.step()

    return iteration


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--against", required=True, help="git revision to compare with (e.g. HEAD~3)")
    ap.add_argument("--pairs", type=int, default=40, help="alternated pairs of iterations")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--batch", type=int, default=8, help="windows per iteration")
    args = ap.parse_args()
    if not DATA.exists():
        raise SystemExit(f"{DATA}: not found (the shared data set this benchmark trains on)")
    with tempfile.TemporaryDirectory() as tmp:
        copy_revision(args.against, Path(tmp))
        sys.path.insert(0, tmp)
        its = {"this checkout": make_iteration("meshseq", args.batch, args.threads),
               args.against: make_iteration("meshseq_rev", args.batch, args.threads)}
        names = list(its)
        for name in names:  # warm-up (the first iterations allocate and build)
            its[name]()
            its[name]()
        times = {n: [] for n in names}
        for i in range(args.pairs):
            for n in (names if i % 2 == 0 else names[::-1]):
                t0 = time.perf_counter()
                its[n]()
                times[n].append(time.perf_counter() - t0)
    print(f"horse-gallop, bd, {args.batch} windows x 32 frames, {args.threads} threads, {args.pairs} alternated pairs")
    for n in names:
        print(f"{n:>20s}: median {statistics.median(times[n]):.3f} s/iteration, best {min(times[n]):.3f}")
    diff = [b - a for a, b in zip(times[names[0]], times[names[1]])]
    sem = statistics.stdev(diff) / len(diff) ** 0.5 if len(diff) > 1 else float("nan")
    print(f"{args.against} minus this checkout, per pair: mean {statistics.mean(diff) * 1e3:+.1f} ms "
          f"+- {sem * 1e3:.1f} (standard error), median {statistics.median(diff) * 1e3:+.1f} ms")


if __name__ == "__main__":
    main()
