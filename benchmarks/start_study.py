"""Does a trained model predict as well from a start frame that no training window began at?

Training chains start at the first frame of a training window. A data set whose training part is
barely longer than a window (horse-gallop: 29 training frames, window 29) has one such start, so
every chain the model ever learned from began at frame 0. This study predicts from every start
``s`` inside the training part (training frames only: the held-out block is never read) and
splits the errors into starts that training windows began at and starts they never began at.

    python benchmarks/start_study.py RUN [RUN ...] --given 1 3 --horizons 10 15 --json FILE
    python benchmarks/start_study.py RUN=LABEL ... --plot FILE [FILE ...] -o CURVES.png

Prints, per run (newest checkpoint or a checkpoint folder) and given count, the mean error
x 1e-4 (centroid-aligned) of ours, zero velocity and linear ACAP extrapolation over trained and
untrained starts, and ours over the better baseline; and how well the model fits its training
windows: the forward chain's L_rec (z = mu, the delivered weights, as in training otherwise) over
zero velocity's on the same windows (1 = no better than standing still, 0 = a perfect fit).
``--json FILE`` writes every start's figures.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

METHODS = ("ours", "zero_velocity", "linear_acap")


def run_data(model):
    """``(vertices (T, V, 3), scaled features (T, V, 9), split, window)`` of a one-sequence run."""
    from meshseq.data.windows import Split
    from meshseq.io import load_sequence
    from meshseq.train import load_training_data

    sets = model.meta["datasets"]
    if len(sets) != 1:
        raise SystemExit(f"start_study: one data set per run, this run has {len(sets)}")
    source = sets[0]["source"]
    feats = load_training_data([source], consistency=model.meta["train"]["consistency"]).features[0]
    verts = load_sequence(source).vertices.astype(np.float64)
    window = int(model.meta["train"]["window"])
    return verts, model.scaling.apply(feats).astype(np.float32), Split.from_dict(sets[0]["split"]), window


def start_errors(model, verts, feats, segment, window: int, given: int, horizons: list[int]) -> list[dict]:
    """Per start of the training segment ``(lo, hi)``: errors at ``horizons`` for each method and
    whether a training window began there (``trained``)."""
    from meshseq.evaluate import prediction_errors, prediction_starts

    lo, hi = segment
    last_trained = hi - window  # windows begin at lo .. hi - window (stride 1)
    out = []
    for s in prediction_starts(lo, hi, given, max(horizons)):
        errs = prediction_errors(model, verts, feats, int(s), int(s) + given + max(horizons), given, horizons,
                                 list(METHODS))
        out.append({"start": int(s), "trained": bool(s <= last_trained),
                    **{m: errs[m]["centroid"] for m in METHODS}})
    return out


def training_fit(model, feats, segment, window: int, most: int = 16) -> tuple[float, float]:
    """``(ours, zero velocity)``: mean forward-chain L_rec (``meshseq.train.window_losses``' sum
    over vertices and channels, mean over frames 2..n) over up to ``most`` evenly spaced training
    windows, ours free-running from each window's first frame with ``z = mu``."""
    import torch

    from meshseq.kernels import frame_error

    lo, hi = segment
    starts = np.unique(np.linspace(lo, hi - window, min(most, hi - window - lo + 1)).round().astype(int))
    w = torch.from_numpy(np.stack([feats[s:s + window] for s in starts]))
    with torch.no_grad():
        fwd = model.net(w.to(model.device), sample=False)["forward"].cpu()
    ours = frame_error(fwd[:, 1:], w[:, 1:]).mean()
    still = frame_error(w[:, :1].expand_as(w)[:, 1:], w[:, 1:]).mean()
    return float(ours), float(still)


def mean_errors(part: list[dict], horizon) -> tuple[dict, float]:
    """Mean error of each method over the starts ``part`` at ``horizon``, and ours over the better
    baseline (zero velocity or linear ACAP)."""
    mean = {m: float(np.mean([r[m][str(horizon)] for r in part])) for m in METHODS}
    return mean, mean["ours"] / min(mean["zero_velocity"], mean["linear_acap"])


