"""meshseq commands of synthesis and evaluation: ``predict``, ``complete``, ``evaluate``.

Nothing heavy is imported at module level or by ``register``: each command imports what it uses
(numpy, torch through the model, ...), so ``--help`` answers at once and a command pays only for
its own imports.
"""

from __future__ import annotations

import warnings
from pathlib import Path

from meshseq.errors import MeshseqError, MeshseqWarning

#: ``meshseq.baselines.PREDICTION_METHODS`` and ``COMPLETION_METHODS``, kept here so that building
#: the parser does not import torch (tests/test_synthesis.py checks that they match)
PREDICTION_METHODS = ("ours", "zero_velocity", "linear_acap", "vae_latent")
COMPLETION_METHODS = ("ours", "corrected", "stitch", "cma", "linear", "linear_vertices")
#: ``meshseq.synthesize.PACES`` (the same check)
PACES = ("given", "warm-up", "model")
#: prediction's guard against given frames unlike the training frames (``meshseq.novelty``)
GUARDS = ("novelty", "off")
#: ``meshseq.synthesize.CONTEXT`` (the same check)
CONTEXT = 7
#: ``meshseq.synthesize.CARRY`` (the same check)
CARRY = 0.6
#: given frames of ``predict`` where DATA holds them (from 2 on the roll-out follows their direction and
#: pace: method.md, "5. Synthesis")
DEFAULT_GIVEN = 3


