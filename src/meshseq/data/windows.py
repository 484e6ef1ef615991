"""Held-out splits and training windows over feature sequences (numpy only).

A data set of T frames is split into one contiguous held-out block (``holdout`` of the frames,
starting at ``at``) and the training frames around it (one or two segments). Optionally the last
``validation`` of the training frames (the end of the last training segment) become a validation
block: never trained on, measured during training to choose a checkpoint without looking at the
held-out block. A window is
``window`` frames ``start, start + stride, ..., start + (window - 1) stride`` that lie inside one
segment; every such window of every data set is equally likely. With a speed augmentation
(``WindowSampler.sample_at_speeds``) a window is played faster or slower: its frames lie at
fractional positions of one segment, each the linear interpolation of the two frames around it.
"""

from __future__ import annotations

import math

from dataclasses import dataclass

import numpy as np

from meshseq.errors import MeshseqError


@dataclass(frozen=True)
class Split:
    """Frame ranges of one data set: ``train`` segments, the ``heldout`` block and the
    ``validation`` block (None unless asked for), as [start, stop)."""

    n_frames: int
    train: tuple[tuple[int, int], ...]
    heldout: tuple[int, int]
    validation: tuple[int, int] | None = None

    def to_dict(self) -> dict:
        d = {"n_frames": self.n_frames, "train": [list(s) for s in self.train], "heldout": list(self.heldout)}
        if self.validation is not None:
            d["validation"] = list(self.validation)
        return d

    @staticmethod
    def from_dict(d: dict) -> "Split":
        val = d.get("validation")
        return Split(int(d["n_frames"]), tuple(tuple(int(v) for v in s) for s in d["train"]),
                     tuple(int(v) for v in d["heldout"]), None if val is None else tuple(int(v) for v in val))

    def train_frames(self) -> np.ndarray:
        """Indices ``(T_train,)`` of the training frames."""
        return np.concatenate([np.arange(a, b) for a, b in self.train] or [np.zeros(0, np.int64)])


def check_holdout(holdout: float, at: str | float) -> float | None:
    """MeshseqError unless ``holdout`` is a fraction in [0, 1) and ``at`` is ``"start"``,
    ``"end"`` or a fraction in [0, 1]; returns ``at`` as a number (None for start/end)."""
    if not isinstance(holdout, (int, float)) or not 0.0 <= holdout < 1.0:
        raise MeshseqError(f"--holdout {holdout}: expected a fraction in [0, 1)")
    if at in ("start", "end"):
        return None
    try:
        frac = float(at)
    except (TypeError, ValueError):
        frac = math.nan
    if not 0.0 <= frac <= 1.0:
        raise MeshseqError(f"--holdout-at {at!r}: expected 'start', 'end' or a fraction in [0, 1]")
    return frac


def check_validation(validation: float) -> None:
    """MeshseqError unless ``validation`` is a fraction in [0, 1)."""
    if isinstance(validation, bool) or not isinstance(validation, (int, float)) or not 0.0 <= validation < 1.0:
        raise MeshseqError(f"--validation {validation}: expected a fraction in [0, 1)")


def split_frames(n_frames: int, holdout: float = 0.2, at: str | float = "end", validation: float = 0.0) -> Split:
    """One contiguous held-out block of ``round(holdout * n_frames)`` frames.

    ``at``: ``"end"`` (default), ``"start"``, or a fraction in [0, 1] of the sequence where the
    block starts (clipped so that it fits). ``holdout = 0`` holds nothing out.
    ``validation`` > 0: the last ``max(2, round(validation * training frames))`` frames of the
    last training segment become the validation block (just before an end held-out block);
    MeshseqError if that leaves the segment without a frame.
    """
    check_validation(validation)
    frac = check_holdout(holdout, at)
    n_hold = int(round(holdout * n_frames))
    if at == "end":
        start = n_frames - n_hold
    elif at == "start":
        start = 0
    else:
        start = min(int(round(frac * n_frames)), n_frames - n_hold)
    stop = start + n_hold
    train = tuple((a, b) for a, b in ((0, start), (stop, n_frames)) if b > a)
    if not validation:
        return Split(n_frames, train, (start, stop))
    n_val = max(2, int(round(validation * sum(b - a for a, b in train))))
    if not train or train[-1][1] - train[-1][0] <= n_val:
        longest = train[-1][1] - train[-1][0] if train else 0
        raise MeshseqError(f"--validation {validation}: a validation block of {n_val} frames leaves no training "
                           f"frame in a training part of {longest} frames (of {n_frames}); use a smaller "
                           "--validation or --holdout")
    a, b = train[-1]
    return Split(n_frames, train[:-1] + ((a, b - n_val),), (start, stop), (b - n_val, b))


def window_span(window: int, stride: int) -> int:
    """Raw frames covered by one window."""
    return (window - 1) * stride + 1


