"""Mesh topology and per-mesh geometry: edges, 1-rings, components, cotangent weights, normals.

Everything here is pure: arrays in, arrays out. Vertices are ``(V, 3)`` or batched ``(T, V, 3)``
float arrays, faces ``(F, 3)`` integer arrays. Topology depends on faces only and is computed
once per mesh; geometry (normals, edge lengths) is vectorised over frames.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import igl
import numpy as np
import scipy.sparse as sp
from scipy.sparse import csgraph

#: Cotangent-weight guards of method.md section 1.1.
MIN_WEIGHT = 1e-10
MAX_WEIGHT = 1e5


def undirected_edges(faces: np.ndarray) -> np.ndarray:
    """Unique undirected edges ``(E, 2)`` with ``i < j``, sorted lexicographically."""
    return edge_face_counts(faces)[0]


def edge_face_counts(faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Undirected edges ``(E, 2)`` and how many faces use each ``(E,)``.

    1 marks a boundary edge, more than 2 a non-manifold edge.
    """
    f = np.asarray(faces, dtype=np.int64)
    e = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    e.sort(axis=1)
    n = int(f.max()) + 1 if f.size else 1
    keys, counts = np.unique(e[:, 0] * n + e[:, 1], return_counts=True)  # one int64 key per edge: a 1-D
    return np.stack([keys // n, keys % n], axis=1), counts  # sort, 10x faster than np.unique(axis=0)


def face_areas(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Triangle areas, ``(..., F)`` for vertices ``(..., V, 3)``."""
    v = np.asarray(vertices)
    a, b, c = (v[..., faces[:, k], :] for k in range(3))
    return 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=-1)


def degenerate_faces(vertices: np.ndarray, faces: np.ndarray, rel_tol: float = 1e-12) -> np.ndarray:
    """Boolean ``(F,)``: faces whose area is (numerically) zero in the ``(V, 3)`` mesh.

    A face counts as degenerate when its area is below ``rel_tol`` times the squared
    bounding-box diagonal, or when it repeats a vertex index.
    """
    v = np.asarray(vertices, dtype=np.float64)
    diag = bounding_box_diagonal(v)
    repeated = (faces[:, 0] == faces[:, 1]) | (faces[:, 1] == faces[:, 2]) | (faces[:, 2] == faces[:, 0])
    return repeated | (face_areas(v, faces) <= rel_tol * max(diag, 1e-300) ** 2)


def bounding_box_diagonal(vertices: np.ndarray) -> float:
    """Length of the axis-aligned bounding box diagonal of all points in ``(..., V, 3)``."""
    p = np.asarray(vertices).reshape(-1, 3)
    return float(np.linalg.norm(p.max(axis=0) - p.min(axis=0)))


@dataclass(frozen=True)
class Topology:
    """Connectivity of one triangle mesh, computed once and shared by every frame.

    Attributes:
        faces: ``(F, 3)`` int64.
        n_vertices: V.
    """

    faces: np.ndarray
    n_vertices: int

    @staticmethod
    def from_faces(faces: np.ndarray, n_vertices: int | None = None) -> "Topology":
        f = np.ascontiguousarray(faces, dtype=np.int64)
        n = int(f.max()) + 1 if n_vertices is None else int(n_vertices)
        return Topology(f, n)

    @cached_property
    def _edges_and_counts(self) -> tuple[np.ndarray, np.ndarray]:
        return edge_face_counts(self.faces)

    @cached_property
    def edges(self) -> np.ndarray:
        """Undirected edges ``(E, 2)``, ``i < j``."""
        return self._edges_and_counts[0]

    @cached_property
    def directed_edges(self) -> np.ndarray:
        """Both directions of every edge, ``(2E, 2)`` rows ``(i, j)``, sorted by ``i`` then ``j``."""
        e = self.edges
        d = np.concatenate([e, e[:, ::-1]])
        return d[np.argsort(d[:, 0] * max(self.n_vertices, 1) + d[:, 1])]  # by i, then j (keys are unique)

    @cached_property
    def adjacency(self) -> sp.csr_matrix:
        """Symmetric 0/1 vertex adjacency ``(V, V)`` in CSR (row i lists the 1-ring of i)."""
        d = self.directed_edges
        n = self.n_vertices
        return sp.csr_matrix((np.ones(len(d)), (d[:, 0], d[:, 1])), shape=(n, n))

    @cached_property
    def degrees(self) -> np.ndarray:
        """1-ring sizes ``(V,)``."""
        return np.diff(self.adjacency.indptr)

    def padded_neighbors(self) -> tuple[np.ndarray, np.ndarray]:
        """1-rings as a padded table for gathers.

        Returns:
            index: ``(V, D)`` int64, D the largest degree; padding repeats the vertex itself.
            mask: ``(V, D)`` bool, True where the entry is a real neighbour.
        """
        adj = self.adjacency
        deg = self.degrees
        width = int(deg.max()) if len(deg) else 0
        slot = np.arange(adj.nnz) - np.repeat(adj.indptr[:-1], deg)
        rows = np.repeat(np.arange(self.n_vertices), deg)
        index = np.repeat(np.arange(self.n_vertices)[:, None], width, axis=1)
        mask = np.zeros((self.n_vertices, width), dtype=bool)
        index[rows, slot] = adj.indices
        mask[rows, slot] = True
        return index, mask

    @cached_property
    def component_labels(self) -> np.ndarray:
        """Connected-component label of each vertex ``(V,)``, components numbered by first vertex."""
        _, labels = csgraph.connected_components(self.adjacency, directed=False)
        # Renumber so component 0 holds vertex 0, component 1 the next unseen vertex, ...
        _, first = np.unique(labels, return_index=True)
        rank = np.empty(len(first), dtype=np.int64)
        rank[np.argsort(np.argsort(first))] = np.arange(len(first))
        return rank[labels]

    @property
    def n_components(self) -> int:
        return int(self.component_labels.max()) + 1 if self.n_vertices else 0

    @cached_property
    def component_roots(self) -> np.ndarray:
        """The lowest-numbered vertex of each component ``(C,)``."""
        _, first = np.unique(self.component_labels, return_index=True)
        return first

    @cached_property
    def bfs(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``bfs_trees`` rooted at each component's lowest vertex."""
        return self.bfs_trees(self.component_roots)

    def bfs_trees(self, roots: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Breadth-first trees over the 1-ring graph from ``roots`` ``(C,)``, one vertex per component.

        Returns:
            order: ``(V,)`` vertices in BFS order (component by component).
            parent: ``(V,)`` parent of each vertex in its tree, -1 for roots.
            depth: ``(V,)`` hops from the root.
        """
        order_parts = []
        parent = np.full(self.n_vertices, -1, dtype=np.int64)
        for root in roots:
            order, pred = csgraph.breadth_first_order(self.adjacency, int(root), directed=False)
            order_parts.append(order)
            parent[order[1:]] = pred[order[1:]]
        order = np.concatenate(order_parts) if order_parts else np.zeros(0, dtype=np.int64)
        return order, parent, tree_depths(parent)

    @cached_property
    def bfs_levels(self) -> list[np.ndarray]:
        """Vertices grouped by BFS depth: ``levels[d]`` holds every vertex at depth d (roots at 0)."""
        return depth_levels(self.bfs[2])

    @cached_property
    def ring_mean_operator(self) -> sp.csr_matrix:
        """Sparse ``(V, E)``: the mean over each vertex's incident edges of a per-edge value."""
        e = self.edges
        rows = np.concatenate([e[:, 0], e[:, 1]])
        deg = np.maximum(self.degrees, 1).astype(np.float64)
        return sp.csr_matrix(
            (1.0 / deg[rows], (rows, np.tile(np.arange(len(e)), 2))), shape=(self.n_vertices, len(e))
        )

    @cached_property
    def boundary_edge_count(self) -> int:
        return int((self._edges_and_counts[1] == 1).sum())

    @cached_property
    def nonmanifold_edge_count(self) -> int:
        return int((self._edges_and_counts[1] > 2).sum())

    @cached_property
    def unreferenced_vertices(self) -> np.ndarray:
        """Vertex indices no face uses ``(K,)``."""
        used = np.zeros(self.n_vertices, dtype=bool)
        used[self.faces.ravel()] = True
        return np.flatnonzero(~used)


def cotangent_weights(vertices: np.ndarray, topology: Topology) -> np.ndarray:
    """Guarded cotangent weights, one per undirected edge ``(E,)`` of ``topology.edges``.

    ``w_ij = 0.5 (cot a_ij + cot b_ij)``, one-sided on boundary edges (method.md 1.1); then
    ``w = max(w, 1e-10)``, and NaN or ``> 1e5`` (degenerate triangles) becomes 1.

    Args:
        vertices: ``(V, 3)`` reference mesh.
    """
    v = np.ascontiguousarray(vertices, dtype=np.float64)
    f = topology.faces
    # igl: C[f, k] = 0.5 cot of the angle opposite edge k, edges ordered [1,2], [2,0], [0,1].
    with np.errstate(all="ignore"):
        half_cot = np.asarray(igl.cotmatrix_entries(v, f), dtype=np.float64)
    e = np.concatenate([f[:, [1, 2]], f[:, [2, 0]], f[:, [0, 1]]])
    e.sort(axis=1)
    vals = np.concatenate([half_cot[:, 0], half_cot[:, 1], half_cot[:, 2]])
    edges = topology.edges
    key_all = e[:, 0] * topology.n_vertices + e[:, 1]
    key = edges[:, 0] * topology.n_vertices + edges[:, 1]
    slot = np.searchsorted(key, key_all)
    w = np.zeros(len(edges))
    np.add.at(w, slot, vals)  # NaN propagates, as intended
    with np.errstate(invalid="ignore"):
        bad = ~np.isfinite(w) | (w > MAX_WEIGHT)
        w = np.maximum(w, MIN_WEIGHT)
    w[bad] = 1.0
    return w


def vertex_normals(vertices: np.ndarray, faces: np.ndarray, scatter: sp.csr_matrix | None = None) -> np.ndarray:
    """Area-weighted unit vertex normals, ``(..., V, 3)`` for vertices ``(..., V, 3)``.

    A vertex whose summed face normal vanishes gets the zero vector. ``scatter``: the
    ``face_scatter(faces, V)`` matrix, for callers that compute normals of many frames.
    """
    v = np.asarray(vertices, dtype=np.float64)
    lead = v.shape[:-2]
    n_v = v.shape[-2]
    pv = np.ascontiguousarray(np.moveaxis(v.reshape((-1, n_v, 3)), 1, 0))  # (V, T, 3) vertex-major
    a, b, c = (pv[faces[:, k]] for k in range(3))  # (F, T, 3) each
    u, w = b - a, c - a
    fn = np.empty(u.shape)  # cross product, length = 2 * area
    fn[..., 0] = u[..., 1] * w[..., 2] - u[..., 2] * w[..., 1]
    fn[..., 1] = u[..., 2] * w[..., 0] - u[..., 0] * w[..., 2]
    fn[..., 2] = u[..., 0] * w[..., 1] - u[..., 1] * w[..., 0]
    scatter = face_scatter(faces, n_v) if scatter is None else scatter
    vn = (scatter @ fn.reshape(len(faces), -1)).reshape(pv.shape)
    norm = np.sqrt(np.einsum("vtc,vtc->vt", vn, vn))[..., None]
    vn = np.divide(vn, norm, out=np.zeros_like(vn), where=norm > 0)
    return np.moveaxis(vn, 0, 1).reshape(lead + (n_v, 3))


def face_scatter(faces: np.ndarray, n_vertices: int) -> sp.csr_matrix:
    """Sparse ``(V, F)`` matrix summing each face's value into its three vertices."""
    nf = len(faces)
    rows = np.asarray(faces, dtype=np.int64).T.ravel()
    cols = np.tile(np.arange(nf), 3)
    return sp.csr_matrix((np.ones(3 * nf), (rows, cols)), shape=(n_vertices, nf))


def mean_ring_edge_length(vertices: np.ndarray, topology: Topology) -> np.ndarray:
    """Mean length of the edges around each vertex, ``(..., V)`` for vertices ``(..., V, 3)``."""
    v = np.asarray(vertices, dtype=np.float64)
    e = topology.edges
    length = np.linalg.norm(v[..., e[:, 1], :] - v[..., e[:, 0], :], axis=-1)  # (..., E)
    lead = length.shape[:-1]
    means = topology.ring_mean_operator @ np.moveaxis(length, -1, 0).reshape(len(e), -1)  # (V, prod(lead))
    return np.moveaxis(means.reshape((topology.n_vertices,) + lead), 0, -1)


def topology_hash(faces: np.ndarray, n_vertices: int) -> str:
    """A short stable fingerprint of a connectivity (faces and vertex count), for checkpoints."""
    import hashlib

    h = hashlib.sha256()
    h.update(np.int64(n_vertices).tobytes())
    h.update(np.ascontiguousarray(faces, dtype=np.int64).tobytes())
    return h.hexdigest()[:16]


def depth_levels(depth: np.ndarray) -> list[np.ndarray]:
    """Vertices grouped by tree depth ``(V,)``: ``levels[d]`` holds every vertex at depth d."""
    order = np.argsort(depth, kind="stable")
    bounds = np.searchsorted(depth[order], np.arange(depth.max() + 2))
    return [order[bounds[d]:bounds[d + 1]] for d in range(len(bounds) - 1)]


def tree_depths(parent: np.ndarray) -> np.ndarray:
    """Hops from each vertex to its tree's root ``(V,)`` for ``parent`` ``(V,)`` (-1 at roots), by
    pointer jumping: each pass adds the distance to the current ancestor and jumps to that
    ancestor's, so the loop runs log2 of the deepest path times, vectorised over vertices."""
    has_parent = parent >= 0
    depth = has_parent.astype(np.int64)
    jump = np.where(has_parent, parent, np.arange(len(parent)))  # roots point at themselves
    while True:
        nxt = jump[jump]
        if np.array_equal(nxt, jump):
            return depth
        depth = depth + depth[jump]
        jump = nxt
