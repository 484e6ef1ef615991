"""Generalisation benchmark: the default recipe, no per-set options, on every real capture at hand.

For each set it trains the default recipe with a held-out block (the paper's held-out end, and
blocks inside the sequence with ``--blocks``), then scores the block: prediction (1 and 3 given
frames, horizons 5/10/15, centroid-aligned and rigidly aligned) against zero velocity, linear
ACAP extrapolation and the mesh-VAE latent; completion at gaps 5/10/20/30 against linear
interpolation of the features and of the vertices; the motion level of 50 generated frames
against the truth's; whether predictions keep the pace of their given frames; and the block's
novelty against the training frames and its motion level next to the errors.

    python benchmarks/generalize.py --sets horse-gallop pcow crane bodies --iterations 2000 \\
        --out runs/generalize --bodies bodies1k.h5
    python benchmarks/generalize.py --table runs/generalize/*.json      # Markdown tables, targets

Runs resume (a run folder with checkpoints continues to ``--iterations``), and a finished
evaluation is reused, so a long benchmark continues across sessions. The body set (``bodies``:
every sequence of a ``meshseq make-bodies`` file) trains on all subjects and motions but one
subject and one motion, and scores the held-out subject's and the held-out motion's sequences
whole, as skeletal in-betweening benchmarks hold out subjects. ``--holdout F`` holds out F of a
capture's frames instead of the paper's 0.2 (records ``SET-holdoutF``): with a smaller F, training
shows the first part of the benchmark's held-out end, and ``benchmarks/score_frames.py`` scores the
benchmark's own run on the frames still held out, for comparison.
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
SHARED = Path(os.environ.get("MESHSEQ_SHARED_DATA", ROOT.parent / "shared" / "data"))
HORIZONS = (5, 10, 15)
GAPS = (5, 10, 20, 30)
COMPLETION = ("ours", "stitch", "linear", "linear_vertices")
PREDICTION = ("ours", "zero_velocity", "linear_acap", "vae_latent")
HOLDOUT = 0.2  # the paper's held-out fraction of a capture
HOLD_SUBJECT, HOLD_MOTION = "male_slim", "shake_arms"  # the body set's held-out subject and motion
#: the pace rule of records scored before they named theirs (``synthesize.PACES``)
PACE_UNNAMED = "warm-up"
#: completion's trust in the chains (``synthesize.context_trust``): the frames around the keys at the
#: pace training shows there and heading where it went (``training``), or, in records scored before
#: they named theirs, at the pace the model's warm-up expected (``warm-up``)
TRUST, TRUST_UNNAMED = "training", "warm-up"
#: the line completion's anchored join draws toward: the geodesic one (``synthesize.anchor_line``)
#: blended toward the vertices' by the run's fitted share (``meshseq.inbetween``, ``fitted``), or, in
#: records scored before records named their line, the straight one
LINE, LINE_UNNAMED = "fitted", "straight"


def scored_pace() -> str:
    """The pace rule ours' predictions are scored with: ``predict``'s default."""
    from meshseq.synthesize import PACES

    return PACES[0]


def record_label(rec: dict, block: str = "") -> str:
    """``"bodies, 2000 it"``, with the seed where not 0, the pace and trust rules and completion's
    line where not today's, and the rotation consistency where not today's default and it changes the
    features; ``block`` (``"@ 0.5"``, ``"unseen sequence"``) follows the set's name."""
    seed = rec["train"].get("seed", 0)
    pace, trust = rec.get("pace", PACE_UNNAMED), rec.get("trust", TRUST_UNNAMED)
    anchor = rec.get("line", LINE_UNNAMED)
    return (f"{rec['set']}{f' {block}' if block else ''}, {rec['iteration']} it{f', seed {seed}' if seed else ''}"
            f"{f', pace {pace}' if pace != scored_pace() else ''}{f', trust {trust}' if trust != TRUST else ''}"
            f"{f', {anchor} line' if anchor != LINE else ''}"
            f"{f', {logs} logs' if (logs := record_consistency(rec)) else ''}")


