"""Accessory parts carried by a body: separately modelled pieces (eyes, a bag strap) that move with it.

Artists' assets are usually several disconnected parts. :func:`attach` appends such parts to a
body's mesh sequence, each its own connected component, so a set keeps one connectivity:

* ``eyes``: two small closed spheres just in front of the face, each carried rigidly by the
  local frame of one head triangle;
* ``strap``: a thin closed band (a flat tube, genus 1) across the torso from one shoulder to the
  opposite hip, lying a few millimetres off the skin; each of its vertices is carried by the
  local frame of its nearest body triangle at rest, so the band bends with the torso.

A triangle's local frame is its centroid and the orthonormal axes (first edge, normal x edge,
normal). A carried point keeps its coordinates in that frame: rigid with the triangle.

Body conventions are those of :mod:`meshseq.data.bodies`: metres, ``+z`` up, facing ``-y``;
landmarks (eye line, shoulder, hip) are found on the rest mesh from its height, so any template
resolution works. Pure numpy.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np

from meshseq.data.synthetic import icosphere
from meshseq.errors import MeshseqError

#: Part names :func:`attach` knows, in the order their vertices are appended.
PARTS = ("eyes", "strap")
UP = np.array([0.0, 0.0, 1.0])
FORWARD = np.array([0.0, -1.0, 0.0])
#: Eyes: radius, gap to the face, half the distance between them, depth of the eye line below the
#: top of the head (the last two as fractions of the body's height).
EYE_RADIUS, EYE_GAP, EYE_HALF_SPACING, EYE_DEPTH = 0.012, 0.002, 0.0195, 0.068
#: Strap: samples along it, sides of its cross-section, width, thickness, gap to the skin.
STRAP_SAMPLES, STRAP_SIDES, STRAP_WIDTH, STRAP_THICKNESS, STRAP_GAP = 48, 6, 0.04, 0.006, 0.002
#: Strap line in the frontal plane: shoulder (x, depth below the top) and opposite hip, in heights.
STRAP_SHOULDER, STRAP_HIP = (0.08, 0.17), (-0.09, 0.50)


@dataclass(frozen=True)
class Part:
    """A part bound to a body: vertex ``i`` has coordinates ``local[i]`` in the frame of body
    triangle ``tri[i]``.

    Attributes:
        tri: ``(P,)`` int64 body triangle carrying each vertex.
        local: ``(P, 3)`` coordinates in that triangle's frame.
        faces: ``(Fp, 3)`` int64 triangles of the part (indices into its own vertices).
    """

    tri: np.ndarray
    local: np.ndarray
    faces: np.ndarray


def resolve_parts(spec: str | Sequence[str] | None) -> list[str]:
    """Part names from a comma-separated string or a list (empty: none); one-line error otherwise."""
    names = [s.strip() for s in (spec.split(",") if isinstance(spec, str) else spec or ()) if s.strip()]
    for name in names:
        if name not in PARTS:
            raise MeshseqError(f"--parts: unknown part {name!r} (known: {', '.join(PARTS)})")
    if len(set(names)) != len(names):
        raise MeshseqError(f"--parts: a part is listed twice in {','.join(names)}")
    return names


# ----------------------------------------------------------------------------------------------
# Triangle frames


def triangle_frames(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Local frames of triangles ``faces (K, 3)`` of ``vertices (..., V, 3)``: origins
    ``(..., K, 3)`` (centroids) and rotations ``(..., K, 3, 3)`` whose columns are the unit first
    edge, normal x edge and the unit normal."""
    tri = np.asarray(vertices, dtype=np.float64)[..., faces, :]  # (..., K, 3, 3)
    e1 = tri[..., 1, :] - tri[..., 0, :]
    n = np.cross(e1, tri[..., 2, :] - tri[..., 0, :])
    e1 = e1 / np.linalg.norm(e1, axis=-1, keepdims=True)
    n = n / np.linalg.norm(n, axis=-1, keepdims=True)
    return tri.mean(axis=-2), np.stack([e1, np.cross(n, e1), n], axis=-1)


def bind(points: np.ndarray, rest: np.ndarray, faces: np.ndarray, tri: np.ndarray) -> np.ndarray:
    """Coordinates ``(P, 3)`` of ``points (P, 3)`` in the rest frames of body triangles ``tri (P,)``."""
    origin, rot = triangle_frames(rest, faces[tri])
    return np.einsum("pji,pj->pi", rot, points - origin)


def carry(vertices: np.ndarray, faces: np.ndarray, part: Part) -> np.ndarray:
    """Positions ``(T, P, 3)`` of ``part``'s vertices on body frames ``vertices (T, V, 3)``."""
    origin, rot = triangle_frames(vertices, faces[part.tri])  # (T, P, 3), (T, P, 3, 3)
    return origin + np.einsum("tpij,pj->tpi", rot, part.local)


