"""Rigid placement of vertex sequences: centroid translation and best-fit (Kabsch) rotation.

ACAP features carry no global translation (and the reconstruction no global rotation beyond the
features'), so results are placed to wherever the caller asks, and errors are measured after
removing translation and, optionally, the best rotation.
"""

from __future__ import annotations

import numpy as np


def kabsch_rotation(source: np.ndarray, target: np.ndarray) -> np.ndarray:
    """Rotations ``(..., 3, 3)`` that best map centred ``source`` onto centred ``target`` ``(..., V, 3)``.

    Minimises ``||R s_k - t_k||`` over proper rotations (reflection excluded).
    """
    s = source - source.mean(axis=-2, keepdims=True)
    t = target - target.mean(axis=-2, keepdims=True)
    H = np.swapaxes(s, -1, -2) @ t  # (..., 3, 3)
    U, _, Vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(np.swapaxes(Vt, -1, -2) @ np.swapaxes(U, -1, -2)))
    D = np.zeros(H.shape)
    D[..., 0, 0] = 1.0
    D[..., 1, 1] = 1.0
    D[..., 2, 2] = np.where(d == 0, 1.0, d)
    return np.swapaxes(Vt, -1, -2) @ D @ np.swapaxes(U, -1, -2)


def place(vertices: np.ndarray, target: np.ndarray | None = None, rigid: bool = False) -> np.ndarray:
    """Translate (and with ``rigid`` rotate) ``vertices (T, V, 3)`` onto a target.

    Args:
        target: ``None`` (centroids to the origin), centroids ``(T, 3)`` or ``(3,)``, or vertices
            ``(T, V, 3)`` / ``(V, 3)`` to match by centroid (and best rotation when ``rigid``).
    """
    v = np.asarray(vertices, dtype=np.float64)
    centred = v - v.mean(axis=-2, keepdims=True)
    if target is None:
        return centred
    tgt = np.asarray(target, dtype=np.float64)
    if tgt.shape[-1] != 3:
        raise ValueError(f"target must end in 3 coordinates, got shape {tgt.shape}")
    if tgt.ndim == 1 or (tgt.ndim == 2 and tgt.shape[0] == v.shape[0] and tgt.shape[0] != v.shape[-2]):
        if rigid:
            raise ValueError("rigid placement needs target vertices, not centroids")
        return centred + tgt.reshape((-1, 1, 3) if tgt.ndim == 2 else (1, 1, 3))
    tgt = np.broadcast_to(tgt, v.shape)
    if rigid:
        R = kabsch_rotation(centred, tgt)
        centred = centred @ np.swapaxes(R, -1, -2)
    return centred + tgt.mean(axis=-2, keepdims=True)


def per_vertex_error(predicted: np.ndarray, truth: np.ndarray, rigid: bool = False) -> np.ndarray:
    """Euclidean distance per vertex ``(T, V)`` after removing translation (and rotation if ``rigid``)."""
    aligned = place(predicted, truth, rigid=rigid)
    return np.linalg.norm(aligned - np.asarray(truth, dtype=np.float64), axis=-1)
