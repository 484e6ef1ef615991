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
    (one pair of keys or a batch of them), keys included: every channel linear as
    ``baselines.linear_interpolation`` but the rotation's, which turns at a constant rate about the
    smallest rotation from key a's rotation to key b's; each in-between log is the representative
    (its principal log plus a multiple of 2 pi along its axis) nearest the straight line's, so the
    logs stay continuous with the keys'."""
    from scipy.spatial.transform import Rotation

    a, b = np.asarray(key_a, dtype=np.float64), np.asarray(key_b, dtype=np.float64)
    s = np.linspace(0.0, 1.0, n_between + 2).reshape((-1,) + (1,) * a.ndim)
    out = (1 - s) * a[None] + s * b[None]
    log_a, log_b = rotation_logs(a), rotation_logs(b)
    start = Rotation.from_rotvec(log_a.reshape(-1, 3))
    turn = (start.inv() * Rotation.from_rotvec(log_b.reshape(-1, 3))).as_rotvec().reshape(log_a.shape)  # angle <= pi
    turned = turned_logs(start.as_quat().reshape(log_a.shape[:-1] + (4,)), turn, s)
    logs = nearest_branch(turned, rotation_logs(out))
    logs[0], logs[-1] = log_a, log_b  # the keys exactly
    out[..., :3] = log_channels(logs)
    return out


def turned_logs(quat: np.ndarray, turn: np.ndarray, s: np.ndarray) -> np.ndarray:
    """Principal logs ``(T, ..., 3)`` of rotations ``quat`` ``(..., 4)`` (scalar last) each followed by
    ``s`` ``(T, 1, ..., 1)`` times its ``turn`` ``(..., 3)`` (a rotation vector): the quaternion product
    and log in numpy, for every frame at once (scipy's ``Rotation`` product and ``as_rotvec`` took
    0.35 s for 32 frames of 10,000 vertices)."""
    angle = np.linalg.norm(turn, axis=-1, keepdims=True)
    axis = np.divide(turn, angle, out=np.zeros_like(turn), where=angle > 0)
    half = 0.5 * s * angle  # (T, ..., 1)
    steps = np.concatenate([np.sin(half) * axis, np.cos(half)], axis=-1)  # (T, ..., 4)
    return quaternion_logs(quaternion_product(quat, steps))


def quaternion_product(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    """``p q`` of quaternions ``(..., 4)`` (scalar last), broadcast."""
    w1, v1, w2, v2 = p[..., 3:], p[..., :3], q[..., 3:], q[..., :3]
    w = w1 * w2 - np.sum(v1 * v2, axis=-1, keepdims=True)
    v = w1 * v2 + w2 * v1 + np.cross(v1, v2)
    return np.concatenate([v, w], axis=-1)


def quaternion_logs(quat: np.ndarray) -> np.ndarray:
    """Principal logs ``(..., 3)`` (angle <= pi) of unit quaternions ``(..., 4)`` (scalar last)."""
    flip = np.where(quat[..., 3:] < 0, -1.0, 1.0)  # the quaternion of angle <= pi
    w, v = quat[..., 3:] * flip, quat[..., :3] * flip
    sin_half = np.linalg.norm(v, axis=-1, keepdims=True)
    scale = np.where(sin_half > 1e-12, 2.0 * np.arctan2(sin_half, w) / np.maximum(sin_half, 1e-300), 2.0 / w)
    return v * scale


def nearest_branch(logs: np.ndarray, target: np.ndarray, shells: int = 2) -> np.ndarray:
    """``logs`` ``(..., 3)`` each moved by a multiple ``k`` of 2 pi along its axis (``|k| <= shells``)
    to the representative nearest ``target`` (same shape); a zero rotation stays zero. The distance
    is quadratic in ``k``, so the nearest integer to its minimum, ``a . (target - log) / 2 pi`` for
    the unit axis ``a``, is the nearest representative."""
    norm = np.linalg.norm(logs, axis=-1, keepdims=True)
    axis = np.divide(logs, norm, out=np.zeros_like(logs), where=norm > 0)
    k = np.clip(np.rint(np.einsum("...i,...i->...", axis, target - logs) / (2.0 * np.pi)), -shells, shells)
    return logs + (2.0 * np.pi) * k[..., None] * axis
