"""Evaluation of the paper's tables and figure (method.md 4) on held-out frames.

- ``prediction_errors``: per-vertex position error in the data's units (reported x 1e-4) at
  given horizons after u given frames, for our model and every prediction baseline, averaged over
  every start in the held-out range that has enough frames; after removing translation
  (centroids) and after a rigid (Kabsch) alignment.
- ``feature_change``: mean ``||X_t - X_{t+1}|| / ||X_t||`` (raw ACAP features) along generated
  sequences (the paper's Fig. 3), beside the ground truth's level.
- ``completion_errors``: in-between error of completions against the truth for held-out gaps,
  for ours, CMA-ES and linear interpolation, and the diversity of K random-state samples.
- ``validation_error``: one number for choosing a checkpoint during training (``meshseq train
  --validation``): ours' prediction error on validation blocks carved out of the training frames.

Functions take arrays and a loaded ``meshseq.api.Model``; they print nothing.
"""

from __future__ import annotations

import numpy as np

from meshseq import baselines
from meshseq.align import per_vertex_error
from meshseq.errors import MeshseqError
from meshseq.plots import feature_change as relative_change
from meshseq.synthesize import (METHOD_JOINS, anchor_line, assemble_vertices, blend_toward_vertices, chain_states,
                                complete_cma, join_chain_states, join_chains, line_shares, predict, run_chains,
                                run_context_chains)

UNITS = 1e-4  # errors are reported in the data's units x 1e-4 (paper's tables)


def prediction_starts(lo: int, hi: int, given: int, horizon: int, every: int = 1) -> np.ndarray:
    """First-given-frame indices ``s`` with ``s .. s + given - 1 + horizon`` inside ``[lo, hi)``."""
    last = hi - given - horizon
    return np.arange(lo, last + 1, max(1, every))


def predicted_features(method: str, model, feats: np.ndarray, starts: np.ndarray, given: int,
                       n_frames: int, vae=None, sample: bool = False, guard: bool = True) -> np.ndarray:
    """Scaled features ``(B, n, V, 9)`` predicted by ``method`` after ``feats[s:s+given]``
    (``sample``: ours draws the VAE latent instead of taking its mean; ``guard``: ours with the
    novelty guard, ``synthesize.predict``'s)."""
    return method_prediction(method, model, np.stack([feats[s:s + given] for s in starts]), n_frames, vae, sample,
                             guard)


def method_prediction(method: str, model, windows: np.ndarray, n_frames: int, vae=None,
                      sample: bool = False, guard: bool = True) -> np.ndarray:
    """Scaled features ``(B, n, V, 9)`` predicted by ``method`` after given frames ``(B, U, V, 9)``."""
    if method == "ours":
        return predict(model, windows, n_frames, sample=sample, guard=guard)
    if method == "zero_velocity":
        return baselines.zero_velocity(windows, n_frames)
    if method == "linear_acap":
        return baselines.linear_acap(windows, n_frames)
    if method == "vae_latent":
        if vae is None:
            raise MeshseqError("the vae_latent baseline needs a trained mesh VAE")
        return baselines.vae_latent(vae, windows, n_frames)
    raise MeshseqError(f"unknown prediction method {method!r}; expected one of {baselines.PREDICTION_METHODS}")


