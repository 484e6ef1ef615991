"""Controlled run for meshes of several parts: train the default recipe on a make-bodies set with or
without the placement channels (meshseq.acap.parts), the same seed, budget and sequences, and score
prediction from 3 given frames on the held-out subject's seen motions against zero velocity.

    python benchmarks/parts_placement.py bodies1k_parts.h5 --placement on --iterations 600 --out runs/pp-on
    python benchmarks/parts_placement.py bodies1k_parts.h5 --placement off --iterations 600 --out runs/pp-off
    python benchmarks/parts_placement.py bodies1k.h5 --placement off --iterations 600 --out runs/pp-onepart

Prints per sequence the mean per-vertex error x 1e-4 (centroids removed) at horizons 5/10/15, ours
and zero velocity, over starts every 4 frames; with placement channels also ours with the truth's
placement channels swapped into its predicted features (how much of ours' error the parts' placement
explains); writes OUT.json. ``--validation-subject S`` also holds out subject S's sequences and scores
them first: choose between recipes on S, then confirm on the held-out subject.
``--placement anchor`` measures each part's placement from its anchor vertex (``TrainConfig.placement``).
``--placement-jitter J`` trains with ``TrainConfig.placement_jitter = J``:

    python benchmarks/parts_placement.py bodies1k_parts.h5 --validation-subject female_old \
        --iterations 2000 --placement-jitter 0.1 --out runs/pp-j0.1
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from generalize import body_specs  # noqa: E402

HORIZONS = (5, 10, 15)


def centred_errors(pred: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """Mean per-vertex distance of ``(n, V, 3)`` frames after removing each frame's centroid, ``(n,)``."""
    p = pred - pred.mean(axis=1, keepdims=True)
    t = truth - truth.mean(axis=1, keepdims=True)
    return np.linalg.norm(p - t, axis=-1).mean(axis=1)


def score(model, vertices: np.ndarray, step: int = 4) -> dict:
    """Ours and zero velocity from 3 given frames, mean over starts, at ``HORIZONS`` (x 1e-4); on a
    model with placement channels also ``ours_true_placement``: ours' predicted features with the
    truth's placement channels, reconstructed; and ``ours_rolled_out_placement``: ours with the
    placement channels as rolled out (``synthesize.predict(..., continue_placement=False)``)."""
    from meshseq import synthesize

    h = max(HORIZONS)
    placement = model.config.channels > 9
    feats = model.features(vertices) if placement else None
    rows = {"ours": [], "zero_velocity": []}
    if placement:
        rows |= {"ours_true_placement": [], "ours_rolled_out_placement": []}
    for s in range(0, len(vertices) - h - 3, step):
        truth = vertices[s + 3:s + 3 + h]
        pred = model.predict(vertices[s:s + 3], h)[3:]
        rows["ours"].append(centred_errors(pred, truth))
        rows["zero_velocity"].append(centred_errors(np.repeat(vertices[s + 2][None], h, 0), truth))
        if placement:
            f = model.features(pred)
            f[..., 9:12] = feats[s + 3:s + 3 + h, :, 9:12]  # (the model's own placement mode)
            rows["ours_true_placement"].append(centred_errors(model.vertices(f), truth))
            given = feats[s:s + 3]
            free = synthesize.predict(model, given, h, continue_placement=False)
            out = synthesize.assemble_vertices(model, np.concatenate([given, free]), dict(enumerate(vertices[s:s + 3])))
            rows["ours_rolled_out_placement"].append(centred_errors(out[3:], truth))
    return {m: [float(np.mean(r, 0)[k - 1] * 1e4) for k in HORIZONS] for m, r in rows.items()}


def finished(run: str, iterations: int) -> bool:
    """Whether ``run`` holds a checkpoint of ``iterations`` iterations."""
    from meshseq import checkpoint as ckpt

    return any(c.name.endswith(f"{iterations:08d}") for c in ckpt.list_checkpoints(run)) if Path(run).is_dir() else False


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("bodies", help="a meshseq make-bodies HDF5 (with or without --parts)")
    p.add_argument("--placement", choices=("on", "off", "anchor"), default="on",
                   help="on: placement channels from the centroid (TrainConfig.placement centroid); anchor: from "
                        "each part's anchor vertex; off: none")
    p.add_argument("--iterations", type=int, default=600)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--hold-subject", default="male_slim")
    p.add_argument("--hold-motion", default="shake_arms")
    p.add_argument("--validation-subject", default=None, help="also hold out this subject; scored first")
    p.add_argument("--placement-jitter", type=float, default=0.0, help="TrainConfig.placement_jitter")
    p.add_argument("--out", required=True)
    args = p.parse_args()

    import meshseq
    from meshseq import acap
    from meshseq.io import load_sequence
    from meshseq.train import TrainConfig, TrainingData, train

    specs, held = body_specs(args.bodies, args.hold_subject, args.hold_motion)
    if args.validation_subject:
        val = [s for s in specs if s.rsplit(":", 1)[-1].startswith(args.validation_subject + "_")]
        if not val:
            sys.exit(f"parts_placement: --validation-subject {args.validation_subject}: no such subject in {args.bodies}")
        specs, held = [s for s in specs if s not in val], val + held
    seqs = [load_sequence(s) for s in specs]
    ref = seqs[0].vertices[0]
    mode = "anchor" if args.placement == "anchor" else "centroid"
    feats = [acap.extract(s.vertices, s.faces, reference=ref, placement=args.placement != "off", placement_mode=mode)
             for s in seqs]
    data = TrainingData([s.name for s in seqs], specs, feats, seqs[0].faces, ref, "temporal", mode)
    if not finished(args.out, args.iterations):  # a finished run is scored again with today's code
        train(data, args.out, TrainConfig(iterations=args.iterations, seed=args.seed, holdout=0.0, eval_every=0,
                                          placement_jitter=args.placement_jitter, placement=mode,
                                          checkpoint_every=args.iterations), device="cpu", progress=False)
    model = meshseq.load(args.out)
    results = {}
    for spec in held:
        if spec.endswith("_" + args.hold_motion):
            continue  # the unseen motion: this run is about the seen ones
        results[spec] = score(model, load_sequence(spec).vertices)
        print(f"{spec}: " + " | ".join(f"{m.replace('_', ' ')} {' '.join(f'{e:.1f}' for e in r)}"
                                       for m, r in results[spec].items())
              + f" (h{'/'.join(map(str, HORIZONS))})", flush=True)
    Path(args.out + ".json").write_text(json.dumps({"args": vars(args), "results": results}, indent=1))


if __name__ == "__main__":
    main()
