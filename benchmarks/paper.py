"""The paper's experiments on this repository's real data: train, evaluate, write the tables.

For every data set (default: pcow, crane, horse-gallop from ../shared/data) and every variant
(bd = ours, std-bd, uni, no-kl = bd without L_KL), train a model for ``--iterations`` (resuming
runs already in ``--out``), evaluate it on the held-out 20% (``meshseq evaluate``), and write:

- Table 1 (ablations): error x 1e-4 at horizons 5/10/15 after u = 1 and 3 given frames, per variant;
- Table 2 (methods): ours against zero velocity, linear ACAP extrapolation and the mesh-VAE
  latent baseline (standing in for Tan et al. 2018);
- completion: ours, CMA-ES and linear interpolation on held-out gaps, and sample diversity;
- Fig. 3: the feature-change curves (PNG per data set),

as Markdown to ``--results`` (default docs/results.md) with the iterations, the times and the
machine. Example (what docs/results.md records):

    python benchmarks/paper.py --data pcow --iterations 600 --variants bd,uni,std-bd,no-kl
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parent.parent
SHARED = Path(os.environ.get("MESHSEQ_SHARED_DATA", ROOT.parent / "shared" / "data"))
#: Held-out fraction per data set: horse-gallop has 48 frames, and 20% (10 frames) leaves no room
#: for 3 given frames and a horizon of 15; its frames 25-48 repeat 1-24 anyway (see the data README).
HOLDOUT = {"horse-gallop": 0.4}
VARIANTS = {"bd": ({"variant": "bd"}, {}), "std-bd": ({"variant": "std-bd"}, {}),
            "uni": ({"variant": "uni"}, {}), "no-kl": ({"variant": "bd"}, {"w_kl": 0.0})}


def train_run(data: Path, run: Path, variant: str, args) -> dict:
    from meshseq.train import RECIPES, TrainConfig, load_training_data, train

    model_opts, weights = VARIANTS[variant]
    options = {**RECIPES[args.recipe], **weights}
    config = TrainConfig(iterations=args.iterations, window=args.window, batch=args.batch, stride=args.stride,
                         seed=args.seed, checkpoint_every=max(50, args.iterations // 4), eval_every=0,
                         holdout=HOLDOUT.get(data.stem, 0.2), **options)
    t0 = time.perf_counter()
    out = train(load_training_data([str(data)]), run, config, model_options=dict(model_opts, latent=args.latent),
                device=args.device, resume=True, progress=not args.quiet)
    return {"seconds": time.perf_counter() - t0, "iteration": out["iteration"], "loss": out["loss"]}


def evaluate_run(data: Path, run: Path, out_json: Path, plots: Path | None, args, baselines: bool) -> dict:
    from meshseq.cli import main

    argv = ["evaluate", str(run), str(data), "--json", str(out_json), "--force", "--device", args.device,
            "--vae-iterations", str(args.vae_iterations), "--cma-evals", str(args.cma_evals),
            "--cma-seconds", str(args.cma_seconds)]
    if not baselines:
        argv += ["--methods", "ours", "--gaps", "none"]
    if plots is not None:
        argv += ["--plots", str(plots)]
    if main(argv) != 0:
        raise SystemExit(f"evaluation of {run} failed")
    return json.loads(out_json.read_text())


def _row(values: dict, keys) -> str:
    return " | ".join(f"{values[u][h]:.1f}" for u, h in keys)


def write_markdown(summaries: dict, device: str, path: Path) -> None:
    """docs/results.md from ``{data set: summary}`` (see ``main``: results, runs, config, argv)."""
    keys = [(u, h) for u in ("u1", "u3") for h in ("5", "10", "15")]
    head = " | ".join(f"{u[1]} given, h={h}" for u, h in keys)
    lines = [
        "# Results: the paper's tables on this repository's data",
        "",
        f"Made by `benchmarks/paper.py` on {platform.node() or 'this machine'} ({platform.machine()}, "
        f"{os.cpu_count()} cores, no GPU used: device {device}, torch {torch.__version__}). The paper trains "
        "7000 iterations of 8 windows x 32 frames (about 8 hours on a Tesla K40c); the runs here are far "
        "shorter (CPU), as each section says. Errors: mean per-vertex distance in the data's units x 1e-4 on "
        "the held-out end of each sequence, averaged over every start with enough frames; translation "
        "removed (centroids), and in the second table also the best rotation.",
        "",
    ]
    for name, summ in summaries.items():
        per_variant, runs, cfg = summ["results"], summ["runs"], summ["config"]
        its = ", ".join(f"{v} {r['iteration']}" for v, r in per_variant.items())
        lines += [f"## {name}", "",
                  f"Command: `python benchmarks/paper.py {' '.join(summ['argv'])}`. Iterations: {its}; "
                  f"{cfg['batch']} windows x {cfg['window']} frames, stride {cfg['stride']}, latent {cfg['latent']}; "
                  f"held-out frames {per_variant[next(iter(per_variant))]['range']}.", ""]
        bd = per_variant.get("bd")
        if bd:
            lines += ["Table 2 (methods; ours = shared-weight BD-LSTM):", "",
                      f"| method | {head} |", "|---" * (len(keys) + 1) + "|"]
            for m, per_u in bd["errors"].items():
                lines.append(f"| {m} | {_row(per_u, keys)} |")
            lines += ["", "Same, after rigid (Kabsch) alignment:", "",
                      f"| method | {head} |", "|---" * (len(keys) + 1) + "|"]
            for m, per_u in bd["errors_aligned"].items():
                lines.append(f"| {m} | {_row(per_u, keys)} |")
            lines.append("")
        lines += ["Table 1 (ablations, ours):", "", f"| variant | {head} | train s |",
                  "|---" * (len(keys) + 2) + "|"]
        for variant, r in per_variant.items():
            lines.append(f"| {variant} | {_row(r['errors']['ours'], keys)} | {runs[variant]['seconds']:.0f} |")
        lines.append("")
        if bd and "completion" in bd:
            lines += ["Completion (in-between error x 1e-4; diversity: mean distance between 4 random-state samples):",
                      "", "| gap | ours | CMA-ES | linear | diversity |", "|---|---|---|---|---|"]
            for gap, r in bd["completion"].items():
                lines.append(f"| {gap} | {r['ours']:.1f} | {r['cma']:.1f} | {r['linear']:.1f} | {r.get('diversity', 0):.1f} |")
            lines.append("")
        if bd:
            fc = bd["feature_change"]
            tail = {m: sum(v[-10:]) / len(v[-10:]) for m, v in fc.items() if m != "ground_truth"}
            lines += [f"Fig. 3 (feature change after 2 given frames): ground truth level {fc['ground_truth']:.4f}; "
                      "mean of the last 10 generated steps: " + ", ".join(f"{m} {v:.4f}" for m, v in tail.items()),
                      "", f"![feature change {name}](img/feature_change_{name}.png)", ""]
    notes = sorted({n for s in summaries.values() for r in s["results"].values() for n in r.get("notes", [])})
    lines += [f"Note: {n}." for n in notes]
    study = path.parent / "recipe_study.md"  # the recipe study (benchmarks/recipe_study.py), kept beside
    if study.is_file():
        lines += ["", study.read_text().rstrip()]
    from meshseq.io import atomic_output

    with atomic_output(path, force=True) as tmp:
        Path(tmp).write_text("\n".join(lines) + "\n")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", default="pcow,crane,horse-gallop", help="names in ../shared/data (without .npz)")
    ap.add_argument("--variants", default="bd,std-bd,uni,no-kl")
    ap.add_argument("--recipe", default="default", help="training recipe (meshseq.train.RECIPES): default or paper")
    ap.add_argument("--iterations", type=int, default=500)
    ap.add_argument("--window", type=int, default=32)
    ap.add_argument("--batch", type=int, default=8)
    ap.add_argument("--stride", type=int, default=1)
    ap.add_argument("--latent", type=int, default=128)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--device", default="auto")
    ap.add_argument("--vae-iterations", type=int, default=1000)
    ap.add_argument("--cma-evals", type=int, default=200)
    ap.add_argument("--cma-seconds", type=float, default=30.0)
    ap.add_argument("--out", default=str(ROOT / "runs" / "paper"))
    ap.add_argument("--results", default=str(ROOT / "docs" / "results.md"))
    ap.add_argument("--quiet", action="store_true", help="no progress bars")
    args = ap.parse_args()
    args.argv = [a for a in os.sys.argv[1:]]
    out = Path(args.out)
    results, runs = {}, {}
    img = Path(args.results).parent / "img"  # noqa: the Fig. 3 PNGs go beside the Markdown
    for name in [d.strip() for d in args.data.split(",") if d.strip()]:
        data = SHARED / f"{name}.npz"
        if not data.is_file():
            raise SystemExit(f"{data}: not found (set MESHSEQ_SHARED_DATA)")
        results[name], runs[name] = {}, {}
        for variant in [v.strip() for v in args.variants.split(",") if v.strip()]:
            run = out / name / variant
            print(f"== {name} / {variant}: training {args.iterations} iterations -> {run}", flush=True)
            runs[name][variant] = train_run(data, run, variant, args)
            plots = run / "plots" if variant == "bd" else None
            r = evaluate_run(data, run, run / "evaluation.json", plots, args, baselines=variant == "bd")
            results[name][variant] = r
            if plots is not None:
                img.mkdir(parents=True, exist_ok=True)
                (img / f"feature_change_{name}.png").write_bytes((plots / "feature_change.png").read_bytes())
            config = {k: getattr(args, k) for k in ("iterations", "batch", "window", "stride", "latent")}
            (out / name / "summary.json").write_text(json.dumps(
                {"results": results[name], "runs": runs[name], "config": config, "argv": args.argv}))
            # after every run, from every data set finished in --out (also by other invocations)
            write_markdown(collect(out), args.device, Path(args.results))
    print(f"wrote {args.results}")


def collect(out: Path) -> dict:
    """``{data set: summary}`` of every data set with a summary.json in ``out``."""
    return {p.parent.name: json.loads(p.read_text()) for p in sorted(out.glob("*/summary.json"))}


if __name__ == "__main__":
    main()