def prediction_errors(model, vertices: np.ndarray, feats: np.ndarray, lo: int, hi: int,
                      given: int, horizons: list[int], methods: list[str], vae=None,
                      every: int = 1, guard: bool = True) -> dict:
    """Errors per method in units of 1e-4, averaged over every start in ``[lo, hi)``.

    ``vertices`` ``(T, V, 3)`` true positions and ``feats`` ``(T, V, 9)`` their scaled features;
    the held-out range is ``[lo, hi)``. Zero velocity is measured in vertex space (the last given
    frame's true vertices: no reconstruction error); the others are reconstructed from features.
    ``guard``: ours with the novelty guard (``synthesize.predict``'s).

    Returns ``{method: {"centroid": {str(h): e}, "rigid": {str(h): e}, "curve": [e_1..e_H],
    "starts": n}}`` (``curve``: centroid-aligned error at every horizon 1..max(horizons)).
    """
    h_max = max(horizons)
    starts = prediction_starts(lo, hi, given, h_max, every)
    if len(starts) == 0:
        raise MeshseqError(f"the range {lo}:{hi} has no room for {given} given frames and a horizon of "
                           f"{h_max} ({hi - lo} frames; need at least {given + h_max})")
    steps = np.arange(1, h_max + 1)
    truth = np.stack([vertices[s + given - 1 + steps] for s in starts])  # (B, H, V, 3)
    flat_truth = truth.reshape(-1, *truth.shape[2:])
    out = {}
    for method in methods:
        if method == "zero_velocity":
            pred = np.repeat(np.stack([vertices[s + given - 1] for s in starts])[:, None], h_max, 1)
        else:
            f = predicted_features(method, model, feats, starts, given, h_max, vae, guard=guard)  # (B, H, V, 9)
            pred = model.vertices(f.reshape(-1, *f.shape[2:])).reshape(truth.shape)
        flat = pred.reshape(flat_truth.shape)
        res = {"starts": int(len(starts))}
        for key, rigid in (("centroid", False), ("rigid", True)):
            err = per_vertex_error(flat, flat_truth, rigid=rigid).mean(axis=-1).reshape(len(starts), h_max)
            curve = err.mean(axis=0) / UNITS
            res[key] = {str(h): float(curve[h - 1]) for h in horizons}
            if not rigid:
                res["curve"] = curve.tolist()
        out[method] = res
    return out


def validation_error(model, vertices: list[np.ndarray], feats: list[np.ndarray], blocks: list[tuple[int, int]],
                     givens: tuple[int, ...] = (1, 3), horizon: int = 15, max_starts: int = 4,
                     method: str = "ours") -> float:
    """Ours' (or a baseline ``method``'s) mean centroid-aligned per-vertex error (x 1e-4) on
    validation blocks.

    For each data set ``d`` and each u in ``givens``, up to ``max_starts`` evenly spaced starts whose
    predicted frames (horizons 1..H, ``H = min(horizon, shortest block)``) all lie in the block
    ``blocks[d] = [lo, hi)``; the u given frames may precede it (they are training frames, the
    predicted ones are not). The error is averaged over horizons, starts, data sets and givens.

    Args:
        model: ``meshseq.api.Model`` (the network in eval mode).
        vertices: true (centred) vertices ``[(T_d, V, 3)]``; ``feats``: their scaled features
            ``[(T_d, V, 9)]``.
    """
    h = min(horizon, min(hi - lo for lo, hi in blocks))
    if h < 1:
        raise MeshseqError("validation_error: a validation block is empty")
    errors = []
    for u in givens:
        windows, truths = [], []
        for v, f, (lo, hi) in zip(vertices, feats, blocks):
            starts = prediction_starts(max(lo - u, 0), hi, u, h)
            if len(starts) == 0:
                continue
            starts = np.unique(starts[np.linspace(0, len(starts) - 1, min(max_starts, len(starts))).round().astype(int)])
            windows += [f[s:s + u] for s in starts]
            truths += [v[s + u:s + u + h] for s in starts]
        if not windows:
            continue
        pred = method_prediction(method, model, np.stack(windows), h)  # (B, H, V, 9)
        truth = np.concatenate(truths)  # (B H, V, 3)
        verts = model.vertices(pred.reshape(-1, *pred.shape[2:]))
        errors.append(per_vertex_error(verts, truth).mean() / UNITS)
    if not errors:
        raise MeshseqError(f"validation_error: no block has room for {min(givens)} given frame(s) and a horizon of {h}")
    return float(np.mean(errors))


#: Starts whose roll-outs ``feature_change`` holds at once (8 starts of a 60-frame crane curve: 0.35 GB
#: in float64, and as much again for their differences; all 34 of its held-out end took 6 GB).
CURVE_STARTS = 8


