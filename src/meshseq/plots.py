"""Plots (matplotlib): error against prediction horizon, the feature-change curve, training curves.

Each plotting function is pure: arrays in, a ``matplotlib.figure.Figure`` out (no pyplot state,
no display needed). :func:`read_metrics_csv` and :func:`save_figure` are the edges that touch
files. :func:`figure_to_array` turns a figure into an ``(H, W, 3)`` uint8 image.
"""

from __future__ import annotations

import csv
import math
import os
from pathlib import Path
from typing import Mapping

import numpy as np

from meshseq.errors import MeshseqError

FIGURE_SUFFIXES = (".png", ".pdf", ".svg")


def _new_figure(width: float = 6.4, height: float = 4.0):
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(width, height), dpi=100, layout="constrained")
    FigureCanvasAgg(fig)
    return fig


def _finish(fig, ax, title: str | None):
    """The common end of a line plot: y from 0, light grid, legend, optional title."""
    ax.set_ylim(bottom=0)
    ax.grid(alpha=0.3)
    ax.legend()
    if title:
        ax.set_title(title)
    return fig


def figure_to_array(fig) -> np.ndarray:
    """The figure drawn as an ``(H, W, 3)`` uint8 RGB image."""
    fig.canvas.draw()
    return np.asarray(fig.canvas.buffer_rgba())[..., :3].copy()


def _scale_text(scale: float) -> str:
    """``1e-4`` -> a mathtext "x 10^-4"; other scales as "x 0.003"."""
    exponent = math.log10(scale)
    if abs(exponent - round(exponent)) < 1e-9:
        return rf"$\times 10^{{{int(round(exponent))}}}$"
    return f"x {scale:g}"


def error_vs_horizon(
    errors: Mapping[str, np.ndarray],
    *,
    unit_scale: float | None = 1e-4,
    title: str | None = "Error against prediction horizon",
    ylabel: str = "mean per-vertex error",
):
    """Error against the number of frames predicted, one line per method.

    ``errors``: method name -> ``(H,)`` mean error at predicted frames 1..H, or ``(N, H)`` for N
    test windows (the line is their mean, the band their 10th-90th percentile). Values are in
    the data's units and shown divided by ``unit_scale`` (the paper reports x 1e-4).
    """
    if not errors:
        raise MeshseqError("error_vs_horizon: no methods given")
    fig = _new_figure()
    ax = fig.add_subplot()
    scale = unit_scale or 1.0
    for name, values in errors.items():
        e = np.asarray(values, dtype=np.float64)
        if e.ndim not in (1, 2) or e.shape[-1] == 0:
            raise MeshseqError(f"error_vs_horizon: {name}: expected (H,) or (N, H) errors, got {e.shape}")
        horizon = np.arange(1, e.shape[-1] + 1)
        mean = (e if e.ndim == 1 else np.nanmean(e, axis=0)) / scale
        (line,) = ax.plot(horizon, mean, marker="o" if len(horizon) <= 30 else None, ms=3, label=name)
        if e.ndim == 2 and e.shape[0] > 1:
            lo, hi = np.nanpercentile(e, [10, 90], axis=0) / scale
            ax.fill_between(horizon, lo, hi, color=line.get_color(), alpha=0.15, linewidth=0)
    ax.set_xlabel("predicted frame")
    ax.set_ylabel(ylabel + (f" ({_scale_text(unit_scale)})" if unit_scale else ""))
    return _finish(fig, ax, title)


def feature_change(features: np.ndarray) -> np.ndarray:
    """Relative change of features between consecutive frames (the paper's Fig. 3 curve).

    ``features (T, V, 9)`` -> ``(T-1,)``: ``||X_{t+1} - X_t|| / ||X_t||`` (Frobenius norms over
    the frame); ``(N, T, V, 9)`` -> ``(T-1,)``, the mean over the N sequences. A curve sinking
    to 0 means a frozen sequence; spikes mean jerks.
    """
    x = np.asarray(features, dtype=np.float64)
    if x.ndim == 3:
        x = x[None]
    if x.ndim != 4 or x.shape[1] < 2:
        raise MeshseqError(f"feature_change: expected (T, V, C) or (N, T, V, C) features with T >= 2, got {x.shape}")
    flat = x.reshape(x.shape[0], x.shape[1], -1)
    num = np.linalg.norm(np.diff(flat, axis=1), axis=-1)
    den = np.maximum(np.linalg.norm(flat[:, :-1], axis=-1), 1e-300)
    return (num / den).mean(axis=0)


