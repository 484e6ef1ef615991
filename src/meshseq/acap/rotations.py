"""Rotation logarithms made consistent over the mesh and over time (method.md 1.4-1.5).

A rotation's axis-angle (w, theta) is ambiguous: (-w, 2 pi - theta) and every theta + 2 pi k
give the same matrix. ACAP picks, per vertex, the representative that agrees with its
neighbours (spatial BFS of the reference code) and, for sequences, with the same vertex in the
previous frame (temporal; removes 2 pi jumps in time that a per-shape method cannot).
"""

from __future__ import annotations

import numpy as np

from meshseq.mesh import Topology

#: Rotation angles at or below this count as "no rotation" (method.md 1.4).
NO_ROTATION = 1e-6
TWO_PI = 2.0 * np.pi

#: ``spatial``: BFS per frame; ``temporal``: BFS on the first frame, then each frame nearest the previous.
CONSISTENCY_MODES = ("temporal", "spatial")


def axis_angle(R: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Axis-angle of rotations ``(..., 3, 3)``: unit axes ``(..., 3)`` and angles ``(...)`` in [0, pi].

    The angle uses atan2 of the skew and symmetric parts (accurate near 0 and pi). For angles
    beyond pi/2 the axis comes from the symmetric part ``(R + R^T)/2 - cos(theta) I``, which stays
    accurate where ``sin(theta)`` vanishes; its sign follows the skew part. Angles <= 1e-6 get
    angle 0 and the axis (1, 0, 0) (callers treat them as no rotation).
    """
    vee = np.stack(
        [R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]], axis=-1
    )  # = 2 sin(theta) w
    two_sin = np.linalg.norm(vee, axis=-1)
    two_cos = np.einsum("...ii->...", R) - 1.0
    theta = np.arctan2(two_sin, two_cos)
    axis = np.divide(vee, two_sin[..., None], out=np.zeros_like(vee), where=two_sin[..., None] > 0)
    wide = theta > 0.5 * np.pi
    if wide.any():
        Rw, c = R[wide], np.cos(theta[wide])
        sym = 0.5 * (Rw + np.swapaxes(Rw, -1, -2)) - c[:, None, None] * np.eye(3)  # (1 - c) w w^T
        k = np.argmax(np.einsum("nii->ni", sym), axis=-1)
        col = sym[np.arange(len(k)), :, k]
        col /= np.linalg.norm(col, axis=-1, keepdims=True)
        sign = np.where(np.einsum("ni,ni->n", col, vee[wide]) < 0, -1.0, 1.0)
        axis[wide] = col * sign[:, None]
    small = theta <= NO_ROTATION
    theta = np.where(small, 0.0, theta)
    axis[small] = (1.0, 0.0, 0.0)
    return axis, theta


def spatial_bfs(axis: np.ndarray, theta: np.ndarray, topology: Topology) -> np.ndarray:
    """Consistent rotation logs by the reference code's greedy BFS (method.md 1.5).

    Applied level by level over the BFS tree (vectorised over frames and the vertices of a level).

    Args:
        axis: ``(T, V, 3)`` unit axes; theta: ``(T, V)`` angles in [0, pi].
    Returns:
        ``(T, V, 3)`` rotation vectors ``Theta w`` with ``Theta = theta + 2 pi k``.
    """
    w = np.ascontiguousarray(axis.transpose(1, 0, 2)).copy()  # (V, T, 3) vertex-major
    th = np.ascontiguousarray(theta.T).copy()  # (V, T)
    k = np.zeros(th.shape, dtype=np.int64)
    _, parent, _ = topology.bfs
    for level in topology.bfs_levels[1:]:
        par = parent[level]
        wj, wi, tj, ti, ki = w[level], w[par], th[level], th[par], k[par]
        small = tj <= NO_ROTATION
        flip = (np.einsum("ntc,ntc->nt", wj, wi) < 0) & ~small
        wj = np.where(flip[..., None], -wj, wj)
        tj = np.where(flip, TWO_PI - tj, tj)
        jump = (np.abs(tj - ti) > np.pi) & ~small
        kj = ki + np.where(jump, np.where(ti < np.pi, -1, 1), 0)
        w[level] = np.where(small[..., None], wi, wj)
        th[level] = tj
        k[level] = kj
    big_theta = th + TWO_PI * k
    return (w * big_theta[..., None]).transpose(1, 0, 2)


def nearest_representative(axis: np.ndarray, theta: np.ndarray, target: np.ndarray) -> np.ndarray:
    """The representative ``(theta + 2 pi m) w`` of each rotation closest to a target vector.

    Every representative of (w, theta) lies on the line through the origin along w (the flipped
    axis -w with 2 pi - theta is m = -1), so the nearest one has
    ``m = round((w . target - theta) / 2 pi)``. For no rotation the axis is taken from the target.

    Args:
        axis: ``(..., 3)``; theta: ``(...)``; target: ``(..., 3)`` rotation vectors.
    Returns:
        ``(..., 3)`` rotation vectors.
    """
    small = theta <= NO_ROTATION
    tnorm = np.linalg.norm(target, axis=-1, keepdims=True)
    target_axis = np.divide(target, tnorm, out=np.zeros_like(target), where=tnorm > 0)
    w = np.where(small[..., None] & (tnorm > 0), target_axis, axis)
    s = np.einsum("...c,...c->...", w, target)
    m = np.round((s - theta) / TWO_PI)
    return w * (theta + TWO_PI * m)[..., None]


def temporal(axis: np.ndarray, theta: np.ndarray, topology: Topology) -> np.ndarray:
    """Spatial BFS on the first frame, then each frame's representative nearest the previous frame.

    Args:
        axis: ``(T, V, 3)``; theta: ``(T, V)``.
    Returns:
        ``(T, V, 3)`` rotation vectors, continuous in time (no 2 pi jumps between frames).
    """
    out = np.empty(axis.shape)
    out[:1] = spatial_bfs(axis[:1], theta[:1], topology)
    for t in range(1, len(theta)):  # sequential in time by definition; vectorised over vertices
        out[t] = nearest_representative(axis[t], theta[t], out[t - 1])
    return out


def consistent_logs(axis: np.ndarray, theta: np.ndarray, topology: Topology, mode: str = "temporal") -> np.ndarray:
    """Rotation vectors ``(T, V, 3)`` made consistent by ``mode`` (one of CONSISTENCY_MODES)."""
    if mode == "temporal":
        return temporal(axis, theta, topology)
    if mode == "spatial":
        return spatial_bfs(axis, theta, topology)
    raise ValueError(f"unknown consistency mode {mode!r}; expected one of {CONSISTENCY_MODES}")
