"""Learning curves of several training runs side by side: one panel per metrics.csv column.

    python benchmarks/compare_runs.py H-before=before H-logvar=logvar_max H-kl=kl_scale H-both=both \\
        --keys kl,rec,latent_rms,latent_sigma --log kl -o docs/img/horse_latent_runaway.png

Each argument is ``RUN`` or ``RUN=LABEL`` (RUN: a ``meshseq train`` output folder, or its
metrics.csv). Columns are the training metrics (``meshseq.train.METRIC_FIELDS``); ``--log``
names the panels drawn on a log scale. Rows without a value (e.g. held-out rows) are skipped.
``--line KEY=VALUE:LABEL`` draws a flat line in KEY's panel (a baseline's figure, e.g. zero
velocity's validation error from ``benchmarks/validation_errors.py``).

It also prints, per run, the loss spikes of ``--spike-key`` (default ``rec``): logged rows whose
value exceeds ``--spike-factor`` times the median of the ``SPIKE_WINDOW`` rows before it, the
worst such ratio, and the median of the last ``SPIKE_WINDOW`` rows (where the run ended up).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np


#: logged rows a spike is measured against (the median of the rows before it)
SPIKE_WINDOW = 10


def spikes(values: np.ndarray, factor: float) -> tuple[int, float]:
    """``(count, worst)``: rows of ``values`` (T,) above ``factor`` x the median of the
    ``SPIKE_WINDOW`` rows before them, and the largest ratio to that median (NaN rows skipped)."""
    v = values[np.isfinite(values)]
    ratios = np.array([v[i] / np.median(v[i - SPIKE_WINDOW:i]) for i in range(SPIKE_WINDOW, len(v))])
    if not len(ratios):
        return 0, float("nan")
    return int((ratios > factor).sum()), float(ratios.max())


def main(argv=None) -> int:
    from meshseq.plots import read_metrics_csv, save_figure

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("runs", nargs="+", help="RUN or RUN=LABEL")
    ap.add_argument("--keys", default="kl,rec,latent_rms,latent_sigma", help="comma-separated metrics columns")
    ap.add_argument("--log", default="kl", help="comma-separated columns drawn on a log scale")
    ap.add_argument("--until", type=int, default=None, help="last iteration shown (and counted)")
    ap.add_argument("--spike-key", default="rec", help="the column whose spikes are counted")
    ap.add_argument("--spike-factor", type=float, default=2.0, help="a spike: above this x the recent median")
    ap.add_argument("--line", action="append", default=[], metavar="KEY=VALUE:LABEL",
                    help="a flat line in KEY's panel (repeatable)")
    ap.add_argument("-o", "--output", required=True, help="PNG to write")
    ap.add_argument("--force", action="store_true", help="overwrite OUTPUT")
    args = ap.parse_args(argv)

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    keys = [k for k in args.keys.split(",") if k]
    log = set(args.log.split(","))
    fig, axes = plt.subplots(1, len(keys), figsize=(4.2 * len(keys), 3.4), squeeze=False)
    for spec in args.runs:
        path, _, label = spec.partition("=")
        csv_path = Path(path) / "metrics.csv" if Path(path).is_dir() else Path(path)
        if not csv_path.is_file():
            raise SystemExit(f"{csv_path}: no metrics.csv")
        m = read_metrics_csv(csv_path)
        it = np.asarray(m["iteration"], dtype=np.float64)
        for ax, key in zip(axes[0], keys):
            if key not in m:
                raise SystemExit(f"{csv_path}: no column {key!r}")
            y = np.asarray(m[key], dtype=np.float64)
            keep = np.isfinite(y) & (it <= (args.until or np.inf))
            ax.plot(it[keep], y[keep], label=label or Path(path).name, linewidth=1.2)
        if args.spike_key in m:
            y = np.asarray(m[args.spike_key], dtype=np.float64)[it <= (args.until or np.inf)]
            count, worst = spikes(y, args.spike_factor)
            end = float(np.median(y[np.isfinite(y)][-SPIKE_WINDOW:]))
            print(f"{label or Path(path).name}: {count} {args.spike_key} spikes (> {args.spike_factor:g}x the median of "
                  f"the {SPIKE_WINDOW} rows before), worst {worst:.2f}x; last {SPIKE_WINDOW} rows' median {end:.4g}")
    for i, spec in enumerate(args.line):
        key, _, rest = spec.partition("=")
        value, _, label = rest.partition(":")
        if key not in keys:
            raise SystemExit(f"--line {spec}: {key!r} is not one of --keys")
        try:
            y = float(value)
        except ValueError:
            raise SystemExit(f"--line {spec}: expected KEY=VALUE:LABEL with a number") from None
        axes[0][keys.index(key)].axhline(y, color="k", linestyle=("--", ":", "-.")[i % 3], linewidth=1, label=label or None)
    for ax, key in zip(axes[0], keys):
        ax.set_title(key)
        if ax.get_legend_handles_labels()[1]:
            ax.legend(fontsize=8)
        ax.set_xlabel("iteration")
        ax.grid(alpha=0.3)
        if key in log:
            ax.set_yscale("log")
    axes[0][0].legend(fontsize=8)
    fig.tight_layout()
    print(f"wrote {save_figure(fig, args.output, force=args.force)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
