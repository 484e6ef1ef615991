"""How well can any predictor do from one given frame? The least error a one-frame predictor can
have on a sequence and its time reversal together, next to ours (method.md, "What the
generalisation benchmark leaves unmet").

    python benchmarks/one_frame.py RUN SPEC ... [--horizon 15]

A motion whose every joint is an even function of its phase (the body set's jumping jacks: each
curve a function of cos phi) played backwards is the same motion at another phase, so one frame
cannot tell whether it plays forwards or backwards. A predictor f gives the same output for frame s
of the sequence p and of its reversal, whose true frames H on are p(s + H) and p(s - H); by the
triangle inequality (centroid-aligned per-vertex distance is a norm of the difference) its two
errors sum to at least d(p(s + H), p(s - H)). Over the given frames s with both neighbours in the
sequence (H <= s < T - H), summed over both sequences and divided by zero velocity's sum:

    bound = sum_s d(p(s+H), p(s-H)) / sum_s [d(p(s), p(s+H)) + d(p(s), p(s-H))]

Ours is scored on the same given frames of the sequence and of its reversal (``predict``'s default,
one given frame, centroid-aligned), each over zero velocity, and both together as the bound is.
"""

from __future__ import annotations

import argparse

import numpy as np


def distances(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``(B,)`` mean centroid-aligned per-vertex distance between frames ``a`` and ``b`` ``(B, V, 3)``."""
    from meshseq.align import per_vertex_error

    return per_vertex_error(a, b).mean(axis=-1)


def one_frame_predictions(model, verts: np.ndarray, given: np.ndarray, horizon: int) -> np.ndarray:
    """``(B, V, 3)``: ours ``horizon`` frames after each single given frame ``verts[given]``."""
    from meshseq.synthesize import predict

    feats = model.features(verts[given])
    return model.vertices(predict(model, feats[:, None], horizon)[:, -1])


def scores(model, verts: np.ndarray, horizon: int) -> dict[str, float]:
    """``bound``, ours ``forward`` / ``reversed`` (each over zero velocity) and ``both`` (the two
    summed over zero velocity's two, comparable with the bound) of one sequence ``(T, V, 3)``."""
    s = np.arange(horizon, len(verts) - horizon)
    if len(s) == 0:
        raise SystemExit(f"one_frame: a sequence of {len(verts)} frames has no frame with {horizon} on either side")
    after, before = verts[s + horizon], verts[s - horizon]
    zero_f, zero_r = distances(verts[s], after).sum(), distances(verts[s], before).sum()
    ours = one_frame_predictions(model, verts, s, horizon)
    # the reversal's frame s is the sequence's frame s; its future is the sequence's past
    ours_r = one_frame_predictions(model, verts[::-1].copy(), len(verts) - 1 - s, horizon)
    ours_f, ours_b = distances(ours, after).sum(), distances(ours_r, before).sum()
    return {"bound": float(distances(after, before).sum() / (zero_f + zero_r)),
            "forward": float(ours_f / zero_f), "reversed": float(ours_b / zero_r),
            "both": float((ours_f + ours_b) / (zero_f + zero_r))}


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("run", help="a trained run")
    p.add_argument("specs", nargs="+", metavar="SPEC", help="sequences (FILE or FILE:NAME)")
    p.add_argument("--horizon", type=int, default=15)
    args = p.parse_args(argv)
    import meshseq
    from meshseq.io import load_sequence

    model = meshseq.load(args.run)
    print(f"| sequence | bound | ours forward | ours reversed | ours both |  (h{args.horizon}, over zero velocity)")
    print("|---|---|---|---|---|")
    for spec in args.specs:
        r = scores(model, load_sequence(spec).vertices.astype(np.float64), args.horizon)
        print(f"| {spec} | {r['bound']:.3f} | {r['forward']:.3f} | {r['reversed']:.3f} | {r['both']:.3f} |", flush=True)


if __name__ == "__main__":
    main()
