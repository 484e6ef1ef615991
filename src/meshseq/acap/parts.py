"""Where the parts of a multi-part mesh sit: three placement channels per vertex (method.md section 2,
"Meshes of several parts").

ACAP features carry each part's shape and rotation but no translation, so on a mesh of several
connected components (eyes, teeth, straps modelled apart from the body) they cannot say where a
part sits relative to the others. The placement channels do: every vertex of part ``c`` carries

    d_c(t) = (centroid_c(t) - centroid(t)) - (centroid_c(ref) - centroid(ref)),

its part's displacement relative to the whole mesh's centroid (vertex-weighted), measured from
the reference, so the reference frame has all zeros as its ACAP channels have the identity.
The way back averages the channels over each part (the model predicts them per vertex) and gives
the parts' centroid offsets from component 0 that ``Reconstructor`` places the parts at.

Single-part meshes have no placement channels (their features stay 9 wide).
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from meshseq.mesh import Topology

#: The channel counts of features: the 9 ACAP channels alone, or with the 3 placement channels.
CHANNEL_COUNTS = (9, 12)
#: Where the placement channels sit in a 12-channel frame.
PLACEMENT_CHANNELS = slice(9, 12)


def relative_centroids(vertices: np.ndarray, topology: Topology) -> np.ndarray:
    """Centroid of each part minus the mesh's centroid ``(T, C, 3)`` for ``(T, V, 3)``."""
    v = np.asarray(vertices, dtype=np.float64)
    return component_centroids(v, topology) - v.mean(axis=1, keepdims=True)


#: What a part's placement is measured from (``placement_channels``): ``centroid``, the whole mesh's
#: centroid; ``anchor``, the vertex of the largest part nearest the part in the reference (the
#: largest part's own channels are zero). A part that rides on the body keeps nearly the same offset
#: from its anchor whatever the body does, where its offset from the centroid moves with every limb.
PLACEMENT_MODES = ("centroid", "anchor")


def placement_channels(vertices: np.ndarray, topology: Topology, reference: np.ndarray,
                       mode: str = "centroid") -> np.ndarray:
    """Placement channels ``(T, V, 3)`` of ``vertices (T, V, 3)`` against ``reference (V, 3)``."""
    if mode not in PLACEMENT_MODES:
        raise ValueError(f"unknown placement mode {mode!r}; expected one of {PLACEMENT_MODES}")
    anchors = part_anchors(reference, topology) if mode == "anchor" else None
    d = part_gaps(vertices, topology, anchors) - part_gaps(np.asarray(reference)[None], topology, anchors)
    return d[:, topology.component_labels]


def part_gaps(vertices: np.ndarray, topology: Topology, anchors: np.ndarray | None = None) -> np.ndarray:
    """Each part's centroid minus what it is measured from, ``(T, C, 3)``: the mesh's centroid
    (``anchors`` None), or its anchor vertex (``part_anchors``; zero for the largest part)."""
    if anchors is None:
        return relative_centroids(vertices, topology)
    v = np.asarray(vertices, dtype=np.float64)
    gaps = component_centroids(v, topology) - v[:, anchors]
    gaps[:, body_part(topology)] = 0.0
    return gaps


def body_part(topology: Topology) -> int:
    """The part with the most vertices (the first of them on a tie)."""
    return int(np.argmax(np.bincount(topology.component_labels, minlength=topology.n_components)))


def part_anchors(reference: np.ndarray, topology: Topology) -> np.ndarray:
    """``(C,)``: each part's anchor, the vertex of the largest part nearest the part's centroid in
    ``reference`` (the largest part's own: its vertex nearest its centroid)."""
    q = np.asarray(reference, dtype=np.float64)
    body = np.flatnonzero(topology.component_labels == body_part(topology))
    cents = component_centroids(q[None], topology)[0]  # (C, 3)
    d2 = ((cents[:, None, :] - q[None, body]) ** 2).sum(-1)  # (C, |body|)
    return body[np.argmin(d2, axis=1)]


