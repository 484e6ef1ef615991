"""Does a prediction keep the pace of its given frames? (still stays still, slow stays slow)

The motion level of a run of frames is the mean distance a vertex moves from one frame to the
next, translation removed (centroids subtracted). For many starts, ``pace_table`` compares the
level of the given frames, of the truth that follows them and of the prediction, binned by the
given level relative to the sequence's typical level (its median step). Numerical code only:
arrays in, arrays out.
"""

from __future__ import annotations

import numpy as np

#: Bins of the given frames' level over the sequence's median step level: ``(name, low, high)``.
PACE_BINS = (("still", 0.0, 0.1), ("slow", 0.1, 0.5), ("steady", 0.5, 1.5), ("fast", 1.5, np.inf))


def step_levels(vertices: np.ndarray) -> np.ndarray:
    """``(..., n, V, 3)`` frames -> ``(..., n - 1)`` mean per-vertex distance between consecutive
    frames, each frame centred on its centroid."""
    centred = vertices - vertices.mean(axis=-2, keepdims=True)
    return np.linalg.norm(np.diff(centred, axis=-3), axis=-1).mean(axis=-1)


def pace_levels(model, vertices: np.ndarray, feats: np.ndarray, starts: np.ndarray, given: int = 3,
                horizon: int = 15, hold: bool = False, guard: bool = True) -> dict:
    """Motion levels around predictions from ``given`` frames at each start.

    Args:
        model: ``meshseq.api.Model``; ``vertices`` ``(T, V, 3)`` and ``feats`` ``(T, V, 9)`` (scaled)
            one sequence; ``starts`` ``(B,)`` first given frames (``s + given + horizon <= T``).
        hold: give the frame ``s`` ``given`` times instead (a pose held still).
        guard: predict with the novelty guard (``synthesize.predict``'s).
    Returns ``{"given", "truth", "ours"}``, each ``(B,)``: the given frames' level (0 for a hold),
    the truth's over the ``horizon`` frames after them (for a hold: the frames after ``s``), and
    the prediction's (from the last given frame's reconstruction through the predicted frames).
    """
    from meshseq.synthesize import predict

    starts = np.asarray(starts)
    idx = starts[:, None] + (np.zeros(given, int) if hold else np.arange(given))[None, :]
    pred = predict(model, feats[idx], horizon, guard=guard)  # (B, H, V, 9)
    last = feats[idx[:, -1]][:, None]
    frames = np.concatenate([last, pred], axis=1)
    recon = model.vertices(frames.reshape(-1, *frames.shape[2:])).reshape(*frames.shape[:2], -1, 3)
    after = idx[:, -1:] + np.arange(horizon + 1)[None, :]
    given_level = step_levels(vertices[idx]).mean(-1) if given > 1 else np.full(len(starts), np.nan)
    return {"given": given_level, "truth": step_levels(vertices[after]).mean(-1),
            "ours": step_levels(recon).mean(-1)}


def pace_table(levels: dict, typical: float) -> list[dict]:
    """Bin ``pace_levels``'s output by the given level over ``typical`` (the sequence's median step).

    Returns one row per non-empty bin of ``PACE_BINS``: ``{"bin", "starts", "given", "truth",
    "ours"}``, the levels' means over ``typical``, and ``"ours_over_truth"``, the mean ratio of
    the prediction's level to the truth's.
    """
    rel = {k: np.asarray(v) / typical for k, v in levels.items()}
    rows = []
    for name, lo, hi in PACE_BINS:
        pick = (rel["given"] >= lo) & (rel["given"] < hi)
        if pick.any():
            rows.append({"bin": name, "starts": int(pick.sum()),
                         **{k: float(rel[k][pick].mean()) for k in ("given", "truth", "ours")},
                         "ours_over_truth": float(np.mean(rel["ours"][pick] / np.maximum(rel["truth"][pick], 1e-3)))})
    return rows
