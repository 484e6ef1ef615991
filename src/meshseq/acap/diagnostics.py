"""Checks of ACAP features: spurious 2 pi jumps of the rotation logs in time.

A step of a vertex's rotation log between consecutive frames is a *spurious jump* when it is
longer than pi (:data:`~meshseq.acap.rotations.JUMP_STEP`) while the rotation it stands for
changes by less than pi/2 (:data:`~meshseq.acap.rotations.JUMP_MOTION`): the log changed branch,
the surface did not move that much. Such steps dominate a squared-error loss.
"""

from __future__ import annotations

import numpy as np

from meshseq.acap.parts import CHANNEL_COUNTS
from meshseq.acap.rotations import JUMP_MOTION, JUMP_STEP, relative_angles
from meshseq.errors import MeshseqError


def rotation_logs(features: np.ndarray) -> np.ndarray:
    """Rotation vectors ``Theta w`` ``(..., 3)`` of ACAP features ``(..., 9)`` (or ``(..., 12)`` with
    the placement channels of a multi-part mesh; method.md 1.6)."""
    q = np.asarray(features)
    if q.ndim < 1 or q.shape[-1] not in CHANNEL_COUNTS:
        raise MeshseqError(f"ACAP features must have 9 (or 12) channels in the last axis; got shape {q.shape}")
    return np.stack([-q[..., 2], q[..., 1], -q[..., 0]], axis=-1).astype(np.float64)


def branch_jumps(logs: np.ndarray) -> dict:
    """Spurious jumps of rotation logs ``(T, V, 3)`` over time.

    Returns a JSON-ready dict: ``spurious_jumps`` (vertex-steps), ``spurious_jump_vertices``,
    ``vertex_steps`` ((T - 1) V), ``largest_step`` (longest log step of any vertex, radians),
    ``largest_spurious_step`` (0 when there is none), ``largest_log_norm``,
    ``median_motion_at_jumps`` (median rotation change at the spurious steps; None when none), and
    ``fast_turns`` / ``fast_turn_vertices``: the vertex-steps, and the vertices with any, where the
    rotation itself turns by pi/2 or more in one frame (real motion, no jump, but more than a straight
    line between two frames' logs follows: where many vertices turn so fast, interpolating the
    features between keys loses to interpolating the vertices).
    """
    r = np.asarray(logs, dtype=np.float64)
    if r.ndim != 3 or r.shape[-1] != 3:
        raise MeshseqError(f"rotation logs must have shape (frames, vertices, 3); got {r.shape}")
    if not np.isfinite(r).all():
        raise MeshseqError("rotation logs contain NaN or infinite values")
    norm = np.linalg.norm(r, axis=-1)
    if len(r) < 2:
        step = np.zeros((0, r.shape[1]))
        spurious = np.zeros((0, r.shape[1]), dtype=bool)
        motion = step
    else:
        step = np.linalg.norm(np.diff(r, axis=0), axis=-1)
        motion = relative_angles(r)
        spurious = (step > JUMP_STEP) & (motion < JUMP_MOTION)
    return {
        "spurious_jumps": int(spurious.sum()),
        "spurious_jump_vertices": int(spurious.any(axis=0).sum()),
        "vertex_steps": int(step.size),
        "largest_step": float(step.max(initial=0.0)),
        "largest_spurious_step": float(step[spurious].max(initial=0.0)),
        "largest_log_norm": float(norm.max(initial=0.0)),
        "median_motion_at_jumps": float(np.median(motion[spurious])) if spurious.any() else None,
        "fast_turns": int((motion >= JUMP_MOTION).sum()),
        "fast_turn_vertices": int((motion >= JUMP_MOTION).any(axis=0).sum()),
    }


def feature_jumps(features: np.ndarray) -> dict:
    """:func:`branch_jumps` of ACAP features ``(T, V, 9)``."""
    f = np.asarray(features)
    if f.ndim != 3:
        raise MeshseqError(f"ACAP features must have shape (frames, vertices, 9); got {f.shape}")
    return branch_jumps(rotation_logs(f))