def summarise(rows: list[dict], horizons: list[int], min_start: int | None = None) -> list[str]:
    lines = []
    groups = [("trained starts", lambda r: r["trained"]), ("untrained starts", lambda r: not r["trained"])]
    if min_start is not None:
        groups.append((f"starts >= {min_start}", lambda r: r["start"] >= min_start))
    for label, keep in groups:
        part = [r for r in rows if keep(r)]
        if not part:
            lines.append(f"  {label}: none")
            continue
        cells = []
        for h in horizons:
            mean, ratio = mean_errors(part, h)
            cells.append(f"h{h}: ours {mean['ours']:.1f} zero {mean['zero_velocity']:.1f} "
                         f"linear {mean['linear_acap']:.1f} ratio {ratio:.2f}")
        starts = [r["start"] for r in part]
        lines.append(f"  {label} ({len(part)}: {min(starts)}..{max(starts)}): " + "; ".join(cells))
    return lines


def untrained_ratios(report: dict, horizons=("10", "15"), min_start: int | None = None) -> dict:
    """``{run: {iteration: {"u1 h10": ratio, ...}}}`` from ``--json`` reports: ours over the better
    baseline, mean over the untrained starts (the held-out protocol's kind of start), or over the
    starts from ``min_start`` on (to compare runs whose windows began at different starts)."""
    out: dict = {}
    for path, figures in report.items():
        folder = Path(path)
        run, iteration = (folder.parent.parent.name, int(folder.name)) if folder.parent.name == "checkpoints" \
            else (folder.name, -1)
        cells = {}
        for given in [k for k in figures if k != "fit"]:
            part = [r for r in figures[given]
                    if (not r["trained"] if min_start is None else r["start"] >= min_start)]
            for h in horizons:
                cells[f"u{given} h{h}"] = mean_errors(part, h)[1]
        out.setdefault(run, {})[iteration] = cells
    return out


def plot(files: list[str], output: str, labels: dict[str, str], min_start: int | None = None) -> None:
    """One panel per (given, horizon): ratio over untrained starts (or starts >= ``min_start``)
    against the iteration, a line a run."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ratios: dict = {}
    for f in files:
        for run, points in untrained_ratios(json.loads(Path(f).read_text()), min_start=min_start).items():
            ratios.setdefault(run, {}).update(points)
    cells = sorted({c for points in ratios.values() for p in points.values() for c in p})
    fig, axes = plt.subplots(1, len(cells), figsize=(3.4 * len(cells), 3.2), squeeze=False)
    for ax, cell in zip(axes[0], cells):
        for run, points in sorted(ratios.items()):
            its = sorted(points)
            ax.plot(its, [points[i][cell] for i in its], marker="o", label=labels.get(run, run))
        ax.axhline(1.0, color="gray", lw=0.8, ls="--")
        ax.set_title(f"{cell}, " + ("untrained starts" if min_start is None else f"starts >= {min_start}"))
        ax.set_xlabel("iteration")
    axes[0][0].set_ylabel("ours / best baseline")
    axes[0][-1].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(output, dpi=110)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("runs", nargs="+", help="run folders (newest checkpoint) or checkpoint folders")
    ap.add_argument("--given", type=int, nargs="+", default=[1, 3])
    ap.add_argument("--horizons", type=int, nargs="+", default=[10, 15])
    ap.add_argument("--json", help="write every start's figures here")
    ap.add_argument("--plot", nargs="+", metavar="JSON", help="plot these --json reports instead (runs: the "
                    "positional arguments as RUN=LABEL, optional) to -o PNG")
    ap.add_argument("-o", "--output", help="PNG for --plot")
    ap.add_argument("--min-start", type=int, help="also average over the starts from this frame on (e.g. "
                    "those that no run's windows began at, when runs differ in --window); --plot: only those")
    args = ap.parse_args(argv)
    if args.plot:
        if not args.output:
            ap.error("--plot needs -o PNG")
        plot(args.plot, args.output, dict(r.split("=", 1) for r in args.runs if "=" in r), args.min_start)
        return 0

    import meshseq

    report = {}
    for run in args.runs:
        model = meshseq.load(run)
        verts, feats, split, window = run_data(model)
        segment = max(split.train, key=lambda ab: ab[1] - ab[0])
        print(f"{run} (iteration {model.iteration}, window {window}, training frames {segment[0]}:{segment[1]})")
        ours, still = training_fit(model, feats, segment, window)
        report[run] = {"fit": {"ours": ours, "zero_velocity": still}}
        print(f" training windows' L_rec: ours {ours:.1f}, zero velocity {still:.1f} ({ours / still:.2f})")
        for given in args.given:
            rows = start_errors(model, verts, feats, segment, window, given, args.horizons)
            report[run][str(given)] = rows
            print(f" u = {given}")
            print("\n".join(summarise(rows, args.horizons, args.min_start)))
    if args.json:
        Path(args.json).write_text(json.dumps(report, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
