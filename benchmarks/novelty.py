"""How new is a data set's held-out motion? Distance of every held-out frame to its nearest
training frame, against the motion of one frame step.

A model that learns from one sequence can recall motion it was shown; baselines such as zero
velocity and linear extrapolation need no recall. This prints, for each sequence and the paper's
protocol (the last ``--holdout`` of the frames held out; horse-gallop 0.4 as in paper.py):

- ``novelty``: the mean over held-out frames of the centroid-aligned mean per-vertex distance to
  the nearest training frame, in units of the sequence's mean frame-to-frame step (0: every
  held-out pose was seen in training; 5: five steps of motion away from anything seen);
- ``period``: the lag (4 frames to two thirds of the sequence) at which the sequence best repeats itself and how close that
  repeat is (``repeat``, same units; ~0 for an exactly periodic sequence);
- the starts a training window of the run's length can begin at (``paper.py``'s window rule).

    python benchmarks/novelty.py horse-gallop crane pcow
    python benchmarks/novelty.py --bodies runs/bodies1k.h5
"""

from __future__ import annotations

import argparse

import numpy as np
from paper import HOLDOUT  # the held-out fraction per data set (benchmarks/paper.py)
from recipe_study import data_specs, sequence_name


def frame_distances(vertices: np.ndarray) -> np.ndarray:
    """``(T, V, 3)`` -> ``(T, T)`` centroid-aligned mean per-vertex distances between frames."""
    v = vertices - vertices.mean(1, keepdims=True)
    flat = v.reshape(len(v), -1, 3)
    return np.stack([np.linalg.norm(flat - f, axis=-1).mean(-1) for f in flat])


def novelty(vertices: np.ndarray, holdout: float, window: int = 32) -> dict:
    """Novelty of the held-out end of one sequence ``(T, V, 3)`` (see the module docstring)."""
    n = len(vertices)
    lo = n - int(round(holdout * n))
    d = frame_distances(vertices.astype(np.float64))
    step = float(np.mean(np.diag(d, 1)))
    lags = np.arange(4, max(5, (2 * n) // 3))  # a repeat seen over at least a third of the frames
    repeat = np.array([np.mean(np.diag(d, k)) for k in lags]) / step
    return {"frames": n, "train": lo, "novelty": float(d[lo:, :lo].min(1).mean() / step),
            "period": int(lags[np.argmin(repeat)]), "repeat": float(repeat.min()),
            "window": min(window, lo), "window_starts": lo - min(window, lo) + 1}


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("data", nargs="*", default=[], help="names in ../shared/data or sequence files/specs")
    p.add_argument("--bodies", default=None, help="also every sequence of this make-bodies HDF5")
    p.add_argument("--window", type=int, default=32)
    args = p.parse_args(argv)
    from meshseq.io import load_sequence

    specs = data_specs(args.data + (["bodies"] if args.bodies else []), args.bodies)
    if not specs:
        raise SystemExit("nothing to measure: name data sets or --bodies FILE")
    print("| sequence | frames | training frames | novelty (frame steps) | period, repeat | window, starts |")
    print("|---|---|---|---|---|---|")
    for spec in specs:
        name = sequence_name(spec)
        r = novelty(load_sequence(spec).vertices, HOLDOUT.get(name, 0.2), args.window)
        print(f"| {name} | {r['frames']} | {r['train']} | {r['novelty']:.2f} | {r['period']}, {r['repeat']:.2f} "
              f"| {r['window']}, {r['window_starts']} |", flush=True)


if __name__ == "__main__":
    main()
