"""Prediction with and without the novelty guard (method.md, "Novelty guard") on chosen sequences.

    python benchmarks/novelty_guard.py RUN --train SPEC,SPEC,... SPEC ... [--unseen squat,wave]
        [--every 4] [--decays 0,0.5,0.9,1]

For every sequence and 1 and 3 given frames (starts every ``--every`` frames over the whole
sequence): the given frame's novelty (median [p10, p90]) and the error at h5 / h10 / h15 of the
roll-out (``--guard off``), of the guard's pose check alone and of the guarded prediction (pose
and direction), each over the best of zero velocity and
linear ACAP extrapolation; then the means (and maxima) over the sequences of each group (``--unseen``:
motions the run never trained on). ``--train``: the run's training sequences, from which the
reference is made for a run stored without one (the training segments recorded in the run).
``--decays``: also the fallback alone with each fixed velocity damping and with its default (the
given frames' own slowing, ``novelty.own_decay``), 3 given frames.
``--completion``: instead, completion (12 gaps of 5, 10, 20 and 30 frames per sequence, 7 frames
on both sides) over the better linear interpolation: ours from the keys alone; the corrected
crossfade where both keys are familiar (the guard's weight, blended); ours warmed up on the 7
frames around the keys, trusting the chains by ``context_fit`` (runs without the training latents)
and by ``context_trust`` (the default).
``--completion --trust-paces 0.5,0.6,0.8``: instead, ours warmed up and trusted by ``context_trust``
with each of those slowest trusted paces (``synthesize.PACE_TRUST``), the same gaps; the means (and
maxima) over the sequences of each group (the untrained motions, then each file's).
"""

from __future__ import annotations

import argparse
import copy
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from generalize import ensure_novelty, training_splits  # noqa: E402  (a sibling script: a run's reference made as it scores)

H = 15
CELLS = [4, 9, 14]  # h5, h10, h15


def errors(model, truth: np.ndarray, feats: np.ndarray) -> np.ndarray:
    """Mean centroid-aligned error at h5 / h10 / h15 of predicted features ``(B, H, V, C)``."""
    pred = model.vertices(feats.reshape(-1, *feats.shape[2:])).reshape(truth.shape)
    return vertex_errors(pred, truth)


def prediction_windows(verts: np.ndarray, feats: np.ndarray, given: int, every: int):
    """Every ``every``-th start of a sequence (vertices ``(T, V, 3)``, scaled features ``(T, V, C)``)
    with ``given`` frames and H after them: ``(starts (B,), given features (B, U, V, C), true vertices
    (B, H, V, 3), the last given frame held (B, H, V, 3): zero velocity)``."""
    from meshseq.evaluate import prediction_starts

    starts = prediction_starts(0, len(verts), given, H, every)
    x = np.stack([feats[s:s + given] for s in starts])
    truth = np.stack([verts[s + given:s + given + H] for s in starts])
    held = np.repeat(verts[starts + given - 1][:, None], H, 1)
    return starts, x, truth, held


def vertex_errors(pred: np.ndarray, truth: np.ndarray, rigid: bool = False) -> np.ndarray:
    """Mean centroid-aligned (``rigid``: also rotation-aligned) error at h5 / h10 / h15 of predicted
    vertices ``(B, H, V, 3)``."""
    from meshseq.align import per_vertex_error

    err = per_vertex_error(pred.reshape(-1, *pred.shape[2:]), truth.reshape(-1, *truth.shape[2:]), rigid=rigid)
    return err.mean(-1).reshape(truth.shape[:2])[:, CELLS].mean(0)