def nearest_triangles(points: np.ndarray, rest: np.ndarray, faces: np.ndarray, candidates: int = 8) -> np.ndarray:
    """Body triangle ``(P,)`` nearest each of ``points (P, 3)``: among the ``candidates`` nearest
    centroids, the one whose plane-projected, clipped point is closest."""
    cent = rest[faces].mean(axis=1)
    d2 = ((points[:, None, :] - cent[None]) ** 2).sum(axis=-1)  # (P, F)
    k = min(candidates, len(faces))
    cand = np.argpartition(d2, k - 1, axis=1)[:, :k]  # (P, k)
    tri = rest[faces[cand]]  # (P, k, 3, 3)
    closest = _closest_on_triangle(np.repeat(points[:, None], k, axis=1), tri)
    best = np.argmin(((closest - points[:, None]) ** 2).sum(axis=-1), axis=1)
    return cand[np.arange(len(points)), best]


def _closest_on_triangle(p: np.ndarray, tri: np.ndarray) -> np.ndarray:
    """Approximate closest points ``(..., 3)`` of ``p (..., 3)`` on triangles ``tri (..., 3, 3)``
    (the plane projection's barycentric coordinates, clipped and renormalised)."""
    a, b, c = tri[..., 0, :], tri[..., 1, :], tri[..., 2, :]
    v0, v1, v2 = b - a, c - a, p - a
    d00, d01, d11 = (v0 * v0).sum(-1), (v0 * v1).sum(-1), (v1 * v1).sum(-1)
    d20, d21 = (v2 * v0).sum(-1), (v2 * v1).sum(-1)
    den = d00 * d11 - d01 * d01
    den = np.where(np.abs(den) > 0, den, 1.0)
    v, w = (d11 * d20 - d01 * d21) / den, (d00 * d21 - d01 * d20) / den
    bary = np.clip(np.stack([1.0 - v - w, v, w], axis=-1), 0.0, None)
    bary /= bary.sum(axis=-1, keepdims=True)
    return np.einsum("...k,...kc->...c", bary, tri)


def _face_normals(rest: np.ndarray, faces: np.ndarray) -> np.ndarray:
    n = np.cross(rest[faces[:, 1]] - rest[faces[:, 0]], rest[faces[:, 2]] - rest[faces[:, 0]])
    return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)


# ----------------------------------------------------------------------------------------------
# Eyes


def eyes(rest: np.ndarray, faces: np.ndarray, subdivisions: int = 2) -> Part:
    """Two closed spheres (``icosphere(subdivisions)``, :data:`EYE_RADIUS`) just in front of the
    face, each bound rigidly to the front-facing head triangle nearest its eye line position."""
    z_top, height = rest[:, 2].max(), np.ptp(rest[:, 2])
    normals = _face_normals(rest, faces)
    cent = rest[faces].mean(axis=1)
    front = normals @ FORWARD
    head = np.flatnonzero((cent[:, 2] > z_top - 0.15 * height) & (np.abs(front) > 0.3))
    if head.size == 0:
        raise MeshseqError("eyes: found no front-facing head triangle on the body")
    sphere, sphere_faces = icosphere(subdivisions)
    tris, points = [], []
    for side in (1.0, -1.0):  # two eyes: a loop of 2, each vectorised
        target = np.array([side * EYE_HALF_SPACING * height, z_top - EYE_DEPTH * height])
        t = head[np.argmin(((cent[head][:, [0, 2]] - target) ** 2).sum(axis=1))]
        n = normals[t] * np.sign(front[t])  # facing forward
        # The eye line's point on the triangle's plane, moved out along -y past the face vertices
        # around the eye line (brow, nose), then EYE_GAP further than the sphere's radius.
        y_plane = cent[t, 1] - (n[0] * (target[0] - cent[t, 0]) + n[2] * (target[1] - cent[t, 2])) / n[1]
        around = np.linalg.norm(rest[:, [0, 2]] - target, axis=1) < EYE_RADIUS
        y_face = min(y_plane, rest[around, 1].min(initial=np.inf))
        centre = np.array([target[0], y_face, target[1]]) + FORWARD * (EYE_RADIUS + EYE_GAP)
        tris.append(np.full(len(sphere), t))
        points.append(centre + EYE_RADIUS * sphere)
    tri, pts = np.concatenate(tris), np.concatenate(points)
    faces_out = np.concatenate([sphere_faces, sphere_faces + len(sphere)])
    return Part(tri=tri, local=bind(pts, rest, faces, tri), faces=faces_out)


# ----------------------------------------------------------------------------------------------
# Strap


