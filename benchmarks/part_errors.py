"""Where a multi-part mesh's prediction error lies: on its largest part (the body) or on the rest
(eyes, straps, props) (method.md, "What the generalisation benchmark leaves unmet").

    python benchmarks/part_errors.py RUN SPEC ... [--given 3] [--every 4] [--rigid]

For each sequence: ours (guarded, the default; ``--guard off``; the paper's roll-out, ``--guard off
--pace model --carry 0``) and zero velocity, the mean centroid-aligned (``--rigid``: also
rotation-aligned) error x 1e-4 at h5 / h10 / h15 over the vertices of the largest part and over the
others (the whole mesh aligned once, as the benchmark scores it), starts every ``--every`` frames
over the whole sequence. A single-part mesh prints the body alone. ``--motion``: instead, the
benchmark's motion of 50 (the feature change of 50 frames predicted from one given frame, over the
truth's; guarded, starts as the benchmark takes them) over each part's rotation, stretch and
placement channels.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from generalize import motion_starts  # noqa: E402  (sibling scripts)
from novelty_guard import CELLS, H as HORIZON, prediction_windows  # noqa: E402


def part_errors(pred: np.ndarray, truth: np.ndarray, masks: dict[str, np.ndarray],
                rigid: bool = False) -> dict[str, np.ndarray]:
    """``{part: (3,)}``: mean centroid-aligned (``rigid``: also rotation-aligned) error at h5 / h10 /
    h15 over each ``(V,)`` bool mask's vertices of predictions ``pred`` ``(B, H, V, 3)`` against
    ``truth`` (same shape)."""
    from meshseq.align import per_vertex_error

    err = per_vertex_error(pred.reshape(-1, *pred.shape[2:]), truth.reshape(-1, *truth.shape[2:]), rigid=rigid)
    err = err.reshape(*truth.shape[:3])[:, CELLS]  # (B, 3, V)
    return {name: err[..., m].mean(axis=(0, 2)) for name, m in masks.items() if m.any()}


def part_masks(faces: np.ndarray, n_vertices: int) -> dict[str, np.ndarray]:
    """``{"body": (V,), "other parts": (V,)}``: the largest connected part's vertices and the rest."""
    from meshseq.acap.parts import body_part
    from meshseq.mesh import Topology

    topology = Topology.from_faces(faces, n_vertices)
    body = topology.component_labels == body_part(topology)
    return {"body": body, "other parts": ~body}


ROLL_OUTS = {"ours": {}, "ours, guard off": {"guard": False},
             "ours, paper's roll-out": {"guard": False, "pace": "model", "carry": 0.0}}


def sequence_errors(model, verts: np.ndarray, faces: np.ndarray, given: int, every: int, rigid: bool = False) -> dict:
    """``{method: {part: (3,)}}`` for one sequence ``(T, V, 3)``: ours by each of ``ROLL_OUTS``, zero velocity."""
    from meshseq.synthesize import predict

    _, x, truth, zero = prediction_windows(verts, model.features(verts), given, every)
    masks = part_masks(faces, verts.shape[1])
    out = {}
    for name, options in ROLL_OUTS.items():
        f = predict(model, x, HORIZON, **options)
        out[name] = part_errors(model.vertices(f.reshape(-1, *f.shape[2:])).reshape(truth.shape), truth, masks, rigid)
    out["zero velocity"] = part_errors(zero, truth, masks, rigid)
    return out


CHANNELS = {"rotation": slice(0, 3), "stretch": slice(3, 9), "placement": slice(9, None)}


def motion_by_part(model, feats: np.ndarray, masks: dict[str, np.ndarray]) -> dict[str, dict[str, float]]:
    """``{part: {channel group: ours' feature change over the truth's}}`` of 50 frames predicted from
    one given frame (``evaluate.feature_change``'s curve, restricted to the part's vertices and the
    group's channels); a group the truth never changes (the body's placement) is left out."""
    from meshseq.evaluate import predicted_features
    from meshseq.plots import feature_change

    starts = motion_starts(0, len(feats))
    pred = predicted_features("ours", model, feats, starts, 1, 50)
    ours = model.scaling.invert(np.concatenate([feats[starts][:, None], pred], axis=1).astype(np.float64))
    truth = model.scaling.invert(feats.astype(np.float64))
    out: dict[str, dict[str, float]] = {}
    for part, mask in masks.items():
        for group, channels in CHANNELS.items():
            if not mask.any() or channels.start >= feats.shape[-1]:
                continue
            moved = feature_change(truth[:, mask, channels]).mean()
            if moved > 0:
                out.setdefault(part, {})[group] = float(feature_change(ours[:, :, mask, channels]).mean() / moved)
    return out


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("run", help="a trained run")
    p.add_argument("specs", nargs="+", metavar="SPEC", help="sequences (FILE or FILE:NAME)")
    p.add_argument("--given", type=int, default=3)
    p.add_argument("--every", type=int, default=4)
    p.add_argument("--rigid", action="store_true", help="align rotations too (the benchmark's rigid figures)")
    p.add_argument("--motion", action="store_true", help="the motion of 50 per part and channel group instead")
    args = p.parse_args(argv)
    import meshseq
    from meshseq.io import load_sequence

    model = meshseq.load(args.run)
    for spec in args.specs:
        seq = load_sequence(spec)
        if args.motion:
            res = motion_by_part(model, model.features(seq.vertices.astype(np.float64)),
                                 part_masks(seq.faces, seq.n_vertices))
            print(f"{spec}: motion of 50 over the truth's, " + "   ".join(
                f"{part} " + ", ".join(f"{g} {v:.2f}" for g, v in groups.items()) for part, groups in res.items()))
            continue
        res = sequence_errors(model, seq.vertices.astype(np.float64), seq.faces, args.given, args.every, args.rigid)
        print(f"{spec}: u{args.given}, x 1e-4 at h5 / h10 / h15{', rigid' if args.rigid else ''}")
        for method, parts in res.items():
            print(f"  {method:22s} " + "   ".join(f"{part} " + " / ".join(f"{v * 1e4:.0f}" for v in e)
                                             for part, e in parts.items()), flush=True)


if __name__ == "__main__":
    main()
