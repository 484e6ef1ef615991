"""How a trained model's roll-outs behave on the recipe study's validation blocks.

Two reports for one checkpoint of a ``benchmarks/recipe_study.py`` run (the same data, cut to the
protocol's first 80%, validated on the run's held-out block; the evaluation frames are never used):

- ``motion``: the motion level of 50 frames generated after 1 given frame, per generated step and
  on average, over the ground truth's level (1.0 = moves like the data), with the latent's mean
  (``z = mu``, how meshseq predicts) and with ``z`` sampled from the VAE head;
- ``completion``: the in-between error (x 1e-4, centroid-aligned) at gaps 5, 10 and 20 of the
  stitched chains (meshseq's completion), of a crossfade of the two chains over the whole gap, of
  both after drift correction (each chain minus its miss of the far key, spread linearly over the
  gap, so it ends exactly on that key), and of linear interpolation in ACAP space and in vertex
  space.

    python benchmarks/rollout_study.py STUDY/b-default/checkpoints/00000600 --data bodies --bodies bodies1k.h5
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import recipe_study  # noqa: E402  (data_specs, development_data: the study's protocol)


def validation_blocks(checkpoint: Path, data: list[str], bodies: str | None, part: str = "validation"):
    """``(model, [(scaled features, vertices, (lo, hi), raw features)])`` for every sequence of
    the run: its validation block, or with ``part="train"`` its (last) training segment."""
    import meshseq
    from meshseq.data.windows import Split

    full, verts = recipe_study.development_data(recipe_study.data_specs(data, bodies))
    model = meshseq.load(checkpoint)
    splits = [Split.from_dict(d["split"]) for d in model.meta["datasets"]]
    blocks = [(model.scaling.apply(f).astype(np.float32), v, s.heldout if part == "validation" else s.train[-1], f)
              for f, v, s in zip(full.features, verts, splits)]
    return model, blocks


def motion_report(model, blocks, frames: int = 50) -> dict:
    """Per-step and mean motion level of generated frames over the truth's (mu and sampled z)."""
    import torch

    from meshseq.evaluate import feature_change, prediction_starts
    from meshseq.plots import feature_change as relative_change

    per_step = {"mu": [], "sampled": []}
    truth = []
    for scaled, _, (lo, hi), raw in blocks:
        starts = prediction_starts(lo, hi, 1, 1)
        for key, sample in (("mu", False), ("sampled", True)):
            torch.manual_seed(0)
            curve = feature_change(model, scaled, starts, 1, frames, ["ours"], sample=sample)["ours"]
            per_step[key].append(np.asarray(curve))
        truth.append(float(relative_change(raw[lo:hi]).mean()))
    level = float(np.mean(truth))
    out = {"truth_level": level}
    for key, curves in per_step.items():
        curve = np.mean(curves, axis=0) / level
        out[key] = {"mean": float(curve.mean()), "per_step": curve.tolist()}
    return out


def spread_stitch(fwd: np.ndarray, bwd: np.ndarray) -> np.ndarray:
    """The chains joined where they agree best (as ``stitch_chains``), each bent to meet the
    other's midpoint there by a correction growing linearly from its own key: no blend window."""
    from meshseq.synthesize import stitch_chains

    back = bwd[::-1]
    n = len(fwd)
    meet = stitch_chains(fwd, bwd)[1]
    mid = 0.5 * (fwd[meet] + back[meet])
    i = np.arange(n)[:, None, None]
    f_c = fwd + np.clip(i / meet, 0, 1) * (mid - fwd[meet])
    b_c = back + np.clip((n - 1 - i) / (n - 1 - meet), 0, 1) * (mid - back[meet])
    return np.where(i <= meet, f_c, b_c)


def completion_report(model, blocks, gaps=(5, 10, 20)) -> dict:
    """In-between errors x 1e-4 of stitched chains, a whole-gap crossfade, and linear baselines."""
    import torch

    from meshseq import baselines
    from meshseq.align import per_vertex_error
    from meshseq.synthesize import assemble_vertices, corrected_chains, corrected_crossfade, stitch_chains

    out = {}
    for gap in gaps:
        n = gap + 2
        ramp = np.linspace(0.0, 1.0, n)[:, None, None]
        errs = {k: [] for k in ("stitched", "spread", "crossfade", "corrected_stitched", "corrected_crossfade",
                                "linear_acap", "linear_vertices")}
        for scaled, verts, (lo, hi), _ in blocks:
            for a in range(lo, hi - gap - 1):
                b = a + gap + 1
                truth, anchors = verts[a + 1:b], {0: verts[a], gap + 1: verts[b]}
                h, c = model.net.initial_state(1, 1, model.device)
                with torch.no_grad():
                    chains, _, _, _ = model.net.rollout(torch.as_tensor(np.stack([scaled[a], scaled[b]])),
                                                        n - 1, (h, c), n_forward=1)
                fwd, bwd = chains.cpu().numpy()
                back = bwd[::-1]  # forward time order
                fwd_c, back_c = corrected_chains(fwd, bwd)
                candidates = {"stitched": stitch_chains(fwd, bwd)[0], "spread": spread_stitch(fwd, bwd),
                              "crossfade": (1 - ramp) * fwd + ramp * back,
                              "corrected_stitched": stitch_chains(fwd_c, back_c[::-1])[0],
                              "corrected_crossfade": corrected_crossfade(fwd, bwd),
                              "linear_acap": baselines.linear_interpolation(scaled[a], scaled[b], gap)}
                for key, feats in candidates.items():
                    feats = feats.copy()
                    feats[0], feats[-1] = scaled[a], scaled[b]
                    v = assemble_vertices(model, feats, anchors)[1:-1]
                    errs[key].append(per_vertex_error(v, truth).mean() * 1e4)
                v = baselines.linear_interpolation(verts[a], verts[b], gap)[1:-1]
                errs["linear_vertices"].append(per_vertex_error(v, truth).mean() * 1e4)
        out[str(gap)] = {k: float(np.mean(e)) for k, e in errs.items()} | {"starts": len(errs["stitched"])}
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("checkpoint", help="a checkpoint folder of a recipe_study.py run")
    ap.add_argument("--data", nargs="+", default=["bodies"])
    ap.add_argument("--bodies", default=None)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--part", choices=("validation", "train"), default="validation",
                    help="motion from starts in the validation blocks (default) or in the training frames")
    ap.add_argument("--motion-only", action="store_true", help="skip the completion report")
    ap.add_argument("--json", default=None, help="also write the figures here")
    args = ap.parse_args()
    import torch

    torch.set_num_threads(args.threads)
    model, blocks = validation_blocks(Path(args.checkpoint), args.data, args.bodies, args.part)
    motion = motion_report(model, blocks)
    steps = [0, 1, 2, 4, 7, 10, 15, 20, 30, 40, 49]
    for key in ("mu", "sampled"):
        curve = motion[key]["per_step"]
        print(f"motion / truth ({key}): mean {motion[key]['mean']:.3f}; at steps "
              + " ".join(f"{s + 1}:{curve[s]:.2f}" for s in steps))
    if args.motion_only:
        return
    completion = completion_report(model, blocks)
    for gap, r in completion.items():
        print(f"completion gap {gap} ({r['starts']} starts): " + ", ".join(
            f"{k} {v:.1f}" for k, v in r.items() if k != "starts"))
    if args.json:
        Path(args.json).write_text(json.dumps({"checkpoint": args.checkpoint, "motion": motion,
                                               "completion": completion}, indent=1))


if __name__ == "__main__":
    main()
