"""From deformation gradients (or ACAP features) back to vertices, by one factored sparse solve.

method.md 2.2: minimise ``sum_i sum_{j in N(i)} w_ij ||(p_i - p_j) - T_i (q_i - q_j)||^2``; its
normal equations are

    L p = b,   b_i = sum_j (w_ij / 2) (T_i + T_j) (q_i - q_j),

with the cotangent Laplacian L of the reference mesh. ``b`` is linear in the gradients: per row a
of the gradients, ``b[:, a] = B vec(T[:, a, :])`` with a sparse ``B`` of shape ``(V, 3V)``. L has one
constant null space per connected component: one vertex of each is pinned, the reduced matrix is
factored once per reference mesh, and every frame (every right-hand side) is solved against it.
Each component is then moved to its centroid offset: given, from the features' placement channels
(``meshseq.acap.parts``), or as in the reference.

The exact encoding (method.md 2.5) corrects least-squares gradients T0 by the minimum-norm change
``dT = B^T (B B^T)^-1 (L p - B T0)`` so that the solve returns the input exactly.
"""

from __future__ import annotations

import numpy as np

from meshseq.acap.features import features_to_gradients, map_frame_chunks
from meshseq.acap.parts import (PLACEMENT_CHANNELS, PLACEMENT_MODES, anchored_shifts, component_centroids,
                                component_offsets, offsets_from_channels, part_anchors, part_gaps)
from meshseq.acap.operators import ExactEncoder, FactoredMatrix, _free_vertices, _laplacian, _rhs_operator
from meshseq.align import place
from meshseq.mesh import Topology, cotangent_weights

__all__ = ["ExactEncoder", "FactoredMatrix", "Reconstructor"]  # the first two: meshseq.acap.operators


class Reconstructor:
    """Features or gradients -> vertices for one reference mesh (factored once, reused for all frames).

    Args:
        reference: ``(V, 3)`` reference vertices (the rest shape the features were taken against).
        faces: ``(F, 3)`` triangles.
        placement: what the placement channels of 12-channel features measure each part from
            (``acap.parts.PLACEMENT_MODES``).
    """

    def __init__(self, reference: np.ndarray, faces: np.ndarray, placement: str = "centroid"):
        if placement not in PLACEMENT_MODES:
            raise ValueError(f"unknown placement mode {placement!r}; expected one of {PLACEMENT_MODES}")
        self.placement = placement
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
        # ``anchor`` placement: each part's anchor vertex (C,) and its gap from it at rest (C, 3)
        self.anchors = part_anchors(q, topo)
        self.anchor_gaps = part_gaps(q[None], topo, self.anchors)[0]

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

    def _solve_rhs(self, rhs_of, n_frames: int, offsets, target, rigid, anchored=None) -> np.ndarray:
        """Solve for right-hand sides ``rhs_of(slice) -> (t, V, 3)``, built a chunk of frames at a time;
        ``anchored``: ``anchor`` placement channels ``(T, V, 3)`` that place the parts instead of ``offsets``."""
        n = self.topology.n_vertices
        b = np.empty((n, n_frames, 3))  # vertex-major: one multi-column solve for all frames

        def build(frames: slice) -> None:  # each chunk writes its own frames of b
            b[:, frames] = rhs_of(frames).transpose(1, 0, 2)

        map_frame_chunks(build, n_frames)  # chunks on frame_threads() threads
        bv = b.reshape(n, 3 * n_frames)
        x = np.zeros((n, 3 * n_frames))
        x[self.free] = self._factor.solve(bv[self.free])
        verts = x.reshape(n, n_frames, 3).transpose(1, 0, 2)
        if anchored is not None:
            shifts = anchored_shifts(verts, anchored, self.topology, self.anchors, self.anchor_gaps)
            verts = verts + shifts[:, self.topology.component_labels]
        else:
            verts = self._place_components(verts, offsets)
        return place(verts, target, rigid=rigid)

    def solve(
        self,
        features: np.ndarray,
        offsets: np.ndarray | None = None,
        target: np.ndarray | None = None,
        rigid: bool = False,
        scaling=None,
    ) -> np.ndarray:
        """Vertices ``(T, V, 3)`` from ACAP features ``(T, V, 9)``; see ``solve_gradients``.

        Features ``(T, V, 12)`` of a multi-part mesh carry its placement channels
        (:mod:`meshseq.acap.parts`): the parts go where they say unless ``offsets`` is given.
        ``scaling``: the features are scaled by this ``Scaling`` (:mod:`meshseq.acap.scaling`),
        inverted a chunk of frames at a time (no float64 copy of them all); None: unscaled.
        """
        f = np.asarray(features, dtype=np.float64) if scaling is None else np.asarray(features)
        single = f.ndim == 2
        f = f[None] if single else f
        place = None
        if offsets is None and f.shape[-1] > 9:
            P = PLACEMENT_CHANNELS
            place = f[..., P] if scaling is None else scaling.channels(P).invert(f[..., P])
            if self.placement == "centroid":
                offsets, place = offsets_from_channels(place, self.topology, self.reference), None

        def unscaled(frames: slice) -> np.ndarray:
            return f[frames] if scaling is None else scaling.invert(f[frames])

        out = self._solve_rhs(
            lambda frames: self.rhs(features_to_gradients(unscaled(frames))), len(f), offsets, target, rigid, place
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
