"""How unlike the training frames given frames are, and prediction's guard against the unfamiliar.

A trained generator continues the motions it has seen. Given frames of a motion it never saw, it
still plays one it knows, and its prediction ends up several times further from the truth than
standing still (method.md, "Novelty guard"). The encoder's latent space tells the two apart:
frames of a new performer doing a trained motion lie within a step or so of a training frame's
latent, frames of an untrained motion several steps away.

A familiar pose can still start an untrained motion (bending forward from standing): the latent
step between the last two given frames then points where no training frame near that pose went.

- ``NoveltyReference``: the latent means of the training frames, each one's latent step from the
  training frame before it, and their typical step (the median distance between the latents of
  consecutive training frames), stored with a checkpoint.
- ``novelty``: each frame's distance to the nearest training latent, in typical steps.
- ``guard_weight``: 1 up to ``GUARD_START`` steps, 0 from ``GUARD_END``, linear between.
- ``direction_familiarity``: how well the given frames' last latent step lines up with the steps of
  the training frames nearest the last pose (the largest cosine); ``direction_weight``: 1 from
  ``DIRECTION_END``, 0 up to ``DIRECTION_START``, linear between; ``heading_weight``: the two for the
  last step of a run of latents.
- ``training_pace``: the given frames' latent pace over the pace of the training frames nearest them.
- ``fallback``: what prediction falls back to: the last given frame held (one given frame), or
  its velocity continued and damped by ``FALLBACK_DECAY`` a frame (two), by the given frames' own
  slowing where they slow faster, stopped where they turned back (three or more: ``own_decay``).
- ``guarded``: the roll-out blended towards the fallback by the weight.

Arrays in, arrays out; nothing here loads, trains or prints.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

#: novelty (in typical training steps) up to which prediction is the model's own
GUARD_START = 2.0
#: novelty from which prediction is the fallback alone
GUARD_END = 4.0
#: cosine from which a given step's direction counts as one training shows at that pose
DIRECTION_END = 0.95
#: cosine up to which it counts as a motion training never shows there (prediction: the fallback)
DIRECTION_START = 0.8
#: a latent step below this many typical steps is a pose held (float rounding, no direction)
HELD = 1e-3
#: training frames nearest the given pose whose steps the given step is compared with
DIRECTION_NEIGHBOURS = 20
#: training frames nearest each given pose whose step sizes set the pace expected there
PACE_NEIGHBOURS = 5
#: the share of the training's pace from which the given frames count as moving at it (the ratio of
#: two step sizes scatters around 1 on a steady motion; without this margin it slows one a little)
PACE_FULL = 0.9
#: a frame's share of the previous frame's velocity in the fallback of two or more given frames
FALLBACK_DECAY = 0.9
#: training frames kept in a reference (evenly spaced beyond it)
MAX_REFERENCE_FRAMES = 4096
_ENCODE_BATCH = 32


@dataclass(frozen=True)
class NoveltyReference:
    """``latents`` ``(N, L)`` float32: latent means of training frames; ``step`` > 0: the median
    latent distance between consecutive training frames; ``steps`` ``(N, L)`` float32: each frame's
    latent change from the training frame before it (a sequence's first frame: to the one after),
    or None (a run stored before they were kept: no direction check)."""

    latents: np.ndarray
    step: float
    steps: np.ndarray | None = None


def reference_latents(encode: Callable[[np.ndarray], np.ndarray], sequences: list[np.ndarray],
                      max_frames: int = MAX_REFERENCE_FRAMES) -> NoveltyReference:
    """The reference of training ``sequences`` (each ``(T_i, V, C)`` scaled features, T_i >= 1;
    at least one with two frames), ``encode``: frames ``(B, V, C)`` -> latent means ``(B, L)``."""
    latents, steps = [], []
    for seq in sequences:
        z = np.concatenate([np.asarray(encode(seq[i:i + _ENCODE_BATCH]), dtype=np.float32)
                            for i in range(0, len(seq), _ENCODE_BATCH)])
        latents.append(z)
        d = np.diff(z, axis=0)
        steps.append(np.concatenate([d[:1], d]) if len(d) else np.zeros_like(z))  # frame 0: to frame 1
    sizes = np.concatenate([np.linalg.norm(d[1:], axis=1) for d in steps])
    if sizes.size == 0:
        raise ValueError("a novelty reference needs a sequence of at least two frames")
    z, d = np.concatenate(latents), np.concatenate(steps)
    step = float(np.median(sizes))
    if len(z) > max_frames:
        keep = np.linspace(0, len(z) - 1, max_frames).round().astype(np.int64)
        z, d = z[keep], d[keep]
    return NoveltyReference(np.ascontiguousarray(z), step if step > 0 else 1.0, np.ascontiguousarray(d))


def novelty(latents: np.ndarray, reference: NoveltyReference) -> np.ndarray:
    """Distance of each latent ``(..., L)`` to the nearest reference latent, in typical steps ``(...)``."""
    z = np.asarray(latents)
    d2 = _nearest(z.reshape(-1, z.shape[-1]), reference)
    return (np.sqrt(d2.min(axis=1)) / reference.step).reshape(z.shape[:-1])


def _nearest(latents: np.ndarray, reference: NoveltyReference) -> np.ndarray:
    """Squared distances ``(B, N)`` of latents ``(B, L)`` to every reference latent."""
    z = np.asarray(latents, dtype=np.float64)
    ref = reference.latents.astype(np.float64)
    return np.maximum((z * z).sum(1)[:, None] - 2.0 * z @ ref.T + (ref * ref).sum(1)[None], 0.0)


def direction_familiarity(last: np.ndarray, previous: np.ndarray, reference: NoveltyReference,
                          neighbours: int = DIRECTION_NEIGHBOURS) -> np.ndarray:
    """The largest cosine ``(B,)`` between the step ``last - previous`` (latents ``(B, L)``) and the
    steps of the ``neighbours`` reference frames nearest ``last`` (a reference frame without a step,
    from a one-frame sequence, lines up with none); 1 where the given step is zero (a held pose goes
    nowhere training did not; below ``HELD`` typical steps it is rounding, not a direction).
    ``reference.steps`` must be present."""
    step = np.asarray(last, dtype=np.float64) - np.asarray(previous, dtype=np.float64)
    k = min(int(neighbours), len(reference.latents))
    near = np.argpartition(_nearest(last, reference), k - 1, axis=1)[:, :k]  # (B, k)
    theirs = reference.steps.astype(np.float64)[near]  # (B, k, L)
    size = np.linalg.norm(step, axis=1)
    cos = (theirs * step[:, None]).sum(-1) / np.maximum(np.linalg.norm(theirs, axis=-1) * size[:, None], 1e-30)
    return np.where(size > HELD * reference.step, cos.max(axis=1), 1.0)


def training_pace(latents: np.ndarray, reference: NoveltyReference, neighbours: int = PACE_NEIGHBOURS,
                  full: float = PACE_FULL) -> np.ndarray:
    """``(B,)`` in [0, 1]: the mean latent step of given frames ``latents`` ``(B, U, L)``, U >= 2, over
    ``full`` times the mean step size of the ``neighbours`` training frames nearest each given frame
    after the first (``reference.steps`` must be present). 0 for a pose held still, 1 for a motion at
    least ``full`` as fast as training moves at those poses: at the turn of a swing the training
    frames there move little too, so a turn is not taken for a slow-down."""
    z = np.asarray(latents, dtype=np.float64)
    bsz, u, size = z.shape
    given = np.linalg.norm(np.diff(z, axis=1), axis=-1).mean(1)
    k = min(int(neighbours), len(reference.latents))
    near = np.argpartition(_nearest(z[:, 1:].reshape(-1, size), reference), k - 1, axis=1)[:, :k]
    step_sizes = np.linalg.norm(reference.steps.astype(np.float64), axis=1)[near]  # (B * (U - 1), k)
    expected = step_sizes.mean(1).reshape(bsz, u - 1).mean(1)
    return np.minimum(given / np.maximum(full * expected, 1e-12 * reference.step), 1.0)


def direction_weight(cos: np.ndarray, start: float = DIRECTION_START, end: float = DIRECTION_END) -> np.ndarray:
    """The model's share of a prediction whose given step has ``direction_familiarity`` ``cos``."""
    return np.clip((np.asarray(cos, dtype=np.float64) - start) / (end - start), 0.0, 1.0)


def heading_weight(latents: np.ndarray, reference: NoveltyReference) -> np.ndarray:
    """``(B,)``: ``direction_weight`` of the last step of latents ``(B, U, L)``, U >= 2 (whether it heads
    where training went from that pose; ``reference.steps`` must be present)."""
    return direction_weight(direction_familiarity(latents[:, -1], latents[:, -2], reference))


def guard_weight(nov: np.ndarray, start: float = GUARD_START, end: float = GUARD_END) -> np.ndarray:
    """The model's share of a prediction at novelty ``nov``: 1 up to ``start``, 0 from ``end``."""
    return np.clip((end - np.asarray(nov, dtype=np.float64)) / (end - start), 0.0, 1.0)


def own_decay(given: np.ndarray, decay: float = FALLBACK_DECAY) -> np.ndarray:
    """The damping ``(B,)`` of the fallback after given ``(B, U, V, C)``, U >= 2: ``decay``, and
    with U >= 3 at most the given frames' own ratio of their last step's size to the one before
    (a slowing motion keeps slowing at its rate), 0 where those two steps point apart (cosine
    below 0: the motion has turned back)."""
    x = np.asarray(given, dtype=np.float64)
    d = np.full(len(x), float(decay))
    if x.shape[1] < 3:
        return d
    last = (x[:, -1] - x[:, -2]).reshape(len(x), -1)
    before = (x[:, -2] - x[:, -3]).reshape(len(x), -1)
    size_last, size_before = np.linalg.norm(last, axis=1), np.linalg.norm(before, axis=1)
    d = np.minimum(d, size_last / np.maximum(size_before, 1e-30))
    return np.where((last * before).sum(1) < 0.0, 0.0, d)


def fallback_reach(given: np.ndarray, n_frames: int, decay: float = FALLBACK_DECAY,
                   own_pace: bool = True) -> np.ndarray:
    """``(B, n)``: how many of the last given step ``fallback`` has added by each frame after given
    ``(B, U, V, C)``, U >= 2 (a share ``decay``, or with ``own_pace`` ``own_decay``'s, kept each frame)."""
    x = np.asarray(given)
    d = own_decay(x, decay) if own_pace else np.full(len(x), float(decay))
    return np.cumsum(d[:, None] ** np.arange(int(n_frames))[None], axis=1)


def fallback(given: np.ndarray, n_frames: int, decay: float = FALLBACK_DECAY, own_pace: bool = True) -> np.ndarray:
    """``(B, n, V, C)`` frames after given ``(B, U, V, C)``: the last held (U = 1), else its
    velocity continued with a share of it kept each frame: ``decay``, or with ``own_pace`` the
    given frames' own (``own_decay``)."""
    x = np.asarray(given)
    last = x[:, -1:]
    if x.shape[1] < 2:
        return np.repeat(last, int(n_frames), axis=1)
    reach = fallback_reach(x, n_frames, decay, own_pace)
    return last + reach.astype(x.dtype)[:, :, None, None] * (x[:, -1:] - x[:, -2:-1])


def guarded(frames: np.ndarray, given: np.ndarray, weight: np.ndarray) -> np.ndarray:
    """Generated ``frames`` ``(B, n, V, C)`` blended towards ``fallback(given, n)`` by ``weight``
    ``(B,)`` (1: the frames unchanged; 0: the fallback)."""
    w = np.asarray(weight, dtype=np.float64)
    rows = np.flatnonzero(w < 1.0)  # the others stay bit for bit the roll-out
    if len(rows) == 0:
        return frames
    base = fallback(np.asarray(given)[rows], frames.shape[1])
    out = frames.copy()
    out[rows] = base + w[rows].astype(frames.dtype)[:, None, None, None] * (frames[rows] - base)
    return out