def window_starts(segments, window: int, stride: int = 1) -> np.ndarray:
    """All valid windows ``(N, 2)`` rows ``(dataset, start frame)``.

    ``segments``: iterable of ``(dataset index, start, stop)``.
    """
    span = window_span(window, stride)
    rows = [
        np.stack([np.full(max(b - a - span + 1, 0), d), np.arange(a, max(b - span + 1, a))], 1)
        for d, a, b in segments
    ]
    return np.concatenate(rows).astype(np.int64) if rows else np.zeros((0, 2), np.int64)


#: ``fitted_window`` never shortens a window below this many frames (the paper's longest
#: evaluated horizon, 15 steps from one given frame), unless no longer window fits at all.
MIN_FITTED_WINDOW = 16


def fitted_window(lengths, window: int, batch: int, stride: int = 1) -> int:
    """The window length to train on: ``window``, shortened until the training segments of
    ``lengths`` frames hold at least ``batch`` different windows (the window rule of the default
    recipe, ``TrainConfig.window_fit = "batch"``).

    With fewer different windows than a batch, every batch repeats the same few starts and the
    model never learns to predict from the phases between them (horse-gallop: one window of 32
    fits its 29 training frames; docs/method.md, "A window that fits the data"). Never below
    ``MIN_FITTED_WINDOW`` frames while a window that long fits; below that, the longest window that fits at all; ``window``
    unchanged if already enough windows fit, or if no window of 2 frames fits (the sampler then
    says why).
    """
    lengths = [int(n) for n in lengths]

    def count(w: int) -> int:
        span = window_span(w, stride)
        return sum(max(n - span + 1, 0) for n in lengths)

    if count(window) >= batch:
        return window
    floor = min(window, MIN_FITTED_WINDOW)
    for w in range(window - 1, floor - 1, -1):
        if count(w) >= batch:
            return w
    for w in range(floor, 1, -1):
        if count(w) >= 1:
            return w
    return window


#: Tempo levels of ``WindowSampler.sample_at_tempos`` (0 holds the pose).
TEMPO_LEVELS = (0.0, 0.25, 0.5, 1.0, 1.0, 1.5)