def main() -> None:
    import meshseq
    from meshseq import baselines, novelty
    from meshseq.io import load_sequence
    from meshseq.synthesize import predict

    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("run")
    p.add_argument("specs", nargs="+", help="sequences to predict")
    p.add_argument("--train", required=True, help="the run's training sequences, comma-separated")
    p.add_argument("--unseen", default="squat,wave,bend", help="motions the run never trained on")
    p.add_argument("--every", type=int, default=4)
    p.add_argument("--decays", default="", help="fallback dampings to score alone, comma-separated")
    p.add_argument("--completion", action="store_true", help="score completion joins instead")
    p.add_argument("--trust-paces", default="", help="with --completion: score these PACE_TRUST values instead")
    args = p.parse_args()
    model = meshseq.load(args.run, backend="numpy")
    ensure_novelty(model, args.train.split(","), training_splits(model.meta))
    if args.completion and args.trust_paces:
        trust_paces(model, args.specs, [float(t) for t in args.trust_paces.split(",")], args.unseen.split(","))
        return
    if args.completion:
        completion(model, args.specs)
        return
    decays = [float(d) for d in args.decays.split(",") if d]
    pose_only = copy.copy(model)  # the guard without its direction check
    pose_only.novelty = novelty.NoveltyReference(model.novelty.latents, model.novelty.step)
    groups: dict[str, list] = {}
    for spec in args.specs:
        verts = load_sequence(spec).vertices.astype(np.float64)
        feats = model.features(verts)
        for u in (1, 3):
            starts, given, truth, zero = prediction_windows(verts, feats, u, args.every)
            best = np.minimum(vertex_errors(zero, truth), errors(model, truth, baselines.linear_acap(given, H)))
            nov = novelty.novelty(model.engine.encode(given.reshape(-1, *given.shape[2:])),
                                  model.novelty).reshape(len(starts), u).max(1)
            off = errors(model, truth, predict(model, given, H, guard=False)) / best
            pose = errors(pose_only, truth, predict(pose_only, given, H)) / best
            on = errors(model, truth, predict(model, given, H)) / best
            alone = [errors(model, truth, novelty.fallback(given, H, d, own_pace=False)) / best for d in decays]
            if decays:
                alone.append(errors(model, truth, novelty.fallback(given, H)) / best)
            alone = alone if u > 1 else []
            unseen = any(spec.endswith("_" + m) for m in args.unseen.split(","))
            groups.setdefault(f"{'untrained' if unseen else 'trained'} motions, u{u}", []).append((off, pose, on, *alone))
            print(f"{spec.split(':')[-1]:28s} u{u} novelty {np.median(nov):4.1f} [{np.percentile(nov, 10):.1f}, "
                  f"{np.percentile(nov, 90):.1f}]  off {fmt(off)}  pose alone {fmt(pose)}  guarded {fmt(on)}"
                  + "".join(f"  fallback {d} {fmt(a)}" for d, a in zip(decays + ["own pace"], alone)), flush=True)
    for name, rows in sorted(groups.items()):
        a = np.array(rows)
        print(f"{name}: " + "  ".join(f"{what} {fmt(a[:, i].mean(0))} (max {fmt(a[:, i].max(0))})" for i, what in
                                      enumerate(["off", "pose alone", "guarded"] + [f"fallback {d}" for d in decays]
                                                + ["fallback own pace"])
                                      if a.shape[1] > i))


def gap_starts(n_frames: int, gap: int, count: int = 12) -> np.ndarray:
    """``count`` evenly spaced first keys of gaps of ``gap`` frames with ``CONTEXT`` frames on both sides."""
    from meshseq.synthesize import CONTEXT

    starts = np.arange(CONTEXT, n_frames - CONTEXT - gap - 1)
    return starts[np.linspace(0, len(starts) - 1, min(count, len(starts))).astype(int)]


def gap_errors(model, verts: np.ndarray, frames: np.ndarray, starts: np.ndarray, gap: int) -> np.ndarray:
    """Per gap ``(P,)``: the mean in-between vertex error of completed features ``frames``
    ``(P, gap + 2, V, C)`` (keys included) reconstructed through the true keys."""
    from meshseq.align import per_vertex_error
    from meshseq.synthesize import assemble_vertices

    return np.array([per_vertex_error(assemble_vertices(model, frames[p], {0: verts[a], gap + 1: verts[a + gap + 1]})
                                      [1:-1], verts[a + 1:a + gap + 1]).mean() for p, a in enumerate(starts)])


def interpolation_error(model, verts: np.ndarray, feats: np.ndarray, starts: np.ndarray, gap: int) -> float:
    """The better of linear interpolation of the features and of the vertices over the gaps."""
    from meshseq import baselines
    from meshseq.align import per_vertex_error

    ends = starts + gap + 1
    in_features = gap_errors(model, verts, np.stack([baselines.linear_interpolation(feats[a], feats[b], gap)
                                                     for a, b in zip(starts, ends)]), starts, gap).mean()
    in_vertices = np.mean([per_vertex_error(baselines.linear_interpolation(verts[a], verts[b], gap)[1:-1],
                                            verts[a + 1:b]).mean() for a, b in zip(starts, ends)])
    return float(min(in_features, in_vertices))


