"""Human motions as smooth periodic joint-rotation curves on Anny's skeleton (numpy only).

A motion is a function of time giving, for each driven bone of the Anny rig, a rotation
``(T, 3, 3)`` per frame: the bone's *delta* in Anny's ``local-ref`` pose parameterization, that
is a rotation about the bone's head in world-aligned axes carried by its parent (identity = the
rest A-pose). Anny's axes: ``+x`` is the body's left, ``-y`` its front, ``+z`` up.

Every curve is built from sines of the motion phase ``phi = 2 pi speed f0 t + phase`` (and
powers of clipped sines that are at least C1), so joint angles, and so vertex positions, move
smoothly and repeat with the motion's cycle. :class:`MotionParams` scales the speed, the
amplitude of every excursion from the motion's base posture, and shifts the phase, so no two
generated sequences are the same.

Motions are authored for the body's left side in degrees with anatomical helpers (see
``_Side``); the right side is the mirror image (``M R M`` with ``M = diag(-1, 1, 1)``), usually
half a cycle later. Besides rotations a motion gives a vertical ``hop`` (metres above the
floor contact, for jumping jacks) and whether it travels (``walk``: the body moves forward so
the stance foot stays put); the grounding itself is done by :mod:`meshseq.data.bodies`.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

#: Built-in motions, in the order ``make-bodies`` lists them.
MOTIONS = ("walk", "jumping_jacks", "punch", "shake_arms", "squat", "wave", "bend")
#: Other accepted spellings.
ALIASES = {
    "walking": "walk", "jumping-jacks": "jumping_jacks", "jumpingjacks": "jumping_jacks",
    "jacks": "jumping_jacks", "punching": "punch", "shake-arms": "shake_arms",
    "shaking_arms": "shake_arms", "squats": "squat", "waving": "wave", "bending": "bend",
}
#: Base cycle frequency of each motion (cycles per second at speed 1).
BASE_FREQUENCY = {
    "walk": 0.9, "jumping_jacks": 0.8, "punch": 0.75, "shake_arms": 0.5,
    "squat": 0.4, "wave": 0.5, "bend": 0.3,
}


@dataclass(frozen=True)
class MotionParams:
    """Variation of one performance: ``speed`` (cycle-rate factor), ``amplitude`` (factor on every
    excursion from the base posture) and ``phase`` (radians into the cycle at frame 0)."""

    speed: float = 1.0
    amplitude: float = 1.0
    phase: float = 0.0

    @staticmethod
    def sample(rng: np.random.Generator) -> "MotionParams":
        """Random variation: speed in [0.85, 1.15], amplitude in [0.8, 1.05], any phase."""
        return MotionParams(
            speed=float(rng.uniform(0.85, 1.15)),
            amplitude=float(rng.uniform(0.8, 1.05)),
            phase=float(rng.uniform(0.0, 2.0 * np.pi)),
        )


@dataclass
class Motion:
    """Joint-rotation curves of one performance over ``T`` frames.

    Attributes:
        rotations: bone label -> ``(T, 3, 3)`` delta rotation (``local-ref`` parameterization).
        hop: ``(T,)`` height in metres added above the floor contact.
        travels: the body moves so that the stance foot stays fixed (walk) instead of keeping
            both feet where they are.
        contact: for a travelling motion, ``(T,)`` weight in [0, 1] of the left foot as the
            stance foot (the right one has the rest).
    """

    rotations: dict[str, np.ndarray]
    hop: np.ndarray
    travels: bool = False
    contact: np.ndarray | None = None
    name: str = ""
    params: MotionParams = field(default_factory=MotionParams)


#: Tempo levels of :func:`varied_tempo` (factors on the motion's own speed): holds, slow, steady, fast.
TEMPO_LEVELS = (0.0, 0.0, 0.25, 0.5, 1.0, 1.0, 1.5)


def varied_tempo(n_frames: int, fps: float, rng: np.random.Generator, segment: tuple[int, int] = (12, 36),
                 ramp: tuple[int, int] = (4, 14)) -> np.ndarray:
    """A time warp with holds, slow-downs to a stop and speed-ups: ``(n_frames,)`` times in seconds.

    The tempo (the motion's speed factor) is piecewise constant on segments of ``segment`` frames,
    each at a level drawn from ``TEMPO_LEVELS`` (a hold is level 0), and moves to the next level
    over a linear ramp of ``ramp`` frames, so a motion slows to a stop, stays still, and starts
    again. ``times[k]`` is the tempo summed over frames ``0..k-1`` over ``fps`` (``times[0] = 0``).
    """
    tempo = np.empty(n_frames)
    level, k = float(rng.choice(TEMPO_LEVELS[2:])), 0  # start in motion
    while k < n_frames:
        length = int(rng.integers(segment[0], segment[1] + 1))
        tempo[k:k + length] = level
        k += length
        nxt = float(rng.choice(TEMPO_LEVELS))
        r = int(rng.integers(ramp[0], ramp[1] + 1))
        tempo[k:k + r] = np.linspace(level, nxt, r + 2)[1:-1][:max(0, min(r, n_frames - k))]
        k += r
        level = nxt
    return np.concatenate([[0.0], np.cumsum(tempo[:-1])]) / float(fps)


def canonical_motion(name: str) -> str | None:
    """The built-in motion called ``name`` (case and aliases tolerated), or None."""
    key = name.strip().lower().replace(" ", "_")
    key = ALIASES.get(key, key)
    return key if key in MOTIONS else None


# ----------------------------------------------------------------------------------------------
# Rotation helpers (vectorised over frames)


def _axis_rotation(axis: np.ndarray, degrees: np.ndarray) -> np.ndarray:
    """Rotations ``(T, 3, 3)`` by ``degrees (T,)`` about the unit ``axis (3,)`` (Rodrigues)."""
    a = np.radians(np.asarray(degrees, dtype=np.float64))
    k = np.asarray(axis, dtype=np.float64)
    k = k / np.linalg.norm(k)
    K = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    s, c = np.sin(a)[:, None, None], np.cos(a)[:, None, None]
    return np.eye(3) + s * K + (1.0 - c) * (K @ K)


_X, _Y, _Z = np.eye(3)
_MIRROR = np.diag([-1.0, 1.0, 1.0])


def mirror(rotations: np.ndarray) -> np.ndarray:
    """The left/right mirror image ``M R M`` of rotations ``(..., 3, 3)`` (M flips x)."""
    return _MIRROR @ rotations @ _MIRROR


def _bump(x: np.ndarray, power: float = 3.0) -> np.ndarray:
    """``max(0, sin x) ** power``: a smooth (C1 for power >= 2) pulse in each first half-cycle."""
    return np.maximum(np.sin(x), 0.0) ** power


def _ease(x: np.ndarray) -> np.ndarray:
    """``(1 - cos x) / 2``: 0 at x = 0, 1 at x = pi, smooth and periodic."""
    return 0.5 * (1.0 - np.cos(x))


class _Side:
    """Collects the rotations of one body side (authored as the left) and the central bones.

    Angles are degrees ``(T,)``; each helper composes onto the bone's rotation in the order
    called (a later call is applied after, in world-aligned axes). Sign conventions, left side:

    * ``hip(flex, abduct)``: flex > 0 swings the thigh forward, abduct > 0 outwards.
    * ``knee(flex)``: flex > 0 bends the shin backwards.
    * ``ankle(pitch, roll)``: pitch > 0 lifts the toes (dorsiflexion), roll > 0 tilts the sole
      outwards; ``flat_foot`` chooses them so the sole stays parallel to the floor.
    * ``shoulder(abduct, flex, adduct_h)``: abduct > 0 raises the arm sideways from the A-pose
      (about -35 hangs it at the side), flex > 0 raises it forward, adduct_h > 0 brings it
      across the front of the body.
    * ``elbow(flex)``: sets the elbow's flexion to ``flex`` (0 = straight; the rest A-pose has
      it bent forward by ``elbow_rest``) about the hinge axis of the rest skeleton. Call it
      once per side.
    * ``elbow_up(angle)``: rotates the forearm in the coronal plane, > 0 upwards/outwards.
    * ``wrist(flex)``.
    """

    def __init__(self, n: int, rig: "RigAxes"):
        self.n = n
        self.rig = rig
        self.rot: dict[str, np.ndarray] = {}
        self._leg = np.broadcast_to(np.eye(3), (n, 3, 3))  # hip @ knee rotations so far

    def _apply(self, bone: str, R: np.ndarray) -> None:
        prev = self.rot.get(bone)
        self.rot[bone] = R if prev is None else R @ prev

    def _angles(self, value) -> np.ndarray:
        return np.broadcast_to(np.asarray(value, dtype=np.float64), (self.n,))

    def hip(self, flex=0.0, abduct=0.0) -> None:
        flex, abduct = self._angles(flex), self._angles(abduct)
        R = _axis_rotation(_X, -flex) @ _axis_rotation(_Y, -abduct)
        self._apply("upperleg01.L", R)
        self._leg = self._leg @ R

    def knee(self, flex=0.0) -> None:
        R = _axis_rotation(_X, self._angles(flex))
        self._apply("lowerleg01.L", R)
        self._leg = self._leg @ R

    def flat_foot(self, extra_pitch=0.0, body: np.ndarray | None = None) -> None:
        """The ankle rotation that undoes the rotations above the foot (``body`` ``(T, 3, 3)``: the
        root's, then the hip's and knee's so far) so the sole stays level, then tilts it by
        ``extra_pitch`` (> 0 lifts the toes). Call it after ``hip`` and ``knee``."""
        chain = self._leg if body is None else body @ self._leg
        self._apply("foot.L", _axis_rotation(_X, self._angles(extra_pitch)) @ np.swapaxes(chain, -1, -2))

    def shoulder(self, abduct=0.0, flex=0.0, adduct_h=0.0) -> None:
        abduct, flex, adduct_h = self._angles(abduct), self._angles(flex), self._angles(adduct_h)
        self._apply("upperarm01.L", _axis_rotation(_Y, -abduct))
        self._apply("upperarm01.L", _axis_rotation(_X, -flex))
        self._apply("upperarm01.L", _axis_rotation(_Z, -adduct_h))

    def elbow(self, flex=0.0) -> None:
        self._apply("lowerarm01.L", _axis_rotation(self.rig.elbow_axis, self._angles(flex) - self.rig.elbow_rest))

    def elbow_up(self, angle=0.0) -> None:
        self._apply("lowerarm01.L", _axis_rotation(_Y, -self._angles(angle)))

    def wrist(self, flex=0.0) -> None:
        self._apply("wrist.L", _axis_rotation(_X, -self._angles(flex)))

    def fingers(self, curl=0.0) -> None:
        """Curl the four fingers (1 = a fist, 0.3 = relaxed) and the thumb about the knuckle line."""
        curl = self._angles(curl)
        for joint, angle in ((1, 85.0), (2, 100.0), (3, 70.0)):
            R = _axis_rotation(self.rig.knuckle_axis, angle * curl)
            for finger in (2, 3, 4, 5):
                self._apply(f"finger{finger}-{joint}.L", R)
        self._apply("finger1-2.L", _axis_rotation(self.rig.knuckle_axis, 35.0 * curl))
        self._apply("finger1-3.L", _axis_rotation(self.rig.knuckle_axis, 45.0 * curl))

    def mirrored(self) -> dict[str, np.ndarray]:
        """These rotations as the right side's (bone labels ``.L`` -> ``.R``, mirrored)."""
        return {k[:-2] + ".R": mirror(v) for k, v in self.rot.items()}


def _spine(n: int, pitch=0.0, yaw=0.0, roll=0.0, bones=("spine04", "spine03", "spine02", "spine01")):
    """Central rotations spreading a torso ``pitch`` (> 0 leans forward), ``yaw`` (> 0 turns to
    the left) and ``roll`` (> 0 leans to the left) in degrees evenly over ``bones``."""
    k = len(bones)
    pitch, yaw, roll = (np.broadcast_to(np.asarray(v, dtype=np.float64), (n,)) / k for v in (pitch, yaw, roll))
    R = _axis_rotation(_Z, yaw) @ _axis_rotation(_Y, -roll) @ _axis_rotation(_X, pitch)
    return {b: R for b in bones}


# ----------------------------------------------------------------------------------------------
# The motions

#: Walk: fraction of the gait cycle a foot is on the floor, half-stride (a fraction of the leg
#: length, per unit of amplitude) and swing-foot lift (metres).
WALK_STANCE = 0.6
WALK_HALF_STRIDE = 0.33
WALK_LIFT = 0.07


def _hermite(s, p0, m0, p1, m1):
    """Cubic Hermite curve at ``s`` in [0, 1] from ``p0`` (slope ``m0``) to ``p1`` (slope ``m1``)."""
    s2, s3 = s * s, s * s * s
    return (2 * s3 - 3 * s2 + 1) * p0 + (s3 - 2 * s2 + s) * m0 + (-2 * s3 + 3 * s2) * p1 + (s3 - s2) * m1


def walk_ankle_path(c: np.ndarray, half: float) -> tuple[np.ndarray, np.ndarray]:
    """Ankle offset from the hip along the walking direction ``(T,)`` and its lift ``(T,)`` at
    gait-cycle fraction ``c`` in [0, 1) (heel strike at 0): on the floor for ``c < WALK_STANCE``
    moving back uniformly from ``+half`` to ``-half``; then swung forward (C1 cubic matching the
    stance speed at both ends) with a ``sin^2`` lift."""
    beta = WALK_STANCE
    speed = -2.0 * half / beta
    stance = c < beta
    s = np.clip((c - beta) / (1.0 - beta), 0.0, 1.0)
    f = np.where(stance, half + speed * c, _hermite(s, -half, speed * (1 - beta), half, speed * (1 - beta)))
    lift = np.where(stance, 0.0, WALK_LIFT * np.sin(np.pi * s) ** 2)
    return f, lift


def walk_legs(phi: np.ndarray, rig: "RigAxes", amplitude: float = 1.0):
    """Hip and knee flexion (degrees, ``(2, T)`` for left and right) that put the ankles on
    :func:`walk_ankle_path`, and the hip height ``(T,)`` above the stance ankles' level.

    The hip rides as high as the stance legs allow (98 % of full reach), smoothed to a few
    harmonics of the gait cycle and lowered so that it never asks for more than that.
    """
    thigh, shin = rig.thigh, rig.shin  # (forward, down) rest vectors of the left leg
    lt, ls = float(np.hypot(*thigh)), float(np.hypot(*shin))
    rest_t = np.arctan2(thigh[0], thigh[1])
    rest_s = np.arctan2(shin[0], shin[1])
    half = WALK_HALF_STRIDE * amplitude * (lt + ls)

    def height_limit(c):
        f, _ = walk_ankle_path(c, half)
        return np.where(c < WALK_STANCE, 0.98 * np.sqrt(np.maximum((lt + ls) ** 2 - f ** 2, 0.0)), np.inf)

    # The hip height over one cycle (left leg's cycle fraction), as a smooth periodic curve.
    grid = np.arange(512) / 512.0
    limit = np.minimum(height_limit(grid), height_limit(np.mod(grid + 0.5, 1.0)))
    spec = np.fft.rfft(limit)
    spec[5:] = 0.0
    smooth = np.fft.irfft(spec, n=grid.size)
    offset = float(np.max(smooth - limit))
    coeffs = spec[:5] / grid.size
    coeffs[0] -= offset

    def hip_height(c):
        k = np.arange(5)
        terms = coeffs[None, :] * np.exp(2j * np.pi * k[None, :] * c[:, None])
        return terms[:, 0].real + 2.0 * terms[:, 1:].real.sum(axis=1)

    c_left = np.mod((phi - np.pi / 2) / (2 * np.pi), 1.0)
    h = hip_height(c_left)
    hips, knees = [], []
    for c in (c_left, np.mod(c_left + 0.5, 1.0)):
        f, lift = walk_ankle_path(c, half)
        down = h - lift
        d = np.minimum(np.hypot(f, down), 0.9999 * (lt + ls))
        knee = np.pi - np.arccos(np.clip((lt ** 2 + ls ** 2 - d ** 2) / (2 * lt * ls), -1.0, 1.0))
        thigh_pitch = np.arctan2(f, down) + np.arccos(np.clip((lt ** 2 + d ** 2 - ls ** 2) / (2 * lt * d), -1.0, 1.0))
        hips.append(np.degrees(thigh_pitch - rest_t))
        knees.append(np.degrees(knee - (rest_t - rest_s)))
    return np.array(hips), np.array(knees), h


def motion_curves(name: str, n_frames: int, fps: float = 30.0, params: MotionParams | None = None,
                  rig: "RigAxes | None" = None, times: np.ndarray | None = None) -> Motion:
    """Joint rotations of motion ``name`` over ``n_frames`` frames at ``fps``.

    Args:
        rig: hinge axes of the body's rest skeleton (:meth:`RigAxes.from_heads`); default
            those of Anny's default body.
        times: ``(n_frames,)`` the motion's time in seconds at each frame (a time warp, e.g.
            :func:`varied_tempo`); default ``k / fps``, a steady tempo.
    """
    key = canonical_motion(name)
    if key is None:
        raise ValueError(f"unknown motion {name!r} (known: {', '.join(MOTIONS)})")
    p = params or MotionParams()
    t = np.arange(n_frames, dtype=np.float64) / float(fps) if times is None else np.asarray(times, np.float64)
    if t.shape != (n_frames,):
        raise ValueError(f"times: expected shape ({n_frames},), got {t.shape}")
    phi = 2.0 * np.pi * BASE_FREQUENCY[key] * p.speed * t + p.phase
    rig = rig or RigAxes.default()
    left, right = _Side(n_frames, rig), _Side(n_frames, rig)
    central: dict[str, np.ndarray] = {}
    hop = np.zeros(n_frames)
    contact = None
    A = p.amplitude
    travels = False

    if key == "walk":
        # Leg inverse kinematics in the sagittal plane: each ankle follows a planned path
        # relative to the hip (stance: straight back along the floor at the walking speed;
        # swing: forward with a lift), so the body walks without the stance foot sliding.
        travels = True
        hip_flex, knee_flex, _ = walk_legs(phi, rig, A)
        # The stance foot, for the body's forward motion: the left one while its ankle is on the
        # floor (gait-cycle fraction below WALK_STANCE), shared smoothly in double support.
        c_left = np.mod((phi - np.pi / 2) / (2 * np.pi), 1.0)
        g = [np.where(c < WALK_STANCE, np.sin(np.pi * c / WALK_STANCE) ** 2, 0.0)
             for c in (c_left, np.mod(c_left + 0.5, 1.0))]
        contact = g[0] / (g[0] + g[1])
        for i, (side, ph) in enumerate(((left, phi), (right, phi + np.pi))):
            side.hip(flex=hip_flex[i])
            side.knee(flex=knee_flex[i])
            side.flat_foot()
            # The arm swings against the leg of the same side.
            side.shoulder(abduct=-28.0, flex=A * 18.0 * np.sin(ph + np.pi))
            side.elbow(flex=15.0 + A * 15.0 * (0.5 + 0.5 * np.sin(ph + np.pi)))
        central.update(_spine(n_frames, pitch=3.0, yaw=A * 6.0 * np.sin(phi + np.pi)))
        central["spine05"] = _axis_rotation(_Z, A * 4.0 * np.sin(phi))

    elif key == "jumping_jacks":
        # Closed (arms down, feet together) at phi = 0, open (arms overhead, feet apart) at pi;
        # in the air between (hop peaks half-way), knees soften at each landing.
        s = _ease(phi)
        land = np.cos(phi) ** 2
        for side in (left, right):
            side.hip(flex=A * 6.0 * land, abduct=A * 16.0 * s)
            side.knee(flex=A * 14.0 * land)
            side.flat_foot()
            side.shoulder(abduct=-28.0 + A * 154.0 * s)
            side.elbow(flex=12.0 + 8.0 * s)
        central.update(_spine(n_frames, pitch=A * 5.0 * land))
        hop = A * 0.07 * np.sin(phi) ** 2

    elif key == "punch":
        # Boxing guard, alternate straight punches (left then right), torso turning into each.
        pl, pr = _bump(phi, 3.0), _bump(phi + np.pi, 3.0)
        for side, e in ((left, pl), (right, pr)):
            e = A * e
            side.hip(flex=10.0)
            side.knee(flex=18.0)
            side.flat_foot()
            side.shoulder(abduct=-40.0 + 8.0 * e, flex=55.0 + 30.0 * e, adduct_h=12.0 * e)
            side.elbow(flex=115.0 - 105.0 * e)
            side.wrist(flex=-10.0)
            side.fingers(curl=1.0)
        central.update(_spine(n_frames, pitch=8.0, yaw=A * 22.0 * (pr - pl)))

    elif key == "shake_arms":
        # Arms held loosely in front and shaken: fast shoulder / elbow / wrist oscillations
        # (several harmonics of the cycle, so the motion stays periodic), a slow body sway.
        for side, off in ((left, 0.0), (right, 1.3)):
            f1, f2 = 6.0 * phi + off, 9.0 * phi + 2.0 * off
            side.hip(flex=4.0)
            side.knee(flex=8.0)
            side.flat_foot()
            side.shoulder(abduct=-20.0 + A * 9.0 * np.sin(f1), flex=35.0 + A * 10.0 * np.sin(f1 + 0.9),
                          adduct_h=A * 6.0 * np.sin(f2))
            side.elbow(flex=35.0 + A * 22.0 * np.sin(f1 - 0.7) + A * 6.0 * np.sin(f2 + 0.3))
            side.wrist(flex=A * 30.0 * np.sin(f1 - 1.4))
        central.update(_spine(n_frames, pitch=6.0, yaw=A * 4.0 * np.sin(phi), roll=A * 3.0 * np.sin(2 * phi)))

    elif key == "squat":
        # The pelvis tips forward, thighs reach about horizontal, knees go forward over the
        # feet (flat on the floor), the back leans and the arms reach forward for balance.
        s = A * _ease(phi)
        pelvis = 20.0 * s
        central["root"] = _axis_rotation(_X, pelvis)
        for side in (left, right):
            side.hip(flex=pelvis + 85.0 * s)
            side.knee(flex=110.0 * s)
            side.flat_foot(body=central["root"])
            side.shoulder(abduct=-28.0 + 18.0 * s, flex=85.0 * s)
            side.elbow(flex=10.0)
        central.update(_spine(n_frames, pitch=25.0 * s))

    elif key == "wave":
        # Right hand raised and waving from the elbow; the left arm hangs; a slight sway.
        w = np.sin(4.0 * phi)
        raise_ = 0.8 + 0.2 * np.sin(phi)  # the arm sinks and rises a little once a cycle
        left.hip(flex=2.0)
        left.flat_foot()
        left.shoulder(abduct=-28.0)
        left.elbow(flex=12.0)
        right.hip(flex=2.0)
        right.flat_foot()
        right.shoulder(abduct=-28.0 + (28.0 + A * 48.0) * raise_, flex=18.0 * raise_)
        right.elbow(flex=10.0)
        right.elbow_up(angle=raise_ * (70.0 + A * 22.0 * w))
        right.wrist(flex=A * 15.0 * w * raise_)
        central.update(_spine(n_frames, yaw=-6.0 * raise_, roll=A * 2.0 * w * raise_))

    elif key == "bend":
        # Forward bend from the hips (the whole body pitches about the root, the legs are
        # turned back upright) and the back rounds; the arms hang towards the shins.
        s = A * _ease(phi)
        body = 45.0 * s
        central["root"] = _axis_rotation(_X, body)
        for side in (left, right):
            side.hip(flex=body)
            side.knee(flex=8.0 * s)
            side.flat_foot(body=central["root"])
            side.shoulder(abduct=-30.0 + 8.0 * s, flex=35.0 * s)
            side.elbow(flex=10.0)
        central.update(_spine(n_frames, pitch=40.0 * s))
        central["neck01"] = _axis_rotation(_X, -15.0 * s)

    rotations = dict(central)
    rotations.update(left.rot)
    rotations.update(right.mirrored())
    return Motion(rotations=rotations, hop=hop, travels=travels, contact=contact, name=key, params=p)


@dataclass(frozen=True)
class RigAxes:
    """Hinge axes of a body's rest skeleton (left side, world coordinates).

    Attributes:
        elbow_axis: ``(3,)`` perpendicular to the upper arm and the front (-y); flexing about
            it bends the forearm forward.
        elbow_rest: the elbow's flexion in the rest A-pose (degrees; about 44 for Anny).
        knuckle_axis: ``(3,)`` along the knuckles (index to little finger base); curling the
            fingers about it closes the hand.
        thigh, shin: ``(2,)`` hip-to-knee and knee-to-ankle in the sagittal plane, as
            (forward, down) components (metres).
    """

    elbow_axis: np.ndarray
    elbow_rest: float
    knuckle_axis: np.ndarray
    thigh: np.ndarray = None
    shin: np.ndarray = None

    @staticmethod
    def from_heads(heads: dict[str, np.ndarray]) -> "RigAxes":
        """From rest bone-head positions ``(3,)`` of the bones in :data:`RIG_BONES`."""
        h = {k: np.asarray(v, dtype=np.float64) for k, v in heads.items()}
        arm = h["lowerarm01.L"] - h["upperarm01.L"]
        fore = h["wrist.L"] - h["lowerarm01.L"]
        axis = np.cross(arm / np.linalg.norm(arm), np.array([0.0, -1.0, 0.0]))
        cos = arm @ fore / (np.linalg.norm(arm) * np.linalg.norm(fore))
        knuckles = h["finger2-1.L"] - h["finger5-1.L"]
        thigh = h["lowerleg01.L"] - h["upperleg01.L"]
        shin = h["foot.L"] - h["lowerleg01.L"]
        return RigAxes(elbow_axis=axis / np.linalg.norm(axis),
                       elbow_rest=float(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))),
                       knuckle_axis=knuckles / np.linalg.norm(knuckles),
                       thigh=np.array([-thigh[1], -thigh[2]]), shin=np.array([-shin[1], -shin[2]]))

    @staticmethod
    def default() -> "RigAxes":
        """Those of Anny's default body."""
        return RigAxes.from_heads(DEFAULT_HEADS)


#: Rest bone heads (metres) of Anny's default body that :class:`RigAxes` needs.
DEFAULT_HEADS = {
    "upperarm01.L": (0.162, -0.017, 0.467), "lowerarm01.L": (0.329, -0.021, 0.279),
    "wrist.L": (0.446, -0.179, 0.164), "finger2-1.L": (0.473, -0.273, 0.125),
    "finger5-1.L": (0.497, -0.220, 0.098), "upperleg01.L": (0.102, -0.008, 0.039),
    "lowerleg01.L": (0.135, -0.040, -0.350), "foot.L": (0.177, -0.004, -0.749),
}
#: The bones :meth:`RigAxes.from_heads` reads.
RIG_BONES = tuple(DEFAULT_HEADS)