def feature_change(model, feats: np.ndarray, starts: np.ndarray, given: int, n_frames: int,
                   methods: list[str], vae=None, sample: bool = False, guard: bool = True) -> dict:
    """Mean feature-change curve (length ``n_frames``) per method, plus ``ground_truth``'s mean level.

    The curve starts at the step from the last given frame to the first generated one.
    ``sample``: ours draws the VAE latent (default: its mean, as meshseq predicts); ``guard``: ours
    with the novelty guard.
    """
    out = {}
    for method in methods:
        total = np.zeros(n_frames)
        for i in range(0, len(starts), CURVE_STARTS):  # a few starts at a time: (B, n, V, C) float64 is large
            part = starts[i:i + CURVE_STARTS]
            windows_last = np.stack([feats[s + given - 1] for s in part])[:, None]
            f = predicted_features(method, model, feats, part, given, n_frames, vae, sample, guard)
            raw = model.scaling.invert(np.concatenate([windows_last, f], axis=1))
            total += relative_change(raw) * len(part)
        out[method] = (total / len(starts)).tolist()
    raw_truth = model.scaling.invert(feats.astype(np.float64))
    out["ground_truth"] = float(relative_change(raw_truth).mean())
    return out


def completion_errors(model, vertices: np.ndarray, feats: np.ndarray, lo: int, hi: int,
                      gaps: list[int], methods: list[str], samples: int = 4, seed: int = 0,
                      max_starts: int = 8, cma_evals: int = 200, cma_seconds: float = 20.0,
                      context: int = 0, line: str = "geodesic", vertex_share: float | None = None) -> dict:
    """In-between errors (x 1e-4, centroid-aligned, mean over in-between frames and starts) for
    held-out gaps, and the diversity of ``samples`` random-state completions (ours).

    With ``context`` > 0 the chains of ours are given up to that many frames of the sequence before
    key a and after key b (``synthesize.complete``'s ``before`` / ``after``, the command's
    ``--context``); the other methods always the keys alone. ``line``: what ours' anchored join draws
    toward (``synthesize.anchor_line``); ``vertex_share``: how far the part of ours taken from it moves
    on toward the vertices' straight lines (``synthesize.complete_keyframes``'; default the model's).

    Returns ``{str(gap): {method: error, ..., "diversity": d, "starts": n}}``.
    """
    out = {}
    share = model.vertex_share if vertex_share is None else vertex_share
    for gap in gaps:
        starts = np.arange(lo, hi - gap - 1)
        if len(starts) == 0:
            continue
        starts = starts[np.linspace(0, len(starts) - 1, min(max_starts, len(starts))).astype(int)]
        res: dict = {"starts": int(len(starts))}
        frames, line_share = _completion_features(model, feats, starts, gap, methods, seed, cma_evals, cma_seconds,
                                                  context, line)
        for m in methods:
            errs = []
            for p, a in enumerate(starts):
                b = a + gap + 1
                if m == "linear_vertices":  # straight lines in vertex space: no features involved
                    verts = baselines.linear_interpolation(vertices[a], vertices[b], gap)
                else:
                    verts = assemble_vertices(model, frames[m][p], {0: vertices[a], gap + 1: vertices[b]})
                if m == "ours" and share:
                    verts = blend_toward_vertices(verts[None], share * line_share[p:p + 1])[0]
                errs.append(per_vertex_error(verts[1:-1], vertices[a + 1:b]).mean() / UNITS)
            res[m] = float(np.mean(errs))
        if samples > 1:
            res["diversity"] = _completion_diversity(model, vertices, feats, starts, gap, samples, seed)
        out[str(gap)] = res
    return out


