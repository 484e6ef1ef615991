"""Which carried velocity a run's own training frames favour (method.md, "What the generalisation
benchmark leaves unmet"): prediction's ``carry`` scored where a fit may look, as the vertex share
is fitted for completion.

    python benchmarks/carry_fit.py RUN [--carries 0,0.4,0.6,0.8] [--every 4]

Over the training segments of RUN (as its checkpoint names them; their files must be readable
where it says): 3 given frames, starts every ``--every`` frames inside each segment, ours
(``predict``'s default but the carry) over zero velocity at h5 / h10 / h15 (centroid-aligned, the
errors summed over every start before the ratio), and the mean of the three.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from generalize import training_specs  # noqa: E402  (sibling scripts)
from novelty_guard import H as HORIZON, vertex_errors  # noqa: E402

GIVEN = 3


def segment_windows(verts: np.ndarray, feats: np.ndarray, lo: int, hi: int, every: int):
    """Starts inside ``[lo, hi)`` of a sequence (vertices ``(T, V, 3)``, scaled features ``(T, V, C)``)
    with ``GIVEN`` frames and ``HORIZON`` after them: ``(given features (B, U, V, C), true vertices
    (B, H, V, 3), the last given frame held (B, H, V, 3))``, or None where none fits."""
    from meshseq.evaluate import prediction_starts

    starts = prediction_starts(lo, hi, GIVEN, HORIZON, every)
    if not len(starts):
        return None
    x = np.stack([feats[s:s + GIVEN] for s in starts])
    truth = np.stack([verts[s + GIVEN:s + GIVEN + HORIZON] for s in starts])
    held = np.repeat(verts[starts + GIVEN - 1][:, None], HORIZON, 1)
    return x, truth, held


def carry_errors(model, carries: list[float], every: int) -> tuple[dict[float, np.ndarray], np.ndarray]:
    """``({carry: (3,) summed error at h5 / h10 / h15}, (3,) zero velocity's)`` over the training
    segments of the run ``model``."""
    from meshseq.io import load_sequence
    from meshseq.synthesize import predict

    ours = {c: np.zeros(3) for c in carries}
    zero = np.zeros(3)
    for spec, split in zip(*training_specs(model)):
        verts = load_sequence(spec).vertices.astype(np.float64)
        feats = model.features(verts)
        for lo, hi in split.train:
            windows = segment_windows(verts, feats, lo, hi, every)
            if windows is None:
                continue
            x, truth, held = windows
            zero += vertex_errors(held, truth) * len(x)
            for c in carries:
                f = predict(model, x, HORIZON, carry=c)
                pred = model.vertices(f.reshape(-1, *f.shape[2:])).reshape(truth.shape)
                ours[c] += vertex_errors(pred, truth) * len(x)
    return ours, zero


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("run", help="a trained run")
    p.add_argument("--carries", default="0,0.4,0.6,0.8", help="carried-velocity shares to score")
    p.add_argument("--every", type=int, default=4, help="a start every K frames")
    args = p.parse_args(argv)
    import meshseq

    model = meshseq.load(args.run)
    ours, zero = carry_errors(model, [float(c) for c in args.carries.split(",")], args.every)
    print(f"{args.run}: its training segments, u{GIVEN}, ours over zero velocity at h5 / h10 / h15, mean")
    for c, err in ours.items():
        ratio = err / np.maximum(zero, 1e-300)
        print(f"  carry {c:<4g} " + " / ".join(f"{r:.3f}" for r in ratio) + f"   {ratio.mean():.3f}", flush=True)


if __name__ == "__main__":
    main()
