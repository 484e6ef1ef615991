"""Hard cases for rotation consistency in time (numpy only, deterministic, a few hundred vertices).

Each case moves a squashed icosphere (or a synthetic limb) so that every vertex's rotation follows
a chosen path in SO(3): many full turns, angles through and near pi, a pass close to the identity,
a single-frame swing of more than pi/2. They are paths whose rotation logs CAN be chosen without a
spurious 2 pi jump (a step longer than pi where the rotation changes by less than pi/2), so a
consistency method should report none on them; :func:`swing_back` is one that the greedy
nearest-previous pass gets wrong.
"""

from __future__ import annotations

import numpy as np

from meshseq.io import MeshSequence

SQUASH = np.array([1.0, 0.6, 0.3])


def rodrigues(logs: np.ndarray) -> np.ndarray:
    """Rotation matrices ``(..., 3, 3)`` of rotation vectors ``(..., 3)``."""
    r = np.asarray(logs, dtype=np.float64)
    t = np.linalg.norm(r, axis=-1)[..., None, None]
    k = np.zeros(r.shape[:-1] + (3, 3))
    k[..., 0, 1], k[..., 0, 2], k[..., 1, 2] = -r[..., 2], r[..., 1], -r[..., 0]
    k = k - np.swapaxes(k, -1, -2)
    safe = np.where(t > 0, t, 1.0)
    s1 = np.where(t > 0, np.sin(safe) / safe, 1.0)
    s2 = np.where(t > 0, (1.0 - np.cos(safe)) / safe**2, 0.5)
    return np.eye(3) + s1 * k + s2 * (k @ k)


def _rigid(name: str, logs: np.ndarray) -> MeshSequence:
    from meshseq.data.synthetic import icosphere

    v, f = icosphere(2)
    v = v * SQUASH
    R = rodrigues(logs)
    return MeshSequence(np.einsum("tij,vj->tvi", R, v), f, name=name, fps=24.0, source=f"synthetic:{name}")


def _unit(a) -> np.ndarray:
    a = np.asarray(a, dtype=np.float64)
    return a / np.linalg.norm(a, axis=-1, keepdims=True)


def spin_turns(frames: int = 72, turns: float = 3.0) -> MeshSequence:
    """A body spinning ``turns`` full turns about a fixed tilted axis (log norm up to 2 pi turns)."""
    angle = np.linspace(0.0, 2 * np.pi * turns, frames)
    return _rigid("spin_turns", angle[:, None] * _unit([0.3, 0.2, 1.0]))


def precessing_spin(frames: int = 96, turns: float = 2.0, tilt: float = 0.5) -> MeshSequence:
    """Spin about an axis that itself swings by ``tilt`` rad (the rotation never nears the identity
    except at the start)."""
    u = np.linspace(0.0, 1.0, frames)
    axis = _unit(np.stack([tilt * np.sin(2 * np.pi * u), tilt * np.cos(3 * np.pi * u) - tilt, np.ones(frames)], -1))
    return _rigid("precessing_spin", (2 * np.pi * turns * u)[:, None] * axis)


def through_pi(frames: int = 60) -> MeshSequence:
    """The angle swings through pi and back (pi +- 0.8) while the axis tilts slowly."""
    u = np.linspace(0.0, 1.0, frames)
    angle = np.minimum(1.0, 3 * u) * (np.pi + 0.8 * np.sin(4 * np.pi * u))
    axis = _unit(np.stack([np.ones(frames), 0.4 * np.sin(2 * np.pi * u), 0.3 + 0.2 * u], -1))
    return _rigid("through_pi", angle[:, None] * axis)


def noise_near_pi(frames: int = 80, seed: int = 0) -> MeshSequence:
    """After a ramp, the angle jitters about pi (+-0.05 rad) and the axis by about 0.03 rad."""
    rng = np.random.default_rng(seed)
    ramp = 20
    angle = np.concatenate([np.linspace(0.0, np.pi, ramp), np.pi + 0.05 * rng.uniform(-1, 1, frames - ramp)])
    axis = _unit(np.array([0.2, 1.0, 0.5]) + 0.03 * rng.normal(size=(frames, 3)) * (np.arange(frames) >= ramp)[:, None])
    return _rigid("noise_near_pi", angle[:, None] * axis)


def near_identity(frames: int = 40, miss: float = 0.01) -> MeshSequence:
    """The rotation passes ``miss`` rad from the identity, its axis swinging by pi within a frame."""
    t = np.linspace(-1.0, 1.0, frames) + 0.5 / frames  # no frame exactly at the closest point
    logs = t[:, None] * np.array([0.0, 0.0, 2.0]) + miss * np.array([1.0, 0.0, 0.0])
    logs = logs + 2.0 * np.array([0.0, 1.0, 0.0]) * (1.0 - t[:, None] ** 2)  # curve away from 0 between
    return _rigid("near_identity", logs - logs[0])


def swing_back(frames: int = 60, tilt: float = 0.05) -> MeshSequence:
    """Turn slowly to 1 rad, swing 2.4 rad in ONE frame, turn on past a full turn with a small tilt.

    After the swing the rotation (3.4 rad about z) has two logs within reach: 3.4 z (nearest the
    previous 1.0 z, the greedy choice) and -2.88 z. Turning on to 2 pi + 0.5 about z while tilted by
    ``tilt`` about x passes within ``tilt`` of the identity: on the 2 pi shell that forces a jump,
    from -2.88 z it passes the origin smoothly.
    """
    slow = 12
    phi = np.concatenate([np.linspace(0.0, 1.0, slow), np.linspace(3.4, 2 * np.pi + 0.5, frames - slow)])
    Rz = rodrigues(phi[:, None] * np.array([0.0, 0.0, 1.0]))
    Rx = rodrigues(np.array([tilt, 0.0, 0.0]) * np.minimum(1.0, np.arange(frames) / slow)[:, None])
    R = Rz @ Rx
    from meshseq.data.synthetic import icosphere

    v, f = icosphere(2)
    v = v * SQUASH
    return MeshSequence(np.einsum("tij,vj->tvi", R, v), f, name="swing_back", fps=24.0,
                        source="synthetic:swing_back")


def cases() -> dict[str, MeshSequence]:
    """All hard cases by name, plus the synthetic limbs (fast twist) and the three-part mesh."""
    from meshseq.data.synthetic import multi_part, twisting_limb

    out = {s.name: s for s in (spin_turns(), precessing_spin(), through_pi(), noise_near_pi(),
                               near_identity(), swing_back())}
    fast = twisting_limb(frames=48, twist_turns=3.0)
    out["fast_twist"] = MeshSequence(fast.vertices, fast.faces, name="fast_twist", fps=24.0, source=fast.source)
    out["twisting_limb"] = twisting_limb()
    out["multi_part"] = multi_part(frames=48)
    return out
