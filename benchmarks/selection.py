"""A run's prediction and completion on selection data (sequences no evaluation block holds), over
the trivial answers: what a controlled run is compared by before anything is adopted.

    python benchmarks/selection.py RUN SPEC ... [--given 1,3] [--pace warm-up] [--carry 0] [--trust pace=0.5]
        [--line straight] [--prediction-only]

Per sequence: ours (``predict``'s default, or its ``--pace`` / ``--carry``) over the better of zero velocity and
linear ACAP extrapolation at h5 / h10 / h15 with 1 and 3 given frames (``--given``; starts every 4 frames over the whole
sequence, centroid-aligned), and ours (``complete``'s default, 7 frames on both sides) over the
better linear interpolation at gaps of 5 / 10 / 20 / 30 (12 gaps each; with ``--trust``, completion
trusts the chains by another rule of ``completion_trust.py``; with ``--line``, the anchored join draws
toward another line between the keys, ``synthesize.anchor_line``); then the means and maxima.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from completion_trust import trust_rule, trusting  # noqa: E402  (sibling scripts)
from replay import ratios  # noqa: E402
import generalize  # noqa: E402

GAPS = (5, 10, 20, 30)


def completion_ratios(model, verts: np.ndarray, feats: np.ndarray, line: str = "geodesic") -> np.ndarray:
    """``(4,)`` ours (anchored toward ``line``) over the better interpolation at ``GAPS``."""
    from meshseq.evaluate import completion_errors
    from meshseq.synthesize import CONTEXT

    res = completion_errors(model, verts, feats, CONTEXT, len(verts) - CONTEXT, list(GAPS),
                            ["ours", "linear", "linear_vertices"], samples=1, max_starts=12, context=CONTEXT,
                            line=line)
    return np.array([res[str(g)]["ours"] / min(res[str(g)]["linear"], res[str(g)]["linear_vertices"]) for g in GAPS])


def main() -> None:
    import meshseq
    from meshseq.io import load_sequence

    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("run")
    p.add_argument("specs", nargs="+")
    p.add_argument("--given", default="1,3", help="given frames of the predictions scored, comma-separated")
    p.add_argument("--pace", default=None, help="predict's pace rule (default: its default)")
    p.add_argument("--carry", type=float, default=None, help="predict's carried share (default: its default)")
    p.add_argument("--trust", default="default", help="completion's trust rule (completion_trust.py's: default, "
                                                      "always, never, pace=P)")
    p.add_argument("--line", default="geodesic", help="the line completion's anchored join draws toward "
                                                      "(synthesize.LINES: geodesic, straight)")
    p.add_argument("--prediction-only", action="store_true", help="leave completion out")
    args = p.parse_args()
    trust = trust_rule(args.trust)
    model = meshseq.load(args.run)
    generalize.ensure_vertex_share(model, *generalize.training_specs(model))
    given = [int(u) for u in args.given.split(",")]
    rows: dict[str, list[np.ndarray]] = {f"u{u}": [] for u in given}
    if not args.prediction_only:
        rows["gaps"] = []
    fmt = "/".join
    for spec in args.specs:
        verts = load_sequence(spec).vertices.astype(np.float64)
        feats = model.features(verts)
        for u in given:
            rows[f"u{u}"].append(ratios(model, verts, feats, u, 4, [1.0], [], args.pace, args.carry)["tempo 1"])
        if not args.prediction_only:
            with trusting(trust):
                rows["gaps"].append(completion_ratios(model, verts, feats, args.line))
        cells = " | ".join(f"{k} {fmt(f'{x:.2f}' for x in v[-1])}" for k, v in rows.items())
        print(f"{spec.rsplit(':', 1)[-1]}  {cells}", flush=True)
    for k, v in rows.items():
        a = np.array(v)
        print(f"{k}: mean {fmt(f'{x:.2f}' for x in a.mean(0))}  max {fmt(f'{x:.2f}' for x in a.max(0))}")


if __name__ == "__main__":
    main()