def feature_change_curve(curves: Mapping[str, np.ndarray], *, title: str | None = "Feature change between frames"):
    """The feature-change curve, one line per method.

    ``curves``: method name -> a ``(T-1,)`` curve from :func:`feature_change`, or the
    generated features themselves (``(T, V, C)`` or ``(N, T, V, C)``), computed here.
    """
    if not curves:
        raise MeshseqError("feature_change_curve: no methods given")
    fig = _new_figure()
    ax = fig.add_subplot()
    for name, values in curves.items():
        c = np.asarray(values, dtype=np.float64)
        c = c if c.ndim == 1 else feature_change(c)
        ax.plot(np.arange(1, len(c) + 1), c, label=name)
    ax.set_xlabel("frame")
    ax.set_ylabel(r"$\|X_{t+1} - X_t\| \,/\, \|X_t\|$")
    return _finish(fig, ax, title)


def training_curves(
    metrics: Mapping[str, np.ndarray],
    *,
    x: str = "iteration",
    log: bool | None = None,
    title: str | None = "Training",
):
    """Loss terms against ``metrics[x]`` (default ``iteration``), one line per other column.

    ``metrics``: column name -> ``(N,)`` values (as :func:`read_metrics_csv` returns); NaN
    entries (terms not logged at a row) are skipped. ``log``: log-scale y; default when every
    plotted value is positive.
    """
    if x not in metrics:
        raise MeshseqError(f"training curves: no {x!r} column (columns: {', '.join(metrics) or 'none'})")
    xs = np.asarray(metrics[x], dtype=np.float64)
    columns = [k for k in metrics if k != x]
    if not columns:
        raise MeshseqError("training curves: no loss columns besides " + repr(x))
    fig = _new_figure()
    ax = fig.add_subplot()
    positive = True
    for name in columns:
        ys = np.asarray(metrics[name], dtype=np.float64)
        ok = np.isfinite(ys) & np.isfinite(xs)
        if not ok.any():
            continue
        positive &= bool(np.all(ys[ok] > 0))
        ax.plot(xs[ok], ys[ok], label=name, lw=1.2)
    if log if log is not None else positive:
        ax.set_yscale("log")
    ax.set_xlabel(x)
    ax.set_ylabel("loss")
    ax.grid(alpha=0.3, which="both")
    ax.legend()
    if title:
        ax.set_title(title)
    return fig


def read_metrics_csv(path: str | os.PathLike) -> dict[str, np.ndarray]:
    """Columns of a run's metrics CSV (header row, then numbers) as float arrays ``(N,)``.

    Empty cells become NaN. A missing file, a missing ``iteration`` column or a cell that is
    not a number -> MeshseqError naming the file, line and column.
    """
    p = Path(path)
    if not p.is_file():
        raise MeshseqError(f"{p}: metrics file does not exist")
    with open(p, newline="") as fh:
        rows = list(csv.reader(fh))
    if not rows:
        raise MeshseqError(f"{p}: empty metrics file (expected a header row)")
    header = [h.strip() for h in rows[0]]
    if "iteration" not in header:
        raise MeshseqError(f"{p}: no 'iteration' column in the header ({', '.join(header)})")
    data = np.full((len(rows) - 1, len(header)), np.nan)
    for i, row in enumerate(rows[1:]):
        for j, cell in enumerate(row[: len(header)]):
            cell = cell.strip()
            if not cell:
                continue
            try:
                data[i, j] = float(cell)
            except ValueError:
                raise MeshseqError(f"{p}: line {i + 2}, column {header[j]!r}: {cell!r} is not a number") from None
    return {name: data[:, j] for j, name in enumerate(header)}


def save_figure(fig, path: str | os.PathLike, *, force: bool = False) -> Path:
    """Write ``fig`` to ``path`` (.png, .pdf or .svg) atomically; returns the path."""
    from meshseq.io import atomic_output

    target = Path(path)
    suffix = target.suffix.lower()
    if suffix not in FIGURE_SUFFIXES:
        raise MeshseqError(f"{target}: unknown figure extension {suffix or '(none)'!r}; expected one of {', '.join(FIGURE_SUFFIXES)}")
    with atomic_output(target, force=force) as tmp:
        fig.savefig(tmp, format=suffix[1:], dpi=150 if suffix == ".png" else None)
    return target
