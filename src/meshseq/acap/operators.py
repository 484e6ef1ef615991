"""The sparse operators of the ACAP solves and their factored matrices (method.md 2.2, 2.5), shared
by the encoding (``meshseq.acap.features``, exact mode) and the reconstruction
(``meshseq.acap.reconstruct``).

``L`` is the cotangent Laplacian of the reference mesh, ``B`` ``(V, 3V)`` the sparse map of the
gradients to the right-hand side ``b`` (``L p = b``). The exact encoding corrects least-squares
gradients T0 by the minimum-norm change ``dT = B^T (B B^T)^-1 (L p - B T0)`` so that the solve
returns the input exactly.
"""

from __future__ import annotations

import threading

import numpy as np
import scipy.sparse as sp

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
