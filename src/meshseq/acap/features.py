"""The 9-dim ACAP feature per vertex, and the way back to deformation gradients (method.md 1.6, 2.1).

    q = (logR01, logR02, logR12, S00, S01, S02, S11, S12, S22),
    logR01 = -Theta w_z, logR02 = Theta w_y, logR12 = -Theta w_x,

with ``T = R S`` the polar decomposition of the deformation gradient and S stored in full (the
identity is (1, 0, 0, 1, 0, 1)).
"""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from meshseq.acap.gradients import GradientOperator, polar_soa
from meshseq.acap.parts import placement_channels
from meshseq.acap.rotations import CONSISTENCY_MODES, DEFAULT_CONSISTENCY, axis_angle, consistent_logs
from meshseq.mesh import Topology

FEATURE_DIM = 9
#: (row, col) of S for feature channels 3..8.
S_ENTRIES = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))
IDENTITY_FEATURE = np.array([0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 1.0, 0.0, 1.0])


def extract_gradients(
    vertices: np.ndarray, faces: np.ndarray, reference: np.ndarray | None = None, normal_row: bool = True
) -> np.ndarray:
    """Deformation gradients ``(T, V, 3, 3)`` of ``vertices (T, V, 3)`` against ``reference (V, 3)``
    (default: the first frame)."""
    v = np.asarray(vertices, dtype=np.float64)
    ref = v[0] if reference is None else np.asarray(reference, dtype=np.float64)
    op = GradientOperator(ref, Topology.from_faces(faces, v.shape[1]), normal_row=normal_row)
    return op(v)


#: Frames processed together: keeps the working arrays in cache (measured fastest on crane).
FRAME_CHUNK = 8


def frame_threads() -> int:
    """Threads for frame-parallel work: ``MESHSEQ_THREADS``, else ``OMP_NUM_THREADS``, else the
    CPUs this process may use."""
    for name in ("MESHSEQ_THREADS", "OMP_NUM_THREADS"):
        value = os.environ.get(name, "").strip()
        if value.isdigit() and int(value) > 0:
            return int(value)
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)


def map_frame_chunks(work, n_frames: int, threads: int | None = None) -> None:
    """Call ``work(frames)`` for consecutive ``FRAME_CHUNK``-frame slices covering ``n_frames``.

    With ``threads > 1`` the chunks run on a thread pool: the per-chunk work is numpy/scipy on
    arrays large enough that the GIL is released most of the time (1.7x on 2 cores for crane's
    gradients + polar + axis-angle). ``work`` must write only to its own frames.
    """
    chunks = [slice(s, s + FRAME_CHUNK) for s in range(0, n_frames, FRAME_CHUNK)]
    threads = frame_threads() if threads is None else threads
    if threads <= 1 or len(chunks) < 2:
        for frames in chunks:
            work(frames)
        return
    with ThreadPoolExecutor(min(threads, len(chunks))) as pool:
        for _ in pool.map(work, chunks):  # re-raises the first error
            pass


def gradients_to_features(
    gradients: np.ndarray, topology: Topology, consistency: str = DEFAULT_CONSISTENCY, threads: int | None = None
) -> np.ndarray:
    """ACAP features ``(T, V, 9)`` of deformation gradients ``(T, V, 3, 3)``.

    Polar decomposition, axis-angle, rotation consistency (one of ``CONSISTENCY_MODES``), packing.
    """
    g = np.asarray(gradients, dtype=np.float64)
    return _pack_features(lambda frames: g[frames], len(g), topology, consistency, threads)


def _pack_features(gradients_of, n_frames: int, topology: Topology, consistency: str,
                   threads: int | None = None) -> np.ndarray:
    """Features ``(T, V, 9)`` from ``gradients_of(slice) -> (t, V, 3, 3)``, a chunk of frames at a
    time (``map_frame_chunks``); the rotation consistency then runs over all frames."""
    n = topology.n_vertices
    axis = np.empty((n_frames, n, 3))
    theta = np.empty((n_frames, n))
    feats = np.empty((n_frames, n, FEATURE_DIM))

    def chunk(frames: slice) -> None:
        g = gradients_of(frames)  # (t, V, 3, 3)
        R9, S6 = polar_soa(g.reshape(-1, 9).T)  # (9, t V), (6, t V): S_ENTRIES order
        axis[frames], theta[frames] = axis_angle(R9.T.reshape(g.shape))
        feats[frames, :, 3:] = S6.T.reshape(g.shape[:2] + (6,))

    map_frame_chunks(chunk, n_frames, threads)
    logs = consistent_logs(axis, theta, topology, consistency)  # (T, V, 3) = Theta w
    feats[..., 0] = -logs[..., 2]
    feats[..., 1] = logs[..., 1]
    feats[..., 2] = -logs[..., 0]
    return feats