class WindowSampler:
    """Draws batches of training windows from several data sets stacked along frames.

    ``offsets[d]`` is the row of data set ``d``'s first frame in the stacked feature array;
    ``frame_index(batch)`` gives ``(batch, window)`` rows of that array.
    """

    def __init__(self, splits: list[Split], names: list[str], window: int, stride: int = 1):
        if window < 2:
            raise MeshseqError(f"--window {window}: a window needs at least 2 frames")
        if stride < 1:
            raise MeshseqError(f"--stride {stride}: expected a positive integer")
        self.window, self.stride = window, stride
        self.offsets = np.concatenate([[0], np.cumsum([s.n_frames for s in splits])[:-1]]).astype(np.int64)
        segs = [(d, a, b) for d, s in enumerate(splits) for a, b in s.train]
        self.starts = window_starts(segs, window, stride)
        # [first, stop) of the segment each window lies in (for sample_at_speeds)
        self.segment_bounds = np.concatenate(
            [np.tile([a, b], (max(b - a - window_span(window, stride) + 1, 0), 1)) for _, a, b in segs]
            or [np.zeros((0, 2))]).astype(np.int64)
        if len(self.starts) == 0:
            longest = max((b - a for _, a, b in segs), default=0)
            raise MeshseqError(
                f"--window {window} --stride {stride} needs {window_span(window, stride)} consecutive "
                f"training frames but the longest training part of {', '.join(names)} has {longest}; "
                "use a shorter --window, --stride 1 or a smaller --holdout"
            )

    def rows(self, picks: np.ndarray) -> np.ndarray:
        """``(N,)`` window numbers -> ``(N, window)`` rows of the stacked frames."""
        d, a = self.starts[picks, 0], self.starts[picks, 1]
        return self.offsets[d][:, None] + a[:, None] + self.stride * np.arange(self.window)[None, :]

    def sample(self, rng: np.random.Generator, batch: int) -> np.ndarray:
        """``batch`` windows drawn uniformly with replacement -> ``(batch, window)`` row indices."""
        return self.rows(rng.integers(0, len(self.starts), size=batch))

    def sample_at_speeds(self, rng: np.random.Generator, batch: int,
                         max_speed: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``batch`` windows played at random speeds (a temporal-resampling augmentation).

        Each window's segment is drawn as by ``sample`` (in proportion to its windows); its speed
        ``s`` log-uniformly in ``[1 / max_speed, max_speed]`` and lowered where the window would not
        fit in the segment; its first position uniformly where it fits. Frame ``k`` lies at the
        fractional position ``p_k = first + s * stride * k``. Returns ``(before, after, weight)``,
        each ``(batch, window)``: rows of the stacked frames around ``p_k`` and ``p_k``'s fraction,
        so frame ``k`` is ``(1 - weight) * frames[before] + weight * frames[after]``.
        """
        picks = rng.integers(0, len(self.starts), size=batch)
        log_max = math.log(max_speed)
        speed = np.exp(rng.uniform(-log_max, log_max, size=batch))
        first, stop = self.segment_bounds[picks, 0], self.segment_bounds[picks, 1]
        room = (stop - 1 - first).astype(np.float64)  # the longest span a window can cover
        steps = (self.window - 1) * self.stride
        speed = np.minimum(speed, room / steps)
        start = first + rng.uniform(0.0, 1.0, size=batch) * (room - speed * steps)
        pos = start[:, None] + (speed * self.stride)[:, None] * np.arange(self.window)[None, :]
        return self._frames_around(picks, pos, first, stop)


    def sample_at_tempos(self, rng: np.random.Generator, batch: int,
                         share: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``batch`` windows, a ``share`` of them played with a changing tempo (holds, slow-downs
        to a stop, speed-ups: a temporal-resampling augmentation that shows the chains paces,
        and changes of pace, the data may lack).

        A window's tempo (frames of the data per frame of the window, at ``stride``) moves from
        level ``a`` to level ``b`` (each from ``TEMPO_LEVELS``; 0 holds the pose) over a linear
        ramp at a random place, and is shrunk where the window would not fit in its segment; the
        other windows keep tempo 1 (their frames exactly). Returns ``(before, after, weight)`` as
        ``sample_at_speeds`` does, each ``(batch, window)``.
        """
        picks = rng.integers(0, len(self.starts), size=batch)
        steps = self.window - 1
        tempo = np.ones((batch, steps))
        varied = rng.uniform(size=batch) < share
        m = int(varied.sum())
        if m:
            a, b = (np.asarray(TEMPO_LEVELS)[rng.integers(0, len(TEMPO_LEVELS), size=(2, m))])
            start = rng.uniform(-0.25, 1.0, size=m) * steps
            length = rng.uniform(0.0, 0.5, size=m) * steps + 1e-9
            k = np.arange(steps)[None, :] + 0.5
            ramp = np.clip((k - start[:, None]) / length[:, None], 0.0, 1.0)
            tempo[varied] = a[:, None] + (b - a)[:, None] * ramp
        first, stop = self.segment_bounds[picks, 0], self.segment_bounds[picks, 1]
        room = (stop - 1 - first).astype(np.float64)
        span = tempo.sum(1) * self.stride
        tempo *= np.minimum(1.0, room / np.maximum(span, 1e-12))[:, None]
        span = tempo.sum(1) * self.stride
        own = self.starts[picks, 1].astype(np.float64)  # exact windows start where they were drawn
        start = np.where(varied, first + rng.uniform(0.0, 1.0, size=batch) * (room - span), own)
        pos = start[:, None] + self.stride * np.concatenate([np.zeros((batch, 1)), np.cumsum(tempo, 1)], 1)
        # summed tempos land a hair below whole frames: the nudge keeps exact windows exact
        return self._frames_around(picks, pos, first, stop, nudge=1e-9)

    def _frames_around(self, picks: np.ndarray, pos: np.ndarray, first: np.ndarray, stop: np.ndarray,
                       nudge: float = 0.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Fractional positions ``pos`` ``(B, window)`` in the segments ``[first, stop)`` of windows
        ``picks`` -> ``(before, after, weight)``: rows of the stacked frames around each position
        and its fraction between them."""
        pos = np.clip(pos, first[:, None], (stop - 1)[:, None])
        before = np.floor(pos + nudge).astype(np.int64)
        after = np.minimum(before + 1, (stop - 1)[:, None])
        offset = self.offsets[self.starts[picks, 0]][:, None]
        return offset + before, offset + after, np.clip(pos - before, 0.0, 1.0)


def heldout_rows(splits: list[Split], window: int, stride: int = 1, per_set: int = 4) -> np.ndarray:
    """Fixed evaluation windows ``(N, w)`` from the held-out blocks (rows of the stacked frames).

    ``w = min(window, frames the shortest block can hold at this stride)``; up to ``per_set``
    evenly spaced windows per data set. Empty ``(0, 0)`` when nothing is held out (or a block is
    shorter than 2 frames at this stride).
    """
    lens = [s.heldout[1] - s.heldout[0] for s in splits]
    if not lens or min(lens) < 1 + stride:
        return np.zeros((0, 0), np.int64)
    w = min(window, (min(lens) - 1) // stride + 1)
    span = window_span(w, stride)
    offsets = np.concatenate([[0], np.cumsum([s.n_frames for s in splits])[:-1]])
    out = []
    for off, s in zip(offsets, splits):
        a, b = s.heldout
        starts = np.unique(np.linspace(a, b - span, num=per_set).round().astype(np.int64))
        out.append(off + starts[:, None] + stride * np.arange(w)[None, :])
    return np.concatenate(out).astype(np.int64)
