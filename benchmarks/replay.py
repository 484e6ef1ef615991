"""Is a prediction off in its tempo or in its amplitude? ``predict``'s roll-out replayed slower or
faster, or scaled, against the best trivial answer (method.md, "What the generalisation benchmark
leaves unmet").

    python benchmarks/replay.py RUN SPEC ... [--tempos 0.6,0.7,0.8,0.9,1] [--amplitudes 0.6,0.8,1,1.2,1.4]

For each sequence, 1 and 3 given frames (starts every ``--every`` frames over the whole sequence)
and each factor k: ours with frame j taken at time ``k j`` of the roll-out (linear between its
frames; k < 1 plays it slower) and, separately, with its displacement from the last given frame
scaled by k; each over the better of zero velocity and linear ACAP extrapolation at h5 / h10 / h15
(centroid-aligned). k = 1 is ``predict``'s default itself in both.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from novelty_guard import H as HORIZON, errors, prediction_windows, vertex_errors  # noqa: E402  (a sibling script)


def replayed(given_last: np.ndarray, rollout: np.ndarray, tempo: float) -> np.ndarray:
    """``(B, H, V, C)``: the roll-out ``(B, n, V, C)`` (after ``given_last`` ``(B, V, C)``) at times
    ``tempo * j``, j = 1..H, linear between frames; needs ``n >= tempo * H``."""
    path = np.concatenate([given_last[:, None], rollout], axis=1)  # time 0: the last given frame
    t = tempo * np.arange(1, HORIZON + 1)
    i = np.floor(t).astype(int)
    w = (t - i)[None, :, None, None]
    upper = np.minimum(i + 1, path.shape[1] - 1)
    return (1 - w) * path[:, i] + w * path[:, upper]


def scaled(given_last: np.ndarray, rollout: np.ndarray, amplitude: float) -> np.ndarray:
    """``(B, H, V, C)``: the roll-out's first H frames, their displacement from the last given frame scaled."""
    return given_last[:, None] + amplitude * (rollout[:, :HORIZON] - given_last[:, None])


def ratios(model, verts: np.ndarray, feats: np.ndarray, given: int, every: int,
           tempos: list[float], amplitudes: list[float], pace: str | None = None,
           carry: float | None = None) -> dict[str, np.ndarray]:
    """``{"tempo k" | "amplitude k": (3,)}`` ours replayed over the best baseline at h5 / h10 / h15
    (``pace``, ``carry``: ``predict``'s, None for its default)."""
    from meshseq.evaluate import predicted_features
    from meshseq.synthesize import predict

    starts, x, truth, held = prediction_windows(verts, feats, given, every)
    best = np.minimum(vertex_errors(held, truth), errors(model, truth, predicted_features(
        "linear_acap", model, feats, starts, given, HORIZON, None)))
    options = {k: v for k, v in (("pace", pace), ("carry", carry)) if v is not None}
    rollout = predict(model, x, int(np.ceil(HORIZON / min(tempos + [1.0]))) + 1, **options)
    out = {f"tempo {k:g}": errors(model, truth, replayed(x[:, -1], rollout, k)) / best for k in tempos}
    out.update({f"amplitude {k:g}": errors(model, truth, scaled(x[:, -1], rollout, k)) / best for k in amplitudes})
    return out


def main() -> None:
    import meshseq
    from meshseq.io import load_sequence

    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("run")
    p.add_argument("specs", nargs="+")
    p.add_argument("--tempos", default="0.6,0.7,0.8,0.9,1")
    p.add_argument("--amplitudes", default="0.6,0.8,1,1.2,1.4")
    p.add_argument("--every", type=int, default=4)
    args = p.parse_args()
    tempos = [float(k) for k in args.tempos.split(",") if k]
    amplitudes = [float(k) for k in args.amplitudes.split(",") if k]
    model = meshseq.load(args.run)
    for spec in args.specs:
        verts = load_sequence(spec).vertices.astype(np.float64)
        feats = model.features(verts)
        for given in (1, 3):
            r = ratios(model, verts, feats, given, args.every, tempos, amplitudes)
            print(f"{spec.rsplit(':', 1)[-1]} u{given} h5/h10/h15: "
                  + "  ".join(f"{k} {'/'.join(f'{x:.2f}' for x in v)}" for k, v in r.items()), flush=True)


if __name__ == "__main__":
    main()