def _completion_features(model, feats: np.ndarray, starts: np.ndarray, gap: int, methods: list[str], seed: int,
                         cma_evals: int, cma_seconds: float, context: int = 0,
                         line: str = "geodesic") -> tuple[dict[str, np.ndarray], np.ndarray | None]:
    """Scaled features ``(P, gap + 2, V, 9)`` of each feature-space method's completion of the gaps
    ``feats[s] .. feats[s + gap + 1]`` for the P ``starts``, and ``(P,)`` the share of ours taken
    from the line between the keys (``synthesize.line_shares``; None without ours). The chains of
    every start run as one roll-out from the trained initial states (what ``complete`` does for
    one gap; ``context_chains``), joined each way."""
    keys_a, keys_b = feats[starts], feats[starts + gap + 1]
    out, chains, line_share = {}, {}, None
    for m in methods:
        if m == "linear_vertices":
            continue
        if m in METHOD_JOINS:
            frames_around = context if m == "ours" else 0  # (stitch and corrected: the keys alone)
            if frames_around not in chains:
                chains[frames_around] = context_chains(model, feats, starts, gap, frames_around)
            fw, bw, trusted = chains[frames_around]
            anchored = METHOD_JOINS[m] == "anchored"
            anchor = anchor_line(model, keys_a, keys_b, gap + 2, line) if anchored else None
            f = join_chains(fw, bw, METHOD_JOINS[m], trusted=trusted, line=anchor)[0]
            if m == "ours":
                line_share = line_shares(fw, bw, trusted)
            f[:, 0], f[:, -1] = keys_a, keys_b
        elif m == "cma":  # one optimisation per gap (each batches its population)
            f = np.stack([complete_cma(model, a, b, gap, max_evals=cma_evals, max_seconds=cma_seconds,
                                       seed=seed).frames[0] for a, b in zip(keys_a, keys_b)])
        elif m == "linear":
            f = np.stack([baselines.linear_interpolation(a, b, gap) for a, b in zip(keys_a, keys_b)])
        else:
            raise MeshseqError(f"unknown completion method {m!r}; expected one of {baselines.COMPLETION_METHODS}")
        out[m] = f
    return out, line_share


def context_chains(model, feats: np.ndarray, starts: np.ndarray, gap: int, context: int):
    """``(forward, backward, trusted)`` of the gaps ``feats[s] .. feats[s + gap + 1]`` for the P
    ``starts``: the chains ``(P, gap + 2, V, C)`` warmed up on up to ``context`` frames of ``feats``
    before key a and after key b, and ``(P,)`` whether the model predicts those frames better than
    standing still and constant velocity (``synthesize.run_context_chains``). Starts
    with as many frames around their keys run as one roll-out; with ``context=0``, the chains from
    the keys alone, none trusted."""
    n_before = np.minimum(context, starts)
    n_after = np.minimum(context, len(feats) - 1 - (starts + gap + 1))
    shape = (len(starts), gap + 2) + feats.shape[1:]
    forward, backward = np.empty(shape, np.float32), np.empty(shape, np.float32)
    trusted = np.zeros(len(starts), bool)
    for la, lb in sorted(set(zip(n_before.tolist(), n_after.tolist()))):
        rows = np.flatnonzero((n_before == la) & (n_after == lb))
        a, b = starts[rows], starts[rows] + gap + 1
        before = np.stack([feats[s - la:s] for s in a])
        after = np.stack([feats[s + 1:s + 1 + lb] for s in b])
        state = model.engine.initial_state(len(rows), len(rows))
        forward[rows], backward[rows], trusted[rows] = run_context_chains(model, feats[a], feats[b], gap, state,
                                                                          before, after)
    return forward, backward, trusted


def _completion_diversity(model, vertices: np.ndarray, feats: np.ndarray, starts: np.ndarray, gap: int,
                          samples: int, seed: int) -> float:
    """Mean pairwise diversity (x 1e-4) of ``samples`` random-state completions per start: start
    ``s`` draws the states ``complete(..., samples=samples, seed=seed + s)`` draws; all starts'
    chains run as one roll-out."""
    state = join_chain_states([chain_states(model, samples, True, seed + int(s))
                               for s in starts])
    rows = np.repeat(starts, samples)
    frames = join_chains(*run_chains(model, feats[rows], feats[rows + gap + 1], gap, state), "corrected")[0]
    frames = frames.reshape(len(starts), samples, *frames.shape[1:])
    diversity = []
    for p, a in enumerate(starts):
        f = frames[p]
        f[:, 0], f[:, -1] = feats[a], feats[a + gap + 1]
        verts = assemble_vertices(model, f, {0: vertices[a], gap + 1: vertices[a + gap + 1]})[:, 1:-1]
        diversity.append(baselines.pairwise_diversity(verts) / UNITS)
    return float(np.mean(diversity))