def strap(rest: np.ndarray, faces: np.ndarray) -> Part:
    """A closed flat tube (:data:`STRAP_SAMPLES` x :data:`STRAP_SIDES` vertices) along the
    torso's section by the plane through one shoulder and the opposite hip (the plane holds the
    front-back axis), :data:`STRAP_GAP` off the skin; each vertex bound to its nearest triangle."""
    plane_o, u, w = _strap_plane(rest)
    curve = _resample_closed(_section(rest, faces, plane_o, u, w), STRAP_SAMPLES)
    normal = _smooth_normals(curve, rest, faces, curve.mean(axis=0))
    pts, tube_faces = _tube(curve, normal)
    tri = nearest_triangles(pts, rest, faces)
    return Part(tri=tri, local=bind(pts, rest, faces, tri), faces=tube_faces)


def _strap_plane(rest: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The strap's plane: a point ``(3,)`` between shoulder and opposite hip, its in-plane unit
    axes ``u`` (hip to shoulder) and ``w`` (the front-back axis)."""
    z_top, height = rest[:, 2].max(), np.ptp(rest[:, 2])
    y_mid = rest[:, 1].mean()
    a = np.array([STRAP_SHOULDER[0] * height, y_mid, z_top - STRAP_SHOULDER[1] * height])
    b = np.array([STRAP_HIP[0] * height, y_mid, z_top - STRAP_HIP[1] * height])
    u = (a - b) / np.linalg.norm(a - b)
    return 0.5 * (a + b), u, -FORWARD


def _section(rest: np.ndarray, faces: np.ndarray, o: np.ndarray, u: np.ndarray, w: np.ndarray,
             rays: int = 720) -> np.ndarray:
    """Closed curve ``(rays, 3)``: for rays from the section's centre in the plane
    ``(o; u, w)``, the first crossing of the mesh's section (the torso, star-shaped from there)."""
    n = np.cross(u, w)
    s = (rest - o) @ n  # signed distance of each vertex to the plane
    sf = s[faces]
    cut = faces[(sf.min(axis=1) < 0) & (sf.max(axis=1) > 0)]
    # Each cut triangle crosses the plane on two of its edges: the segment between those points.
    e = np.stack([cut[:, [0, 1]], cut[:, [1, 2]], cut[:, [2, 0]]], axis=1)  # (S, 3, 2)
    se = s[e]
    crosses = (se[..., 0] < 0) != (se[..., 1] < 0)
    t = se[..., 0] / np.where(crosses, se[..., 0] - se[..., 1], 1.0)
    pts = rest[e[..., 0]] + t[..., None] * (rest[e[..., 1]] - rest[e[..., 0]])  # (S, 3, 3)
    seg = pts[crosses].reshape(-1, 2, 3)  # (S, 2, 3): exactly two crossing edges per triangle
    seg2 = np.stack([(seg - o) @ u, (seg - o) @ w], axis=-1)  # (S, 2, 2) in-plane
    centre = _seg_centre(seg2)
    angles = np.linspace(0.0, 2.0 * np.pi, rays, endpoint=False)
    d = np.stack([np.cos(angles), np.sin(angles)], axis=1)  # (R, 2)
    r = _first_hits(centre, d, seg2)
    hit = centre + r[:, None] * d
    return o + hit[:, :1] * u + hit[:, 1:] * w


def _seg_centre(seg2: np.ndarray) -> np.ndarray:
    """Length-weighted centre ``(2,)`` of the torso's segments ``(S, 2, 2)`` near the plane's
    origin (the largest section around it, not a stray cut through a limb)."""
    mid = seg2.mean(axis=1)
    length = np.linalg.norm(seg2[:, 1] - seg2[:, 0], axis=1)
    near = np.linalg.norm(mid, axis=1) < 1.5 * np.median(np.linalg.norm(mid, axis=1))
    return (mid[near] * length[near, None]).sum(axis=0) / length[near].sum()


def _first_hits(c: np.ndarray, d: np.ndarray, seg2: np.ndarray) -> np.ndarray:
    """Distance ``(R,)`` from ``c (2,)`` along unit rays ``d (R, 2)`` to the nearest of the
    segments ``seg2 (S, 2, 2)``."""
    p, q = seg2[:, 0] - c, seg2[:, 1] - seg2[:, 0]  # (S, 2)
    cross = lambda a, b: a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]  # noqa: E731
    den = cross(d[:, None, :], q[None])  # (R, S)
    ok = np.abs(den) > 1e-15
    den = np.where(ok, den, 1.0)
    t = cross(p[None], q[None]) / den  # along the ray
    s = cross(p[None], d[:, None, :]) / den  # along the segment
    t = np.where(ok & (t > 0) & (s >= 0) & (s <= 1), t, np.inf)
    r = t.min(axis=1)
    if not np.isfinite(r).all():
        raise MeshseqError("strap: the torso's section is not closed around its centre")
    return r