def record_consistency(rec: dict) -> str | None:
    """The rotation consistency a record's run was trained with, where it is not today's default
    and gives other features: on a single capture (its first frame the reference, every
    first-frame rotation the identity) every temporal walk gives the same features."""
    from meshseq.acap import DEFAULT_CONSISTENCY
    from meshseq.checkpoint_schema import UNNAMED_CONSISTENCY

    consistency = rec["train"].get("consistency", UNNAMED_CONSISTENCY)
    return None if consistency == DEFAULT_CONSISTENCY or single_capture(rec) else consistency


def single_capture(rec: dict) -> bool:
    """Whether a record scored one capture's held-out block (a body set's scores unseen sequences)."""
    return rec["train"]["holdout"] != 0


def frames_spec(spec: str) -> tuple[str, tuple[int, int] | None]:
    """``SPEC[@FIRST,STOP]`` -> ``(the sequence's spec, (FIRST, STOP) or None)``, as the benchmark
    scripts take sequences; a file in the shared data folder may be named alone (``pcow.npz``)."""
    path, _, frames = spec.partition("@")
    shared = SHARED / path
    first_stop = tuple(int(x) for x in frames.split(",")) if frames else None
    return (str(shared) if shared.is_file() else path), first_stop


def body_specs(path: str, subject: str, motion: str) -> tuple[list[str], list[str]]:
    """``(training specs, held-out specs)`` of a make-bodies file: every ``SUBJECT_MOTION``
    sequence, those of ``subject`` or ``motion`` held out."""
    import h5py

    with h5py.File(path, "r") as fh:
        names = sorted(k for k in fh.keys() if k != "faces")
    held = [n for n in names if n.startswith(subject + "_") or n.endswith("_" + motion)]
    return [f"{path}:{n}" for n in names if n not in held], [f"{path}:{n}" for n in held]


def novelty(train_feats: np.ndarray, block_feats: np.ndarray) -> float:
    """Median over the block's frames of the distance to the nearest training frame, over the
    median distance between consecutive training frames (1 = one typical step away)."""
    a = train_feats.reshape(len(train_feats), -1).astype(np.float64)
    b = block_feats.reshape(len(block_feats), -1).astype(np.float64)
    d2 = (b * b).sum(1)[:, None] + (a * a).sum(1)[None, :] - 2.0 * b @ a.T
    nearest = np.sqrt(np.maximum(d2.min(1), 0.0))
    step = np.median(np.linalg.norm(np.diff(a, axis=0), axis=1))
    return float(np.median(nearest) / max(step, 1e-12))


def block_gaps(lo: int, hi: int) -> list[int]:
    """The completion gaps (``GAPS``) a block ``[lo, hi)`` is long enough for."""
    return [g for g in GAPS if hi - lo >= g + 2]


