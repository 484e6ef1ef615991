"""The paper's experiments on this repository's real data: train, evaluate, write the tables.

For every data set (default: pcow, crane, horse-gallop from ../shared/data, and ``bodies``: a
Dyna-like body set from ``meshseq make-bodies``, several subjects x motions trained together and
evaluated per sequence, 20% held out per sequence) and every variant
(bd = ours, std-bd, uni, no-kl = bd without L_KL), train a model for ``--iterations`` (resuming
runs already in ``--out``), evaluate it on the held-out 20% (``meshseq evaluate``), and write:

- Table 1 (ablations): error x 1e-4 at horizons 5/10/15 after u = 1 and 3 given frames, per variant;
- Table 2 (methods): ours against zero velocity, linear ACAP extrapolation and the mesh-VAE
  latent baseline (standing in for Tan et al. 2018);
- completion: ours, CMA-ES and linear interpolation on held-out gaps, and sample diversity;
- Fig. 3: the feature-change curves (PNG per data set),

one record per data set (and ``--tag``) in ``--records`` (docs/results/NAME.json), and from all
records the Markdown ``--results`` (docs/results.md) and the results table of README.md;
``--markdown-only`` rewrites both from the records without training. Example:

    python benchmarks/paper.py --data pcow --iterations 600 --variants bd,uni,std-bd,no-kl
    python benchmarks/paper.py --data bodies --iterations 1500 --variants bd

``--data bodies`` uses ``--bodies FILE.h5`` and makes it first when it is missing (``BODY_SET``,
the arguments of ``meshseq make-bodies``; about 2 minutes).
"""

from __future__ import annotations

import argparse
import json
import os
import re
from pathlib import Path


from meshseq.errors import MeshseqError

ROOT = Path(__file__).resolve().parent.parent
SHARED = Path(os.environ.get("MESHSEQ_SHARED_DATA", ROOT.parent / "shared" / "data"))
#: Held-out fraction per data set: horse-gallop has 48 frames, and 20% (10 frames) leaves no room
#: for 3 given frames and a horizon of 15; its frames 25-48 repeat 1-24 anyway (see the data README).
HOLDOUT = {"horse-gallop": 0.4}
#: The body set of ``--data bodies`` (``meshseq make-bodies`` arguments): 4 subjects x 4 motions,
#: 120 frames at 1,000 vertices; the same set as the recipe study (docs/method.md).
BODY_SET = ["--subjects", "female_fit,male_heavy,female_old,male_slim",
            "--motions", "punch,shake_arms,jumping_jacks,walk", "--frames", "120", "--vertices", "1000"]
GAPS = "10,20"  # completion gaps (issue 12's targets)
BASELINES = ("zero_velocity", "linear_acap", "vae_latent")
VARIANTS = {"bd": ({"variant": "bd"}, {}), "std-bd": ({"variant": "std-bd"}, {}),
            "uni": ({"variant": "uni"}, {}), "no-kl": ({"variant": "bd"}, {"w_kl": 0.0})}


def dataset_specs(name: str, args) -> list[str]:
    """The sequences of data set ``name``: one .npz of ../shared/data, or every sequence of the
    body set (made first when ``--bodies`` is missing)."""
    if name != "bodies":
        data = SHARED / f"{name}.npz"
        if not data.is_file():
            raise SystemExit(f"{data}: not found (set MESHSEQ_SHARED_DATA)")
        return [str(data)]
    import h5py

    from meshseq.cli import main as cli

    bodies = Path(args.bodies)
    if not bodies.is_file():
        print(f"== making the body set {bodies}: meshseq make-bodies {' '.join(BODY_SET)}", flush=True)
        bodies.parent.mkdir(parents=True, exist_ok=True)
        if cli(["make-bodies", *BODY_SET, "-o", str(bodies), "--quiet"]) != 0:
            raise SystemExit(f"making {bodies} failed")
    with h5py.File(bodies, "r") as fh:
        return [f"{bodies}:{k}" for k in sorted(fh.keys()) if k != "faces"]