def _resample_closed(curve: np.ndarray, n: int) -> np.ndarray:
    """``n`` points ``(n, 3)`` at equal arc length along the closed polyline ``curve (M, 3)``."""
    closed = np.concatenate([curve, curve[:1]])
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(closed, axis=0), axis=1))])
    at = np.linspace(0.0, s[-1], n, endpoint=False)
    return np.stack([np.interp(at, s, closed[:, k]) for k in range(3)], axis=1)


def _smooth_normals(points: np.ndarray, rest: np.ndarray, faces: np.ndarray, inside: np.ndarray,
                    sigma: float = 0.03) -> np.ndarray:
    """Unit skin normals ``(P, 3)`` at ``points (P, 3)``: face normals weighted by area and a
    Gaussian of the distance to their centroids, pointing away from ``inside (3,)``."""
    n = np.cross(rest[faces[:, 1]] - rest[faces[:, 0]], rest[faces[:, 2]] - rest[faces[:, 0]])  # 2 x area
    cent = rest[faces].mean(axis=1)
    d2 = ((points[:, None, :] - cent[None]) ** 2).sum(axis=-1)  # (P, F)
    n = np.exp(-0.5 * d2 / sigma ** 2) @ n
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    return n * np.where(((points - inside) * n).sum(axis=1) < 0, -1.0, 1.0)[:, None]


def _tube(curve: np.ndarray, normal: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A closed flat tube around the closed ``curve (N, 3)``: vertices ``(N * K, 3)`` (an ellipse
    of K = :data:`STRAP_SIDES` points per sample, wide across the curve, thin along ``normal``,
    lifted :data:`STRAP_GAP` off the skin) and its ``(2 N K, 3)`` outward triangles."""
    n_s, k = len(curve), STRAP_SIDES
    tangent = np.roll(curve, -1, axis=0) - np.roll(curve, 1, axis=0)
    tangent /= np.linalg.norm(tangent, axis=1, keepdims=True)
    nrm = normal - (normal * tangent).sum(axis=1, keepdims=True) * tangent
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    side = np.cross(tangent, nrm)
    psi = 2.0 * np.pi * np.arange(k) / k
    centre = curve + (STRAP_GAP + 0.5 * STRAP_THICKNESS) * nrm
    pts = (centre[:, None] + 0.5 * STRAP_WIDTH * np.cos(psi)[None, :, None] * side[:, None]
           + 0.5 * STRAP_THICKNESS * np.sin(psi)[None, :, None] * nrm[:, None])
    i, j = np.meshgrid(np.arange(n_s), np.arange(k), indexing="ij")
    a, b = i * k + j, i * k + (j + 1) % k
    c, d = ((i + 1) % n_s) * k + j, ((i + 1) % n_s) * k + (j + 1) % k
    quads = np.stack([a, b, d, c], axis=-1).reshape(-1, 4)
    tri = np.concatenate([quads[:, [0, 1, 2]], quads[:, [0, 2, 3]]])
    return pts.reshape(-1, 3), _outward(pts.reshape(-1, 3), tri)


def _outward(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """``faces`` flipped if the closed mesh's signed volume is negative."""
    a, b, c = (vertices[faces[:, i]] for i in range(3))
    return faces[:, ::-1].copy() if np.einsum("fi,fi->f", a, np.cross(b, c)).sum() < 0 else faces


# ----------------------------------------------------------------------------------------------
# Attaching


def build_parts(rest: np.ndarray, faces: np.ndarray, kinds: Sequence[str]) -> list[Part]:
    """The parts ``kinds`` (names from :data:`PARTS`) bound to the rest body ``rest (V, 3)``."""
    rest = np.asarray(rest, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64)
    makers = {"eyes": eyes, "strap": strap}
    return [makers[k](rest, faces) for k in resolve_parts(kinds)]


def attach(vertices: np.ndarray, faces: np.ndarray, rest: np.ndarray,
           kinds: Sequence[str]) -> tuple[np.ndarray, np.ndarray]:
    """Body frames ``vertices (T, V, 3)`` with the parts ``kinds`` (bound to ``rest (V, 3)``,
    the body's rest pose, faces ``faces (F, 3)``) appended.

    Returns:
        ``(T, V + P, 3)`` vertices (the body's first, unchanged) and ``(F + Fp, 3)`` faces (the
        parts' offset past the body's and earlier parts' vertices).
    """
    v = np.asarray(vertices, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64)
    out_v, out_f, n = [v], [faces], v.shape[1]
    for part in build_parts(rest, faces, kinds):
        out_v.append(carry(v, faces, part))
        out_f.append(part.faces + n)
        n += len(part.tri)
    return np.concatenate(out_v, axis=1), np.concatenate(out_f)
