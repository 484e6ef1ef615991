"""The benchmark's motion of 50 under other roll-out rules (method.md, "What the generalisation
benchmark leaves unmet"): what the generated motion level does where the novelty guard acts and on
a mesh's small parts.

    python benchmarks/motion_rules.py RUN SPEC[@FIRST,STOP] ...

For each block (the whole sequence without ``@``): the feature change of 50 frames predicted from
one given frame over the truth's over the block (``generalize.motion_scores``' figure, its starts),
and ours' error at h5 / h10 / h15 from those starts over zero velocity's (centroid-aligned), for:
``guarded`` (the benchmark's), ``unguarded`` (the paper's roll-out: one given frame leaves pace and
carry nothing to act on), ``sampled`` (unguarded, the VAE latent drawn at each step: one
draw per start), ``training pace`` (unguarded, replayed at the tempo that brings its mean step to
the training frames': ``at_training_pace``), ``block's pace`` (the same at the block's own mean step:
an oracle, which shows what the tempo alone would give), and on a mesh of several parts ``parts rigid`` (unguarded, each part but the
largest given, every frame, one rotation and stretch: the mean of its vertices') and ``parts held``
(unguarded, those parts' rotation and stretch held at the given frame's) and ``parts follow``
(unguarded, each of those parts turned with the vertex of the largest part it sits at, its stretch
held: ``following_parts``).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from generalize import frames_spec, motion_starts  # noqa: E402  (sibling scripts)

N_FRAMES = 50
CELLS = (4, 9, 14)  # h5, h10, h15
SHAPE = slice(0, 9)  # rotation and stretch channels
MAX_TEMPO = 3  # the fastest replay of ``at_training_pace``


def rigid_parts(pred: np.ndarray, parts: list[np.ndarray]) -> np.ndarray:
    """``pred`` ``(B, n, V, C)`` with each part's ``(V,)`` mask's rotation and stretch channels set, in
    every frame, to the mean over the part's vertices."""
    out = pred.copy()
    for mask in parts:
        out[:, :, mask, SHAPE] = pred[:, :, mask, SHAPE].mean(axis=2, keepdims=True)
    return out


def held_parts(pred: np.ndarray, given: np.ndarray, parts: list[np.ndarray]) -> np.ndarray:
    """``pred`` ``(B, n, V, C)`` with each part's rotation and stretch channels held at the last given
    frame's (``given`` ``(B, V, C)``)."""
    out = pred.copy()
    for mask in parts:
        out[:, :, mask, SHAPE] = given[:, None][:, :, mask, SHAPE]
    return out


def quaternions(logs: np.ndarray) -> np.ndarray:
    """Unit quaternions ``(..., 4)`` (scalar last) of rotation vectors ``(..., 3)``."""
    from scipy.spatial.transform import Rotation

    return Rotation.from_rotvec(logs.reshape(-1, 3)).as_quat().reshape(logs.shape[:-1] + (4,))


def following_parts(raw: np.ndarray, given: np.ndarray, parts: list[np.ndarray], anchors: list[int]) -> np.ndarray:
    """Unscaled ``raw`` ``(B, n, V, C)`` with each part's rotations turned from the last given frame's
    (``given`` ``(B, V, C)``, unscaled) by the turn of its anchor vertex (on the largest part) since
    that frame, ``R_p(t) = R_a(t) R_a(given)^-1 R_p(given)``, and its stretch held: the part carried
    as if fixed to the body where it sits."""
    from meshseq.acap.diagnostics import rotation_logs
    from meshseq.acap.interpolation import log_channels, nearest_branch, quaternion_logs, quaternion_product

    out = raw.copy()
    logs, logs_given = rotation_logs(raw), rotation_logs(given)  # (B, n, V, 3), (B, V, 3)
    for mask, a in zip(parts, anchors):
        inverse_given = quaternions(-logs_given[:, a])  # (B, 4)
        turn = quaternion_product(quaternions(logs[:, :, a]), inverse_given[:, None])  # (B, n, 4)
        turned = quaternion_logs(quaternion_product(turn[:, :, None], quaternions(logs_given[:, mask])[:, None]))
        held = np.broadcast_to(logs_given[:, None][:, :, mask], turned.shape)  # (B, n, m, 3)
        out[:, :, mask, :3] = log_channels(nearest_branch(turned, held))
        out[:, :, mask, 3:9] = given[:, None][:, :, mask, 3:9]
    return out


def small_parts(faces: np.ndarray, reference: np.ndarray) -> tuple[list[np.ndarray], list[int]]:
    """``(V,)`` masks of every connected part but the largest, and each one's anchor vertex
    (``acap.parts.part_anchors``)."""
    from meshseq.acap.parts import body_part, part_anchors
    from meshseq.mesh import Topology

    topology = Topology.from_faces(faces, len(reference))
    body, anchors = body_part(topology), part_anchors(reference, topology)
    others = [c for c in range(topology.n_components) if c != body]
    return [topology.component_labels == c for c in others], [int(anchors[c]) for c in others]


def step_size(feats: np.ndarray) -> np.ndarray:
    """Mean norm of the steps between consecutive frames of ``feats`` ``(..., T, V, C)`` -> ``(...)``."""
    return np.linalg.norm(np.diff(feats, axis=-3).reshape(feats.shape[:-3] + (feats.shape[-3] - 1, -1)),
                          axis=-1).mean(axis=-1)


