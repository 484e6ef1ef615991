"""Generated mesh sequences for tests and demos (numpy only, deterministic for a seed).

* :func:`twisting_limb`: a closed tube skinned to a chain of bones that swing (the limb bends
  past 90 degrees) while the tube twists about its own axis by more than a full turn at the tip,
  so rotation-consistency code has to get past 2 pi.
* :func:`multi_part`: a limb plus two separate closed "eyes" carried rigidly by its tip: a
  three-component mesh for multi-component reconstruction.

Both are smooth in time, watertight (every edge has exactly two faces), free of degenerate
triangles in every frame, and a few hundred vertices big, so tests using them are fast.
"""

from __future__ import annotations

import numpy as np

from meshseq.io import MeshSequence

LIMB_LENGTH = 3.0
LIMB_RADIUS = 0.3
ELLIPSE = 0.6  # minor/major axis ratio of the cross-section, so a twist is visible in the shape


def twisting_limb(frames: int = 48, rings: int = 24, segments: int = 16, bones: int = 3,
                  twist_turns: float = 1.5, seed: int = 0) -> MeshSequence:
    """A twisting, bending, capped tube.

    The rest tube lies along +z (length 3, tapering elliptical cross-section, a cone cap at each
    end). Each frame twists it about its axis, by an angle growing linearly from 0 at the root to
    ``theta(t)`` at the tip (``theta`` rises smoothly from about 0 to ``2 pi twist_turns`` over
    the sequence), then deforms it by linear blend skinning to ``bones`` bones whose joints
    swing sinusoidally about two axes (the tip direction leaves the rest axis by more than
    pi/2). The seed varies phases and amplitudes slightly; the same seed gives the same mesh.

    Args:
        frames: T >= 2. With the default 48 frames the tip turns by less than 0.6 rad between
            frames; below about 24 frames single steps exceed 1 rad (and near pi at 8 frames),
            too coarse for temporal rotation consistency.
        rings: rings of vertices along the tube (>= 3).
        segments: vertices per ring (>= 3).
        bones: bones in the chain (>= 1).
        twist_turns: total twist at the tip, in turns.
        seed: randomises phases/amplitudes a little.

    Returns:
        MeshSequence with vertices ``(T, rings * segments + 2, 3)`` and
        ``2 * segments * rings`` faces; name ``"twisting_limb"``, fps 24.
    """
    _check(frames >= 2 and rings >= 3 and segments >= 3 and bones >= 1,
           f"twisting_limb needs frames >= 2, rings >= 3, segments >= 3, bones >= 1 "
           f"(got {frames}, {rings}, {segments}, {bones})")
    rest, faces, axial = _tube(rings, segments)
    motion = _LimbMotion(frames, bones, twist_turns, seed)
    vertices = motion.deform(rest, axial)
    return MeshSequence(vertices, faces, name="twisting_limb", fps=24.0,
                        source=f"synthetic:twisting_limb(frames={frames}, rings={rings}, segments={segments}, "
                               f"bones={bones}, twist_turns={twist_turns}, seed={seed})")


def multi_part(frames: int = 24, seed: int = 0) -> MeshSequence:
    """A body tube plus two eyes (closed icospheres, 42 vertices each) riding rigidly on its tip.

    The body is :func:`twisting_limb` geometry (20 rings x 12 segments, 2 bones, one twist
    turn); the eyes sit just outside the surface near the tip and follow the tip's rigid motion
    (twist and bone), so they keep their distance to each other and to the tip exactly.

    Returns:
        MeshSequence with 3 connected components: vertices ``(T, 326, 3)``, faces ``(640, 3)``
        (body first, then the two eyes); name ``"multi_part"``, fps 24.
    """
    _check(frames >= 2, f"multi_part needs frames >= 2 (got {frames})")
    rest, faces, axial = _tube(20, 12)
    motion = _LimbMotion(frames, 2, 1.0, seed)
    body = motion.deform(rest, axial)

    sphere_v, sphere_f = icosphere(1)
    s_eye = 0.85  # fraction of the tube length where the eyes sit
    z_eye = s_eye * LIMB_LENGTH
    r_eye = 0.09
    offset = _radius(s_eye) * 1.0 + 1.6 * r_eye  # clear of the surface, any direction
    parts, part_faces = [body], [faces]
    n = body.shape[1]
    for side in (-1.0, 1.0):
        centre = np.array([offset * np.cos(side * 0.5), offset * np.sin(side * 0.5), z_eye])
        eye_rest = centre + r_eye * sphere_v
        parts.append(motion.rigid_tip(eye_rest, s_eye))
        part_faces.append(sphere_f + n)
        n += len(sphere_v)
    return MeshSequence(np.concatenate(parts, axis=1), np.concatenate(part_faces), name="multi_part",
                        fps=24.0, source=f"synthetic:multi_part(frames={frames}, seed={seed})")


