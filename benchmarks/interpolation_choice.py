"""Which linear interpolation fills a gap better, ACAP features or vertices, and can the frames
given around the keys tell? (method.md, "What the generalisation benchmark leaves unmet").

    python benchmarks/interpolation_choice.py RUN SPEC[@FIRST,LAST] ...

For every sequence (frames [FIRST, LAST) only: a capture's training part) and gap of 5 / 10 / 20 /
30 frames (12 gaps, ``CONTEXT`` frames on both sides, as the benchmark places them), the mean
in-between error of interpolating the ACAP features (reconstructed through the keys, as
``complete --method linear``), the vertices (``--method linear_vertices``), the two averaged, the
one the context picks, and the better of the two per gap (an oracle), each over the better of the
two means (the benchmark's reference), the truth's own features reconstructed through the keys
(what the features lose before any interpolation), and the features interpolated with each vertex's
rotation turned along its shortest path (``acap.interpolation.geodesic_interpolation``). The
context pick: the same two interpolations over the
frames given before key a and after key b (windows of ``min(gap, CONTEXT - 1)`` in-between frames
ending on the keys), the one with the smaller error there. ``--blend W,...`` adds blends of the
two, ``(1 - W)`` features + ``W`` vertices (``--blend-with geodesic``: the geodesic features' frames
instead of the straight line's). RUN only supplies the mesh and the feature scaling: the
network is not used, so a run of one iteration serves.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from generalize import frames_spec  # noqa: E402  (sibling scripts)
from novelty_guard import gap_starts  # noqa: E402  (the gaps as the benchmarks place them)

GAPS = (5, 10, 20, 30)
COLUMNS = ("features", "vertices", "average", "context pick", "oracle", "true features", "geodesic features")


def interpolations(model, verts: np.ndarray, feats: np.ndarray, a: int, b: int) -> tuple[np.ndarray, np.ndarray]:
    """In-between frames ``(b - a - 1, V, 3)`` from frame a to frame b: features, vertices."""
    from meshseq.baselines import linear_interpolation
    from meshseq.synthesize import assemble_vertices

    n = b - a - 1
    in_features = assemble_vertices(model, linear_interpolation(feats[a], feats[b], n), {0: verts[a], n + 1: verts[b]})
    return in_features[1:-1], linear_interpolation(verts[a], verts[b], n)[1:-1]


def geodesic_frames(model, verts: np.ndarray, feats: np.ndarray, a: int, b: int) -> np.ndarray:
    """In-between frames ``(b - a - 1, V, 3)`` of ``geodesic_interpolation`` from frame a to frame b,
    reconstructed through the keys as ``interpolations``' features are."""
    from meshseq.synthesize import anchor_line, assemble_vertices

    n = b - a - 1
    inner = anchor_line(model, feats[a][None].astype(np.float64), feats[b][None].astype(np.float64), n + 2)[0]
    return assemble_vertices(model, inner, {0: verts[a], n + 1: verts[b]})[1:-1]


def context_errors(model, verts: np.ndarray, feats: np.ndarray, a: int, b: int, gap: int) -> np.ndarray:
    """``(2,)`` summed error (features, vertices) of both interpolations over windows inside the
    ``CONTEXT`` frames before a (ending on a) and after b (starting at b)."""
    from meshseq.align import per_vertex_error
    from meshseq.synthesize import CONTEXT

    inner = min(gap, CONTEXT - 1)
    total = np.zeros(2)
    for first, last in ((a - CONTEXT, a), (b, b + CONTEXT)):
        for s in range(first, last - inner):
            e = s + inner + 1
            total += [per_vertex_error(x, verts[s + 1:e]).mean() for x in interpolations(model, verts, feats, s, e)]
    return total


def gap_table(model, verts: np.ndarray, gap: int, blends: tuple[float, ...] = (),
              blend_with: str = "features") -> np.ndarray | None:
    """``(7 + len(blends),)`` mean in-between error of each ``COLUMNS`` entry, then of each blend
    ``(1 - w)`` features (``blend_with``: the straight line's or the ``geodesic`` one's) + ``w``
    vertices, over the better of features and vertices, over 12 gaps of ``gap`` frames; None where
    the sequence is too short."""
    from meshseq.align import per_vertex_error
    from meshseq.synthesize import assemble_vertices

    starts = gap_starts(len(verts), gap)
    if not len(starts):
        return None
    feats = model.features(verts)
    rows = []
    for a in starts:
        b = a + gap + 1
        truth = verts[a + 1:b]
        in_f, in_v = interpolations(model, verts, feats, a, b)
        e_f, e_v = per_vertex_error(in_f, truth).mean(), per_vertex_error(in_v, truth).mean()
        pick = context_errors(model, verts, feats, a, b, gap)
        own = assemble_vertices(model, feats[a:b + 1], {0: verts[a], gap + 1: verts[b]})[1:-1]
        geo = geodesic_frames(model, verts, feats, a, b)
        base = geo if blend_with == "geodesic" else in_f
        rows.append([e_f, e_v, per_vertex_error(0.5 * (in_f + in_v), truth).mean(),
                     e_v if pick[1] < pick[0] else e_f, min(e_f, e_v), per_vertex_error(own, truth).mean(),
                     per_vertex_error(geo, truth).mean()]
                    + [per_vertex_error((1 - w) * base + w * in_v, truth).mean() for w in blends])
    means = np.mean(rows, axis=0)
    return means / min(means[0], means[1])


def main() -> None:
    import meshseq
    from meshseq.io import load_sequence

    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("run", help="a trained run (its mesh and feature scaling)")
    p.add_argument("specs", nargs="+", help="sequences, each optionally SPEC@FIRST,LAST")
    p.add_argument("--blend", default="", help="blend weights W of the vertices, comma-separated")
    p.add_argument("--blend-with", choices=("features", "geodesic"), default="features",
                   help="what the vertices are blended with: the features' straight line or the geodesic one")
    args = p.parse_args()
    model = meshseq.load(args.run)
    blends = tuple(float(w) for w in args.blend.split(",") if w)
    columns = COLUMNS + tuple(f"blend {w:g}" for w in blends)
    per_gap: dict[int, list[np.ndarray]] = {g: [] for g in GAPS}
    print("over the better of features and vertices, at gaps " + " / ".join(map(str, GAPS)) + ": "
          + ", ".join(columns))
    for spec in args.specs:
        path, frames = frames_spec(spec)
        verts = load_sequence(path).vertices.astype(np.float64)
        if frames:
            verts = verts[slice(*frames)]
        cells = []
        for gap in GAPS:
            row = gap_table(model, verts, gap, blends, args.blend_with)
            if row is not None:
                per_gap[gap].append(row)
                cells.append(f"gap {gap}: " + " ".join(f"{x:.3f}" for x in row))
        print(f"{spec.rsplit('/', 1)[-1]}  " + " | ".join(cells), flush=True)
    for gap, rows in per_gap.items():
        if rows:
            r = np.array(rows)
            print(f"gap {gap}, mean (max) over {len(r)}: "
                  + "  ".join(f"{c} {m:.3f} ({x:.3f})" for c, m, x in zip(columns, r.mean(0), r.max(0))))


if __name__ == "__main__":
    main()