def anchored_shifts(vertices: np.ndarray, channels: np.ndarray, topology: Topology, anchors: np.ndarray,
                    reference_gaps: np.ndarray) -> np.ndarray:
    """``(T, C, 3)``: how far to move each part of ``vertices (T, V, 3)`` (each part solved up to a
    translation) so that it sits where ``anchor`` placement channels ``(T, V, 3)`` put it: its centroid
    at its anchor plus its gap (the channels' mean over the part plus the reference's gap,
    ``reference_gaps`` ``(C, 3)``: ``part_gaps`` of the reference). The largest part stays."""
    v = np.asarray(vertices, dtype=np.float64)
    gap = reference_gaps + component_centroids(channels, topology)
    shift = v[:, anchors] + gap - component_centroids(v, topology)
    shift[:, body_part(topology)] = 0.0
    return shift


def offsets_from_channels(channels: np.ndarray, topology: Topology, reference: np.ndarray) -> np.ndarray:
    """Centroid offsets of the parts from component 0 ``(T, C, 3)`` (what ``Reconstructor`` takes)
    from placement channels ``(T, V, 3)``, each part's channels averaged over its vertices."""
    rel = relative_centroids(np.asarray(reference)[None], topology) + component_centroids(channels, topology)
    return rel - rel[:, :1]


def component_offsets(vertices: np.ndarray, topology: Topology) -> np.ndarray:
    """Centroid of each connected component minus that of component 0, ``(T, C, 3)``.

    ACAP features carry no translation; on a mesh of several parts these offsets keep the parts'
    relative placement.
    """
    v = np.asarray(vertices, dtype=np.float64)
    cents = component_centroids(v, topology)
    return cents - cents[:, :1]


def component_centroids(vertices: np.ndarray, topology: Topology) -> np.ndarray:
    """Centroid of each connected component, ``(T, C, 3)`` for vertices ``(T, V, 3)``."""
    v = np.asarray(vertices, dtype=np.float64)
    t, n = v.shape[0], v.shape[1]
    labels = topology.component_labels
    counts = np.bincount(labels, minlength=topology.n_components).astype(np.float64)
    member = sp.csr_matrix((1.0 / counts[labels], (labels, np.arange(n))), shape=(topology.n_components, n))
    flat = member @ np.ascontiguousarray(v.transpose(1, 0, 2)).reshape(n, 3 * t)  # (C, T*3)
    return flat.reshape(-1, t, 3).transpose(1, 0, 2)


def collapsed_parts(reference: np.ndarray, topology: Topology) -> np.ndarray:
    """Indices of the parts whose vertices all sit at one point in ``reference (V, 3)``: against such a
    reference a part's shape cannot be encoded (every gradient maps zero-length edges), only its place."""
    q = np.asarray(reference, dtype=np.float64)
    labels, n = topology.component_labels, topology.n_components
    lo = np.full((n, 3), np.inf)
    hi = np.full((n, 3), -np.inf)
    np.minimum.at(lo, labels, q)
    np.maximum.at(hi, labels, q)
    size = (hi - lo).max(axis=1)
    return np.flatnonzero(size <= 1e-12 * max(float(np.ptp(q, axis=0).max()), 1e-300))


def check_reference_parts(reference: np.ndarray, topology: Topology, where: str) -> None:
    """MeshseqError naming ``where`` (the file and frame) when a part of the reference is one point."""
    from meshseq.errors import MeshseqError

    bad = collapsed_parts(reference, topology)
    if len(bad):
        part = int(bad[0])
        count = int((topology.component_labels == part).sum())
        raise MeshseqError(f"{where}: part {part} (of {topology.n_components}; {count} vertices from vertex "
                           f"{int(topology.component_roots[part])}) has all its vertices at one point, so its shape "
                           "cannot be taken against this frame; use a reference frame where it has a size, or remove it")