def icosphere(subdivisions: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """Unit sphere by subdividing an icosahedron: vertices ``(V, 3)``, faces ``(F, 3)`` outward.

    V = 10 * 4**k + 2, F = 20 * 4**k for k subdivisions.
    """
    p = (1.0 + 5 ** 0.5) / 2
    v = np.array([[-1, p, 0], [1, p, 0], [-1, -p, 0], [1, -p, 0], [0, -1, p], [0, 1, p],
                  [0, -1, -p], [0, 1, -p], [p, 0, -1], [p, 0, 1], [-p, 0, -1], [-p, 0, 1]], dtype=np.float64)
    f = np.array([[0, 11, 5], [0, 5, 1], [0, 1, 7], [0, 7, 10], [0, 10, 11], [1, 5, 9], [5, 11, 4],
                  [11, 10, 2], [10, 7, 6], [7, 1, 8], [3, 9, 4], [3, 4, 2], [3, 2, 6], [3, 6, 8],
                  [3, 8, 9], [4, 9, 5], [2, 4, 11], [6, 2, 10], [8, 6, 7], [9, 8, 1]], dtype=np.int64)
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    for _ in range(subdivisions):
        e = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
        edges, inverse = np.unique(e, axis=0, return_inverse=True)
        mid = v[edges].mean(axis=1)
        mid /= np.linalg.norm(mid, axis=1, keepdims=True)
        m = inverse.reshape(3, -1) + len(v)  # midpoint of edge (0,1), (1,2), (2,0) of each face
        a, b, c = f.T
        f = np.concatenate([np.stack([a, m[0], m[2]], 1), np.stack([b, m[1], m[0]], 1),
                            np.stack([c, m[2], m[1]], 1), np.stack([m[0], m[1], m[2]], 1)])
        v = np.concatenate([v, mid])
    return v, f


# --------------------------------------------------------------------------------------------


def _check(ok: bool, message: str) -> None:
    if not ok:
        from meshseq.errors import MeshseqError

        raise MeshseqError(message)


def _radius(s: np.ndarray | float) -> np.ndarray | float:
    """Tube (major) radius at axial fraction ``s`` in [0, 1]: tapers by a third to the tip."""
    return LIMB_RADIUS * (1.0 - 0.35 * np.clip(s, 0.0, 1.0))


def _tube(rings: int, segments: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rest tube along +z with cone caps.

    Returns:
        vertices ``(rings * segments + 2, 3)`` (ring-major, then the bottom and top apex),
        faces ``(2 * segments * rings, 3)`` oriented outward,
        axial ``(V,)`` fraction of the length in [0, 1] (apexes clipped), for twist and weights.
    """
    s = np.linspace(0.0, 1.0, rings)
    phi = 2 * np.pi * np.arange(segments) / segments
    r = _radius(s)[:, None]
    ring = np.stack([r * np.cos(phi), ELLIPSE * r * np.sin(phi), np.broadcast_to(s[:, None] * LIMB_LENGTH,
                                                                                 (rings, segments))], axis=-1)
    cap = 0.6 * LIMB_RADIUS
    apex = np.array([[0.0, 0.0, -cap], [0.0, 0.0, LIMB_LENGTH + 0.6 * _radius(1.0)]])
    vertices = np.concatenate([ring.reshape(-1, 3), apex])
    axial = np.clip(vertices[:, 2] / LIMB_LENGTH, 0.0, 1.0)

    i, j = np.meshgrid(np.arange(rings - 1), np.arange(segments), indexing="ij")
    a = i * segments + j
    b = i * segments + (j + 1) % segments
    c = (i + 1) * segments + j
    d = (i + 1) * segments + (j + 1) % segments
    side = np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3), np.stack([b, d, c], -1).reshape(-1, 3)])
    bottom, top = rings * segments, rings * segments + 1
    jj = np.arange(segments)
    last = (rings - 1) * segments
    caps = np.concatenate([
        np.stack([np.full(segments, bottom), (jj + 1) % segments, jj], -1),
        np.stack([np.full(segments, top), last + jj, last + (jj + 1) % segments], -1),
    ])
    return vertices, np.concatenate([side, caps]).astype(np.int64), axial


def _rot(axis: int, angle: np.ndarray) -> np.ndarray:
    """Rotations about coordinate axis ``axis`` by ``angle`` ``(...,)`` -> ``(..., 3, 3)``."""
    c, s = np.cos(angle), np.sin(angle)
    out = np.zeros(np.shape(angle) + (3, 3))
    k1, k2 = [(1, 2), (2, 0), (0, 1)][axis]
    out[..., axis, axis] = 1.0
    out[..., k1, k1] = c
    out[..., k2, k2] = c
    out[..., k1, k2] = -s
    out[..., k2, k1] = s
    return out


class _LimbMotion:
    """Twist angle and bone transforms of the limb over time (all arrays over T frames)."""

    def __init__(self, frames: int, bones: int, twist_turns: float, seed: int):
        rng = np.random.default_rng(seed)
        u = np.linspace(0.0, 1.0, frames)  # normalised time
        # Tip twist: smooth ramp 0 -> 2 pi turns (+ a small wobble that vanishes at both ends).
        self.tip_twist = 2 * np.pi * twist_turns * (0.5 - 0.5 * np.cos(np.pi * u)) \
            + 0.3 * rng.uniform(0.8, 1.2) * np.sin(2 * np.pi * u) * np.sin(np.pi * u)
        self.bone_length = LIMB_LENGTH / bones
        self.bones = bones
        # Joint swings about x (main bend, roughly in phase so the bends add up) and y.
        amp_x = 2.7 / bones * rng.uniform(0.9, 1.1, bones)
        amp_y = 0.35 * rng.uniform(0.8, 1.2, bones)
        phase_x = 0.25 * np.arange(bones) + rng.uniform(-0.15, 0.15, bones)
        phase_y = rng.uniform(0.0, 2 * np.pi, bones)
        w = 2 * np.pi * u[:, None]
        swing_x = amp_x * np.sin(w + phase_x)  # (T, B)
        swing_y = amp_y * np.sin(2 * w + phase_y)
        local = _rot(0, swing_x) @ _rot(1, swing_y)  # (T, B, 3, 3)
        rot = np.empty_like(local)
        pos = np.zeros(local.shape[:2] + (3,))
        step = np.array([0.0, 0.0, self.bone_length])
        rot[:, 0] = local[:, 0]
        for b in range(1, bones):  # a chain: each bone hangs off its parent's end
            rot[:, b] = rot[:, b - 1] @ local[:, b]
            pos[:, b] = pos[:, b - 1] + rot[:, b - 1] @ step
        self.rot, self.pos = rot, pos  # (T, B, 3, 3), (T, B, 3): rest origin (0, 0, b l) maps to pos
        self.rest_origin = np.arange(bones)[:, None] * step  # (B, 3)

    def weights(self, axial: np.ndarray) -> np.ndarray:
        """Smooth skinning weights ``(V, B)`` from axial fractions ``(V,)``."""
        z = axial * LIMB_LENGTH
        centres = (np.arange(self.bones) + 0.5) * self.bone_length
        w = np.exp(-(((z[:, None] - centres) / (0.4 * self.bone_length)) ** 2))
        return w / w.sum(axis=1, keepdims=True)

    def twist(self, rest: np.ndarray, axial: np.ndarray) -> np.ndarray:
        """Rest points ``(V, 3)`` twisted about z by ``tip_twist * axial`` -> ``(T, V, 3)``."""
        angle = self.tip_twist[:, None] * axial[None]  # (T, V)
        c, s = np.cos(angle), np.sin(angle)
        x, y, z = rest.T
        return np.stack([c * x - s * y, s * x + c * y, np.broadcast_to(z, angle.shape)], axis=-1)

    def deform(self, rest: np.ndarray, axial: np.ndarray) -> np.ndarray:
        """Twist then linear-blend-skin rest points ``(V, 3)`` -> ``(T, V, 3)``."""
        twisted = self.twist(rest, axial)
        weights = self.weights(axial)
        out = np.zeros_like(twisted)
        for b in range(self.bones):
            moved = np.einsum("tij,tvj->tvi", self.rot[:, b], twisted - self.rest_origin[b]) + self.pos[:, b, None]
            out += weights[None, :, b, None] * moved
        return out

    def rigid_tip(self, rest: np.ndarray, s: float) -> np.ndarray:
        """Move points ``(V, 3)`` rigidly with the tube's cross-section at fraction ``s``
        (its twist, then the last bone) -> ``(T, V, 3)``."""
        twisted = self.twist(rest, np.full(len(rest), s))
        b = self.bones - 1
        return np.einsum("tij,tvj->tvi", self.rot[:, b], twisted - self.rest_origin[b]) + self.pos[:, b, None]
