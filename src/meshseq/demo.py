"""The built-in demonstration: data -> training -> prediction and completion -> pictures and tables.

``run_demo`` needs no data of the user's. It prepares the embedded default data (human bodies
from the Anny model when the ``bodies`` extra works here, cached after the first build; else the
generated twisting limb), trains a small model for a few minutes with a progress bar, predicts
and completes held-out motion, compares with the baselines, and writes into one folder:

    prediction.png    film strip: ground truth, ours and linear extrapolation (error heat map)
    prediction.gif    the same as an animation
    completion.png    film strip of an in-between completion against the ground truth
    prediction.glb    our prediction as a glTF animation (Blender, browsers)
    errors.md/.json   per-vertex error x 1e-4 at horizons 5/10/15 for ours and the baselines
    run/              the trained model (``meshseq predict run DATA ...`` uses it)
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from meshseq.errors import MeshseqError


@dataclass
class DemoData:
    specs: list[str]  # DATA arguments of the sequences trained on
    description: str
    up: str = "y"  # the data's up axis, for pictures and the glTF export


def default_cache_dir() -> Path:
    return Path(os.environ.get("MESHSEQ_CACHE", Path.home() / ".cache" / "meshseq"))


def prepare_data(cache: Path, source: str, log) -> DemoData:
    """The demo's data: ``bodies`` (Anny; built once, cached), ``limb`` (generated), or ``auto``."""
    cache.mkdir(parents=True, exist_ok=True)
    if source in ("auto", "bodies"):
        try:
            import h5py

            from meshseq.data.bodies import default_body_set

            log("preparing the human body data (Anny; the first time builds the model, a few minutes)")
            path = default_body_set(cache, on_sequence=lambda name: log(f"  generated {name}"))
            with h5py.File(path, "r") as fh:
                names = sorted(k for k in fh.keys() if k != "faces")
            return DemoData([f"{path}:{n}" for n in names],
                            f"{len(names)} Anny body sequences (subjects x motions) from {path}", up="z")
        except (ImportError, MeshseqError, OSError, RuntimeError) as err:
            if source == "bodies":
                raise MeshseqError(f"--data bodies: the body data cannot be made here: {err}") from err
            log(f"note: body data unavailable ({str(err).splitlines()[0][:120]}); using the generated limb")
    from meshseq.data.synthetic import twisting_limb
    from meshseq.io import save_sequence

    path = cache / "twisting_limb_120.npz"
    if not path.is_file():
        save_sequence(twisting_limb(frames=120), path, force=True)
    return DemoData([str(path)], "a generated twisting, bending limb (120 frames)")