def train_run(specs: list[str], name: str, run: Path, variant: str, args) -> dict:
    from meshseq.checkpoint import best_folder, best_validation, list_checkpoints
    from meshseq.data.windows import split_frames
    from meshseq.train import RECIPE_OPTIONS, RECIPES, TrainConfig, load_training_data, train

    model_opts, weights = VARIANTS[variant]
    options = {**RECIPES[args.recipe], **weights}
    if args.lr is not None:
        options["lr"] = args.lr
    data = load_training_data(specs)
    holdout = HOLDOUT.get(name, 0.2)
    # a sequence shorter than a window plus its held-out part (horse-gallop: 48 frames, 29 for
    # training) trains on windows as long as its training part
    # (with --validation, its block comes out of the training part too)
    shortest = min(len(split_frames(len(f), holdout, "end", args.validation).train_frames())
                   for f in data.features) // args.stride
    window = min(args.window, shortest)
    config = TrainConfig(iterations=args.iterations, window=window, batch=args.batch, stride=args.stride,
                         seed=args.seed, checkpoint_every=max(50, args.iterations // 4),
                         eval_every=args.eval_every if args.validation else 0,
                         holdout=holdout, validation=args.validation, **options)
    out = train(data, run, config, model_options=dict(model_opts, latent=args.latent),
                device=args.device, resume=bool(list_checkpoints(run)), progress=not args.quiet)
    newest = list_checkpoints(run)[-1]  # the options the run really trained with (a resume keeps its own)
    stored = TrainConfig.from_dict(json.loads((newest / "model.json").read_text())["train"])
    # the window trained on: the recipe's window_fit may have shortened it further (fitted_window)
    result = {"seconds": training_seconds(run), "iteration": out["iteration"], "loss": out["loss"],
              "window": stored.window,
              "options": {k: getattr(stored, k) for k in RECIPE_OPTIONS}}
    if stored.validation:  # evaluate the checkpoint chosen on the validation block
        best = out.get("best") or {**best_validation(run), "checkpoint": str(best_folder(run))}
        result.update(validation=stored.validation, best=best, last_iteration=out["iteration"],
                      iteration=best["iteration"], checkpoint=best["checkpoint"])
    return result


def training_seconds(run: Path) -> float:
    """Training time of a run over all its invocations, from its metrics.csv: ``seconds`` counts
    from the start of each invocation, so every drop starts a new one."""
    import csv

    with open(run / "metrics.csv", newline="") as fh:
        seconds = [float(r["seconds"]) for r in csv.DictReader(fh) if r.get("seconds")]
    ends = [a for a, b in zip(seconds, seconds[1:]) if b < a]
    return sum(ends) + (seconds[-1] if seconds else 0.0)


def evaluate_run(data: str, run: Path, out_json: Path, plots: Path | None, args, baselines: bool,
                 iteration: int) -> dict:
    """``meshseq evaluate`` of one sequence; an evaluation of the same checkpoint iteration with
    the same gaps already in ``out_json`` is reused (a restarted paper.py does not redo it)."""
    from meshseq.cli import main

    if out_json.is_file() and plots is None:
        done = json.loads(out_json.read_text())
        gaps = sorted(done.get("completion", {})) == sorted(args.gaps.split(",")) or not baselines
        if done.get("iteration") == iteration and gaps and ("vae_latent" in done["errors"]) == baselines:
            print(f"   reusing {out_json} (iteration {iteration})", flush=True)
            return done

    argv = ["evaluate", str(run), data, "--json", str(out_json), "--force", "--device", args.device,
            "--vae-iterations", str(args.vae_iterations), "--cma-evals", str(args.cma_evals),
            "--cma-seconds", str(args.cma_seconds), "--gaps", args.gaps]
    if not baselines:
        argv += ["--methods", "ours", "--gaps", "none"]
    if plots is not None:
        argv += ["--plots", str(plots)]
    if main(argv) != 0:
        raise SystemExit(f"evaluation of {run} failed")
    return json.loads(out_json.read_text())


def _weighted(values: list[float], weights: list[float]) -> float:
    return float(sum(v * w for v, w in zip(values, weights)) / max(sum(weights), 1e-30))


def combine_results(per_sequence: list[dict]) -> dict:
    """One result from the evaluations of several sequences of one run (``meshseq evaluate
    --json`` each): errors averaged over every start of every sequence (weights: the starts per
    number of given frames), completion over every gap's starts, Fig. 3 curves averaged."""
    if len(per_sequence) == 1:
        return per_sequence[0]
    first = per_sequence[0]
    out = {"dataset": f"{len(per_sequence)} sequences", "range": first["range"], "units": first["units"],
           "iteration": first["iteration"], "variant": first["variant"],
           "notes": sorted({n for r in per_sequence for n in r.get("notes", [])}),
           "sequences": {r["dataset"]: {"range": r["range"], "errors": r["errors"]} for r in per_sequence}}
    for key in ("errors", "errors_aligned", "errors_per_diagonal", "errors_aligned_per_diagonal"):
        if key not in first:
            continue
        out[key] = {m: {u: {h: _weighted([r[key][m][u][h] for r in per_sequence],
                                         [r["starts"][u] for r in per_sequence]) for h in per_h}
                        for u, per_h in per_u.items()} for m, per_u in first[key].items()}
    out["starts"] = {u: sum(r["starts"][u] for r in per_sequence) for u in first["starts"]}
    fc = first["feature_change"]
    out["feature_change"] = {m: ([sum(r["feature_change"][m][i] for r in per_sequence) / len(per_sequence)
                                  for i in range(len(c))] if isinstance(c, list) else
                                 sum(r["feature_change"][m] for r in per_sequence) / len(per_sequence))
                             for m, c in fc.items()}
    if "completion" in first:
        out["completion"] = {}
        for gap in first["completion"]:
            rs = [r["completion"][gap] for r in per_sequence if gap in r.get("completion", {})]
            w = [c["starts"] for c in rs]
            out["completion"][gap] = {k: _weighted([c[k] for c in rs], w) for k in rs[0] if k != "starts"}
            out["completion"][gap]["starts"] = sum(w)
    return out


#: The data sets of the paper's protocol here (the body set is ``bodies``), in the order shown.
TARGET_SETS = ("bodies", "horse-gallop", "crane", "pcow")
PAPER_ITERATIONS = 7000
MOTION_FRAMES = 50
CELLS = [(u, h) for u in ("u1", "u3") for h in ("5", "10", "15")]
README_BEGIN = "<!-- results: made by `python benchmarks/paper.py --markdown-only` from docs/results/*.json -->"
README_END = "<!-- end of results -->"


def recipe_text(options: dict | None, window_kept: bool = False) -> str:
    """How a record's training options differ from today's default recipe, in a few words.

    Options a record lacks were added after it was made: it trained with their legacy values
    (``LEGACY_TRAIN_DEFAULTS``). Records without options predate the motion term.
    ``window_kept``: the default's window rule (``window_fit``) would have kept the record's
    window, so a record made without the rule counts as made with it. ``rollback`` is left out: it
    changes nothing in a run whose loss never blew up, and a run that blew up without it trained on
    from noise (its figures would show it)."""
    from meshseq.train import LEGACY_TRAIN_DEFAULTS, RECIPES

    if not options:
        return "w_motion 0 (no options recorded)"
    used = {**LEGACY_TRAIN_DEFAULTS, **options}
    diff = [f"{k} {used[k]}" for k, v in RECIPES["default"].items() if k in used and used[k] != v
            and not (k == "window_fit" and window_kept) and k != "rollback"]
    return "default recipe" if not diff else "default recipe except " + ", ".join(diff)


def window_kept(heldout: list[int], trained: int | None, window: int = 32, batch: int = 8) -> bool:
    """Whether a record trained on windows of ``trained`` frames (None: older records, the paper's
    window or the training part if shorter) trained on the window the default recipe's rule gives
    sequences whose held-out part is ``heldout = [lo, hi]`` (the records' sets have sequences of
    one length, ``lo`` training frames): then its ``window_fit none`` made no difference."""
    from meshseq.data.windows import fitted_window

    return fitted_window([heldout[0]], window, batch, 1) == (trained or min(window, heldout[0]))


def run_recipe(summary: dict, variant: str = "bd") -> str:
    """``recipe_text`` of one variant's run in a record."""
    run, res = summary["runs"].get(variant, {}), summary["results"].get(variant)
    if res is None:
        return recipe_text(run.get("options"))
    return recipe_text(run.get("options"), window_kept(res["range"], run.get("window")))


def shipped_records(summaries: dict) -> dict[str, str]:
    """``{data set: record name}``: per data set, the record of bd with baselines trained with
    today's default recipe (the checkpoint of its last iteration, not one chosen on a validation
    block), the one with the most iterations."""
    out = {}
    for base in TARGET_SETS:
        best = None
        for name, summ in summaries.items():
            bd = summ["results"].get("bd")
            if (name != base and not name.startswith(base + "-")) or not bd or len(bd["errors"]) < 2:
                continue
            if summ["runs"]["bd"].get("validation") or run_recipe(summ) != "default recipe":
                continue
            if best is None or bd["iteration"] > summaries[best]["results"]["bd"]["iteration"]:
                best = name
        if best:
            out[base] = best
    return out


def prediction_ratios(result: dict) -> list[float]:
    """Ours over the best baseline at h10 and h15 after 1 and 3 given frames, raw then rigid (8)."""
    ratios = []
    for key in ("errors", "errors_aligned"):
        errs = result[key]
        for u in ("u1", "u3"):
            for h in ("10", "15"):
                ratios.append(errs["ours"][u][h] / min(errs[b][u][h] for b in BASELINES if b in errs))
    return ratios


def motion_level(result: dict) -> float:
    """Mean feature change of the first ``MOTION_FRAMES`` generated frames over the truth's (Fig. 3)."""
    fc = result["feature_change"]
    head = fc["ours"][:MOTION_FRAMES]
    return sum(head) / len(head) / fc["ground_truth"]


def _completion_cell(result: dict, gap: str) -> str:
    comp = result.get("completion", {})
    if gap not in comp:
        return "does not fit"
    c = comp[gap]
    lin = min(c["linear"], c.get("linear_vertices", float("inf")))
    return f"{c['ours'] / lin:.2f}"


def shipped_table(summaries: dict, shipped: dict[str, str]) -> list[str]:
    """The shipped recipe on every data set: one row each (the README's table too)."""
    lines = ["| data | iterations | prediction: ours / best baseline (8 cells) | cells below 1 | "
             "completion gap 10 / 20: ours / linear | motion level |", "|---|---|---|---|---|---|"]
    for base, name in shipped.items():
        bd = summaries[name]["results"]["bd"]
        r = prediction_ratios(bd)
        lines.append(f"| {base} | {bd['iteration']} of {PAPER_ITERATIONS} | {min(r):.2f}-{max(r):.2f} "
                     f"(mean {sum(r) / len(r):.2f}) | {sum(x < 1 for x in r)} of {len(r)} | "
                     f"{_completion_cell(bd, '10')} / {_completion_cell(bd, '20')} | {motion_level(bd):.2f} |")
    return lines


def _row(values: dict, keys) -> str:
    return " | ".join(f"{values[u][h]:.1f}" for u, h in keys)


def _mean6(errors: dict) -> float:
    return sum(errors[u][h] for u, h in CELLS) / len(CELLS)


def ablation_records(summaries: dict) -> list[str]:
    """The body-set ablation records (all four variants) trained with today's default recipe: the
    family (NAME, NAME-s1 ...) with the most seeds, NAME first."""
    families: dict[str, list[str]] = {}
    for name, summ in summaries.items():
        if name.startswith("bodies-") and len(summ["runs"]) == 4 and run_recipe(summ) == "default recipe":
            families.setdefault(re.sub(r"-s\d+$", "", name), []).append(name)
    if not families:
        return []
    return sorted(max(families.values(), key=len), key=lambda n: (len(n), n))


def ablation_table(summaries: dict) -> list[str]:
    """Table 1 from the body-set ablation records trained with today's default recipe (one per
    seed: NAME, NAME-s1 ...), the 6 cells averaged over the seeds."""
    names = ablation_records(summaries)
    if not names:
        return ["No ablation record with today's default recipe."]
    head = " | ".join(f"{u[1]} given, h={h}" for u, h in CELLS)
    its = summaries[names[0]]["config"]["iterations"]
    lines = [f"Records {', '.join(f'`{n}.json`' for n in names)} ({len(names)} seeds, {its} iterations each, "
             "the body set, ours only); errors x 1e-4, each cell the mean over the seeds:", "",
             f"| variant | {head} | mean | " + " | ".join(f"mean, seed of `{n}`" for n in names) + " |",
             "|---" * (len(CELLS) + 2 + len(names)) + "|"]
    for variant in ("bd", "std-bd", "uni", "no-kl"):
        per_seed = [summaries[n]["results"].get(variant) for n in names]
        if any(r is None for r in per_seed):
            continue
        cells = {u: {h: sum(r["errors"]["ours"][u][h] for r in per_seed) / len(per_seed) for _, h in CELLS}
                 for u in ("u1", "u3")}
        lines.append(f"| {variant} | {_row(cells, CELLS)} | {_mean6(cells):.1f} | "
                     + " | ".join(f"{_mean6(r['errors']['ours']):.1f}" for r in per_seed) + " |")
    return lines


def dataset_section(base: str, name: str, summ: dict) -> list[str]:
    """Table 2, completion and Fig. 3 of one shipped record."""
    bd, run = summ["results"]["bd"], summ["runs"]["bd"]
    head = " | ".join(f"{u[1]} given, h={h}" for u, h in CELLS)
    seqs = sorted(bd.get("sequences", {}))
    lines = [f"### {base}", "",
             f"Record `docs/results/{name}.json`: `python benchmarks/paper.py {' '.join(summ['argv'])}`; "
             f"{bd['iteration']} iterations, {summ['config']['batch']} windows x {run.get('window', summ['config']['window'])} "
             f"frames, latent {summ['config']['latent']}, {run['seconds'] / 3600:.1f} h of training; held-out frames "
             f"{bd['range']}" + (f" of each of its {len(seqs)} sequences" if seqs else "") + ".", "",
             f"| method | {head} |", "|---" * (len(CELLS) + 1) + "|"]
    for m, per_u in bd["errors"].items():
        lines.append(f"| {m} | {_row(per_u, CELLS)} |")
    lines += ["", "After rigid (Kabsch) alignment:", "", f"| method | {head} |", "|---" * (len(CELLS) + 1) + "|"]
    for m, per_u in bd["errors_aligned"].items():
        lines.append(f"| {m} | {_row(per_u, CELLS)} |")
    lines.append("")
    comp = bd.get("completion", {})
    if comp:
        lines += ["| completion gap | ours | stitch (paper) | CMA-ES | linear (ACAP) | linear (vertices) | diversity |",
                  "|---|---|---|---|---|---|---|"]
        for gap, c in comp.items():
            lines.append(f"| {gap} | {c['ours']:.1f} | {c.get('stitch', float('nan')):.1f} | {c['cma']:.1f} | "
                         f"{c['linear']:.1f} | {c.get('linear_vertices', float('nan')):.1f} | {c.get('diversity', 0):.1f} |")
        lines.append("")
    lines += [f"Fig. 3: motion level {motion_level(bd):.2f} of the truth's over the first {MOTION_FRAMES} generated "
              f"frames. ![feature change {name}](img/feature_change_{name}.png)", ""]
    return lines


def record_list(summaries: dict, shipped: dict[str, str]) -> list[str]:
    """Every record: what it is and how its recipe differs from today's default."""
    lines = ["| record | command (`python benchmarks/paper.py ...`) | recipe of bd | used above |", "|---|---|---|---|"]
    shown, ablation = set(shipped.values()), set(ablation_records(summaries))
    for name, summ in summaries.items():
        variants = ", ".join(summ["runs"])
        args = " ".join(a for a in summ.get("argv", []) if a not in ("--quiet",))
        lines.append(f"| `{name}.json` ({variants}) | `{args}` | {run_recipe(summ)} | "
                     + ("shipped recipe" if name in shown else "ablations" if name in ablation else "") + " |")
    return lines


#: The generalisation benchmark's own sets; records of any other set name are controlled runs.
BENCHMARK_SETS = ("bodies", "bodies-parts", "crane", "horse-gallop", "pcow")


def _generalize_module():
    import importlib.util

    spec = importlib.util.spec_from_file_location("generalize_benchmark", Path(__file__).with_name("generalize.py"))
    generalize = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(generalize)
    return generalize


def generalization_section(files: list[Path]) -> list[str]:
    """The generalisation benchmark's tables (``benchmarks/generalize.py``) of its records ``files``:
    the benchmark's sets, their targets, then the controlled runs (other set names)."""
    if not files:
        return []
    generalize = _generalize_module()
    sets = {f: json.loads(Path(f).read_text())["set"] for f in files}
    bench = [str(f) for f in files if sets[f] in BENCHMARK_SETS]
    controlled = [str(f) for f in files if sets[f] not in BENCHMARK_SETS]
    lines = ["## Generalisation: the default recipe on every capture, no per-set options", "",
             "Made by `benchmarks/generalize.py` (records in `docs/results/generalize/`): each set trained with "
             "every default (seed 0 unless its row names another) for the iterations its row says, then scored on blocks it never saw: the held-out end "
             "of each capture (and for pcow a block inside it as well, `--blocks 0.5`: its frames 102-142), and for the body set the sequences of one subject (male_slim) and one motion "
             "(shake_arms) held out entirely; bodies-parts is the same set made with `make-bodies --parts eyes,strap` "
             "(two eyes and a bag strap as separate parts, 1,612 vertices). Novelty: the block's median distance to the nearest training frame "
             "in typical training steps (1 = one step away). Motion: the block's mean vertex motion per frame over "
             "the training part's. Prediction: ours (`predict`'s default, the novelty guard and the carried velocity "
             "included; records trained before the carry was fitted were scored with 0.6, the body set's share, which the fit on "
             "the training frames keeps on the runs measured (a body-set, a multi-part and a pcow run); horse-gallop's was "
             "trained with the fit, which gave it 0: [method.md](method.md#5-synthesis)) over the best of zero velocity, linear ACAP extrapolation and "
             "the VAE latent (centroid-aligned; rigid: also rotation-aligned); a row that names a pace was scored "
             "with that rule (`predict --pace`) because its checkpoint was not kept to score it again, and one "
             "that names trust warm-up completed with the rule before (the chains trusted where the frames around "
             "the keys moved at the pace the model's warm-up expected), and one that names temporal logs trained on "
             "features whose first frame was walked breadth-first (`consistency = \"temporal\"`, the default "
             "before the smallest-turn walk: [method.md](method.md#2-reconstruction-features-to-vertices); a "
             "single capture's features are the same under both). Completion: ours (`complete`'s default, "
             "7 frames around the keys included) over the better "
             "linear interpolation (ACAP features or vertices) between keys that far apart. Motion of 50: the "
             "feature change of 50 generated frames over the truth's. -: the block is shorter than the horizon or gap "
             "needs (horse-gallop's held-out end is its last 10 frames).", "",
             *generalize.table(bench).splitlines(), "",
             "### Targets", "",
             "What the benchmark holds each record to, and its worst cell for each (bold: missed, and where). "
             "Prediction at h10 and h15, 1 and 3 given frames, raw and rigid: below the best baseline on blocks "
             "whose motion training shows (a held-out subject's trained motions, a held-out end within one typical "
             "step of training), at most 1.5x on a novel block (a motion never trained on, or a held-out end "
             "farther away). Completion over the better interpolation, mean over the record's blocks. Motion of 50: "
             "every block. Held-out subject: every h15 cell and gap 30 of the subject's blocks. Why the missed "
             "targets are missed and what would meet them: "
             "[method.md](method.md#what-the-generalisation-benchmark-leaves-unmet).", "",
             *generalize.targets_table(bench).splitlines(), ""]
    if controlled:
        commands = [f"- {json.loads(Path(f).read_text())['set']}: `{json.loads(Path(f).read_text())['command']}`"
                    for f in controlled]
        lines += ["### Controlled runs", "",
                  "A benchmark run with one thing changed (seed and budget kept), named by its set: bodies-* the "
                  "body set's, bodies-parts-* the multi-part set's, CAPTURE-holdoutF the capture with only the last F "
                  "of its frames held out, so that training shows the first part of the benchmark's held-out end "
                  "([method.md](method.md#what-the-generalisation-benchmark-leaves-unmet) says what each changes):", "",
                  *commands, "", *generalize.table(controlled).splitlines(), "",
                  *generalize.targets_table(controlled).splitlines(), ""]
    return lines


def write_markdown(summaries: dict, device: str, path: Path, readme: Path | None = None,
                   generalization: list[Path] | None = None) -> None:
    """docs/results.md from ``{data set: summary}`` (see ``main``: results, runs, config, argv) and the
    generalisation records, and the table between ``README_BEGIN`` and ``README_END`` in ``readme``."""
    shipped = shipped_records(summaries)
    table = shipped_table(summaries, shipped)
    lines = [
        "# Results",
        "",
        "Everything on this page is computed from the records in `docs/results/` (one JSON per data set "
        "and tag, written by `benchmarks/paper.py` after it trains and evaluates) by",
        "",
        "    python benchmarks/paper.py --markdown-only",
        "",
        "which also rewrites the results table of README.md. Nothing here is typed by hand. Errors: mean "
        "per-vertex distance in the data's units x 1e-4 on the held-out end of each sequence (the last 20%; "
        "horse-gallop 40%), averaged over every start with enough frames, translation removed (centroids); "
        "\"rigid\" also removes the best rotation. Baselines: zero velocity, linear extrapolation of the ACAP "
        "features, and the latent extrapolation of a mesh VAE (standing in for Tan et al. 2018). "
        "Completion: in-between error against linear interpolation of the ACAP features and of the "
        "vertices (the better of the two). Motion level: the feature change of the generated frames over "
        "the truth's (Fig. 3 of the paper; 1 = moves as much as the truth). The paper trains 7000 "
        "iterations of 8 windows x 32 frames; the runs here stop earlier where the CPU budget ran out, as "
        "each row says. Data: [docs/guide.md](guide.md#data); the body set is `meshseq make-bodies "
        + " ".join(BODY_SET) + "` (16 sequences of 120 frames at 1,000 vertices).",
        "",
        "## The shipped recipe on each data set",
        "",
        "Per data set the longest record trained with today's default recipe (`meshseq train` as shipped):",
        "",
        *table,
        "",
        "Ratios below 1: ours is better than every baseline (h10 and h15, 1 and 3 given frames, raw and "
        "rigid). Completion below 1: better than both linear interpolations. Why horse-gallop, crane and "
        "pcow differ from the body set: [method.md](method.md#what-the-data-can-teach).",
        "",
    ]
    for base, name in shipped.items():
        lines += dataset_section(base, name, summaries[name])
    lines += generalization_section(list(generalization or []))
    lines += ["## Ablations (the paper's Table 1)", "",
              "bd: the shared-weight bidirectional LSTM (ours); std-bd: two LSTMs, one per direction; uni: "
              "the forward chain only, no L_bd; no-kl: bd without L_KL.", "",
              *ablation_table(summaries), "",
              "## Records", "",
              "Which figure comes from which record. Records whose recipe differs from today's default are "
              "kept as the evidence behind the decisions in [method.md](method.md); the tables above use "
              "only the rows marked \"shipped recipe\" and \"ablations\".", "",
              *record_list(summaries, shipped), ""]
    notes = sorted({n for name in shipped.values() for n in summaries[name]["results"]["bd"].get("notes", [])})
    lines += [f"Note: {n}." for n in notes]
    from meshseq.io import atomic_output

    with atomic_output(path, force=True) as tmp:
        Path(tmp).write_text("\n".join(lines).rstrip() + "\n")
    if readme is not None and readme.is_file():
        update_readme(readme, table)


def update_readme(readme: Path, table: list[str]) -> None:
    """Replace the lines between ``README_BEGIN`` and ``README_END`` in ``readme`` by ``table``."""
    text = readme.read_text()
    if README_BEGIN not in text or README_END not in text:
        return
    head, rest = text.split(README_BEGIN, 1)
    tail = rest.split(README_END, 1)[1]
    readme.write_text(head + README_BEGIN + "\n" + "\n".join(table) + "\n" + README_END + tail)



def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", default="pcow,crane,horse-gallop",
                    help="names in ../shared/data (without .npz), or bodies (--bodies)")
    ap.add_argument("--bodies", default=str(ROOT / "runs" / "bodies1k.h5"),
                    help="the body set of --data bodies (made with BODY_SET when missing)")
    ap.add_argument("--gaps", default=GAPS, help="completion gaps (meshseq evaluate --gaps)")
    ap.add_argument("--variants", default="bd,std-bd,uni,no-kl")
    ap.add_argument("--recipe", default="default", help="training recipe (meshseq.train.RECIPES): default or paper")
    ap.add_argument("--iterations", type=int, default=500)
    ap.add_argument("--lr", type=float, default=None, help="Adam learning rate (default: the recipe's, 1e-3)")
    ap.add_argument("--window", type=int, default=32)
    ap.add_argument("--batch", type=int, default=8)
    ap.add_argument("--stride", type=int, default=1)
    ap.add_argument("--latent", type=int, default=128)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--validation", type=float, default=0.0,
                    help="meshseq train --validation: keep this fraction of the training frames as a validation "
                    "block and evaluate the checkpoint with the lowest validation error (default 0: the last)")
    ap.add_argument("--eval-every", type=int, default=100, help="with --validation: validate every K iterations")
    ap.add_argument("--device", default="auto")
    ap.add_argument("--vae-iterations", type=int, default=1000)
    ap.add_argument("--cma-evals", type=int, default=200)
    ap.add_argument("--cma-seconds", type=float, default=30.0)
    ap.add_argument("--out", default=str(ROOT / "runs" / "paper"))
    ap.add_argument("--results", default=str(ROOT / "docs" / "results.md"))
    ap.add_argument("--readme", default=str(ROOT / "README.md"),
                    help="the README whose results table (between its markers) is rewritten")
    ap.add_argument("--records", default=str(ROOT / "docs" / "results"),
                    help="one summary JSON per data set; the Markdown is made from every record here")
    ap.add_argument("--markdown-only", action="store_true",
                    help="train nothing: write --results from the records in --records")
    ap.add_argument("--tag", default="",
                    help="record and run folder NAME-TAG instead of NAME (e.g. Table 1 at another budget)")
    ap.add_argument("--no-baselines", action="store_true",
                    help="evaluate ours only (Table 1), also for bd: no baselines, completion or Fig. 3")
    ap.add_argument("--quiet", action="store_true", help="no progress bars")
    args = ap.parse_args()
    if args.markdown_only:
        write_markdown(collect(Path(args.records)), args.device, Path(args.results), Path(args.readme),
                       generalization_records(Path(args.records)))
        print(f"wrote {args.results}")
        return
    args.argv = [a for a in os.sys.argv[1:]]
    out = Path(args.out)
    results, runs = {}, {}
    img = Path(args.results).parent / "img"  # noqa: the Fig. 3 PNGs go beside the Markdown
    for name in [d.strip() for d in args.data.split(",") if d.strip()]:
        specs = dataset_specs(name, args)
        key = f"{name}-{args.tag}" if args.tag else name
        results[key], runs[key] = {}, {}
        for variant in [v.strip() for v in args.variants.split(",") if v.strip()]:
            run = out / key / variant
            baselines = variant == "bd" and not args.no_baselines
            print(f"== {name} / {variant}: training {args.iterations} iterations -> {run}", flush=True)
            try:
                runs[key][variant] = train_run(specs, name, run, variant, args)
            except MeshseqError as e:  # a variant that diverges is a result of Table 1, not a crash
                if "diverged" not in str(e):
                    raise
                print(f"   {variant} diverged: {e}", flush=True)
                runs[key][variant] = {"diverged": str(e)}
                _record(args, out, key, results, runs)
                continue
            per_sequence = []
            for i, spec in enumerate(specs):
                plots = run / "plots" if baselines and len(specs) == 1 else None
                suffix = "" if len(specs) == 1 else "_" + spec.rsplit(":", 1)[-1]
                chosen = Path(runs[key][variant].get("checkpoint", run))  # with --validation: the best
                per_sequence.append(evaluate_run(spec, chosen, run / f"evaluation{suffix}.json", plots, args,
                                                 baselines=baselines, iteration=runs[key][variant]["iteration"]))
            r = results[key][variant] = combine_results(per_sequence)
            if baselines:
                img.mkdir(parents=True, exist_ok=True)
                _feature_change_png(r, key, img / f"feature_change_{key}.png")
            _record(args, out, key, results, runs)
    print(f"wrote {args.results}")