def extract(
    vertices: np.ndarray,
    faces: np.ndarray,
    reference: np.ndarray | None = None,
    consistency: str = DEFAULT_CONSISTENCY,
    normal_row: bool = True,
    exact: bool = False,
    threads: int | None = None,
    placement: bool | None = None,
    placement_mode: str = "centroid",
) -> np.ndarray:
    """ACAP features ``(T, V, 9)`` of a sequence ``vertices (T, V, 3)`` sharing ``faces (F, 3)``.

    Args:
        reference: ``(V, 3)`` rest shape; default the first frame (whose features are then the
            identity feature).
        consistency: ``temporal-mst`` (default: rotation logs continuous in time, with the fewest
            spurious 2 pi jumps possible, the first frame made consistent along its smallest
            rotation differences; see :mod:`meshseq.acap.rotations`), ``temporal`` (the same from
            the first frame's breadth-first walk), ``spatial`` (the reference code's per-frame BFS)
            or ``greedy`` (each frame nearest the previous; the earlier temporal pass, kept for
            comparison).
        normal_row: include the normal term in the gradient fit (method.md 1.2).
        exact: correct the least-squares gradients by the minimum-norm change that makes the
            reconstruction return the input (method.md 2.5), a chunk of frames at a time.
        threads: threads over frame chunks (default ``frame_threads()``); the result does not
            depend on it.
        placement: append the three placement channels of :mod:`meshseq.acap.parts`, making the
            features ``(T, V, 12)``; default: when the mesh has several connected components.
        placement_mode: what they measure each part from (``acap.parts.PLACEMENT_MODES``).
    """
    v = np.asarray(vertices, dtype=np.float64)
    if consistency not in CONSISTENCY_MODES:
        raise ValueError(f"unknown consistency mode {consistency!r}; expected one of {CONSISTENCY_MODES}")
    topo = Topology.from_faces(faces, v.shape[1])
    ref = v[0] if reference is None else np.asarray(reference, dtype=np.float64)
    op = GradientOperator(ref, topo, normal_row=normal_row)
    if exact:
        from meshseq.acap.operators import ExactEncoder

        encoder = ExactEncoder(ref, topo, op.edge_weights)
        feats = _pack_features(lambda frames: encoder(op(v[frames]), v[frames]), len(v), topo, consistency, threads)
    else:
        feats = _pack_features(lambda frames: op(v[frames]), len(v), topo, consistency, threads)
    if topo.n_components > 1 if placement is None else placement:
        feats = np.concatenate([feats, placement_channels(v, topo, ref, placement_mode)], axis=-1)
    return feats


#: Vertex-frames per block of the numpy ``features_to_gradients``: its ~60 elementwise temporaries
#: then stay in cache (3x faster than whole arrays on 256 crane frames; results bit for bit equal).
GRADIENT_BLOCK = 4096


def features_to_gradients(features):
    """Deformation gradients ``T = R S`` ``(..., 3, 3)`` from features ``(..., 9)`` (method.md 2.1).

    ``K = [[0, a, b], [-a, 0, c], [-b, -c, 0]]``, ``R = I + sin(t)/t K + (1 - cos t)/t^2 K^2``
    (``R = I`` at ``t = 0``), ``S`` the symmetric matrix of channels 3..8. Written out entry by
    entry (several times faster than batched 3x3 products). Takes numpy arrays or torch tensors
    (differentiable, finite gradients at ``t = 0``) and returns the same kind.
    """
    if hasattr(features, "dim") and not isinstance(features, np.ndarray):
        # torch: one unbind, not nine slices (under autograd each slice's backward fills a zero tensor
        # of the input's size), of a channel-first contiguous copy, so that the ~60 elementwise
        # operations run on contiguous planes (on strided channel views each took 5-10x longer)
        import torch

        return _gradients_of_channels(features.movedim(-1, 0).contiguous().unbind(0), torch)
    q = np.asarray(features, dtype=np.float64)
    flat = q.reshape(-1, q.shape[-1])
    out = np.empty((flat.shape[0], 3, 3))
    for s in range(0, flat.shape[0], GRADIENT_BLOCK):
        out[s:s + GRADIENT_BLOCK] = _gradients_of_channels(tuple(flat[s:s + GRADIENT_BLOCK].T), np)
    return out.reshape(q.shape[:-1] + (3, 3))


def _gradients_of_channels(cols, xp):
    """``features_to_gradients`` of the nine channel planes ``cols`` (each ``(...)``), ``xp`` numpy
    or torch."""
    a, b, c = cols[:3]
    aa, bb, cc = a * a, b * b, c * c
    t2 = aa + bb + cc
    small = t2 < 1e-12
    t = xp.sqrt(xp.where(small, xp.ones_like(t2), t2))
    s1 = xp.where(small, 1.0 - t2 / 6.0, xp.sin(t) / t)
    s2 = xp.where(small, 0.5 - t2 / 24.0, (1.0 - xp.cos(t)) / (t * t))
    # R = I + s1 K + s2 K^2, K^2 = [[-aa-bb, -bc, ac], [-bc, -aa-cc, -ab], [ac, -ab, -bb-cc]]
    bc, ac, ab = s2 * b * c, s2 * a * c, s2 * a * b
    r00, r11, r22 = 1.0 - s2 * (aa + bb), 1.0 - s2 * (aa + cc), 1.0 - s2 * (bb + cc)
    sa, sb, sc = s1 * a, s1 * b, s1 * c
    R = ((r00, sa - bc, sb + ac), (-sa - bc, r11, sc - ab), (-sb + ac, -sc - ab, r22))
    s00, s01, s02, s11, s12, s22 = cols[3:9]
    S = ((s00, s01, s02), (s01, s11, s12), (s02, s12, s22))
    T = [R[i][0] * S[0][j] + R[i][1] * S[1][j] + R[i][2] * S[2][j] for i in range(3) for j in range(3)]
    return xp.stack(T, -1).reshape(*T[0].shape, 3, 3)  # row-major: T[i][j] at [..., i, j]
