"""Benchmark: this checkout's C++ CPU kernels against another git revision's, call by call.

Builds the C++ kernels as they are at ``--against REV`` as a second extension (the revision's
package copied as ``meshseq_rev`` by ``revision.py``, its operators in the ``meshseq_rev``
namespace, so both builds load into one process), then times the two builds' calls alternately on the horse's mesh (8431
vertices, 9 channels, 16 windows, the FC weight 128 x 75879) and prints, per operation, the 10th
percentile and the median of each in milliseconds, whether the outputs have the same bits, and
the median over the alternated pairs of this checkout's time over the revision's (``ratio``).

Why this way: this machine's speed drifts by 20-50% from one minute to the next, so two
separately measured runs cannot show a 5% lever; alternating A and B call by call in one
process, and reading the 10th percentile (the median moves with the drift much more), can.
Whole training iterations are compared the same way by ``iteration_ab.py``.

    python benchmarks/kernel_ab.py --against HEAD~3 [--threads 2] [--calls 150] [--windows 16] [--only conv]

Operations: conv forward with tanh and without, conv backward with the tanh derivative and
without (a revision without ``input_tanh`` is called with its own signature), ``fc_wx`` (W x),
``fc_wtx`` (W^T h), and the window losses' ``frame_errors`` forward and backward with L_motion's
steps on a roll-out's 32 frames of 2 x (windows / 2) chains (the frames and the truth, 233 MB,
come from memory: a 96 MB read-only pass, not timed, before each of these calls, as in the
training loop); the LSTM step's forward and backward (3 layers of 128) and the banked FC weight
gradient over 62 pairs, where both builds have them.
"""

from __future__ import annotations

import argparse
import importlib
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from meshseq import kernels
from meshseq.mesh import Topology
from meshseq.model import NeighborMean
from revision import copy_revision

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data" / "horse-gallop.npz"


def build_revision(rev: str, folder: Path) -> None:
    """Build the kernels of git revision ``rev`` as operators ``torch.ops.meshseq_rev.*``: its package
    copied into ``folder`` (``revision.copy_revision``), its own ``cpu_kernels_available`` compiling
    them."""
    copy_revision(rev, folder)
    sys.path.insert(0, str(folder))
    if not importlib.import_module("meshseq_rev.kernels").cpu_kernels_available():
        raise SystemExit(f"--against {rev}: its C++ kernels could not be built")


