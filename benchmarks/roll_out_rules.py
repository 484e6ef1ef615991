"""What prediction's departures from the paper's roll-out do on chosen sequences: the default
against ``--pace model`` (no pace factor), ``--carry 0`` (no carried velocity), both, ``--guard off``
(no novelty guard) and all three (the paper's roll-out) (method.md, "What the generalisation benchmark leaves unmet").

    python benchmarks/roll_out_rules.py RUN SPEC ... [--given 3] [--every 1]

For each sequence: ours with each rule over zero velocity at h5 / h10 / h15 (starts every
``--every`` frames over the whole sequence), centroid-aligned and rigid (also rotation-aligned),
and how many starts the training pace (``novelty.training_pace``) slows below 0.95.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from novelty_guard import H as HORIZON, prediction_windows, vertex_errors  # noqa: E402  (a sibling script)

RULES = {"default": {}, "pace model": {"pace": "model"}, "carry 0": {"carry": 0.0},
         "pace model, carry 0": {"pace": "model", "carry": 0.0}, "guard off": {"guard": False},
         "guard off, pace model, carry 0": {"guard": False, "pace": "model", "carry": 0.0}}


def rule_ratios(model, verts: np.ndarray, given: int, every: int) -> tuple[dict, float]:
    """``({rule: {"centroid" / "rigid": (3,)}}, share of starts slowed)``: each rule's error over
    zero velocity's at h5 / h10 / h15 for one sequence ``(T, V, 3)``."""
    from meshseq import novelty
    from meshseq.synthesize import predict

    _, x, truth, zero = prediction_windows(verts, model.features(verts), given, every)
    out = {}
    for name, options in RULES.items():
        f = predict(model, x, HORIZON, **options)
        pred = model.vertices(f.reshape(-1, *f.shape[2:])).reshape(truth.shape)
        out[name] = {key: vertex_errors(pred, truth, rigid) / vertex_errors(zero, truth, rigid)
                     for key, rigid in (("centroid", False), ("rigid", True))}
    slowed = float("nan")
    if given > 1 and getattr(model, "novelty", None) is not None and model.novelty.steps is not None:
        z = model.encode(x)
        slowed = float((novelty.training_pace(z, model.novelty) < 0.95).mean())
    return out, slowed


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("run", help="a trained run")
    p.add_argument("specs", nargs="+", metavar="SPEC", help="sequences (FILE or FILE:NAME)")
    p.add_argument("--given", type=int, default=3)
    p.add_argument("--every", type=int, default=1)
    args = p.parse_args(argv)
    import meshseq
    from meshseq.io import load_sequence

    model = meshseq.load(args.run)
    for spec in args.specs:
        res, slowed = rule_ratios(model, load_sequence(spec).vertices.astype(np.float64), args.given, args.every)
        print(f"{spec}: u{args.given}, over zero velocity, h5 / h10 / h15; starts slowed by the training pace: "
              f"{slowed:.2f}")
        for name, r in res.items():
            print(f"  {name:20s} centroid " + " / ".join(f"{v:.3f}" for v in r["centroid"])
                  + "   rigid " + " / ".join(f"{v:.3f}" for v in r["rigid"]), flush=True)


if __name__ == "__main__":
    main()
