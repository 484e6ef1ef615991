"""L_vertex: the error of generated frames measured on the vertices they reconstruct to.

Not in the paper (its losses are all in the scaled feature space). The feature loss weighs every
vertex and channel alike, but the vertex error the evaluation reports does not: on horse-gallop a
4 x better feature fit gave no better vertex error (docs/method.md, "A vertex term"), because a
few outlier vertices set the S channels' range and because coherent rotation errors over a limb
add up along it. This term reconstructs generated and true frames
with the differentiable torch reconstruction (the same linear solve as evaluation) and compares
the vertices::

    L_vertex = unit * mean_chains mean_{i in picked frames} ||P(S_i) - P(X_i)||^2

``P``: scaled features -> centred vertices (``TorchReconstructor`` after ``Scaling.invert``); the
truth's vertices are reconstructed from its features too, so a perfect roll-out costs 0.
``||.||^2`` sums over vertices and xyz. ``unit`` (``vertex_unit``) converts squared vertex
distance into the feature loss's units: the mean squared frame-to-frame change of the training
frames in scaled features over the same in vertices, so that zero velocity costs about as much in
L_vertex as in L_rec on every data set and one weight fits every mesh size and scale.

Reconstruction costs a sparse solve per frame, so only ``frames`` evenly spaced frames of each
chain are measured (the last always among them): ``picked_frames``.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import nn


def picked_frames(n: int, frames: int) -> list[int]:
    """Indices in ``1..n-1`` of ``frames`` evenly spaced frames of an ``n``-frame chain, the last
    (``n - 1``) always included; all of them when ``frames >= n - 1``."""
    if frames >= n - 1:
        return list(range(1, n))
    picks = np.linspace(n - 1, 1, frames).round().astype(int)
    return sorted({int(i) for i in picks})


def vertex_unit(scaled: list[np.ndarray], vertices: list[np.ndarray], segments: list[list[tuple[int, int]]]) -> float:
    """Squared scaled-feature change per squared vertex change of consecutive training frames.

    Args:
        scaled: scaled features ``[(T_d, V, 9)]``.
        vertices: centred reconstructed vertices ``[(T_d, V, 3)]`` of the same frames.
        segments: per data set, the ``(start, stop)`` frame ranges used for training.
    """
    feat, vert = 0.0, 0.0
    for x, p, segs in zip(scaled, vertices, segments):
        for a, b in segs:
            if b - a < 2:
                continue
            feat += float(np.square(np.diff(np.asarray(x[a:b], dtype=np.float64), axis=0)).sum())
            vert += float(np.square(np.diff(np.asarray(p[a:b], dtype=np.float64), axis=0)).sum())
    if not (vert > 0 and feat > 0):
        return 1.0  # no motion in the training frames: nothing to calibrate against
    return feat / vert


class VertexLoss(nn.Module):
    """``forward(generated, truth)``: scaled frames ``(B, n, V, 9)`` -> L_vertex (scalar).

    Args:
        reconstructor: a ``TorchReconstructor`` of the training reference (float32).
        scaling: the run's ``Scaling``.
        unit: ``vertex_unit`` of the training data.
        frames: frames measured per chain (``picked_frames``).
    """

    #: the most bytes ``cache_targets`` keeps (the reconstructed vertices of all training frames)
    CACHE_BYTES = 512 * 2**20

    def __init__(self, reconstructor: nn.Module, scaling, unit: float, frames: int):
        super().__init__()
        self.reconstructor = reconstructor
        self.scaling = scaling
        self.unit = float(unit)
        self.frames = int(frames)
        self.targets: torch.Tensor | None = None  # (T, V, 3), see cache_targets

    def _vertices(self, scaled: torch.Tensor) -> torch.Tensor:
        B, k, V, C = scaled.shape
        return self.reconstructor(self.scaling.invert(scaled).reshape(B * k, V, C))

    def cache_targets(self, frames: torch.Tensor, batch: int = 64) -> bool:
        """Reconstruct the truth's vertices of every training frame once: ``frames`` ``(T, V, 9)``
        (scaled, the rows that ``forward``'s ``rows`` index), kept as ``targets`` ``(T, V, 3)``, so
        that an iteration indexes them instead of solving for the truth's picked frames again
        (about a quarter of L_vertex's time on the horse). The same arithmetic, frame by frame.
        False (nothing kept) when they would take more than ``CACHE_BYTES``."""
        T, V = frames.shape[:2]
        self.targets = None
        if T * V * 3 * 4 > self.CACHE_BYTES:
            return False
        with torch.no_grad(), torch.autocast(frames.device.type, enabled=False):
            self.targets = torch.cat([self._vertices(frames[a:a + batch].float()[None])
                                      for a in range(0, T, batch)])
        return True

    def forward(self, generated: torch.Tensor, truth: torch.Tensor, rows: torch.Tensor | None = None) -> torch.Tensor:
        """``rows`` ``(B, n)``: the training frames ``truth`` holds (its ``cache_targets`` rows),
        when known and cached; otherwise the truth's picked frames are reconstructed."""
        pick = self.picks(generated.shape[1])
        return self.of_picked(generated[:, pick], truth, rows)

    def picks(self, n: int) -> list[int]:
        """The frames of an ``n``-frame chain this loss measures (``picked_frames``)."""
        return picked_frames(n, self.frames)

    def of_picked(self, ours: torch.Tensor, truth: torch.Tensor, rows: torch.Tensor | None = None) -> torch.Tensor:
        """``forward`` given the generated chains' picked frames only: ``ours`` ``(B, k, V, 9)``, the
        frames ``picks(n)`` of chains over ``truth`` ``(B, n, V, 9)`` (training picks them from the
        roll-out's frames without stacking the others)."""
        pick = self.picks(truth.shape[1])
        # in float32 whatever the training precision: the solver takes float32 only
        with torch.autocast(ours.device.type, enabled=False):
            if rows is not None and self.targets is not None:
                target = self.targets[rows[:, pick].to(self.targets.device)].flatten(0, 1)
            else:
                with torch.no_grad():
                    target = self._vertices(truth[:, pick].float())
            ours = self._vertices(ours.float())
            return self.unit * (ours - target).square().sum((-2, -1)).mean()