def _record(args, out: Path, key: str, results: dict, runs: dict) -> None:
    """Write the record of data set ``key`` (its summary.json and docs/results/KEY.json), then the
    Markdown from every data set recorded (also by earlier invocations)."""
    from meshseq.io import json_text

    config = {k: getattr(args, k) for k in ("iterations", "batch", "window", "stride", "latent")}
    summary = json_text({"results": results[key], "runs": runs[key], "config": config,
                         "argv": args.argv, "recipe": args.recipe, "device": args.device}, indent=None)
    (out / key / "summary.json").write_text(summary)
    _write_text(Path(args.records) / f"{key}.json", summary)
    write_markdown(collect(Path(args.records)), args.device, Path(args.results), Path(args.readme),
                   generalization_records(Path(args.records)))


def _write_text(path: Path, text: str) -> None:
    from meshseq.io import atomic_output

    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_output(path, force=True) as tmp:
        Path(tmp).write_text(text)


def _feature_change_png(result: dict, name: str, path: Path) -> None:
    """Fig. 3 of one data set (curves averaged over its sequences) as a PNG."""
    import numpy as np

    from meshseq import plots

    fc = result["feature_change"]
    fig = plots.feature_change_curve({m: np.array(c) for m, c in fc.items() if m != "ground_truth"},
                                     title=f"{name}: feature change (ground truth mean {fc['ground_truth']:.3g})")
    ax = fig.axes[0]
    ax.axhline(fc["ground_truth"], color="k", ls="--", label="ground truth")
    ax.legend()
    plots.save_figure(fig, path, force=True)


def generalization_records(records: Path) -> list[Path]:
    """The generalisation benchmark's records kept beside the paper's (``records/generalize/*.json``)."""
    return sorted((records / "generalize").glob("*.json"))


def collect(records: Path) -> dict:
    """``{data set: summary}`` of every data set recorded in ``records`` (``NAME.json``)."""
    return {p.stem: json.loads(p.read_text()) for p in sorted(records.glob("*.json"))}


if __name__ == "__main__":
    main()