def register(sub) -> None:
    """Add ``predict``, ``complete`` and ``evaluate`` to the ``meshseq`` parser's subparsers."""
    p = sub.add_parser("predict", help="continue a motion from given frames",
                       description="Feed U given frames of DATA (from --start) to a trained model and "
                       "generate N more. Writes the given frames followed by the generated ones; the "
                       "first generated frame continues from the last given one.")
    _run_data(p)
    p.add_argument("--start", type=int, default=0, metavar="F", help="first given frame (default 0)")
    p.add_argument("--given", type=int, default=None, metavar="U",
                   help=f"how many frames to give (default {DEFAULT_GIVEN}, or as many as DATA holds from --start: "
                   "one frame says nothing of the motion's direction or pace)")
    p.add_argument("--frames", type=int, default=60, metavar="N", help="frames to generate (default 60)")
    p.add_argument("--method", choices=PREDICTION_METHODS, default="ours",
                   help="ours (the trained model, default) or a baseline: zero_velocity, linear_acap, "
                   "vae_latent (a mesh VAE trained on the run's training frames on first use)")
    p.add_argument("--pace", choices=PACES, default=PACES[0],
                   help="given (default): with --given 2 or more, slow the roll-out to the given frames' pace "
                   "where they move slower than the training frames nearest them (a pose held still stays "
                   "still); warm-up: slower than the model predicted them; model: the roll-out as trained")
    p.add_argument("--guard", choices=GUARDS, default=GUARDS[0],
                   help="novelty (default): where the given frames are unlike every training frame, or head "
                   "where no training frame near them went, blend the roll-out towards the given motion "
                   "continued and slowing (the model's own motion there is a guess); off: the roll-out "
                   "alone (the paper's)")
    p.add_argument("--carry", type=float, default=None, metavar="SHARE",
                   help="with --given 2 or more, the generated steps start from the given frames' velocity, its "
                   "difference from the model's own fading by this share a frame (default: the run's, fitted on "
                   f"its training frames; {CARRY} for older runs); 0: the model's steps as they are (the paper's)")
    _output(p)
    p.set_defaults(func=cmd_predict)

    p = sub.add_parser("complete", help="fill in the frames between keyframes",
                       description="Fill every gap between consecutive keyframes of DATA: the forward "
                       "chain from the first key and the backward chain from the second, joined. "
                       "The output passes exactly through every keyframe.")
    _run_data(p)
    p.add_argument("--keyframes", required=True, metavar="A,B[,C...]",
                   help="increasing frame numbers of DATA to keep as keys")
    p.add_argument("--between", type=int, default=None, metavar="N",
                   help="frames to generate between consecutive keys (default: as many as DATA has there)")
    p.add_argument("--context", type=int, default=CONTEXT, metavar="N",
                   help=f"frames of DATA before the first key and after the last that ours' chains warm up on "
                   f"(default {CONTEXT}); where the keys look like the training frames and these frames move as "
                   "training does there (at its pace, where it went), ours keeps the chains' own motion instead "
                   "of drawing it toward the line between the keys. 0: the keys alone (as --samples K "
                   "always: their random initial states stay apart)")
    p.add_argument("--samples", type=int, default=1, metavar="K",
                   help="K completions from random initial states (default 1: the trained states)")
    p.add_argument("--seed", type=int, default=0, help="seed of the random initial states")
    p.add_argument("--method", choices=COMPLETION_METHODS, default="ours",
                   help="ours (default: the two chains, each corrected to end on the far key, crossfaded, and "
                   "drawn toward the line between the keys as far as they missed the far key: the ACAP features "
                   "with each local rotation turned the short way, blended toward the vertices' straight lines "
                   "by the share the run fitted on its training frames), "
                   "corrected (the same without that pull), stitch (the same chains joined where they agree best, as in the paper), "
                   "cma (CMA-ES over the forward chain's initial state), linear "
                   "(interpolation of ACAP features) or linear_vertices (straight lines between the keys' "
                   "vertices)")
    p.add_argument("--cma-evals", type=int, default=400, help="CMA-ES: at most this many roll-outs per gap")
    p.add_argument("--cma-seconds", type=float, default=60.0, help="CMA-ES: at most this many seconds per gap")
    _output(p)
    p.set_defaults(func=cmd_complete)

    p = sub.add_parser("evaluate", help="the paper's tables on held-out frames",
                       description="Prediction error at several horizons (data units x 1e-4, after "
                       "removing translation and after rigid alignment) for the model and every "
                       "baseline, the feature-change curve, and completion errors, on the held-out "
                       "part of DATA recorded in RUN (or --range).")
    _run_data(p)
    p.add_argument("--given", default="1,3", metavar="U,...", help="numbers of given frames (default 1,3)")
    p.add_argument("--horizons", default="5,10,15", metavar="H,...", help="horizons (default 5,10,15)")
    p.add_argument("--range", default=None, metavar="A:B", help="evaluate on frames [A, B) instead of the held-out part")
    p.add_argument("--methods", default=",".join(PREDICTION_METHODS), metavar="M,...",
                   help=f"prediction methods (default all: {','.join(PREDICTION_METHODS)})")
    p.add_argument("--gaps", default="5,10", metavar="G,...",
                   help="completion gaps (frames between keys) to evaluate; 'none' to skip (default 5,10)")
    p.add_argument("--samples", type=int, default=4, help="completions per gap for the diversity figure (default 4)")
    p.add_argument("--curve-frames", type=int, default=60, help="length of the feature-change curves (default 60)")
    p.add_argument("--vae-iterations", type=int, default=1000, help="training of the VAE baseline (first use)")
    p.add_argument("--cma-evals", type=int, default=200, help="CMA-ES roll-outs per gap (default 200)")
    p.add_argument("--cma-seconds", type=float, default=30.0, help="CMA-ES seconds per gap (default 30)")
    p.add_argument("--guard", choices=GUARDS, default=GUARDS[0],
                   help="ours' prediction as predict makes it: novelty (default) or off (the roll-out alone); "
                   "completion is the same either way")
    p.add_argument("--json", dest="json_out", default=None, metavar="OUT.json", help="write the results as JSON")
    p.add_argument("--plots", default=None, metavar="DIR", help="write error and feature-change plots (PNG) here")
    p.add_argument("--force", action="store_true", help="overwrite outputs")
    p.set_defaults(func=cmd_evaluate)


def _run_data(p) -> None:
    p.add_argument("run", metavar="RUN", help="a training run folder (or one of its checkpoints)")
    p.add_argument("data", metavar="DATA", help="a sequence of the model's mesh (see `meshseq --help`)")
    p.add_argument("--device", default="auto", help="auto (CUDA if available), cpu or cuda; predict and complete run "
                   "on CPU without torch (MESHSEQ_INFERENCE=torch: with it)")


def _output(p) -> None:
    p.add_argument("-o", "--output", required=True, metavar="OUT",
                   help="output: a .npz, a folder path for OBJ frames (--format ply for PLY), or "
                   ".glb, .usd/.usda/.usdc, .mdd/.pc2 (with the base mesh OUT.obj beside it)")
    p.add_argument("--format", choices=("npz", "obj", "ply"), default=None, help="output format (default: from OUT)")
    p.add_argument("--force", action="store_true", help="overwrite OUT if it exists")


