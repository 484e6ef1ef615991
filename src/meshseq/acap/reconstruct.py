"""From deformation gradients (or ACAP features) back to vertices, by one factored sparse solve.

method.md 2.2: minimise ``sum_i sum_{j in N(i)} w_ij ||(p_i - p_j) - T_i (q_i - q_j)||^2``; its
normal equations are

    L p = b,   b_i = sum_j (w_ij / 2) (T_i + T_j) (q_i - q_j),

with the cotangent Laplacian L of the reference mesh. ``b`` is linear in the gradients: per row a
of the gradients, ``b[:, a] = B vec(T[:, a, :])`` with a sparse ``B`` of shape ``(V, 3V)``. L has one
constant null space per connected component: one vertex of each is pinned, the reduced matrix is
factored once per reference mesh, and every frame (every right-hand side) is solved against it.
Each component is then moved to its centroid offset (method.md 2.6).

The exact encoding (method.md 2.5) corrects least-squares gradients T0 by the minimum-norm change
``dT = B^T (B B^T)^-1 (L p - B T0)`` so that the solve returns the input exactly.
"""

from __future__ import annotations

import threading

import numpy as np
import scipy.sparse as sp

from meshseq.acap.features import FRAME_CHUNK, component_centroids, component_offsets, features_to_gradients
from meshseq.align import place
from meshseq.mesh import Topology, cotangent_weights


class FactoredMatrix:
    """A sparse symmetric positive definite matrix, factored once, solving many right-hand sides.

    Uses CHOLMOD through cholespy; falls back to SciPy's sparse LU where cholespy is unavailable.
    """

    def __init__(self, matrix: sp.spmatrix):
        coo = sp.coo_matrix(matrix)
        self._lock = threading.Lock()
        self.n = coo.shape[0]
        self.matrix = coo.tocsr()
        try:
            import cholespy

            self._chol = cholespy.CholeskySolverD(
                self.n,
                np.ascontiguousarray(coo.row, dtype=np.int32),
                np.ascontiguousarray(coo.col, dtype=np.int32),
                np.ascontiguousarray(coo.data, dtype=np.float64),
                cholespy.MatrixType.COO,
            )
            self.backend = "cholmod"
        except ImportError:  # pragma: no cover - cholespy is a dependency; kept as a fallback
            from scipy.sparse.linalg import splu

            self._lu = splu(self.matrix.tocsc())
            self.backend = "splu"

    def solve(self, b: np.ndarray) -> np.ndarray:
        """Solve for ``b`` of shape ``(n,)`` or ``(n, k)``; returns the same shape. One solve at a
        time per factor (CHOLMOD's workspace is shared), so threads may call it."""
        rhs = np.ascontiguousarray(b, dtype=np.float64)
        with self._lock:
            if self.backend == "splu":
                return self._lu.solve(rhs)
            x = np.empty_like(rhs)
            self._chol.solve(rhs, x)
        return x


