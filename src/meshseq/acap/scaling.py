"""Scaling of ACAP features to [-0.95, 0.95] and back (method.md 1.7).

``x' = 1.9 (x - min) / (max - min) - 0.95``. ``two-group`` (default, as the reference code): one
min/max over the three rotation channels and one over the six S channels (and, on a mesh of
several parts, a third over its three placement channels, :mod:`meshseq.acap.parts`); ``per-channel``: one
per channel (the paper's text); ``robust``: one range per group like ``two-group``, but from the
``ROBUST_QUANTILE`` and ``1 - ROBUST_QUANTILE`` quantiles of the group's training values instead
of their min and max, so that a few outlier vertices (horse-gallop: 1% of its vertices stretch
its S range to -4.5..16.2) do not squeeze every other vertex into a sliver of the range; values
beyond the quantiles map outside [-0.95, 0.95] (the map stays affine and exactly invertible).
Fit on the training frames only; saved with the model as JSON.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from meshseq.acap.parts import CHANNEL_COUNTS

SCALING_MODES = ("two-group", "per-channel", "robust")
ROBUST_QUANTILE = 0.001
_LOW, _HIGH = -0.95, 0.95
_GROUPS = (slice(0, 3), slice(3, 9), slice(9, 12))  # rotation, S, placement


@dataclass(frozen=True)
class Scaling:
    """Per-channel affine map; ``minimum`` and ``maximum`` are ``(C,)``, C = 9 or 12 (equal within a group)."""

    minimum: np.ndarray
    maximum: np.ndarray
    mode: str = "two-group"

    @staticmethod
    def fit(features: np.ndarray, mode: str = "two-group") -> "Scaling":
        """Fit on features ``(..., C)`` (the training frames), C = 9 or 12."""
        c = np.shape(features)[-1]
        if c not in CHANNEL_COUNTS:
            raise ValueError(f"features have {c} channels; expected 9 (ACAP) or 12 (ACAP and placement)")
        x = np.asarray(features, dtype=np.float64).reshape(-1, c)
        groups = [g for g in _GROUPS if g.stop <= c]
        if mode == "two-group":
            lo, hi = np.empty(c), np.empty(c)
            for g in groups:
                lo[g], hi[g] = x[:, g].min(), x[:, g].max()
        elif mode == "per-channel":
            lo, hi = x.min(axis=0), x.max(axis=0)
        elif mode == "robust":
            lo, hi = np.empty(c), np.empty(c)
            for g in groups:
                lo[g], hi[g] = np.quantile(x[:, g], [ROBUST_QUANTILE, 1.0 - ROBUST_QUANTILE])
        else:
            raise ValueError(f"unknown scaling mode {mode!r}; expected one of {SCALING_MODES}")
        # A constant channel (e.g. every frame equal to the reference) would divide by zero.
        span = hi - lo
        pad = np.where(span > 1e-12, 0.0, 0.5)
        return Scaling(lo - pad, hi + pad, mode)

    @property
    def _scale(self) -> np.ndarray:
        return (_HIGH - _LOW) / (self.maximum - self.minimum)

    def apply(self, features):
        """Features ``(..., C)`` -> scaled, numpy or torch (dtype and device kept)."""
        lo, scale = self._as(features, self.minimum), self._as(features, self._scale)
        return (features - lo) * scale + _LOW

    def channels(self, which: slice) -> "Scaling":
        """The map of channels ``which`` alone (for features ``(..., len(which))``)."""
        return Scaling(self.minimum[which], self.maximum[which], self.mode)

    def invert(self, scaled):
        """Scaled ``(..., C)`` -> features, numpy or torch."""
        if isinstance(scaled, np.ndarray):  # the same operations, in place after the first (no temporaries)
            out = np.subtract(scaled, _LOW, dtype=np.result_type(scaled, self._scale))  # float32 in: one pass
            out /= self._scale
            out += self.minimum
            return out
        lo, scale = self._as(scaled, self.minimum), self._as(scaled, self._scale)
        return (scaled - _LOW) / scale + lo

    @staticmethod
    def _as(like, values: np.ndarray):
        if isinstance(like, np.ndarray):
            return values
        import torch

        return torch.as_tensor(values, dtype=like.dtype, device=like.device)

    def to_dict(self) -> dict:
        return {"mode": self.mode, "minimum": self.minimum.tolist(), "maximum": self.maximum.tolist()}

    @staticmethod
    def from_dict(d: dict) -> "Scaling":
        lo, hi = np.asarray(d["minimum"], dtype=np.float64), np.asarray(d["maximum"], dtype=np.float64)
        if lo.ndim != 1 or lo.size not in CHANNEL_COUNTS or hi.shape != lo.shape or not np.all(hi > lo):
            raise ValueError("scaling needs 9 (or 12) minima below as many maxima")
        return Scaling(lo, hi, str(d.get("mode", "two-group")))

    def save(self, path: str | Path) -> None:
        """Write as JSON (atomically)."""
        from meshseq.io import atomic_output

        with atomic_output(Path(path), force=True) as tmp:
            Path(tmp).write_text(json.dumps(self.to_dict(), indent=2))

    @staticmethod
    def load(path: str | Path) -> "Scaling":
        return Scaling.from_dict(json.loads(Path(path).read_text()))