def _int_list(text: str, option: str) -> list[int]:
    try:
        values = [int(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise MeshseqError(f"{option} {text!r}: expected comma-separated integers") from None
    if not values:
        raise MeshseqError(f"{option} {text!r}: expected at least one integer")
    return values


def _load(args, backend: str = "torch"):
    """Model (``backend``: ``meshseq.api.load``'s) and sequence, checked against the model's mesh."""
    from meshseq.api import load
    from meshseq.io import load_sequence

    model = load(args.run, device=args.device, backend=backend)
    seq = load_sequence(args.data)
    model.check_mesh(seq.faces, seq.n_vertices, what=args.data)
    return model, seq


def _vae(model, run: str, seq, feats: np.ndarray, exclude: tuple[int, int], iterations: int):
    """The VAE baseline of this run: loaded from RUN/baselines/vae, else trained on the run's
    training frames of this data set (all frames outside ``exclude``) and saved there."""
    import numpy as np

    from meshseq import baselines
    from meshseq.checkpoint import resolve
    from meshseq.mesh import Topology

    topo = Topology.from_faces(model.faces, model.config.n_vertices)
    run_dir = resolve(run)
    folder = (run_dir.parent.parent if run_dir.parent.name == "checkpoints" else run_dir) / "baselines" / "vae"
    if (folder / "vae.json").exists():
        try:
            vae, meta = baselines.load_vae(folder, topo, model.device)
        except MeshseqError as err:  # a cache: train a new one
            warnings.warn(f"{err}; training a new VAE baseline", MeshseqWarning)
        else:
            # a VAE cached before its FC learned at the fan-in rate (vae_param_groups), or before it
            # saw normalised frames (MeshVAE), is retrained
            if meta.get("data") == seq.source and meta.get("exclude") == list(exclude) \
                    and meta.get("fc_lr") == baselines.VAE_FC_LR and vae.config.input_norm:
                return vae
    frames = np.concatenate([feats[: exclude[0]], feats[exclude[1]:]])
    if len(frames) < 2:
        raise MeshseqError(f"{seq.source}: no training frames outside {exclude[0]}:{exclude[1]} for the VAE baseline")
    vae = baselines.train_vae(frames, topo, latent=model.config.latent, iterations=iterations, device=model.device)
    baselines.save_vae(vae, folder, {"data": seq.source, "exclude": list(exclude), "iterations": iterations,
                                     "fc_lr": baselines.VAE_FC_LR, "note": baselines.VAE_NOTE})
    return vae


def _heldout(model, seq, range_text: str | None) -> tuple[int, int]:
    if range_text:
        try:
            a, b = (int(v) for v in range_text.split(":"))
        except ValueError:
            raise MeshseqError(f"--range {range_text!r}: expected A:B (frame numbers)") from None
        if not 0 <= a < b <= seq.n_frames:
            raise MeshseqError(f"--range {range_text}: must satisfy 0 <= A < B <= {seq.n_frames} (frames of {seq.source})")
        return a, b
    src = str(Path(seq.source).resolve()) if seq.source else ""
    for d in model.meta.get("datasets", []):
        same = d.get("source") and Path(d["source"]).exists() and str(Path(d["source"]).resolve()) == src
        if same or (d.get("name") == seq.name and d.get("n_frames") == seq.n_frames):
            lo, hi = d["split"]["heldout"]
            if hi <= lo:
                raise MeshseqError(f"{seq.source}: the run held out no frames of it; give --range A:B")
            return int(lo), int(hi)
    names = ", ".join(d.get("source", d.get("name", "?")) for d in model.meta.get("datasets", []))
    raise MeshseqError(f"{seq.source}: not one of the run's data sets ({names}); give --range A:B")


def _write(seq_vertices: np.ndarray, faces: np.ndarray, name: str, args, fps=None) -> Path:
    from meshseq.io import MeshSequence, save_sequence

    out = MeshSequence(seq_vertices, faces, name=name, fps=fps)
    return save_sequence(out, args.output, format=args.format, force=args.force)


# --------------------------------------------------------------------------------------------


def cmd_predict(args) -> int:
    from meshseq.device import inference_setup

    backend = inference_setup(args.device)  # (before numpy loads)
    import numpy as np

    from meshseq import baselines, synthesize
    from meshseq.io import check_output

    check_output(args.output, force=args.force)
    if args.given is not None and args.given < 1:
        raise MeshseqError(f"--given {args.given}: expected at least 1")
    if args.frames < 1:
        raise MeshseqError(f"--frames {args.frames}: expected at least 1")
    if args.carry is not None and not 0 <= args.carry < 1:
        raise MeshseqError(f"--carry {args.carry}: expected a share in [0, 1) (0: the model's steps as they are)")
    model, seq = _load(args, backend)
    if not 0 <= args.start < seq.n_frames:
        raise MeshseqError(f"--start {args.start}: {args.data} has frames 0..{seq.n_frames - 1}")
    if args.given is None:
        args.given = min(DEFAULT_GIVEN, seq.n_frames - args.start)
    if args.start + args.given > seq.n_frames:
        raise MeshseqError(f"--given {args.given}: only {seq.n_frames - args.start} frames of {args.data} "
                           f"from --start {args.start}")
    given_v = seq.vertices[args.start:args.start + args.given]
    feats = model.features(given_v)
    if args.method == "ours":
        guard = args.guard == "novelty"
        gen = synthesize.predict(model, feats, args.frames, pace=args.pace, guard=guard, carry=args.carry)
        weight = synthesize.novelty_weights(model, feats[None]) if guard else None
        if weight is not None and weight[0] < 1.0:
            print(f"note: the given frames (their poses, or where they head from there) are unlike the training "
                  f"frames: the prediction is {weight[0]:.0%} the model's, the rest the given motion continued and "
                  "slowing (--guard off: the model alone)")
        if args.carry is None and args.given > 1 and model.carry != CARRY:
            print(f"note: the run carries {model.carry:g} of the given frames' velocity into the roll-out a frame, "
                  f"fitted on its training frames (--carry SHARE to choose)")
    elif args.method == "vae_latent":
        all_feats = model.features(seq.vertices)
        lo, hi = _recorded_heldout(model, seq) or (args.start, args.start + args.given)
        vae = _vae(model, args.run, seq, all_feats, (lo, hi), 1000)
        gen = baselines.vae_latent(vae, feats[None], args.frames)[0]
        print(f"note: {baselines.VAE_NOTE}")
    else:
        gen = getattr(baselines, args.method)(feats[None], args.frames)[0]
    u = args.given
    if args.method == "zero_velocity":
        verts = np.concatenate([given_v, np.repeat(given_v[-1:], args.frames, 0)])
    else:
        allf = np.concatenate([feats, gen])
        verts = synthesize.assemble_vertices(model, allf, {i: given_v[i] for i in range(u)})
    path = _write(verts, seq.faces, f"{seq.name}_predicted", args, seq.fps)
    print(f"wrote {path}: {u} given + {args.frames} generated frames ({args.method})")
    return 0


def _recorded_heldout(model, seq) -> tuple[int, int] | None:
    """The held-out range the run recorded for this data set, or None if it is not one of its sets."""
    try:
        return _heldout(model, seq, None)
    except MeshseqError:
        return None


def cmd_complete(args) -> int:
    from meshseq.device import inference_setup

    backend = inference_setup(args.device)  # (before numpy loads)
    import numpy as np

    from meshseq import baselines, synthesize
    from meshseq.io import MeshSequence, atomic_output, check_output, json_text, save_sequence

    check_output(args.output, force=args.force)
    keys = _int_list(args.keyframes, "--keyframes")
    if len(keys) < 2:
        raise MeshseqError(f"--keyframes {args.keyframes}: give at least two keyframes")
    if any(b <= a for a, b in zip(keys, keys[1:])):
        raise MeshseqError(f"--keyframes {args.keyframes}: keyframes must be strictly increasing")
    if args.samples < 1:
        raise MeshseqError(f"--samples {args.samples}: expected at least 1")
    if args.between is not None and args.between < 0:
        raise MeshseqError(f"--between {args.between}: expected >= 0")
    if args.context < 0:
        raise MeshseqError(f"--context {args.context}: expected >= 0")
    if args.samples > 1 and Path(args.output).suffix:
        raise MeshseqError(f"-o {args.output}: with --samples > 1 the output is a folder (one file per "
                           "sample and diversity.json); give a path without an extension")
    if args.method not in synthesize.METHOD_JOINS and args.samples > 1:
        raise MeshseqError(f"--samples {args.samples}: several samples need --method ours or stitch")
    model, seq = _load(args, backend)
    if keys[0] < 0 or keys[-1] >= seq.n_frames:
        raise MeshseqError(f"--keyframes {args.keyframes}: {args.data} has frames 0..{seq.n_frames - 1}")
    gaps = [args.between if args.between is not None else b - a - 1 for a, b in zip(keys, keys[1:])]
    before = seq.vertices[max(0, keys[0] - args.context):keys[0]]
    after = seq.vertices[keys[-1] + 1:keys[-1] + 1 + args.context]
    samples_v = synthesize.complete_keyframes(model, seq.vertices[keys], gaps, method=args.method,
                                              before=before, after=after,
                                              samples=args.samples, seed=args.seed, cma_evals=args.cma_evals,
                                              cma_seconds=args.cma_seconds)
    if args.samples == 1:
        path = _write(samples_v[0], seq.faces, f"{seq.name}_completed", args, seq.fps)
        lean = model.vertex_share if args.method == "ours" else 0.0
        note = f"; its line {lean:.0%} of the way to the keys' vertex lines, fitted in training" if lean else ""
        print(f"wrote {path}: {len(samples_v[0])} frames through keyframes {keys} ({args.method}{note})")
        return 0
    diversity = baselines.pairwise_diversity(samples_v)
    fmt = args.format or "npz"
    with atomic_output(args.output, force=args.force) as tmp:
        tmp.mkdir()
        for s, verts in enumerate(samples_v):
            name = f"sample_{s:02d}" + (".npz" if fmt == "npz" else "")
            save_sequence(MeshSequence(verts, seq.faces, name=f"{seq.name}_sample{s}", fps=seq.fps),
                          tmp / name, format=fmt)
        (tmp / "diversity.json").write_text(json_text(
            {"samples": args.samples, "seed": args.seed, "keyframes": keys,
             "mean_pairwise_vertex_distance": diversity, "units": "data units"}))
    print(f"wrote {args.samples} completions and diversity.json (mean pairwise distance {diversity:.4g})")
    return 0


def cmd_evaluate(args) -> int:
    import numpy as np

    from meshseq import baselines, evaluate
    from meshseq.io import atomic_output, check_output, json_text
    from meshseq.mesh import bounding_box_diagonal

    if args.json_out:
        check_output(args.json_out, force=args.force)
    if args.plots:
        check_output(args.plots, force=args.force)
    given = _int_list(args.given, "--given")
    horizons = _int_list(args.horizons, "--horizons")
    if min(given) < 1 or min(horizons) < 1:
        raise MeshseqError("--given and --horizons must be positive")
    methods = [m.strip() for m in args.methods.split(",") if m.strip()]
    for m in methods:
        if m not in baselines.PREDICTION_METHODS:
            raise MeshseqError(f"--methods: unknown method {m!r}; expected some of {', '.join(baselines.PREDICTION_METHODS)}")
    gaps = [] if args.gaps.strip().lower() == "none" else _int_list(args.gaps, "--gaps")
    model, seq = _load(args)
    guard = args.guard == "novelty"
    lo, hi = _heldout(model, seq, args.range)
    feats = model.features(seq.vertices)
    vae = _vae(model, args.run, seq, feats, (lo, hi), args.vae_iterations) if "vae_latent" in methods else None
    result = {"dataset": seq.name, "source": seq.source, "range": [lo, hi], "units": "x1e-4",
              "iteration": model.iteration, "variant": model.config.variant,
              "errors": {}, "errors_aligned": {}, "curves": {}, "notes": []}
    stride = int(model.meta.get("train", {}).get("stride", 1))
    vertices = seq.vertices
    if stride > 1:  # the model steps `stride` frames at a time: evaluate on every stride-th frame
        vertices, feats = vertices[lo:hi:stride], feats[lo:hi:stride]
        lo, hi = 0, len(vertices)
        result["stride"] = stride
        result["notes"].append(f"the run was trained with stride {stride}: one predicted step = {stride} frames")
    if vae is not None:
        result["notes"].append(baselines.VAE_NOTE)
    if not guard:
        result["notes"].append("ours' prediction without the novelty guard (--guard off: the roll-out alone, "
                               "as the paper)")
    # scale-free errors: per bounding-box diagonal of the first held-out frame (data units)
    diagonal = bounding_box_diagonal(np.asarray(vertices[lo], dtype=np.float64))
    result["diagonal"] = diagonal
    for u in given:
        errs = evaluate.prediction_errors(model, vertices, feats, lo, hi, u, horizons, methods, vae=vae, guard=guard)
        for m, r in errs.items():
            result["errors"].setdefault(m, {})[f"u{u}"] = r["centroid"]
            result["errors_aligned"].setdefault(m, {})[f"u{u}"] = r["rigid"]
            result["curves"].setdefault(m, {})[f"u{u}"] = r["curve"]
            for key, src in (("errors_per_diagonal", "centroid"), ("errors_aligned_per_diagonal", "rigid")):
                result.setdefault(key, {}).setdefault(m, {})[f"u{u}"] = {
                    h: e * evaluate.UNITS / diagonal for h, e in r[src].items()}
            result.setdefault("starts", {})[f"u{u}"] = r["starts"]
    # two given frames, so the extrapolating baselines have a velocity to continue
    starts = evaluate.prediction_starts(lo, hi, 2, 0)
    result["feature_change"] = evaluate.feature_change(model, feats, starts, 2, args.curve_frames,
                                                       [m for m in methods if m != "zero_velocity"], vae,
                                                       guard=guard)
    if gaps:
        if model.vertex_share:
            result["notes"].append(f"ours' completion: its line between the keys {model.vertex_share:.0%} of the way "
                                   "to the keys' vertex lines (the share fitted on the training frames)")
        result["completion"] = evaluate.completion_errors(
            model, vertices, feats, lo, hi, gaps, list(baselines.COMPLETION_METHODS), samples=args.samples,
            cma_evals=args.cma_evals, cma_seconds=args.cma_seconds, context=CONTEXT)
    _print_tables(result, horizons)
    if args.json_out:
        with atomic_output(args.json_out, force=args.force) as tmp:
            Path(tmp).write_text(json_text(result))
        print(f"wrote {args.json_out}")
    if args.plots:
        _plots(result, args.plots, args.force)
        print(f"wrote plots to {args.plots}/")
    return 0


def _print_tables(result: dict, horizons: list[int]) -> None:
    from rich.console import Console
    from rich.table import Table

    console = Console()
    for key, title in (("errors", "translation removed"), ("errors_aligned", "rigidly aligned")):
        table = Table(title=f"{result['dataset']} frames {result['range'][0]}:{result['range'][1]}: "
                      f"per-vertex error x 1e-4 ({title})")
        table.add_column("method")
        cols = [(u, h) for u in next(iter(result[key].values())) for h in horizons]
        for u, h in cols:
            table.add_column(f"{u} h{h}", justify="right")
        for m, per_u in result[key].items():
            table.add_row(m, *[f"{per_u[u][str(h)]:.1f}" for u, h in cols])
        console.print(table)
    if "completion" in result:
        table = Table(title="completion: in-between error x 1e-4 (and diversity of samples)")
        table.add_column("gap")
        cols = ("ours", "stitch", "cma", "linear", "linear_vertices", "diversity")
        for col in cols:
            table.add_column(col, justify="right")
        for gap, r in result["completion"].items():
            table.add_row(gap, *[f"{r[c]:.1f}" if c in r else "-" for c in cols])
        console.print(table)


def _plots(result: dict, folder: str, force: bool) -> None:
    import numpy as np

    from meshseq import plots
    from meshseq.io import atomic_output

    with atomic_output(folder, force=force) as tmp:
        tmp.mkdir()
        for u in next(iter(result["curves"].values())):
            fig = plots.error_vs_horizon({m: np.array(c[u]) * 1e-4 for m, c in result["curves"].items()},
                                         title=f"{result['dataset']}: error vs horizon ({u})")
            plots.save_figure(fig, tmp / f"error_{u}.png")
        curves = {m: np.array(c) for m, c in result["feature_change"].items() if m != "ground_truth"}
        fig = plots.feature_change_curve(curves, title=f"{result['dataset']}: feature change "
                                         f"(ground truth mean {result['feature_change']['ground_truth']:.3g})")
        ax = fig.axes[0]
        ax.axhline(result["feature_change"]["ground_truth"], color="k", ls="--", label="ground truth")
        ax.legend()
        plots.save_figure(fig, tmp / "feature_change.png")
