"""Controlled training runs for the recipe study (docs/results.md, "Why the model froze").

One run = one recipe (``--recipe``, plus ``--set key=value`` overrides of training options)
on one data collection, with the seed and budget fixed. The evaluation frames of the paper's
protocol (the last 20% of every sequence) are never touched: every sequence is cut to its first
80% (the protocol's training part), and the run holds out the last ``--val`` of THAT as a
validation block. Every ``--every`` iterations a checkpoint is evaluated on the validation
blocks, giving learning curves of:

- prediction error (x 1e-4 of the data's units, and per bounding-box diagonal) at horizons 5, 10,
  15 after u = 1 and u = 3 given frames, centroid-aligned and rigidly aligned, for ours and the
  baselines zero velocity and linear ACAP extrapolation (flat lines: they do not train);
- KL (nats, summed over the latent) and the latent spread (std of mu over frames) from the
  training metrics;
- motion level: the mean relative feature change of 50 generated frames (paper Fig. 3) over
  the ground truth's level (1.0 = moves like the data, 0 = frozen);
- with ``--gaps``: completion between two keyframes of the validation block (the in-between
  frames' error for ours, linear interpolation of the ACAP features and of the vertices, and the
  diversity of two random-state completions), as ``paper.py`` measures it on held-out frames.

    python benchmarks/recipe_study.py --data bodies --recipe paper --iterations 600 --every 100 \\
        --out /tmp/study --name paper
    python benchmarks/recipe_study.py --plot /tmp/study/*.json -o docs/img/study_bodies.png

``--data``: ``bodies`` (``BODIES`` file: every sequence of a ``meshseq make-bodies`` HDF5),
``pcow``/``crane``/``horse-gallop`` (../shared/data), or paths/specs. ``--evaluate-on NAME...``
scores only the training sequences with these names (the part after ``:`` or the file's stem), so
runs trained on different sets can be compared on the same validation frames (the data study);
``--unseen NAME...`` leaves those sequences out of training and scores only them, on the frames
their validation block would hold (a motion the model was never shown).
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import json
import os
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
SHARED = Path(os.environ.get("MESHSEQ_SHARED_DATA", ROOT.parent / "shared" / "data"))
PROTOCOL_TRAIN = 0.8  # the paper's protocol holds out the last 20%: never looked at here


def data_specs(data: list[str], bodies: str | None) -> list[str]:
    specs = []
    for d in data:
        if d == "bodies":
            import h5py

            if not bodies:
                raise SystemExit("--data bodies needs --bodies FILE.h5 (meshseq make-bodies)")
            with h5py.File(bodies, "r") as fh:
                specs += [f"{bodies}:{k}" for k in sorted(fh.keys()) if k != "faces"]
        elif (SHARED / f"{d}.npz").is_file():
            specs.append(str(SHARED / f"{d}.npz"))
        else:
            specs.append(d)
    return specs


def development_data(specs: list[str]):
    """Features and vertices of every sequence cut to its first 80% (the protocol's training part)."""
    from meshseq.io import load_sequence
    from meshseq.train import load_training_data

    full = load_training_data(specs)
    verts = []
    for i, spec in enumerate(specs):
        v = load_sequence(spec).vertices.astype(np.float64)
        n = int(round(PROTOCOL_TRAIN * len(v)))
        full.features[i] = full.features[i][:n]
        verts.append(v[:n])
    return full, verts


def sequence_name(spec: str) -> str:
    """``FILE.h5:SEQ`` -> ``SEQ``; ``path/NAME.npz`` -> ``NAME``."""
    return spec.rpartition(":")[2] if ":" in Path(spec).name else Path(spec).stem


def scored_indices(specs: list[str], names: list[str] | None, option: str = "--evaluate-on") -> list[int]:
    """Indices of the specs whose sequence name is in ``names`` (all when ``names`` is empty);
    ``option`` names the command-line option in the error for an unknown name."""
    if not names:
        return list(range(len(specs)))
    known = [sequence_name(s) for s in specs]
    missing = sorted(set(names) - set(known))
    if missing:
        raise SystemExit(f"{option}: {', '.join(missing)} not among the training sequences ({', '.join(known)})")
    return [i for i, k in enumerate(known) if k in names]


def parse_sets(items: list[str]) -> dict:
    out = {}
    for item in items:
        key, _, value = item.partition("=")
        if value.lower() in ("true", "false"):
            out[key] = value.lower() == "true"
            continue
        if value.lower() == "none":  # e.g. logvar_max=none (unbounded)
            out[key] = None
            continue
        for cast in (int, float):
            try:
                out[key] = cast(value)
                break
            except ValueError:
                continue
        else:
            out[key] = value
    return out


COMPLETION_METHODS = ("ours", "linear", "linear_vertices")  # no CMA-ES here: seconds per gap


def evaluate_checkpoint(path: Path, verts: list[np.ndarray], feats_raw: list[np.ndarray], splits,
                        horizons=(5, 10, 15), givens=(1, 3), motion_frames: int = 50,
                        gaps: tuple[int, ...] = ()) -> dict:
    """Validation metrics of one checkpoint, averaged over sequences (weighted by their starts);
    ``gaps``: also completion errors (``completion``: gap -> method -> error x 1e-4, with
    ``diversity`` and ``starts``) where a gap fits in a validation block."""
    import meshseq
    from meshseq.evaluate import completion_errors, feature_change, prediction_errors, prediction_starts
    from meshseq.mesh import bounding_box_diagonal
    from meshseq.plots import feature_change as relative_change

    model = meshseq.load(path)
    methods = ["ours", "zero_velocity", "linear_acap"]
    acc: dict = {}
    motion, truth_level = [], []
    completion: dict = {}
    for v, f, split in zip(verts, feats_raw, splits):
        lo, hi = split.heldout
        scaled = model.scaling.apply(f).astype(np.float32)
        diag = bounding_box_diagonal(v[0])
        for u in givens:
            try:
                res = prediction_errors(model, v, scaled, lo, hi, u, list(horizons), methods)
            except meshseq.MeshseqError:
                continue
            for m, r in res.items():
                for key in ("centroid", "rigid"):
                    for h in horizons:
                        k = (m, u, key, h)
                        e = r[key][str(h)]
                        a = acc.setdefault(k, [0.0, 0.0, 0])
                        a[0] += e * r["starts"]
                        a[1] += e * 1e-4 / diag * r["starts"]
                        a[2] += r["starts"]
        starts = prediction_starts(lo, hi, 1, 1)
        if len(starts):
            fc = feature_change(model, scaled, starts, 1, motion_frames, ["ours"])
            motion.append(float(np.mean(fc["ours"])))
            truth_level.append(float(relative_change(f[lo:hi]).mean()))
        for gap, res in completion_errors(model, v, scaled, lo, hi, list(gaps), list(COMPLETION_METHODS),
                                          samples=2).items():
            a = completion.setdefault(gap, {"starts": 0})
            for k, e in res.items():
                if k != "starts":
                    a[k] = a.get(k, 0.0) + e * res["starts"]
            a["starts"] += res["starts"]
    errors = {}
    for (m, u, key, h), (e, ed, n) in acc.items():
        errors.setdefault(m, {}).setdefault(f"u{u}", {}).setdefault(key, {})[str(h)] = e / n
        errors[m][f"u{u}"].setdefault(key + "_per_diagonal", {})[str(h)] = ed / n
    completion = {g: {k: (e if k == "starts" else e / a["starts"]) for k, e in a.items()}
                  for g, a in completion.items()}
    return {"iteration": model.iteration, "errors": errors, "completion": completion,
            "motion": float(np.mean(motion)) if motion else None,
            "truth_motion": float(np.mean(truth_level)) if truth_level else None}


def completion_line(point: dict) -> str:
    """``  gap 10 ours/linear/linear_vertices 512/540/601 div 12`` per scored gap ('' without)."""
    return "".join(f"  gap {g} ours/linear/linear_vertices {r['ours']:.0f}/{r['linear']:.0f}/"
                   f"{r['linear_vertices']:.0f} div {r.get('diversity', float('nan')):.1f}"
                   for g, r in point.get("completion", {}).items())


def read_metrics(run: Path) -> dict:
    rows = {}
    with open(run / "metrics.csv", newline="") as fh:
        for r in csv.DictReader(fh):
            rows[int(r["iteration"])] = r
    return rows


def run_study(args) -> dict:
    import torch

    from meshseq import checkpoint as ckpt
    from meshseq.data.windows import Split, split_frames
    from meshseq.train import RECIPES, TrainConfig, train

    torch.set_num_threads(args.threads)
    specs = data_specs(args.data, args.bodies)
    scored = scored_indices(specs, args.evaluate_on)  # before training: a wrong name fails now
    unseen = scored_indices(specs, args.unseen, "--unseen") if args.unseen else []
    if unseen:  # scored only on these (those of them named by --evaluate-on), never trained on
        scored = [i for i in unseen if i in scored] if args.evaluate_on else unseen
        if not scored:
            raise SystemExit("--evaluate-on names none of the --unseen sequences")
    data, verts = development_data(specs)
    unseen_features = [data.features[i] for i in unseen]
    unseen_splits = [split_frames(len(f), args.val) for f in unseen_features]  # where a validation block would be
    trained = [i for i in range(len(specs)) if i not in unseen]
    data = dataclasses.replace(data, names=[data.names[i] for i in trained],
                               sources=[data.sources[i] for i in trained],
                               features=[data.features[i] for i in trained])
    options = dict(RECIPES[args.recipe])
    model_options = {}
    sets = parse_sets(args.set)
    for k, v in sets.items():
        if k in ("latent", "lstm_layers", "conv_layers", "variant"):
            model_options[k] = v
        else:
            options[k] = v
    config = TrainConfig(iterations=args.iterations, window=args.window, batch=args.batch, seed=args.seed,
                         holdout=args.val, eval_every=args.every, checkpoint_every=args.every, keep=10000,
                         log_every=10, **options)
    run = Path(args.out) / args.name
    t0 = time.perf_counter()
    train(data, run, config, model_options, device="cpu", resume=bool(ckpt.list_checkpoints(run)),
          progress=not args.quiet)
    seconds = time.perf_counter() - t0
    metrics = read_metrics(run)
    curve = []
    for path in ckpt.list_checkpoints(run):
        meta = json.loads((path / "model.json").read_text())
        if unseen:
            feats, splits = unseen_features, unseen_splits
        else:
            splits = [Split.from_dict(d["split"]) for d in meta["datasets"]]
            feats, splits = [data.features[i] for i in scored], [splits[i] for i in scored]
        point = evaluate_checkpoint(path, [verts[i] for i in scored], feats, splits, gaps=tuple(args.gaps))
        row = metrics.get(point["iteration"], {})
        for k in ("kl", "latent_spread", "rec", "l2", "heldout_rec"):
            point[k] = float(row[k]) if row.get(k) not in (None, "") else None
        curve.append(point)
        e = point["errors"]
        print(f"{args.name} it {point['iteration']:5d}  h15 u1 ours {e['ours']['u1']['centroid']['15']:8.1f} "
              f"zv {e['zero_velocity']['u1']['centroid']['15']:8.1f}  u3 ours {e['ours']['u3']['centroid']['15']:8.1f} "
              f"lin {e['linear_acap']['u3']['centroid']['15']:8.1f}  rigid u3 ours {e['ours']['u3']['rigid']['15']:8.1f} "
              f"zv {e['zero_velocity']['u3']['rigid']['15']:8.1f}  KL {point['kl']}  spread {point['latent_spread']}  "
              f"motion {point['motion']:.4f}/{point['truth_motion']:.4f}{completion_line(point)}", flush=True)
    result = {"name": args.name, "recipe": args.recipe, "set": sets, "data": [specs[i] for i in trained],
              "scored": [specs[i] for i in scored], "train": config.to_dict(),
              "model": model_options, "seconds": seconds, "curve": curve,
              "command": "python benchmarks/recipe_study.py " + " ".join(args.argv)}
    out = Path(args.out) / f"{args.name}.json"
    out.write_text(json.dumps(result, indent=1))
    return result


TABLE1_CELLS = [(u, h) for u in ("u1", "u3") for h in ("5", "10", "15")]  # Table 1's six cells


def prediction_figure(errors: dict, method: str, given: str, key: str, horizon: str) -> float:
    """One method's validation error (x 1e-4) at ``horizon`` after ``given`` frames; ``horizon``
    "mean": the mean of Table 1's six cells (u1/u3 x h5/h10/h15, ``given`` ignored)."""
    if horizon == "mean":
        return float(np.mean([errors[method][u][key][h] for u, h in TABLE1_CELLS]))
    return errors[method][given][key][horizon]


def plot(files: list[str], output: str, given: str = "u3", horizon: str = "15") -> None:
    """Learning curves of the runs: validation error (centroid, rigid), KL, motion level, and the
    completion ratios of runs scored with ``--gaps`` (a fifth panel)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    runs = [json.loads(Path(f).read_text()) for f in files]
    gaps = sorted({g for r in runs for p in r["curve"] for g in p.get("completion", {})}, key=int)
    fig, axes = plt.subplots(1, 5 if gaps else 4, figsize=(23.5 if gaps else 19, 4.2))
    for r in runs:
        it = [p["iteration"] for p in r["curve"]]
        for ax, key in zip(axes[:2], ("centroid", "rigid")):
            ax.plot(it, [prediction_figure(p["errors"], "ours", given, key, horizon) for p in r["curve"]],
                    marker="o", label=r["name"])
        axes[2].plot(it, [max(p["kl"] or 0, 1e-4) for p in r["curve"]], marker="o", label=r["name"])
        axes[3].plot(it, [p["motion"] / p["truth_motion"] for p in r["curve"]], marker="o", label=r["name"])
        for gap, style in zip(gaps, ("-", "--", ":", "-.")):
            pts = [(p["iteration"], p["completion"][gap]) for p in r["curve"] if gap in p.get("completion", {})]
            axes[4].plot([i for i, _ in pts], [c["ours"] / min(c["linear"], c["linear_vertices"]) for _, c in pts],
                         marker="o", ls=style, label=f"{r['name']}, gap {gap}")
    first = runs[0]["curve"][-1]["errors"]
    what = "mean of u1/u3 x h5/h10/h15" if horizon == "mean" else f"h{horizon} {given}"
    for ax, key in zip(axes[:2], ("centroid", "rigid")):
        for m, style in (("zero_velocity", "k--"), ("linear_acap", "k:")):
            ax.axhline(prediction_figure(first, m, given, key, horizon), color="k", ls=style[1:], label=m)
        ax.set_title(f"validation error, {what} ({key}), x1e-4", fontsize=9)
    axes[2].set_yscale("log")
    axes[2].set_title("KL (nats)")
    axes[3].axhline(1.0, color="k", ls="--", label="ground truth")
    axes[3].set_title("motion level / ground truth's")
    if gaps:
        axes[4].axhline(1.0, color="k", ls="--", label="linear interpolation")
        axes[4].set_title("completion: ours / better linear interpolation")
        axes[4].legend(fontsize=7)
    for ax in axes:
        ax.set_xlabel("iteration")
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=7)
    axes[3].legend(fontsize=7)
    fig.tight_layout()
    tmp = Path(output).with_name(".tmp-" + Path(output).name)
    fig.savefig(tmp, dpi=90, format="png")
    os.replace(tmp, output)


def mean_ratio(errors: dict) -> float:
    """Mean over u1/u3 x h10/h15 x centroid/rigid of ours / the best of zero velocity and linear
    ACAP (issue 12's 8 prediction cells, here on validation blocks)."""
    ratios = [errors["ours"][u][k][h] / min(errors[m][u][k][h] for m in ("zero_velocity", "linear_acap"))
              for u in ("u1", "u3") for k in ("centroid", "rigid") for h in ("10", "15")]
    return float(np.mean(ratios))


def completion_ratios(point: dict) -> str:
    """``0.93 / 1.05``: ours over the better of the two linear interpolations per scored gap."""
    return " / ".join(f"{r['ours'] / min(r['linear'], r['linear_vertices']):.2f}"
                      for _, r in sorted(point.get("completion", {}).items(), key=lambda kv: int(kv[0])))


def summary_table(files: list[str]) -> str:
    """Markdown table of the last checkpoint of each run (validation, h15, x 1e-4); runs scored
    with ``--gaps`` add their completion ratios."""
    runs = [json.loads(Path(f).read_text()) for f in files]
    gaps = sorted({g for r in runs for g in r["curve"][-1].get("completion", {})}, key=int)
    extra = f" completion gap {' / '.join(gaps)}: ours / better linear |" if gaps else ""
    lines = ["| run | changed (vs. the paper's recipe) | it | u1 ours / zero vel. | u3 ours / best baseline "
             "| u3 rigid ours / best | mean ratio (8 cells) | KL nats | latent spread | motion / truth |" + extra,
             "|---|---|---|---|---|---|---|---|---|---|" + ("---|" if gaps else "")]
    for r in runs:
        p = r["curve"][-1]
        e = p["errors"]
        best = lambda u, k: min(e[m][u][k]["15"] for m in ("zero_velocity", "linear_acap"))  # noqa: E731
        changed = ", ".join(f"{k}={v}" for k, v in r["set"].items()) or "-"
        lines.append(
            f"| {r['name']} | {changed} | {p['iteration']} | {e['ours']['u1']['centroid']['15']:.0f} / "
            f"{e['zero_velocity']['u1']['centroid']['15']:.0f} | {e['ours']['u3']['centroid']['15']:.0f} / "
            f"{best('u3', 'centroid'):.0f} | {e['ours']['u3']['rigid']['15']:.0f} / {best('u3', 'rigid'):.0f} | "
            f"{mean_ratio(e):.3f} | {p['kl']:.3g} | {p['latent_spread']:.3g} | {p['motion'] / p['truth_motion']:.2f} |"
            + (f" {completion_ratios(p) or '-'} |" if gaps else ""))
    return "\n".join(lines)


def main(argv=None) -> None:
    import sys

    argv = list(sys.argv[1:] if argv is None else argv)
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--data", nargs="+", default=["bodies"])
    p.add_argument("--bodies", default=None, help="make-bodies HDF5 for --data bodies")
    p.add_argument("--evaluate-on", nargs="*", default=None, metavar="NAME",
                   help="score only these training sequences (names after ':' or file stems)")
    p.add_argument("--unseen", nargs="*", default=None, metavar="NAME",
                   help="leave these sequences out of training and score only them, on the frames their "
                   "validation block would hold (features against the same reference as the rest)")
    p.add_argument("--recipe", default="default")
    p.add_argument("--set", nargs="*", default=[], help="training option overrides key=value")
    p.add_argument("--name", default=None)
    p.add_argument("--iterations", type=int, default=600)
    p.add_argument("--every", type=int, default=100)
    p.add_argument("--window", type=int, default=32)
    p.add_argument("--batch", type=int, default=8)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--val", type=float, default=0.25, help="validation fraction of the training part")
    p.add_argument("--gaps", type=int, nargs="*", default=[], metavar="GAP",
                   help="also score completion over these gaps (in-between frames) in the validation blocks")
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--out", default="/tmp/meshseq-study")
    p.add_argument("--quiet", action="store_true")
    p.add_argument("--plot", nargs="*", default=None, help="plot these result JSONs instead of training")
    p.add_argument("-o", "--output", default=None, help="PNG for --plot")
    p.add_argument("--given", default="u3")
    p.add_argument("--horizon", default="15", choices=("5", "10", "15", "mean"),
                   help="--plot: the horizon of the error panels; mean: Table 1's six cells")
    p.add_argument("--summary", nargs="*", default=None, help="print a Markdown table of these result JSONs")
    args = p.parse_args(argv)
    args.argv = argv
    if args.summary is not None:
        print(summary_table(args.summary))
        return
    if args.plot is not None:
        plot(args.plot, args.output or "study.png", args.given, args.horizon)
        return
    args.name = args.name or args.recipe
    run_study(args)


if __name__ == "__main__":
    main()