def training_levels(model) -> tuple[float, float]:
    """The training frames' mean step (scaled features, ``step_size``) and mean feature change
    (``plots.feature_change``, unscaled) of the run ``model``, over its training segments."""
    from generalize import training_segments
    from meshseq.plots import feature_change

    segments = [f for f, _ in training_segments(model) if len(f) > 1]
    changes = [feature_change(model.scaling.invert(f.astype(np.float64))).mean() for f in segments]
    return float(np.mean([step_size(f) for f in segments])), float(np.mean(changes))


def at_training_pace(x: np.ndarray, long_roll_out: np.ndarray, typical: float) -> np.ndarray:
    """``(B, 50, V, C)``: each start's roll-out ``long_roll_out`` ``(B, n, V, C)`` after ``x``
    ``(B, 1, V, C)`` replayed at the tempo ``k`` that brings its first 50 steps' mean to ``typical``
    (frame j at time ``k j``, linear between frames; ``k`` within [0.25, MAX_TEMPO])."""
    path = np.concatenate([x, long_roll_out], axis=1)
    k = np.clip(typical / np.maximum(step_size(path[:, :N_FRAMES + 1]), 1e-12), 0.25, MAX_TEMPO)  # (B,)
    t = k[:, None] * np.arange(1, N_FRAMES + 1)  # (B, 50)
    i = np.minimum(np.floor(t).astype(int), path.shape[1] - 2)
    w = (t - i)[..., None, None]
    rows = np.arange(len(path))[:, None]
    return ((1 - w) * path[rows, i] + w * path[rows, i + 1]).astype(np.float32)


def roll_outs(model, x: np.ndarray, parts: list[np.ndarray], anchors: list[int], training_step: float,
              block_step: float) -> dict[str, np.ndarray]:
    """``{rule: (B, 50, V, C)}`` scaled features predicted from given frames ``x`` ``(B, 1, V, C)``
    (``training_step``, ``block_step``: the training frames' and the block's mean step, ``step_size``)."""
    from meshseq.synthesize import predict

    long = predict(model, x, MAX_TEMPO * N_FRAMES, guard=False)
    free = long[:, :N_FRAMES]
    out = {"guarded": predict(model, x, N_FRAMES), "unguarded": free,
           "training pace": at_training_pace(x, long, training_step),
           "block's pace": at_training_pace(x, long, block_step)}
    out["sampled"] = predict(model, x, N_FRAMES, guard=False, sample=True)
    if parts:
        out["parts rigid"] = rigid_parts(free, parts)
        out["parts held"] = held_parts(free, x[:, -1], parts)
        raw, given = model.scaling.invert(free.astype(np.float64)), model.scaling.invert(x[:, -1].astype(np.float64))
        out["parts follow"] = model.scaling.apply(following_parts(raw, given, parts, anchors)).astype(np.float32)
    return out


def block_figures(model, verts: np.ndarray, faces: np.ndarray, lo: int, hi: int, training_step: float) -> dict:
    """``{rule: (motion of 50, (3,) error over zero velocity's at h5 / h10 / h15)}`` of block ``[lo, hi)``
    (``training_step``: ``training_levels``' first)."""
    from meshseq.align import per_vertex_error
    from meshseq.plots import feature_change

    feats = model.features(verts)
    starts = motion_starts(lo, hi)
    x = feats[starts][:, None]
    truth_level = feature_change(model.scaling.invert(feats[lo:hi].astype(np.float64))).mean()
    reach = np.array([s + 1 + h for s in starts for h in CELLS])
    ok = (reach < len(verts)).reshape(len(starts), len(CELLS))
    out = {}
    for rule, pred in roll_outs(model, x, *small_parts(faces, model.reference), training_step,
                                 step_size(feats[lo:hi])).items():
        raw = model.scaling.invert(np.concatenate([x, pred], axis=1).astype(np.float64))
        level = feature_change(raw).mean() / max(truth_level, 1e-300)
        errors = np.zeros(len(CELLS))
        for j, h in enumerate(CELLS):
            s = starts[ok[:, j]]
            if not len(s):
                errors[j] = np.nan
                continue
            shapes = model.vertices(pred[ok[:, j], h])
            ours = per_vertex_error(shapes, verts[s + 1 + h]).mean()
            still = per_vertex_error(verts[s], verts[s + 1 + h]).mean()
            errors[j] = ours / max(still, 1e-300)
        out[rule] = (float(level), errors)
    return out


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("run", help="a trained run")
    p.add_argument("specs", nargs="+", metavar="SPEC[@FIRST,STOP]", help="sequences, each with an optional block")
    args = p.parse_args(argv)
    import meshseq
    from meshseq.io import load_sequence
    from meshseq.plots import feature_change

    model = meshseq.load(args.run)
    training_step, training_change = training_levels(model)
    for text in args.specs:
        spec, block = frames_spec(text)
        seq = load_sequence(spec)
        verts = seq.vertices.astype(np.float64)
        lo, hi = block if block is not None else (0, len(verts))
        feats = model.features(verts)[lo:hi]
        change = feature_change(model.scaling.invert(feats.astype(np.float64))).mean()
        print(f"{text}: the truth's mean step {step_size(feats) / training_step:.2f} and feature change "
              f"{change / training_change:.2f} of the training frames'; motion of 50 | ours over zero velocity "
              "at h5 / h10 / h15 from the same starts")
        for rule, (level, errors) in block_figures(model, verts, seq.faces, lo, hi, training_step).items():
            print(f"  {rule:13s} {level:5.2f} | " + " / ".join(f"{e:.2f}" for e in errors), flush=True)


if __name__ == "__main__":
    main()