def completion(model, specs: list[str]) -> None:
    """Per sequence and gap, ours over the better interpolation: from the keys alone, corrected
    where the keys are familiar (keys alone), and warmed up on 7 frames around the keys trusting
    the chains by ``context_fit`` (a run without the training latents) or by ``context_trust`` (the
    default); 12 gaps per length, each with 7 frames on both sides."""

    from meshseq import novelty
    from meshseq.evaluate import completion_errors, context_chains
    from meshseq.io import load_sequence
    from meshseq.synthesize import CONTEXT, join_chains

    without = copy.copy(model)
    without.novelty = None
    for spec in specs:
        verts = load_sequence(spec).vertices.astype(np.float64)
        feats = model.features(verts)
        nov = novelty.novelty(model.engine.encode(feats), model.novelty)
        lo, hi = CONTEXT, len(verts) - CONTEXT
        cells = []
        for gap in (5, 10, 20, 30):
            def ours(m, context: int) -> float:
                r = completion_errors(m, verts, feats, lo, hi, [gap], ["ours", "linear", "linear_vertices"],
                                      samples=1, max_starts=12, context=context)[str(gap)]
                return r["ours"] / min(r["linear"], r["linear_vertices"])

            starts = gap_starts(len(verts), gap)
            fw, bw, _ = context_chains(model, feats, starts, gap, 0)
            anchored, corrected = join_chains(fw, bw, "anchored")[0], join_chains(fw, bw, "corrected")[0]
            familiar = novelty.guard_weight(np.maximum(nov[starts], nov[starts + gap + 1])).astype(np.float32)
            blended = anchored + familiar[:, None, None, None] * (corrected - anchored)
            lines = interpolation_error(model, verts, feats, starts, gap)
            cells.append(f"gap {gap}: keys {ours(model, 0):.2f} "
                         f"familiar-corrected {gap_errors(model, verts, blended, starts, gap).mean() / lines:.2f} "
                         f"context/fit {ours(without, CONTEXT):.2f} context/trust {ours(model, CONTEXT):.2f}")
        print(f"{spec.split(':')[-1]:28s} " + " | ".join(cells), flush=True)


def trust_paces(model, specs: list[str], paces: list[float], unseen: list[str]) -> None:
    """Ours over the better interpolation at gaps 5 / 10 / 20 / 30 (12 gaps each, ``CONTEXT`` frames
    on both sides) with ``context_trust`` at each slowest trusted pace: the chains and both joins
    are made once, each pace's trust picks per gap the corrected join or the anchored one."""
    from meshseq.evaluate import context_chains
    from meshseq.io import load_sequence
    from meshseq.synthesize import CONTEXT, context_trust, join_chains

    groups: dict[str, list] = {}
    for spec in specs:
        verts = load_sequence(spec).vertices.astype(np.float64)
        feats = model.features(verts).astype(np.float32)
        rows = []
        for gap in (5, 10, 20, 30):
            starts = gap_starts(len(verts), gap)
            fw, bw, _ = context_chains(model, feats, starts, gap, CONTEXT)
            ends = starts + gap + 1
            around = (np.stack([feats[a - CONTEXT:a] for a in starts]), feats[starts],
                      np.stack([feats[b + 1:b + CONTEXT + 1] for b in ends]), feats[ends])
            anchored, corrected = (gap_errors(model, verts, join_chains(fw, bw, j)[0], starts, gap)
                                   for j in ("anchored", "corrected"))
            lines = interpolation_error(model, verts, feats, starts, gap)
            rows.append([np.where(context_trust(model, *around, pace_trust=t), corrected, anchored).mean() / lines
                         for t in paces])
        rows = np.array(rows).T  # (paces, gaps)
        name = spec.split(":")[-1]
        group = "untrained motions" if any(name.endswith("_" + m) for m in unseen) else Path(spec.split(":")[0]).name
        groups.setdefault(group, []).append(rows)
        print(f"{name:28s} " + " | ".join(f"pace {t}: {fmt(r)}" for t, r in zip(paces, rows)), flush=True)
    for group, rows in sorted(groups.items()):
        a = np.array(rows)  # (sequences, paces, gaps)
        for i, t in enumerate(paces):
            print(f"{group} ({len(a)}), pace {t}: {fmt(a[:, i].mean(0))} (max {fmt(a[:, i].max(0))})")


def fmt(x: np.ndarray) -> str:
    return " / ".join(f"{v:.2f}" for v in x)


if __name__ == "__main__":
    main()