def run_demo(out: Path, *, iterations: int = 300, data: str = "auto", force: bool = False,
             device: str = "auto", seed: int = 0, cache: Path | None = None, log=print) -> dict:
    """Run the whole demonstration into ``out`` (written atomically); returns the error table."""
    from meshseq import baselines, evaluate, export, render, synthesize
    from meshseq.api import load
    from meshseq.io import atomic_output, check_output, json_text, load_sequence
    from meshseq.train import TrainConfig, load_training_data, train

    check_output(out, force=force)
    t_start = time.perf_counter()
    demo_data = prepare_data(cache or default_cache_dir(), data, log)
    log(f"data: {demo_data.description}")
    with atomic_output(out, force=force) as tmp:
        tmp.mkdir()
        run = tmp / "run"
        log(f"training {iterations} iterations (8 windows x 16 frames; latent 64) on {device} ...")
        t0 = time.perf_counter()
        # hold out the last 40%: the body sequences have 64 frames, and 3 given frames plus a
        # horizon of 15 need 18 held-out frames
        config = TrainConfig(iterations=iterations, window=16, batch=8, seed=seed, eval_every=0,
                             holdout=0.4, checkpoint_every=max(50, iterations // 2), log_every=10)
        train(load_training_data(demo_data.specs), run, config, model_options={"latent": 64},
              device=device, progress=True, log=lambda m: None)
        t_train = time.perf_counter() - t0
        model = load(run, device=device)
        seq = load_sequence(demo_data.specs[0])
        lo, hi = model.meta["datasets"][0]["split"]["heldout"]
        feats = model.features(seq.vertices)

        log("evaluating on the held-out frames ...")
        table = {}
        for u in (1, 3):
            errs = evaluate.prediction_errors(model, seq.vertices, feats, lo, hi, u, [5, 10, 15],
                                              ["ours", "zero_velocity", "linear_acap"])
            for m, r in errs.items():
                table.setdefault(m, {})[f"u{u}"] = r["centroid"]
        n_pred = min(30, hi - lo - 2)
        given = feats[lo:lo + 2]
        ours = synthesize.predict(model, given, n_pred)
        linear = baselines.linear_acap(given[None], n_pred)[0]
        anchors = {0: seq.vertices[lo], 1: seq.vertices[lo + 1]}
        ours_v = synthesize.assemble_vertices(model, np.concatenate([given, ours]), anchors)
        lin_v = synthesize.assemble_vertices(model, np.concatenate([given, linear]), anchors)
        truth = seq.vertices[lo:lo + 2 + n_pred]
        labels = ["ours (BD-LSTM)", "linear ACAP"]
        up = demo_data.up
        img = render.film_strip([ours_v, lin_v], seq.faces, labels=labels, ground_truth=truth, up=up,
                                first_frame=lo, title=f"prediction from 2 given frames ({seq.name})")
        render.save_image(tmp / "prediction.png", img)
        frames = render.animation_frames([ours_v, lin_v], seq.faces, labels=labels, ground_truth=truth,
                                         first_frame=lo, tile_height=200, up=up)
        render.save_animation(tmp / "prediction.gif", frames, fps=12)
        export.save_glb(tmp / "prediction.glb", ours_v, seq.faces, fps=24, up=up)

        gap = min(14, hi - lo - 2)
        a, b = lo, lo + gap + 1
        comp = synthesize.complete(model, feats[a], feats[b], gap).frames[0]
        lin_c = baselines.linear_interpolation(feats[a], feats[b], gap)
        keys = {0: seq.vertices[a], gap + 1: seq.vertices[b]}
        comp_v = synthesize.assemble_vertices(model, comp, keys)
        lin_cv = synthesize.assemble_vertices(model, lin_c, keys)
        img = render.film_strip([comp_v, lin_cv], seq.faces, labels=["ours (both chains, anchored to the keys)", "linear ACAP"],
                                ground_truth=seq.vertices[a:b + 1], first_frame=a, up=up,
                                title=f"completion between keyframes {a} and {b}")
        render.save_image(tmp / "completion.png", img)

        result = {"data": demo_data.description, "dataset": seq.name, "heldout": [lo, hi],
                  "iterations": iterations, "train_seconds": t_train, "units": "x1e-4", "errors": table}
        (tmp / "errors.json").write_text(json_text(result))
        (tmp / "errors.md").write_text(errors_markdown(result))
    result["total_seconds"] = time.perf_counter() - t_start
    return result


def errors_markdown(result: dict) -> str:
    keys = [(u, h) for u in ("u1", "u3") for h in ("5", "10", "15")]
    lines = [f"Per-vertex error x 1e-4 on held-out frames {result['heldout'][0]}:{result['heldout'][1]} of "
             f"{result['dataset']} after {result['iterations']} training iterations (translation removed).", "",
             "| method | " + " | ".join(f"{u[1]} given, h={h}" for u, h in keys) + " |",
             "|---" * (len(keys) + 1) + "|"]
    for m, per_u in result["errors"].items():
        lines.append(f"| {m} | " + " | ".join(f"{per_u[u][h]:.1f}" for u, h in keys) + " |")
    return "\n".join(lines) + "\n"