def takes_input_tanh(ops) -> bool:
    """Whether this build's ``conv_backward`` has the ``input_tanh`` flag (since 2026-12-03)."""
    return len(ops.conv_backward.default._schema.arguments) == 9


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--against", required=True, help="git revision whose kernels to compare with (e.g. HEAD~3)")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--calls", type=int, default=150, help="alternated calls per build and operation")
    ap.add_argument("--windows", type=int, default=16)
    ap.add_argument("--only", default="", help="time only the operations whose name contains this (e.g. conv)")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    kernels.keep_freed_memory()
    if not kernels.cpu_kernels_available():
        raise SystemExit("the C++ kernels could not be built here")
    with tempfile.TemporaryDirectory() as tmp:
        build_revision(args.against, Path(tmp))
    d = np.load(DATA)
    V = d["vertices"].shape[1]
    ring = NeighborMean(Topology.from_faces(d["faces"], V))
    A, At = ring.A, ring.At
    g = torch.Generator().manual_seed(0)
    B = args.windows
    x, gy = torch.randn(V, 9, B, generator=g), torch.randn(V, 9, B, generator=g)
    ws, wr, bias = 0.3 * torch.randn(9, 9, generator=g), 0.3 * torch.randn(9, 9, generator=g), torch.randn(9, generator=g)
    W, xf, h = torch.randn(128, V * 9, generator=g), torch.randn(V * 9, B, generator=g), torch.randn(128, B, generator=g)
    y = torch.tanh(torch.randn(V, 9, B, generator=g))
    builds = {"this checkout": torch.ops.meshseq, f"{args.against}": torch.ops.meshseq_rev}

    def conv_bwd(ops, y_or_none):
        extra = (False,) if takes_input_tanh(ops) else ()
        return ops.conv_backward(gy, y_or_none, x, ws, wr, At.crow_indices(), At.col_indices(), At.values(), *extra)

    operations = {
        "conv forward, tanh": lambda o: o.conv_forward(x, ws, wr, bias, A.crow_indices(), A.col_indices(), A.values(), True, None),
        "conv forward, linear": lambda o: o.conv_forward(x, ws, wr, bias, A.crow_indices(), A.col_indices(), A.values(), False, None),
        "conv backward, tanh": lambda o: conv_bwd(o, y),
        "conv backward, linear": lambda o: conv_bwd(o, None),
        "fc_wx (W x)": lambda o: o.fc_wx(W, xf, None),
        "fc_wtx (W^T h)": lambda o: o.fc_wtx(W, h, None),
    }
    # the window losses: n frames (V, 9, R) of R = 2 x (B / 2) chains, the truth (B / 2, n, V x 9)
    n_frames, Bw = 32, max(1, B // 2)
    frames = [torch.randn(V, 9, 2 * Bw, generator=g) for _ in range(n_frames)]
    truth, ge = torch.randn(Bw, n_frames, V * 9, generator=g), torch.randn(6, Bw, n_frames, generator=g)
    flush = torch.ones(96 << 18)  # 96 MB, read before each call of these (not timed)
    operations["frame_errors, steps"] = lambda o: o.frame_errors(frames, truth, True)
    operations["frame_errors backward"] = lambda o: o.frame_errors_backward(ge, frames, truth,
                                                                          list(range(1, n_frames)))
    cold = {"frame_errors, steps", "frame_errors backward"}
    # the LSTM step (3 layers of 128 at the batch's B chains) and the banked FC weight gradient
    # (62 pairs of (B, 128) and (V x 9, B), as in a roll-out), where both builds have them
    K, H = 3, 128
    z, hs, cs = torch.randn(B, H, generator=g), torch.randn(K, B, H, generator=g), torch.randn(K, B, H, generator=g)
    w_ih = [0.1 * torch.randn(4 * H, H, generator=g) for _ in range(K)]
    w_hh = [0.1 * torch.randn(4 * H, H, generator=g) for _ in range(K)]
    bsum = [torch.randn(4 * H, generator=g) for _ in range(K)]
    t_ih, t_hh = [w.t().contiguous() for w in w_ih], [w.t().contiguous() for w in w_hh]
    if all(hasattr(o, "lstm_forward") for o in builds.values()):
        h_out, c_out, gates = torch.ops.meshseq.lstm_forward(z, hs, cs, t_ih, t_hh, bsum)
        dh, dc = torch.randn(K, B, H, generator=g), torch.randn(K, B, H, generator=g)
        operations["lstm step forward"] = lambda o: o.lstm_forward(z, hs, cs, t_ih, t_hh, bsum)
        operations["lstm step backward"] = lambda o: o.lstm_backward(dh, dc, z, hs, cs, h_out, c_out, gates,
                                                                     w_ih, w_hh)
    if all(hasattr(o, "fc_weight_grad") for o in builds.values()):
        left = torch.randn(62 * B, 128, generator=g)
        rights = [torch.randn(V * 9, B, generator=g) for _ in range(62)]
        operations["fc weight gradient (62 pairs)"] = lambda o: o.fc_weight_grad(left, rights)
    print(f"horse: {V} vertices, {B} windows, FC weight 128 x {V * 9}, {args.threads} threads; "
          f"{args.calls} alternated calls each; milliseconds, 10th percentile / median")
    names = list(builds)
    print(f"{'operation':30s} {names[0]:>22s} {names[1]:>22s}   same bits   ratio")
    for label, op in operations.items():
        if args.only not in label:
            continue
        outs = [op(builds[n]) for n in names]  # warm-up, and the outputs to compare
        flat = [[o] if isinstance(o, torch.Tensor) else list(o) for o in outs]
        same = all(torch.equal(a, b) for a, b in zip(*flat))
        times = {n: [] for n in names}
        for i in range(args.calls):
            for n in (names if i % 2 == 0 else names[::-1]):
                if label in cold:
                    flush.sum()
                t0 = time.perf_counter()
                op(builds[n])
                times[n].append(time.perf_counter() - t0)
        cells = [f"{np.percentile(times[n], 10) * 1e3:9.3f} / {np.median(times[n]) * 1e3:8.3f}" for n in names]
        ratio = np.median(np.array(times[names[0]]) / np.array(times[names[1]]))  # per alternated pair
        print(f"{label:30s} {cells[0]:>22s} {cells[1]:>22s}   {'yes' if same else 'no':9s} {ratio:5.3f}")


if __name__ == "__main__":
    main()
