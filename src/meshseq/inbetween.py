"""How far completion leans toward the straight lines between the keys' vertices: a share fitted on
a capture's training frames (method.md, "5. Synthesis").

Where chains are not trusted, completion gives the line between the keys: the ACAP features with
each vertex's rotation turned the short way (``synthesize.anchor_line``). Where a capture's surface
turns and deforms fast (an elastic body), straight lines between the keys' vertices fill short gaps
about as well, and a blend of the two better than either; where limbs swing, the features' line
alone is best. ``fit_vertex_share`` picks the blend from the training frames alone, over gaps of
``FIT_GAPS`` frames; training stores it in the checkpoint (``model.json``'s ``completion``) and
``synthesize.complete_keyframes`` blends the line's share of each completion by it
(``synthesize.blend_toward_vertices``).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

#: the shares of the vertices' line tried (0: the features' line alone)
VERTEX_SHARES = (0.0, 0.25, 0.5, 0.75, 1.0)
#: the gap lengths the share is fitted on (where interpolation is nearly right: the line matters most)
FIT_GAPS = (5, 10)
#: gaps per training segment and length (on crane's and pcow's training parts, 12 gaps moved the
#: scores by up to 10% against every gap and picked other shares; 24 or more pick those of every gap)
FIT_STARTS = 48
#: a larger share is taken only where it lowers the score by more than this: a blend must gain half a
#: percent over the smaller share (ties, and gains within what the choice of gaps moves, keep the features)
MARGIN = 5e-3


def fit_starts(n_frames: int, gap: int, count: int) -> np.ndarray:
    """Up to ``count`` evenly spaced first keys of gaps of ``gap`` frames in ``n_frames`` frames."""
    starts = np.arange(max(n_frames - gap - 1, 0))
    return starts[np.linspace(0, len(starts) - 1, min(count, len(starts))).astype(int)]


def blend_errors(features: np.ndarray, vertices: np.ndarray, reconstruct: Callable, gap: int,
                 shares=VERTEX_SHARES) -> np.ndarray:
    """``(P, len(shares))`` mean in-between vertex error (centroid-aligned) of each share's blend
    ``(1 - s)`` features' line + ``s`` vertices' line, over P gaps of ``gap`` frames in one segment.

    ``features`` ``(T, V, C)`` unscaled ACAP features of the segment's ``vertices`` ``(T, V, 3)``;
    ``reconstruct``: unscaled features ``(N, V, C)`` -> centred vertices ``(N, V, 3)``.
    """
    from meshseq.acap.interpolation import geodesic_interpolation
    from meshseq.align import per_vertex_error
    from meshseq.baselines import linear_interpolation
    from meshseq.synthesize import pass_through_anchors

    starts = fit_starts(len(features), gap, FIT_STARTS)
    if not len(starts):
        return np.zeros((0, len(shares)))
    ends = starts + gap + 1
    line = geodesic_interpolation(features[starts], features[ends], gap)  # (gap + 2, P, V, C)
    recon = reconstruct(line.swapaxes(0, 1).reshape(-1, *features.shape[1:]))
    recon = recon.reshape(len(starts), gap + 2, -1, 3)
    out = np.empty((len(starts), len(shares)))
    for p, (a, b) in enumerate(zip(starts, ends)):
        geo = pass_through_anchors(recon[p:p + 1], {0: vertices[a], gap + 1: vertices[b]})[0, 1:-1]
        lin = linear_interpolation(vertices[a], vertices[b], gap)[1:-1]
        out[p] = [per_vertex_error((1 - s) * geo + s * lin, vertices[a + 1:b]).mean() for s in shares]
    return out


def fit_vertex_share(segments: list[tuple[np.ndarray, np.ndarray]], reconstruct: Callable,
                     shares=VERTEX_SHARES, gaps=FIT_GAPS) -> dict:
    """The share of the vertices' line that fits training segments best.

    ``segments``: ``(features (T, V, C) unscaled, vertices (T, V, 3))`` of each training segment;
    ``reconstruct`` as ``blend_errors``'. Each share's score is its mean error over every gap of a
    length, over the better of the features' line alone and the vertices' alone (as the benchmark
    scores completion), averaged over ``gaps``. Returns ``{"vertex_share": s, "scores": {str(s): score}}``
    (JSON-ready; share 0 where no segment holds a gap).
    """
    per_gap = []
    for gap in gaps:
        errs = [blend_errors(f, v, reconstruct, gap, shares) for f, v in segments]
        errs = np.concatenate(errs) if errs else np.zeros((0, len(shares)))
        if len(errs):
            mean = errs.mean(axis=0)
            per_gap.append(mean / max(min(mean[0], mean[-1]), 1e-12))
    if not per_gap:
        return {"vertex_share": 0.0, "scores": {}}
    score = np.mean(per_gap, axis=0)
    best = 0
    for i in range(1, len(shares)):
        if score[i] < score[best] - MARGIN:
            best = i
    return {"vertex_share": float(shares[best]), "scores": {f"{s:g}": float(x) for s, x in zip(shares, score)}}

