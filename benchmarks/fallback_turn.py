"""The novelty guard's fallback alone against two that continue the mesh's global turn as a turn
(method.md, "What the generalisation benchmark leaves unmet").

    python benchmarks/fallback_turn.py RUN SPEC[@FIRST,STOP] ... [--every 2]

Three given frames, starts every ``--every`` frames over frames ``[FIRST, STOP)`` of each sequence
(features made from the whole sequence): the fallback (``novelty.fallback``: every channel's
velocity continued at the given frames' own pace), the last shape turned rigidly (the vertices'
mean rotation step continued, every stretch and own turn held) and the turn continued with each
vertex's own turn and stretch weighted by the share of the vertices' turning the global turn leaves
(a mesh that only turns: the rigid turn; one that turns nowhere: the fallback). Each over the best
of zero velocity and linear ACAP extrapolation at h5 / h10 / h15, centroid-aligned and rigid (also
rotation-aligned), per sequence and their mean.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from generalize import frames_spec  # noqa: E402  (sibling scripts)
from novelty_guard import H as HORIZON, prediction_windows, vertex_errors  # noqa: E402

RULES = ("fallback", "rigid turn", "turn + own share")


def mean_rotation(matrices: np.ndarray) -> np.ndarray:
    """``(B, 3, 3)``: the rotation nearest the mean of each row of rotation matrices ``(B, V, 3, 3)``."""
    u, _, vt = np.linalg.svd(matrices.mean(1))
    flip = np.ones((len(u), 3))
    flip[:, 2] = np.sign(np.linalg.det(u @ vt))
    return (u * flip[:, None, :]) @ vt


def turn_steps(raw: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(mean turn (B, 3), each vertex's own step after it (B, V, 3), each vertex's step (B, V, 3))``
    as rotation vectors: the rotation steps between the last two given frames ``raw`` ``(B, 2, V, C)``
    (unscaled features; their rotations read with ``diagnostics.rotation_logs``), their mean rotation
    and what each leaves after it."""
    from scipy.spatial.transform import Rotation

    from meshseq.acap.diagnostics import rotation_logs

    b, _, v, _ = raw.shape
    logs = rotation_logs(raw[:, :2])
    steps = Rotation.from_rotvec(logs[:, 1].reshape(-1, 3)) * Rotation.from_rotvec(logs[:, 0].reshape(-1, 3)).inv()
    q = mean_rotation(steps.as_matrix().reshape(b, v, 3, 3))
    own = Rotation.from_matrix(np.repeat(q[:, None], v, 1).reshape(-1, 3, 3)).inv() * steps
    return Rotation.from_matrix(q).as_rotvec(), own.as_rotvec().reshape(b, v, 3), steps.as_rotvec().reshape(b, v, 3)


def turn_share(own_step: np.ndarray, steps: np.ndarray) -> np.ndarray:
    """``(B,)``: the vertices' mean own rotation step over their mean rotation step (``turn_steps``'
    ``(B, V, 3)``)."""
    total = np.linalg.norm(steps, axis=-1).mean(1)
    return np.clip(np.linalg.norm(own_step, axis=-1).mean(1) / np.maximum(total, 1e-12), 0.0, 1.0)


def turned(raw: np.ndarray, reach: np.ndarray, own: np.ndarray, turn: np.ndarray, own_step: np.ndarray) -> np.ndarray:
    """Frames ``(B, n, V, C)`` (unscaled features) after the last two given ``raw`` ``(B, 2, V, C)``:
    each vertex's rotation turned by the mean ``turn`` ``(B, 3)`` ``reach`` ``(B, n)`` times and by
    its ``own_step`` ``(B, V, 3)`` ``own * reach`` times (``own`` ``(B,)``; both from ``turn_steps``),
    its stretch (channels 3-8) continued ``own * reach`` steps, placement channels (9-) ``reach`` steps."""
    from scipy.spatial.transform import Rotation

    from meshseq.acap.diagnostics import rotation_logs
    from meshseq.acap.interpolation import log_channels, nearest_branch

    b, _, v, _ = raw.shape
    n = reach.shape[1]
    own_reach = (own[:, None] * reach)[:, :, None, None]  # (B, n, 1, 1)
    velocity = raw[:, 1:2] - raw[:, 0:1]
    out = raw[:, 1:2] + reach[:, :, None, None] * velocity  # every channel continued, then rotations and stretch replaced
    out[..., 3:9] = raw[:, 1:2, :, 3:9] + own_reach * velocity[..., 3:9]
    rot = (Rotation.from_rotvec(np.repeat((reach[:, :, None] * turn[:, None])[:, :, None], v, 2).reshape(-1, 3))
           * Rotation.from_rotvec((own_reach * own_step[:, None]).reshape(-1, 3))
           * Rotation.from_rotvec(np.repeat(rotation_logs(raw[:, 1:2]), n, 1).reshape(-1, 3))).as_rotvec()
    out[..., :3] = log_channels(nearest_branch(rot.reshape(b, n, v, 3), rotation_logs(out)))
    return out


