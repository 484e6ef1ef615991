"""How much of the given frames' velocity prediction carries into its roll-out: a share fitted on a
capture's training frames (method.md, "5. Synthesis").

With two or more given frames, ``synthesize.carried_steps`` starts the roll-out at the given
velocity and fades it into the model's own steps by ``synthesize.CARRY`` a frame, chosen on the
body set. A capture whose frames turn fast from one frame to the next (a gallop) is continued past
where it turns, and there a smaller share, or none, predicts better. ``fit_carry`` scores the
shares ``CARRIES`` on the training frames alone, 3 given frames at a time; training stores the
choice in the checkpoint (``model.json``'s ``prediction``) and ``synthesize.predict`` uses it.
"""

from __future__ import annotations

import numpy as np

from meshseq.synthesize import CARRY, predict

#: the shares tried (0: the model's steps as they are; the largest: the body set's ``synthesize.CARRY``)
CARRIES = (0.0, 0.3, CARRY)
#: a smaller share is taken only where it lowers the score by more than this (2%): where the training
#: frames cannot tell, the share chosen on the body set stays
MARGIN = 0.02
#: given frames, horizons scored (h5 / h10 / h15), and a start every STRIDE frames of a segment
GIVEN, HORIZONS, STRIDE = 3, (5, 10, 15), 4


def segment_starts(n_frames: int, stride: int = STRIDE) -> np.ndarray:
    """First given frames of every window of ``GIVEN`` + 15 frames in a segment, ``stride`` apart."""
    return np.arange(0, max(n_frames - GIVEN - max(HORIZONS) + 1, 0), stride)


def summed_errors(pred: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """Vertices ``(B, H, V, 3)`` against the truth (same shape) -> ``(H,)``: each horizon's mean vertex
    error (centroid-aligned), summed over the B starts."""
    from meshseq.align import per_vertex_error

    err = per_vertex_error(pred.reshape(-1, *pred.shape[2:]), truth.reshape(-1, *truth.shape[2:]))
    return err.mean(-1).reshape(truth.shape[:2]).sum(0)


def carry_errors(model, segments: list[tuple[np.ndarray, np.ndarray]], carries=CARRIES) -> tuple[np.ndarray, np.ndarray]:
    """``(ours (len(carries), 3), zero velocity (3,))``: ``summed_errors`` at h5 / h10 / h15 over every
    start of ``segments`` (``(scaled features (T, V, C), vertices (T, V, 3))`` each), ours by
    ``synthesize.predict`` with each carry."""
    cells = np.array(HORIZONS) - 1
    ours, zero = np.zeros((len(carries), len(cells))), np.zeros(len(cells))
    for feats, verts in segments:
        starts = segment_starts(len(feats))
        if not len(starts):
            continue
        x = np.stack([feats[s:s + GIVEN] for s in starts])  # (B, GIVEN, V, C)
        truth = np.stack([verts[s + GIVEN + cells] for s in starts])  # (B, 3, V, 3)
        zero += summed_errors(np.repeat(verts[starts + GIVEN - 1][:, None], len(cells), 1), truth)
        for i, c in enumerate(carries):
            f = predict(model, x, max(HORIZONS), carry=c)[:, cells]
            ours[i] += summed_errors(model.vertices(f.reshape(-1, *f.shape[2:])).reshape(truth.shape), truth)
    return ours, zero


def choose_carry(scores: np.ndarray, carries=CARRIES) -> float:
    """The largest of ``carries`` (ascending), unless the best-scoring smaller one scores lower than it
    by more than ``MARGIN``."""
    smaller = int(np.argmin(scores[:-1])) if len(carries) > 1 else len(carries) - 1
    return float(carries[smaller] if scores[smaller] < scores[-1] - MARGIN else carries[-1])


def fit_carry(model, segments: list[tuple[np.ndarray, np.ndarray]], carries=CARRIES) -> dict:
    """The carry that predicts ``segments`` best (``carry_errors``): each carry's score is its error over
    zero velocity's, averaged over h5 / h10 / h15. Returns ``{"carry": c, "scores": {str(c): score}}``
    (JSON-ready; the largest carry where no segment holds a window)."""
    ours, zero = carry_errors(model, segments, carries)
    if not zero.any():
        return {"carry": float(carries[-1]), "scores": {}}
    score = (ours / np.maximum(zero, 1e-300)).mean(axis=1)
    return {"carry": choose_carry(score, carries), "scores": {f"{c:g}": float(s) for c, s in zip(carries, score)}}
