"""Benchmark: each C++ kernel's time inside whole training iterations, and the same call alone.

Runs ``iteration_ab.py``'s training iteration (horse-gallop, bd, 8 windows x 32 frames, this
checkout's code) with the C++ operators wrapped by a timer, and after each iteration calls each
operator again, five times, on copies of the arguments of its last call in that iteration (its
inputs then in the caches). Prints, per operator, calls per iteration, the 10th percentile and the
median of the call's time in the loop and alone, and the milliseconds per iteration it takes.

Why: the kernels are tuned alone (``kernel_ab.py``), where a layer's 4.9 MB input is in the L3
cache; in the loop the FC weight's 39 MB stream evicts it between layers. The difference between
the two columns is what the loop's memory traffic costs each kernel.

    python benchmarks/op_times.py [--iterations 5] [--threads 2]
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch

from iteration_ab import make_iteration

OPERATORS = ("conv_forward", "conv_backward", "fc_wx", "fc_wx_row_sums", "fc_wtx", "fc_weight_grad",
             "lstm_forward", "lstm_backward", "frame_errors", "frame_errors_backward")


def copy(arg):
    """A copy of an operator's argument: tensors cloned, lists of them too, anything else as it is."""
    if isinstance(arg, torch.Tensor):
        return arg.clone()
    if isinstance(arg, (list, tuple)):
        return [copy(x) for x in arg]
    return arg


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--iterations", type=int, default=5)
    ap.add_argument("--threads", type=int, default=2)
    args = ap.parse_args()
    iteration = make_iteration("meshseq", 8, args.threads)
    iteration()
    iteration()  # warm-up: the first iterations allocate and build
    ops = torch.ops.meshseq
    in_loop: dict[str, list[float]] = {}
    last_args: dict[str, tuple] = {}
    plain = {name: getattr(ops, name) for name in OPERATORS}

    def timed(name):
        def call(*a):
            t0 = time.perf_counter()
            out = plain[name](*a)
            in_loop.setdefault(name, []).append(time.perf_counter() - t0)
            last_args[name] = a
            return out
        return call

    for name in OPERATORS:
        setattr(ops, name, timed(name))  # kernels.py looks the operators up at each call
    alone: dict[str, list[float]] = {}
    seconds = []
    try:
        for _ in range(args.iterations):
            t0 = time.perf_counter()
            iteration()
            seconds.append(time.perf_counter() - t0)
            for name, a in last_args.items():
                copies = [copy(x) for x in a]
                for _ in range(5):
                    t0 = time.perf_counter()
                    plain[name](*copies)
                    alone.setdefault(name, []).append(time.perf_counter() - t0)
    finally:
        for name in OPERATORS:
            setattr(ops, name, plain[name])
    print(f"horse-gallop, bd, 8 windows x 32 frames, {args.threads} threads: {args.iterations} iterations, "
          f"median {np.median(seconds):.2f} s; milliseconds, 10th percentile / median")
    print(f"{'operator':24s} {'calls/it':>8s} {'in the loop':>18s} {'alone':>18s} {'ms/iteration':>13s}")
    for name in sorted(in_loop, key=lambda n: -sum(in_loop[n])):
        t, s = np.array(in_loop[name]) * 1e3, np.array(alone[name]) * 1e3
        print(f"{name:24s} {len(t) / args.iterations:8.0f} {np.percentile(t, 10):8.2f} / {np.median(t):7.2f} "
              f"{np.percentile(s, 10):8.2f} / {np.median(s):7.2f} {t.sum() / args.iterations:13.0f}")


if __name__ == "__main__":
    main()
