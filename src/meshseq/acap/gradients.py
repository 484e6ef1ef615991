"""Per-vertex deformation gradients against a reference mesh, and their polar decomposition.

method.md 1.2: for vertex i with 1-ring N(i), reference edges e_ij = q_j - q_i and deformed edges
e'_ij = p_j - p_i,

    T_i = argmin_D  sum_j w_ij ||e'_ij - D e_ij||^2 + ||0.3 l'_i n'_i - D 0.3 l_i n_i||^2
        = (sum_j w_ij e'_ij e_ij^T + 0.09 l'_i l_i n'_i n_i^T) A_i^-1,
    A_i = sum_j w_ij e_ij e_ij^T + 0.09 l_i^2 n_i n_i^T,

with cotangent weights w of the reference mesh, vertex normals n and mean 1-ring edge lengths l.
Everything reference-only (weights, A_i^-1, sparse edge operators) is computed once.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from meshseq.mesh import Topology, cotangent_weights, face_scatter, mean_ring_edge_length, vertex_normals

#: Scale of the normal row relative to the mean edge length (reference code: 0.3).
NORMAL_ROW_SCALE = 0.3


class GradientOperator:
    """Everything needed to turn deformed vertices into deformation gradients, for one reference.

    Args:
        reference: ``(V, 3)`` reference vertices.
        topology: connectivity shared by every frame.
        normal_row: include the normal term (method.md 1.2; on by default, as the reference code).
    """

    def __init__(self, reference: np.ndarray, topology: Topology, normal_row: bool = True):
        q = np.ascontiguousarray(reference, dtype=np.float64)
        self.topology = topology
        self.reference = q
        self.normal_row = normal_row
        n = topology.n_vertices
        self.edge_weights = cotangent_weights(q, topology)  # (E,)
        d = topology.directed_edges  # (2E, 2) rows (i, j)
        self.directed = d
        # weight of each directed edge: look up its undirected edge
        lo, hi = np.minimum(d[:, 0], d[:, 1]), np.maximum(d[:, 0], d[:, 1])
        ekey = topology.edges[:, 0] * n + topology.edges[:, 1]
        self.directed_weights = self.edge_weights[np.searchsorted(ekey, lo * n + hi)]  # (2E,)
        e_ref = q[d[:, 1]] - q[d[:, 0]]  # (2E, 3)
        we = self.directed_weights[:, None] * e_ref  # (2E, 3)
        # Stacked sparse operator: row (b*V + i) sums w_ij e_ij[b] * x_j over j in N(i).
        rows = np.concatenate([b * n + d[:, 0] for b in range(3)])
        self._neighbor_sum = sp.csr_matrix(
            (np.concatenate([we[:, b] for b in range(3)]), (rows, np.tile(d[:, 1], 3))),
            shape=(3 * n, n),
        )
        self._ring_sum = np.zeros((n, 3))  # C_i = sum_j w_ij e_ij
        np.add.at(self._ring_sum, d[:, 0], we)
        A = np.einsum("ea,eb->eab", we, e_ref)
        A_sum = np.zeros((n, 3, 3))
        np.add.at(A_sum, d[:, 0], A)
        if normal_row:
            self._face_scatter = face_scatter(topology.faces, n)  # (V, F), reused every frame
            self._ref_normal = vertex_normals(q, topology.faces) * (
                NORMAL_ROW_SCALE * mean_ring_edge_length(q, topology)
            )[:, None]  # (V, 3), 0.3 l n
            A_sum += np.einsum("va,vb->vab", self._ref_normal, self._ref_normal)
        self.A_inv = _robust_inverse(A_sum)  # (V, 3, 3)

    def __call__(self, vertices: np.ndarray) -> np.ndarray:
        """Deformation gradients ``(T, V, 3, 3)`` of vertices ``(T, V, 3)`` (or ``(V, 3)`` -> ``(V, 3, 3)``)."""
        p = np.asarray(vertices, dtype=np.float64)
        single = p.ndim == 2
        if single:
            p = p[None]
        t, n = p.shape[0], p.shape[1]
        pv = np.ascontiguousarray(p.transpose(1, 0, 2))  # (V, T, 3) vertex-major
        # B[t,i,a,b] = sum_j w_ij e_ij[b] p_j[a] - p_i[a] C_i[b] (+ normal term)
        nb = (self._neighbor_sum @ pv.reshape(n, 3 * t)).reshape(3, n, t, 3)  # [b, i, t, a]
        B = nb.transpose(2, 1, 3, 0) - p[..., :, None] * self._ring_sum[None, :, None, :]
        if self.normal_row:
            nrm = vertex_normals(p, self.topology.faces, self._face_scatter) * (
                NORMAL_ROW_SCALE * mean_ring_edge_length(p, self.topology)
            )[..., None]  # (T, V, 3)
            B += nrm[..., :, None] * self._ref_normal[None, :, None, :]
        grads = np.matmul(B, self.A_inv[None])
        return grads[0] if single else grads


def _robust_inverse(A: np.ndarray) -> np.ndarray:
    """Inverse of each ``(N, 3, 3)`` matrix; pseudo-inverse where it is (near) singular."""
    det = np.linalg.det(A)
    scale = np.einsum("nii->n", A) / 3.0
    ok = np.abs(det) > 1e-12 * np.maximum(np.abs(scale), 1e-300) ** 3
    out = np.empty_like(A)
    out[ok] = np.linalg.inv(A[ok])
    if (~ok).any():
        out[~ok] = np.linalg.pinv(A[~ok])
    return out


def polar_decomposition(T: np.ndarray, tol: float = 1e-13, max_iter: int = 30) -> tuple[np.ndarray, np.ndarray]:
    """Polar decomposition ``T = R S`` of many 3x3 matrices, R a proper rotation, S symmetric.

    Equal to the SVD recipe of method.md 1.3 (``R = U V^T``; when ``det < 0`` the column of U of the
    smallest singular value is negated, and that singular value with it, so ``S = R^T T`` has one
    negative eigenvalue). Matrices with positive determinant (nearly all) use the scaled Newton
    iteration ``X <- (g X + X^-T / g) / 2``, ``g = |det X|^(-1/3)``, which converges quadratically;
    it runs on cache-sized chunks in structure-of-arrays form (ten times faster than batched SVD).
    The rest, and any that fail to converge, use batched SVD.

    Args:
        T: ``(..., 3, 3)``.
    Returns:
        R, S: ``(..., 3, 3)`` each.
    """
    T = np.asarray(T, dtype=np.float64)
    R9, S6 = polar_soa(T.reshape(-1, 9).T, tol, max_iter)
    R = R9.T.reshape(T.shape)
    S = S6[[0, 1, 2, 1, 3, 4, 2, 4, 5]].T.reshape(T.shape)
    return R, S


def polar_soa(M9: np.ndarray, tol: float = 1e-13, max_iter: int = 30) -> tuple[np.ndarray, np.ndarray]:
    """:func:`polar_decomposition` in structure-of-arrays form: ``M9 (9, N)`` row-major 3x3
    matrices -> rotations ``R9 (9, N)`` and the six entries ``S00, S01, S02, S11, S12, S22`` of the
    symmetric factor ``(6, N)``."""
    M9 = np.ascontiguousarray(M9, dtype=np.float64)
    n = M9.shape[1]
    R9 = np.empty_like(M9)
    todo = [np.zeros(0, dtype=np.int64)]
    for s in range(0, n, _POLAR_CHUNK):
        block = M9[:, s:s + _POLAR_CHUNK]
        Rb, ok = _newton_polar(block, tol, max_iter)
        R9[:, s:s + _POLAR_CHUNK] = Rb
        todo.append(s + np.flatnonzero(~ok))
    rest = np.concatenate(todo)
    if len(rest):
        R9[:, rest] = _svd_rotation(M9[:, rest].T.reshape(-1, 3, 3)).reshape(-1, 9).T
    # S = R^T M, symmetrised: S_ab = sum_k R_ka M_kb
    def entry(a: int, b: int) -> np.ndarray:
        return R9[a] * M9[b] + R9[3 + a] * M9[3 + b] + R9[6 + a] * M9[6 + b]

    S6 = np.empty((6, n))
    for k, (a, b) in enumerate(((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))):
        S6[k] = entry(a, b) if a == b else 0.5 * (entry(a, b) + entry(b, a))
    return R9, S6


_POLAR_CHUNK = 8192


def _newton_polar(M9: np.ndarray, tol: float, max_iter: int) -> tuple[np.ndarray, np.ndarray]:
    """Scaled Newton polar iteration on ``(9, N)`` row-major 3x3 matrices (structure of arrays).

    Returns the rotations ``(9, N)`` and which are valid ``(N,)``: converged, with a determinant
    that was positive and not tiny (the others need the SVD recipe).
    """
    X = list(M9)
    a, b, c, d, e, f, g, h, i = X
    det0 = a * (e * i - f * h) + b * (f * g - d * i) + c * (d * h - e * g)
    fro2 = sum(x * x for x in X)
    proper = det0 > 1e-6 * np.maximum(fro2, 1e-300) ** 1.5
    X = [np.where(proper, x, eye) for x, eye in zip(X, (1, 0, 0, 0, 1, 0, 0, 0, 1))]
    change = np.zeros(M9.shape[1])
    for it in range(max_iter):
        a, b, c, d, e, f, g, h, i = X
        cof = [e * i - f * h, f * g - d * i, d * h - e * g,
               c * h - b * i, a * i - c * g, b * g - a * h,
               b * f - c * e, c * d - a * f, a * e - b * d]  # det(X) X^-T, row-major
        det = a * cof[0] + b * cof[1] + c * cof[2]
        half_gam = 0.5 / np.cbrt(np.abs(det))  # gamma / 2
        half_inv = 0.25 / (half_gam * det)  # 1 / (2 gamma det)
        new = [half_gam * x + half_inv * cx for x, cx in zip(X, cof)]
        if it < 2 < max_iter:  # the first steps never converge to tol: skip the check
            X = new
            continue
        change = np.abs(new[0] - X[0])
        for x, nx in zip(X[1:], new[1:]):
            np.maximum(change, np.abs(nx - x), out=change)
        X = new
        if change.max() <= tol:
            break
    return np.stack(X), proper & (change <= tol)


def _svd_rotation(M: np.ndarray) -> np.ndarray:
    """Rotation factor by SVD with the reflection fix of method.md 1.3, ``(N, 3, 3)``."""
    U, _, Vt = np.linalg.svd(M)
    R = U @ Vt
    flip = np.linalg.det(R) < 0
    if flip.any():
        U = U.copy()
        U[flip, :, 2] *= -1.0  # singular values come sorted: column 2 is the smallest
        R[flip] = U[flip] @ Vt[flip]
    return R