def motion_starts(lo: int, hi: int) -> np.ndarray:
    """The starts the motion of 50 is measured from in block ``[lo, hi)``: about 8 of its one-frame
    starts, evenly spaced."""
    from meshseq.evaluate import prediction_starts

    starts = prediction_starts(lo, hi, 1, 1)
    return starts[:: max(1, len(starts) // 8)]


def score_block(model, vae, verts: np.ndarray, feats: np.ndarray, train_feats: np.ndarray, train_level: float,
                lo: int, hi: int, guard: bool = True) -> dict:
    """Every figure of one held-out block ``[lo, hi)`` of one sequence; ``train_level``: the training
    frames' mean vertex motion per frame (``training_level``); ``guard``: ours' predictions with the
    novelty guard (the benchmark's)."""
    from meshseq.evaluate import completion_errors
    from meshseq.pace import step_levels
    from meshseq.synthesize import CONTEXT

    out = {"frames": [int(lo), int(hi)], "novelty": novelty(train_feats, feats[lo:hi]),
           "motion_level": float(np.mean(step_levels(verts[lo:hi])) / max(train_level, 1e-12)),
           "prediction": prediction_scores(model, vae, verts, feats, lo, hi, PREDICTION, guard), "completion": {}}
    gaps = block_gaps(lo, hi)
    out["completion"] = completion_errors(model, verts, feats, lo, hi, gaps, list(COMPLETION), samples=1,
                                          context=CONTEXT)
    out.update(motion_scores(model, verts, feats, train_level, lo, hi, guard))
    return out


def prediction_scores(model, vae, verts: np.ndarray, feats: np.ndarray, lo: int, hi: int, methods,
                      guard: bool = True) -> dict:
    """``{"u1" / "u3": {method: {"centroid" / "rigid": {h: error}}}}`` of one block ``[lo, hi)``
    (``guard``: ours with the novelty guard)."""
    from meshseq.evaluate import prediction_errors, prediction_starts

    out = {}
    for u in (1, 3):
        horizons = [h for h in HORIZONS if len(prediction_starts(lo, hi, u, h))]  # a short block scores fewer
        if not horizons:
            continue
        res = prediction_errors(model, verts, feats, lo, hi, u, horizons, list(methods), vae=vae, guard=guard)
        out[f"u{u}"] = {m: {k: r[k] for k in ("centroid", "rigid")} for m, r in res.items()}
    return out


def motion_scores(model, verts: np.ndarray, feats: np.ndarray, train_level: float, lo: int, hi: int,
                  guard: bool = True) -> dict:
    """``motion_50`` (the feature change of 50 generated frames over the truth's) and ``pace``
    (``pace.pace_table``, where the block is long enough) of one block ``[lo, hi)`` (``guard``: ours
    with the novelty guard)."""
    from meshseq.evaluate import feature_change, prediction_starts
    from meshseq.pace import pace_levels, pace_table
    from meshseq.plots import feature_change as relative_change

    out = {}
    fc = feature_change(model, feats, motion_starts(lo, hi), 1, 50, ["ours"], guard=guard)
    truth = float(relative_change(model.scaling.invert(feats[lo:hi].astype(np.float64))).mean())
    out["motion_50"] = float(np.mean(fc["ours"]) / max(truth, 1e-12))
    starts3 = prediction_starts(lo, hi, 3, 15)
    if len(starts3):
        levels = pace_levels(model, verts, feats, starts3, 3, 15, guard=guard)
        out["pace"] = pace_table(levels, train_level)
    return out


def training_level(specs: list[str], splits) -> float:
    """Mean vertex motion per frame (``pace.step_levels``) over the training segments of ``specs``."""
    from meshseq.io import load_sequence
    from meshseq.pace import step_levels

    levels = [step_levels(load_sequence(spec).vertices[a:b]) for spec, split in zip(specs, splits)
              for a, b in split.train if b - a > 1]
    return float(np.concatenate(levels).mean())


def run_set(name: str, specs: list[str], scored: list[tuple[int | None, str]], args, holdout_at: str,
            holdout: float = HOLDOUT, held_out: dict | None = None) -> dict:
    """Train (or resume) the default recipe on ``specs`` and score the held-out blocks.

    ``scored``: ``(index into specs or None for an unseen sequence, spec)``; ``held_out``: for a
    body set, ``{"subject": ..., "motion": ...}`` held out of training (kept in the record).
    """
    import meshseq
    from meshseq import checkpoint as ckpt
    from meshseq.checkpoint_schema import feature_options
    from meshseq.train import TrainConfig, load_training_data, train

    tag = f"{name}@{holdout_at}"
    run = Path(args.out) / tag.replace("@", "-at-")
    record = Path(args.out) / f"{tag.replace('@', '-at-')}.json"
    if record.exists():
        done = json.loads(record.read_text())
        if done.get("iteration") == args.iterations:
            if args.rescore_prediction:
                done = rescore_prediction(done, run, record, specs, args)
            return rescore_completion(done, run, record, specs, args) if args.rescore_completion else done
    config = TrainConfig(iterations=args.iterations, seed=args.seed, holdout_at=holdout_at, holdout=holdout,
                         eval_every=0,
                         checkpoint_every=min(500, args.iterations), keep=2, **recipe_changes(args.change))
    resume = bool(ckpt.list_checkpoints(run))  # a run stopped before its first checkpoint starts over
    consistency, placement = config.consistency, config.placement
    if resume:  # features as the run was trained on (its stored options)
        consistency, placement = feature_options(ckpt.latest_meta(run))
    data = load_training_data(specs, consistency=consistency, placement=placement)
    t0 = time.perf_counter()
    train(data, run, config, device=args.device, resume=resume, force=not resume, progress=not args.quiet)
    seconds = time.perf_counter() - t0
    model = meshseq.load(run)
    splits = training_splits(model.meta)
    reference = ensure_novelty(model, specs, splits)
    vertex_share = ensure_vertex_share(model, specs, splits)
    train_feats = np.concatenate([model.scaling.apply(f)[a:b] for f, s in zip(data.features, splits) for a, b in s.train])
    held = [(spec, *(splits[index].heldout if index is not None else (None, None))) for index, spec in scored]
    blocks = []
    for block in score_blocks(model, specs, splits, train_feats, held):
        blocks.append(block)
        print(line(tag, block), flush=True)
    out = {"set": name, "holdout_at": holdout_at, "iteration": model.iteration, "seconds_training": seconds,
           "pace": scored_pace(), "trust": TRUST, "line": LINE, "vertex_share": vertex_share, "carry": run_carry(model),
           "train": model.meta["train"], "novelty_reference": reference,
           "blocks": blocks,
           "command": "python benchmarks/generalize.py " + " ".join(args.argv)}
    if held_out:
        out["held_out"] = held_out
    record.write_text(json.dumps(out, indent=1))
    return out


def score_blocks(model, specs: list[str], splits, train_feats: np.ndarray, blocks, guard: bool = True):
    """Every figure of each held-out block ``(spec, lo, hi)`` (``None`` bounds: the whole sequence),
    scored as ``score_block`` scores it (``guard`` too), with the sequence named; ``train_feats``
    ``(T, V, C)``: the training frames of ``specs`` (split by ``splits``), which the VAE baseline is
    trained on first. A generator: each block is yielded when scored."""
    from meshseq.io import load_sequence

    vae = train_vae_baseline(model, train_feats)
    level = training_level(specs, splits)
    for spec, lo, hi in blocks:
        verts = load_sequence(spec).vertices.astype(np.float64)
        feats = model.features(verts)
        block = score_block(model, vae, verts, feats, train_feats, level, 0 if lo is None else lo,
                            len(verts) if hi is None else hi, guard)
        block["sequence"] = spec
        yield block


def recipe_changes(changes: list[str]) -> dict:
    """``--change KEY=VALUE`` options -> TrainConfig fields (for controlled runs: one change against
    the default recipe, named in the record's ``train``): each a line of ``meshseq train --config``
    (VALUE a TOML value; a bare word is taken as a string), checked as that file's lines are."""
    try:
        import tomllib
    except ImportError:  # Python 3.10, as meshseq.training.config.read_toml
        import tomli as tomllib

    from meshseq.errors import MeshseqError
    from meshseq.training.config import config_from_table

    table = {}
    for change in changes:
        key, _, value = (part.strip() for part in change.partition("="))
        try:
            table.update(tomllib.loads(f"{key} = {value}"))
        except tomllib.TOMLDecodeError:
            table[key] = value
    try:
        train, model = config_from_table(table, "--change")
    except MeshseqError as err:
        raise SystemExit(str(err)) from None
    if model:
        raise SystemExit("--change: model options are not training options")
    return train


def training_specs(model) -> tuple[list[str], list]:
    """``(specs, splits)`` a run trained on, as its checkpoint names them."""
    return [d["source"] for d in model.meta["datasets"]], training_splits(model.meta)


def training_segments(model) -> list[tuple[np.ndarray, np.ndarray]]:
    """``(scaled features (T, V, C), vertices (T, V, 3))`` of each training segment of the run
    ``model`` (its sequences read where its checkpoint names them, each extracted once)."""
    from meshseq.io import load_sequence

    out = []
    for spec, split in zip(*training_specs(model)):
        verts = load_sequence(spec).vertices.astype(np.float64)
        feats = model.features(verts)
        out += [(feats[a:b], verts[a:b]) for a, b in split.train]
    return out


def training_splits(meta: dict) -> list:
    """The ``Split`` of each sequence a run trained on, from its model.json ``meta``."""
    from meshseq.data.windows import Split

    return [Split.from_dict(d["split"]) for d in meta["datasets"]]


def ensure_vertex_share(model, specs: list[str], splits) -> dict:
    """The run's fitted vertex share (model.json's ``completion``; ``meshseq.inbetween``), fitted on
    the training segments of ``specs`` as training fits it where the run was stored without one
    (set on ``model``). Returns it, and where it came from, for the record."""
    from meshseq.training.data import load_training_data
    from meshseq.training.loop import completion_fit

    stored = model.meta.get("completion")
    if stored is not None:
        return {**stored, "source": "stored"}
    data = load_training_data(specs, consistency=model.consistency, placement=model.placement)
    fitted = completion_fit(data, splits, model.placement)
    model.vertex_share = fitted["vertex_share"]
    return {**fitted, "source": "fitted when scored"}


def run_carry(model) -> dict:
    """The carried velocity the run's predictions use, for the record: fitted at the end of its
    training (model.json's ``prediction``; ``meshseq.carry``), or the body set's share for a run
    stored without one."""
    from meshseq.carry import CARRY

    stored = model.meta.get("prediction")
    return {**stored, "source": "stored"} if stored is not None else {"carry": CARRY, "source": "not fitted"}


def ensure_novelty(model, specs: list[str], splits) -> str:
    """Give a model stored before checkpoints held the training frames' latents and their steps
    (``meshseq.novelty``) the reference training would have stored: its latents of the training
    segments of ``specs``. Returns where the reference came from (for the record)."""
    from meshseq.io import load_sequence
    from meshseq.novelty import reference_latents

    if model.novelty is not None and model.novelty.steps is not None:
        return "stored"
    stored = model.novelty is not None
    feats = [model.features(load_sequence(spec).vertices.astype(np.float64)) for spec in specs]
    model.novelty = reference_latents(model.engine.encode, [f[a:b] for f, split in zip(feats, splits)
                                                            for a, b in split.train if b - a > 0])
    return "latents stored, steps made when scored" if stored else "made when scored"


def rescore(done: dict, run: Path, record: Path, specs: list[str], args, kind: str, update) -> dict:
    """A finished record with some of its figures made again by today's code from the same checkpoint:
    ``update(model, block, verts, feats)`` for every block; the command is kept as ``KIND_command``."""
    import meshseq
    from meshseq.io import load_sequence

    model = meshseq.load(run)
    if model.iteration != done["iteration"]:
        raise SystemExit(f"{run}: the newest checkpoint is iteration {model.iteration}, the record {done['iteration']}")
    splits = training_splits(model.meta)
    done["novelty_reference"] = ensure_novelty(model, specs, splits)
    done["vertex_share"] = ensure_vertex_share(model, specs, splits)
    done["carry"] = run_carry(model)
    for block in done["blocks"]:
        verts = load_sequence(block["sequence"]).vertices.astype(np.float64)
        update(model, block, verts, model.features(verts))
        print(line(done["set"] + "@" + done["holdout_at"], block), flush=True)
    done[f"{kind}_command"] = "python benchmarks/generalize.py " + " ".join(args.argv)
    record.write_text(json.dumps(done, indent=1))
    return done


def rescore_completion(done: dict, run: Path, record: Path, specs: list[str], args) -> dict:
    """``rescore`` of the completion figures (prediction is left as recorded)."""
    from meshseq.evaluate import completion_errors
    from meshseq.synthesize import CONTEXT

    def update(model, block, verts, feats):
        lo, hi = block["frames"]
        gaps = block_gaps(lo, hi)
        block["completion"] = completion_errors(model, verts, feats, lo, hi, gaps, list(COMPLETION), samples=1,
                                                context=CONTEXT)

    done["trust"], done["line"] = TRUST, LINE
    return rescore(done, run, record, specs, args, "completion", update)


def rescore_prediction(done: dict, run: Path, record: Path, specs: list[str], args) -> dict:
    """``rescore`` of ours' prediction figures (``motion_50`` and ``pace`` too); the baselines' are left
    as recorded (their code did not change; the VAE baseline would be trained again)."""
    from meshseq import checkpoint as ckpt

    meta = json.loads((ckpt.resolve(run) / "model.json").read_text())
    train_level = training_level(specs, training_splits(meta))

    def update(model, block, verts, feats):
        lo, hi = block["frames"]
        for u, methods in prediction_scores(model, None, verts, feats, lo, hi, ["ours"]).items():
            block["prediction"][u]["ours"] = methods["ours"]
        block.update(motion_scores(model, verts, feats, train_level, lo, hi))

    done["pace"] = scored_pace()
    return rescore(done, run, record, specs, args, "prediction", update)


def train_vae_baseline(model, train_feats: np.ndarray):
    from meshseq import baselines
    from meshseq.mesh import Topology

    topo = Topology.from_faces(model.faces, model.config.n_vertices)
    return baselines.train_vae(train_feats, topo, latent=model.config.latent, device=model.device)


def prediction_ratio(block: dict, u: str, h: str, key: str = "centroid") -> float:
    """Ours over the best baseline at one cell of a scored block (NaN where the block is too short
    for the horizon)."""
    p = block["prediction"].get(u)
    if p is None or h not in p["ours"][key]:
        return float("nan")
    return p["ours"][key][h] / min(p[m][key][h] for m in PREDICTION[1:] if m in p)


def completion_ratio(block: dict, gap: str) -> float:
    """Ours over the better linear interpolation (features or vertices) at one gap."""
    c = block["completion"][gap]
    return c["ours"] / min(c["linear"], c["linear_vertices"])


def line(tag: str, b: dict) -> str:
    cells = " ".join(f"{u}h{h}{'r' if key == 'rigid' else ''} {prediction_ratio(b, u, h, key):.2f}"
                     for u in ("u1", "u3") for h in ("5", "10", "15") for key in ("centroid", "rigid"))
    comp = " ".join(f"g{g} {completion_ratio(b, g):.2f}" for g in b["completion"])
    return (f"{tag} {Path(b['sequence']).name}: novelty {b['novelty']:.1f} motion {b['motion_level']:.2f} | "
            f"ours/best {cells} | ours/interp {comp} | motion50 {b['motion_50']:.2f}")


def ratio_cell(r: float) -> str:
    """A table cell: the ratio, or "-" where the block could not be scored."""
    return "-" if np.isnan(r) else f"{r:.2f}"


def table(files: list[str]) -> str:
    """Markdown: one row per block, ratios against the best baseline (prediction, h10/h15,
    u1/u3, raw and rigid), against the better interpolation (completion), motion level."""
    rows = ["| set, block, iterations | sequence | novelty | motion | u1 h5 | u1 h10 | u1 h15 | u3 h5 | u3 h10 | "
            "u3 h15 | rigid u3 h15 | gap 5 | gap 10 | gap 20 | gap 30 | motion of 50 |", "|" + "---|" * 16]
    cells = [("u1", "5", "centroid"), ("u1", "10", "centroid"), ("u1", "15", "centroid"), ("u3", "5", "centroid"),
             ("u3", "10", "centroid"), ("u3", "15", "centroid"), ("u3", "15", "rigid")]
    for f in files:
        rec = json.loads(Path(f).read_text())
        for b in rec["blocks"]:
            pred = [ratio_cell(prediction_ratio(b, *cell)) for cell in cells]
            comp = [f"{completion_ratio(b, g):.2f}" if g in b["completion"] else "-" for g in ("5", "10", "20", "30")]
            block = f"@ {rec['holdout_at']}" if single_capture(rec) else "unseen sequence"
            rows.append(f"| {record_label(rec, block)} | "
                        f"{Path(b['sequence']).name} | "
                        f"{b['novelty']:.1f} | "
                        f"{b['motion_level']:.2f} | {' | '.join(pred)} | {' | '.join(comp)} | {b['motion_50']:.2f} |")
    return "\n".join(rows)


TARGET_CELLS = [(u, h, key) for u in ("u1", "u3") for h in ("10", "15") for key in ("centroid", "rigid")]
TARGETS = ("motion training shows: below 1", "novel motion: at most 1.5", "gaps 5 and 10: at most 1",
           "gaps 20 and 30 (bodies, horse): below 1", "motion of 50: 0.7-1.3", "held-out subject: h15 at most 0.5, gap 30 at most 0.7")


def block_kind(rec: dict, block: dict) -> str:
    """``subject`` (a held-out subject's trained motion), ``novel`` (a motion never trained on, or a
    held-out end at least one typical step from every training frame) or ``shown``."""
    if single_capture(rec):
        return "novel" if block["novelty"] >= 1 else "shown"
    held = rec.get("held_out") or held_out_of(rec["command"])
    name = block["sequence"].rsplit(":", 1)[-1]
    return "novel" if name.endswith("_" + held["motion"]) else "subject"


def held_out_of(command: str) -> dict:
    """``{"subject", "motion"}`` a body-set record's command held out (records written before
    they kept ``held_out``)."""
    words = command.split()
    def option(name, default):
        return words[words.index(name) + 1] if name in words[:-1] else default
    return {"subject": option("--hold-subject", HOLD_SUBJECT), "motion": option("--hold-motion", HOLD_MOTION)}


def worst(values: list[tuple[float, str]], limit: float, strict: bool = False) -> str:
    """A target's cell: the largest of ``(ratio, where)`` and whether it keeps to ``limit``."""
    values = [v for v in values if not np.isnan(v[0])]
    if not values:
        return "-"
    r, where = max(values)
    met = r < limit if strict else r <= limit
    return f"{r:.2f} met" if met else f"**{r:.2f}** ({where})"


def block_name(block: dict) -> str:
    """A block's sequence name without its file (``male_slim_walk``, ``pcow.npz``)."""
    return block["sequence"].rsplit(":", 1)[-1].replace("\\", "/").rsplit("/", 1)[-1]


def prediction_cells(rec: dict, kinds: tuple[str, ...], horizons=("10", "15")) -> list[tuple[float, str]]:
    """``(ratio, where)`` of every target cell (``TARGET_CELLS``) at ``horizons`` of the blocks of ``kinds``."""
    return [(prediction_ratio(b, u, h, key), f"{block_name(b)} {u} h{h}{' rigid' if key == 'rigid' else ''}")
            for b in rec["blocks"] if block_kind(rec, b) in kinds for u, h, key in TARGET_CELLS if h in horizons]


def gap_means(rec: dict, gaps: tuple[str, ...]) -> list[tuple[float, str]]:
    """``(ratio, where)`` per gap: completion over the better interpolation, mean over the blocks."""
    return [(float(np.mean([completion_ratio(b, g) for b in rec["blocks"] if g in b["completion"]])), f"gap {g}")
            for g in gaps if any(g in b["completion"] for b in rec["blocks"])]


def motion_target(rec: dict) -> str:
    """Motion of 50 within 30% of the truth's on every block: the range, or the block furthest off."""
    levels = [b["motion_50"] for b in rec["blocks"]]
    far = max(rec["blocks"], key=lambda b: abs(np.log(max(b["motion_50"], 1e-12))))  # the furthest off, as a factor
    if not all(0.7 <= m <= 1.3 for m in levels):
        return f"**{far['motion_50']:.2f}** ({block_name(far)})"
    lo, hi = f"{min(levels):.2f}", f"{max(levels):.2f}"
    return f"{lo if lo == hi else lo + '-' + hi} met"


def record_targets(rec: dict) -> list[str]:
    """The six targets (``TARGETS``) for one record: the worst cell of each, or "-" where the record
    has no block the target concerns."""
    nonlinear = rec["set"].startswith("bodies") or rec["set"] == "horse-gallop"
    subject = [b for b in rec["blocks"] if block_kind(rec, b) == "subject"]
    held_subject = "-"
    if subject:
        gap30 = [(completion_ratio(b, "30"), f"{block_name(b)} gap 30") for b in subject if "30" in b["completion"]]
        held_subject = f"{worst(prediction_cells(rec, ('subject',), ('15',)), 0.5)}; {worst(gap30, 0.7)}"
    return [worst(prediction_cells(rec, ("subject", "shown")), 1.0, strict=True),
            worst(prediction_cells(rec, ("novel",)), 1.5),
            worst(gap_means(rec, ("5", "10")), 1.0),
            worst(gap_means(rec, ("20", "30")), 1.0, strict=True) if nonlinear else "-",
            motion_target(rec), held_subject]


def targets_table(files: list[str]) -> str:
    """Markdown: per record, the worst cell of each target (met, or the cell that misses it)."""
    rows = ["| set, iterations | " + " | ".join(TARGETS) + " |", "|" + "---|" * (len(TARGETS) + 1)]
    for f in files:
        rec = json.loads(Path(f).read_text())
        inside = single_capture(rec) and rec["holdout_at"] != "end"  # a block inside the capture
        label = record_label(rec, f"@ {rec['holdout_at']}" if inside else "")
        rows.append(f"| {label} | " + " | ".join(record_targets(rec)) + " |")
    return "\n".join(rows)


def capture_name(spec: str, holdout: float) -> str:
    """A capture's set name in the records: its file's stem, with ``-holdoutF`` where a controlled
    run holds out another fraction ``F`` than the paper's."""
    return Path(spec).stem + ("" if holdout == HOLDOUT else f"-holdout{holdout:g}")


def main(argv=None) -> None:
    import sys

    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--sets", nargs="+", default=["horse-gallop", "pcow", "crane", "bodies"])
    p.add_argument("--blocks", nargs="+", default=["end"], help="where the held-out block lies: end, start or a fraction")
    p.add_argument("--bodies", default=None, help="make-bodies HDF5 for the set 'bodies'")
    p.add_argument("--bodies-name", default="bodies", help="the body set's name in the records (e.g. bodies-parts "
                   "for a set made with make-bodies --parts)")
    p.add_argument("--holdout", type=float, default=HOLDOUT,
                   help=f"the fraction of a capture held out ({HOLDOUT:g}, the paper's); another names the "
                   "records SET-holdoutF (a controlled run: training shows part of the paper's held-out end)")
    p.add_argument("--hold-subject", default=HOLD_SUBJECT)
    p.add_argument("--hold-motion", default=HOLD_MOTION)
    p.add_argument("--change", action="append", default=[], metavar="KEY=VALUE",
                   help="a controlled run: this TrainConfig field changed from the default recipe (give the "
                   "set another --bodies-name)")
    p.add_argument("--iterations", type=int, default=2000)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--device", default="cpu")
    p.add_argument("--threads", type=int, default=None)
    p.add_argument("--out", default="runs/generalize")
    p.add_argument("--quiet", action="store_true")
    p.add_argument("--table", nargs="*", default=None, help="print the Markdown table of these records")
    p.add_argument("--rescore-completion", action="store_true",
                   help="for finished records: make the completion figures again with today's code")
    p.add_argument("--rescore-prediction", action="store_true",
                   help="for finished records: make ours' prediction figures again with today's code")
    args = p.parse_args(argv)
    args.argv = list(sys.argv[1:] if argv is None else argv)
    if args.table is not None:
        print(table(args.table) + "\n\n" + targets_table(args.table))
        return
    if args.threads:
        import torch

        torch.set_num_threads(args.threads)
    Path(args.out).mkdir(parents=True, exist_ok=True)
    for name in args.sets:
        if name == "bodies":
            if not args.bodies:
                raise SystemExit("--sets bodies needs --bodies FILE.h5 (meshseq make-bodies)")
            specs, held = body_specs(args.bodies, args.hold_subject, args.hold_motion)
            # the training sequences' own held-out ends, then the unseen sequences whole
            run_set(args.bodies_name, specs, [(None, s) for s in held], args, "end", holdout=0.0,
                    held_out={"subject": args.hold_subject, "motion": args.hold_motion})
            continue
        spec = str(SHARED / f"{name}.npz") if (SHARED / f"{name}.npz").is_file() else name
        name = capture_name(spec, args.holdout)
        for at in args.blocks:
            run_set(name, [spec], [(0, spec)], args, at, holdout=args.holdout)


if __name__ == "__main__":
    main()