class Reconstructor:
    """Features or gradients -> vertices for one reference mesh (factored once, reused for all frames).

    Args:
        reference: ``(V, 3)`` reference vertices (the rest shape the features were taken against).
        faces: ``(F, 3)`` triangles.
    """

    def __init__(self, reference: np.ndarray, faces: np.ndarray):
        q = np.ascontiguousarray(reference, dtype=np.float64)
        topo = Topology.from_faces(faces, q.shape[0])
        self.topology = topo
        self.reference = q
        n = topo.n_vertices
        e = topo.edges
        w = cotangent_weights(q, topo)
        self.edge_weights = w
        self.laplacian = _laplacian(e, w, n)
        self.pinned = topo.component_roots
        self.free = _free_vertices(topo)
        self._factor = FactoredMatrix(self.laplacian[self.free][:, self.free])
        self.rhs_operator = _rhs_operator(q, e, w, n)  # (V, 3V)
        self.reference_offsets = component_offsets(q[None], topo)[0]  # (C, 3)

    # -- gradients <-> right-hand side -------------------------------------------------------
    def rhs(self, gradients: np.ndarray) -> np.ndarray:
        """Right-hand sides ``b`` ``(T, V, 3)`` of gradients ``(T, V, 3, 3)``."""
        g = np.asarray(gradients, dtype=np.float64)
        t, n = g.shape[0], g.shape[1]
        tv = np.ascontiguousarray(g.transpose(1, 3, 0, 2)).reshape(3 * n, 3 * t)  # [j*3+c, t*3+a]
        return (self.rhs_operator @ tv).reshape(n, t, 3).transpose(1, 0, 2)

    def solve_gradients(
        self,
        gradients: np.ndarray,
        offsets: np.ndarray | None = None,
        target: np.ndarray | None = None,
        rigid: bool = False,
    ) -> np.ndarray:
        """Vertices ``(T, V, 3)`` from deformation gradients ``(T, V, 3, 3)``.

        Args:
            offsets: ``(T, C, 3)`` or ``(C, 3)`` centroid of each component relative to component
                0 (``acap.features.component_offsets``); default: as in the reference. Only used
                when the mesh has several components.
            target: where to put the result: ``(T, V, 3)``/``(V, 3)`` vertices whose centroid (and,
                with ``rigid``, best-fit rotation) it takes, or ``(T, 3)``/``(3,)`` centroids.
                Default: centroid at the origin.
        """
        g = np.asarray(gradients, dtype=np.float64)
        return self._solve_rhs(lambda frames: self.rhs(g[frames]), len(g), offsets, target, rigid)

    def _solve_rhs(self, rhs_of, n_frames: int, offsets, target, rigid) -> np.ndarray:
        """Solve for right-hand sides ``rhs_of(slice) -> (t, V, 3)``, built a chunk of frames at a time."""
        n = self.topology.n_vertices
        b = np.empty((n, n_frames, 3))  # vertex-major: one multi-column solve for all frames
        for start in range(0, n_frames, FRAME_CHUNK):
            frames = slice(start, start + FRAME_CHUNK)
            b[:, frames] = rhs_of(frames).transpose(1, 0, 2)
        bv = b.reshape(n, 3 * n_frames)
        x = np.zeros((n, 3 * n_frames))
        x[self.free] = self._factor.solve(bv[self.free])
        verts = x.reshape(n, n_frames, 3).transpose(1, 0, 2)
        verts = self._place_components(verts, offsets)
        return place(verts, target, rigid=rigid)

    def solve(
        self,
        features: np.ndarray,
        offsets: np.ndarray | None = None,
        target: np.ndarray | None = None,
        rigid: bool = False,
    ) -> np.ndarray:
        """Vertices ``(T, V, 3)`` from ACAP features ``(T, V, 9)`` (unscaled); see ``solve_gradients``."""
        f = np.asarray(features, dtype=np.float64)
        single = f.ndim == 2
        f = f[None] if single else f
        out = self._solve_rhs(
            lambda frames: self.rhs(features_to_gradients(f[frames])), len(f), offsets, target, rigid
        )
        return out[0] if single else out

    def _place_components(self, verts: np.ndarray, offsets: np.ndarray | None) -> np.ndarray:
        """Move every component so its centroid sits at its offset from component 0's centroid."""
        topo = self.topology
        if topo.n_components == 1:
            return verts
        off = self.reference_offsets if offsets is None else np.asarray(offsets, dtype=np.float64)
        off = np.broadcast_to(off, (verts.shape[0],) + off.shape[-2:])
        cents = component_centroids(verts, topo)  # (T, C, 3)
        shift = off - (cents - cents[:, :1])  # (T, C, 3)
        return verts + shift[:, topo.component_labels]

    # -- exact encoding ----------------------------------------------------------------------