def rule_frames(model, given: np.ndarray) -> dict[str, np.ndarray]:
    """``{rule: (B, H, V, C)}`` scaled features of each fallback after ``given`` ``(B, 3, V, C)``."""
    from meshseq import novelty

    reach = novelty.fallback_reach(given, HORIZON)
    raw = model.scaling.invert(given[:, -2:].astype(np.float64))
    turn, own_step, steps = turn_steps(raw)
    out = {"fallback": novelty.fallback(given, HORIZON)}
    for rule, own in (("rigid turn", np.zeros(len(given))), ("turn + own share", turn_share(own_step, steps))):
        out[rule] = model.scaling.apply(turned(raw, reach, own, turn, own_step)).astype(given.dtype)
    return out


def ratios(model, verts: np.ndarray, feats: np.ndarray, every: int) -> dict[str, np.ndarray]:
    """``{rule: (2, 3)}``: each fallback's errors (centroid, rigid) at h5 / h10 / h15 over the best
    baseline's, and ``"starts"``."""
    from meshseq import baselines

    _, given, truth, zero = prediction_windows(verts, feats, 3, every)
    def vertices(f):
        return model.vertices(f.reshape(-1, *f.shape[2:])).reshape(truth.shape)
    linear = vertices(baselines.linear_acap(given, HORIZON))
    best = np.array([np.minimum(vertex_errors(zero, truth, r), vertex_errors(linear, truth, r)) for r in (False, True)])
    out = {rule: np.array([vertex_errors(p, truth, r) for r in (False, True)]) / best
           for rule, p in ((rule, vertices(f)) for rule, f in rule_frames(model, given).items())}
    return out | {"starts": len(given)}


def main(argv: list[str] | None = None) -> None:
    import meshseq
    from meshseq.io import load_sequence

    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("run", help="a trained run (its mesh and feature scaling)")
    p.add_argument("specs", nargs="+", metavar="SPEC", help="sequences, each optionally SPEC@FIRST,STOP")
    p.add_argument("--every", type=int, default=2)
    args = p.parse_args(argv)
    model = meshseq.load(args.run)
    pooled = {rule: [] for rule in RULES}
    for spec in args.specs:
        path, frames = frames_spec(spec)
        verts = load_sequence(path).vertices.astype(np.float64)
        feats = model.features(verts)
        first, stop = frames or (0, len(verts))
        res = ratios(model, verts[first:stop], feats[first:stop], args.every)
        for rule in RULES:
            pooled[rule].append(res[rule])
        print(f"{spec.rsplit('/', 1)[-1]} ({res['starts']} starts): " + "  ".join(
            f"{rule} {fmt(res[rule])}" for rule in RULES), flush=True)
    if len(args.specs) > 1:
        print(f"mean over the {len(args.specs)} sequences: " + "  ".join(
            f"{rule} {fmt(np.mean(rows, axis=0))}" for rule, rows in pooled.items()))


def fmt(r: np.ndarray) -> str:
    """``(2, 3)`` ratios as ``c / c / c, rigid r / r / r``."""
    return " / ".join(f"{x:.2f}" for x in r[0]) + ", rigid " + " / ".join(f"{x:.2f}" for x in r[1])


if __name__ == "__main__":
    main()
