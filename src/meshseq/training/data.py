"""The training data: features of the data sets (``TrainingData``), and the windows an iteration
trains on (``training_windows``), with the window fitted to short sequences (``fit_window``)."""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
import torch

from meshseq.data.windows import Split, WindowSampler, fitted_window
from meshseq.errors import MeshseqError
from meshseq.training.config import TrainConfig


@dataclass
class TrainingData:
    """Raw ACAP features of one or more data sets sharing one connectivity.

    ``features[d]`` ``(T_d, V, 9)`` float64; ``reference`` ``(V, 3)`` the mesh the features
    refer to (first frame of the first data set); ``faces`` ``(F, 3)`` int64; ``vertices[d]``
    ``(T_d, V, 3)`` the frames themselves where they were loaded (None for features given alone),
    which completion's vertex share is fitted on (``meshseq.inbetween``).
    """

    names: list[str]
    sources: list[str]
    features: list[np.ndarray]
    faces: np.ndarray
    reference: np.ndarray
    consistency: str = TrainConfig.consistency  # the rotation consistency the features were extracted with
    placement: str = TrainConfig.placement  # what the placement channels (several parts) measure from: acap.parts
    vertices: list[np.ndarray] | None = None

    @property
    def n_vertices(self) -> int:
        return int(self.reference.shape[0])


def load_training_data(specs: list[str], consistency: str | None = None, placement: str | None = None) -> TrainingData:
    """Load sequences (``meshseq.io.load_sequence``) and extract features against one reference
    (``consistency``: the rotation consistency, default ``TrainConfig.consistency``'s; ``placement``:
    what a multi-part mesh's placement channels measure from, default ``TrainConfig.placement``'s).

    MeshseqError if the data sets do not share one connectivity.
    """
    from meshseq import acap
    from meshseq.io import load_sequence

    if not specs:
        raise MeshseqError("no training data given")
    seqs = [load_sequence(s) for s in specs]
    first = seqs[0]
    for spec, s in zip(specs[1:], seqs[1:]):
        if s.n_vertices != first.n_vertices or s.faces.shape != first.faces.shape or not np.array_equal(
            s.faces, first.faces
        ):
            raise MeshseqError(
                f"{spec}: connectivity differs from {specs[0]} ({s.n_vertices} vertices, {s.n_faces} faces "
                f"vs {first.n_vertices} vertices, {first.n_faces} faces); data sets trained together "
                "must share one mesh connectivity"
            )
    reference = first.vertices[0].copy()
    from meshseq.acap.parts import check_reference_parts
    from meshseq.mesh import Topology

    check_reference_parts(reference, Topology.from_faces(first.faces, first.n_vertices), f"{specs[0]} frame 0")
    placement = TrainConfig.placement if placement is None else placement
    consistency = TrainConfig.consistency if consistency is None else consistency
    feats = [acap.extract(s.vertices, s.faces, reference=reference, consistency=consistency, placement_mode=placement)
             for s in seqs]
    return TrainingData([s.name for s in seqs], [str(sp) for sp in specs], feats, first.faces, reference, consistency,
                        placement, [s.vertices for s in seqs])


def step_spread(scaled: list[np.ndarray], splits: list[Split], stride: int = 1) -> np.ndarray:
    """Root mean square per channel ``(C,)`` of the frame-to-frame changes ``X_{t+stride} - X_t`` of
    scaled features ``[(T_d, V, C)]`` inside the training segments (the ``data`` step scale).

    Channels that never change get the mean of the others (or 1), so every factor is positive.
    """
    sums, count = 0.0, 0
    for x, split in zip(scaled, splits):
        for a, b in split.train:
            seg = np.asarray(x[a:b], dtype=np.float64)
            if len(seg) > stride:
                d = seg[stride:] - seg[:-stride]
                sums = sums + np.square(d).sum(axis=(0, 1))
                count += d.shape[0] * d.shape[1]
    if count == 0:
        raise MeshseqError(f"--step-scale data: no training segment is longer than --stride {stride}")
    rms = np.sqrt(np.asarray(sums) / count)
    good = rms > 1e-8
    return np.where(good, rms, rms[good].mean() if good.any() else 1.0)



def fit_window(config: TrainConfig, splits: list[Split], log=lambda msg: None) -> TrainConfig:
    """``config`` with its window shortened by ``fitted_window`` to the training segments of
    ``splits`` (the same config when it already fits); says so through ``log``."""
    lengths = [b - a for s in splits for a, b in s.train]
    window = fitted_window(lengths, config.window, config.batch, config.stride)
    if window == config.window:
        return config
    if not config.given < window:
        raise MeshseqError(f"given {config.given}: the training frames hold only windows of {window} frames "
                           f"(--window {config.window} shortened to a batch of {config.batch} starts); "
                           'use a smaller given or window_fit = "none" (--config)')
    log(f"--window {config.window}: the training frames hold fewer than a batch ({config.batch}) of different "
        f"windows of {config.window} frames; training on windows of {window} frames (window_fit = \"none\" in "
        f"--config keeps {config.window})")
    return replace(config, window=window)


def gather_frames(frames: torch.Tensor, rows: torch.Tensor) -> torch.Tensor:
    """``frames[rows]``: ``(T, ...)`` frames at indices ``rows`` (any shape) -> ``rows.shape + (...)``,
    as one ``index_select`` (a row copy each: 5.4 against 10.8 ms for advanced indexing, 8 x 32
    frames of the horse)."""
    return frames.index_select(0, rows.reshape(-1)).view(*rows.shape, *frames.shape[1:])


def training_windows(frames: torch.Tensor, sampler: WindowSampler, rng: np.random.Generator,
                     config: TrainConfig, share: slice = slice(None)) -> tuple[torch.Tensor, torch.Tensor | None]:
    """This process's ``share`` of one iteration's ``(batch, window, V, 9)`` windows of the
    stacked ``(T, V, 9)`` frames (every process draws the whole batch, so the generators stay in
    step); with ``speed_augment > 1`` played at random speeds (``WindowSampler.sample_at_speeds``),
    with ``tempo_augment > 0`` that share of them with a changing tempo (``sample_at_tempos``),
    each frame the linear interpolation of the two frames around its position.
    Returns ``(windows, rows)``, ``rows`` ``(batch, window)`` the frames' indices (None for windows
    played at other speeds: their frames are interpolations)."""
    def rows(r: np.ndarray) -> torch.Tensor:
        return gather_frames(frames, torch.from_numpy(r[share]).to(frames.device))

    if config.speed_augment <= 1 and config.tempo_augment <= 0:
        r = sampler.sample(rng, config.batch)
        return rows(r), torch.from_numpy(r[share])
    if config.tempo_augment > 0:
        before, after, weight = sampler.sample_at_tempos(rng, config.batch, config.tempo_augment)
    else:
        before, after, weight = sampler.sample_at_speeds(rng, config.batch, config.speed_augment)
    w = torch.from_numpy(weight[share]).to(frames.device, frames.dtype)[..., None, None]
    return torch.lerp(rows(before), rows(after), w), None