class ExactEncoder:
    """The exact encoding of method.md 2.5 for one reference mesh: least-squares gradients made
    to reconstruct their frame exactly by the minimum-norm change

        dT = B^T (B B^T)^-1 (L p - B T0)   (per gradient row),

    with ``B B^T`` factored once (one vertex per component pinned: its null space is the
    constants). Only ``L`` and ``B`` are needed, not the Laplacian's factor. Safe to call from
    several threads (the factor's solve takes a lock).

    Args:
        reference: ``(V, 3)``; topology: its connectivity; weights: ``(E,)`` cotangent weights of
            ``topology.edges`` (computed when not given).
    """

    def __init__(self, reference: np.ndarray, topology: Topology, weights: np.ndarray | None = None):
        q = np.ascontiguousarray(reference, dtype=np.float64)
        n = topology.n_vertices
        w = cotangent_weights(q, topology) if weights is None else np.asarray(weights, dtype=np.float64)
        self.laplacian = _laplacian(topology.edges, w, n)
        self.rhs_operator = _rhs_operator(q, topology.edges, w, n)  # (V, 3V)
        self.free = _free_vertices(topology)
        bbt = (self.rhs_operator @ self.rhs_operator.T).tocsr()
        self._factor = FactoredMatrix(bbt[self.free][:, self.free])

    def __call__(self, gradients: np.ndarray, vertices: np.ndarray) -> np.ndarray:
        """Corrected ``gradients (T, V, 3, 3)`` of ``vertices (T, V, 3)``: solving returns the vertices."""
        g = np.asarray(gradients, dtype=np.float64)
        p = np.asarray(vertices, dtype=np.float64)
        t, n = g.shape[0], g.shape[1]
        pv = np.ascontiguousarray(p.transpose(1, 0, 2)).reshape(n, 3 * t)
        tv = np.ascontiguousarray(g.transpose(1, 3, 0, 2)).reshape(3 * n, 3 * t)
        residual = self.laplacian @ pv - self.rhs_operator @ tv  # (V, 3T)
        y = np.zeros_like(residual)
        y[self.free] = self._factor.solve(residual[self.free])
        dt = (self.rhs_operator.T @ y).reshape(n, 3, t, 3).transpose(2, 0, 3, 1)  # (T, V, a, c)
        return g + dt


def _free_vertices(topology: Topology) -> np.ndarray:
    """Indices of every vertex but one pinned per connected component (the solves' unknowns)."""
    free = np.ones(topology.n_vertices, dtype=bool)
    free[topology.component_roots] = False
    return np.flatnonzero(free)


def _laplacian(edges: np.ndarray, w: np.ndarray, n: int) -> sp.csr_matrix:
    """Cotangent Laplacian ``(V, V)``: ``L_ii = sum_j w_ij``, ``L_ij = -w_ij``."""
    rows = np.concatenate([edges[:, 0], edges[:, 1], edges[:, 0], edges[:, 1]])
    cols = np.concatenate([edges[:, 1], edges[:, 0], edges[:, 0], edges[:, 1]])
    return sp.csr_matrix((np.concatenate([-w, -w, w, w]), (rows, cols)), shape=(n, n))


def _rhs_operator(q: np.ndarray, edges: np.ndarray, w: np.ndarray, n: int) -> sp.csr_matrix:
    """Sparse ``B`` ``(V, 3V)`` with ``b_i[a] = sum_{j,c} B[i, 3j+c] T_j[a, c]`` (method.md 2.2).

    ``b_i = 1/2 T_i D_i + 1/2 sum_j w_ij T_j (q_i - q_j)``, ``D_i = sum_j w_ij (q_i - q_j)``.
    """
    i = np.concatenate([edges[:, 0], edges[:, 1]])
    j = np.concatenate([edges[:, 1], edges[:, 0]])
    ww = np.concatenate([w, w])
    d_ij = q[i] - q[j]  # (2E, 3): q_i - q_j
    wd = 0.5 * ww[:, None] * d_ij
    D = np.zeros((n, 3))
    np.add.at(D, i, wd)  # 1/2 D_i, set-up only
    rows = np.concatenate([np.repeat(np.arange(n), 3), np.repeat(i, 3)])
    cols = np.concatenate([np.arange(3 * n), (3 * j[:, None] + np.arange(3)).ravel()])
    vals = np.concatenate([D.ravel(), wd.ravel()])
    return sp.csr_matrix((vals, (rows, cols)), shape=(n, 3 * n))
