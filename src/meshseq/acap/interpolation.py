"""Interpolating ACAP features between two keys with each vertex's rotation turned along its
shortest path (method.md, "What the generalisation benchmark leaves unmet").

A straight line between two keys' rotation logs is the shortest turn only while the logs lie on the
same branch near zero. Where a vertex's log sits on an outer 2 pi shell, or its rotation turns by
more than pi/2 between the keys, the line passes through rotations neither key is near (the
chord of an arc), and reconstructing the in-between frames from it loses to interpolating the
vertices themselves. ``geodesic_interpolation`` turns each vertex's rotation from one key's to the
other's by the smallest rotation between them and keeps every other channel linear.
"""

from __future__ import annotations

import numpy as np

from meshseq.acap.diagnostics import rotation_logs


def log_channels(logs: np.ndarray) -> np.ndarray:
    """The rotation channels ``(..., 3)`` of ACAP features holding rotation vectors ``logs``
    ``(..., 3)``: the inverse of ``diagnostics.rotation_logs``' reordering."""
    return np.stack([-logs[..., 2], logs[..., 1], -logs[..., 0]], axis=-1)


def geodesic_interpolation(key_a: np.ndarray, key_b: np.ndarray, n_between: int) -> np.ndarray:
    """Unscaled features ``(n_between + 2, ..., V, C)`` from ``key_a`` to ``key_b`` ``(..., V, C)``
    (one pair of keys or a batch of them), keys included: every channel linear as ``baselines.linear_interpolation`` but the rotation's, which
    turns at a constant rate about the smallest rotation from key a's rotation to key b's; each
    in-between log is the representative (its principal log plus a multiple of 2 pi along its
    axis) nearest the straight line's, so the logs stay continuous with the keys'."""
    from scipy.spatial.transform import Rotation

    a, b = np.asarray(key_a, dtype=np.float64), np.asarray(key_b, dtype=np.float64)
    s = np.linspace(0.0, 1.0, n_between + 2).reshape((-1,) + (1,) * a.ndim)
    out = (1 - s) * a[None] + s * b[None]
    log_a, log_b = rotation_logs(a), rotation_logs(b)
    turn = (Rotation.from_rotvec(log_a).inv() * Rotation.from_rotvec(log_b)).as_rotvec()  # (V, 3), angle <= pi
    every = (len(s),) + log_a.shape  # (n_between + 2, V, 3): all frames in one batch
    start = Rotation.from_rotvec(np.broadcast_to(log_a, every).reshape(-1, 3))
    turned = start * Rotation.from_rotvec((s * turn).reshape(-1, 3))
    logs = nearest_branch(turned.as_rotvec().reshape(every), rotation_logs(out))
    logs[0], logs[-1] = log_a, log_b  # the keys exactly
    out[..., :3] = log_channels(logs)
    return out


def nearest_branch(logs: np.ndarray, target: np.ndarray, shells: int = 2) -> np.ndarray:
    """``logs`` ``(..., 3)`` each moved by a multiple ``k`` of 2 pi along its axis (``|k| <= shells``)
    to the representative nearest ``target`` (same shape); a zero rotation stays zero."""
    norm = np.linalg.norm(logs, axis=-1, keepdims=True)
    axis = np.divide(logs, norm, out=np.zeros_like(logs), where=norm > 0)
    shifts = 2.0 * np.pi * np.arange(-shells, shells + 1)
    cand = logs[None] + np.reshape(shifts, (-1,) + (1,) * logs.ndim) * axis[None]  # (2 shells + 1, ..., 3)
    best = np.argmin(np.linalg.norm(cand - target[None], axis=-1), axis=0)
    return np.take_along_axis(cand, best[None, ..., None], axis=0)[0]
