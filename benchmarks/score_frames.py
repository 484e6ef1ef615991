"""Score a trained generalize.py run on any frames of a capture, as the benchmark scores a held-out
block: the reference for a controlled run that shows training part of a block (method.md, "What
the generalisation benchmark leaves unmet").

    python benchmarks/generalize.py --sets pcow --holdout 0.1 --out runs/generalize
    python benchmarks/score_frames.py runs/generalize/pcow-at-end pcow.npz 184 204

prints the benchmark's line for frames ``[FIRST, STOP)`` of SPEC scored with RUN (its novelty
against RUN's training frames, ours over the best baseline, ours over the better interpolation,
the motion of 50 generated frames), and with ``-o`` writes the block as the records hold it.
``--guard off`` scores ours' predictions without the novelty guard (the roll-out it replaces);
``--vertex-share S`` completes with another vertex share than the run's (``meshseq.inbetween``).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import generalize  # noqa: E402  (a sibling script)


def score_frames(run: str, spec: str, first: int, stop: int, guard: bool = True,
                 vertex_share: float | None = None) -> dict:
    """The benchmark's block ``[first, stop)`` of ``spec`` scored with the run in ``run``, against
    the frames that run trained on (every sequence it trained on must be ``spec``); ``guard``: ours'
    predictions with the novelty guard; ``vertex_share``: completion's (default the run's)."""
    import meshseq
    from meshseq.io import load_sequence

    model = meshseq.load(run)
    splits = generalize.training_splits(model.meta)
    if len(splits) != 1:
        raise SystemExit(f"{run}: trained on {len(splits)} sequences; this scores a run of one capture")
    verts = load_sequence(spec).vertices.astype(np.float64)
    if not 0 <= first < stop <= len(verts):
        raise SystemExit(f"{spec}: frames {first}-{stop} outside its {len(verts)} frames")
    feats = model.features(verts)
    generalize.ensure_novelty(model, [spec], splits)
    generalize.ensure_vertex_share(model, [spec], splits)
    if vertex_share is not None:
        model.vertex_share = vertex_share
    train_feats = np.concatenate([feats[a:b] for a, b in splits[0].train])
    return next(generalize.score_blocks(model, [spec], splits, train_feats, [(spec, first, stop)], guard))


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("run")
    p.add_argument("spec", help="the capture (a file in the shared data folder may be named alone)")
    p.add_argument("first", type=int, help="the block's first frame")
    p.add_argument("stop", type=int, help="the frame after its last")
    p.add_argument("-o", "--out", help="write the scored block as JSON")
    p.add_argument("--guard", choices=("on", "off"), default="on", help="ours' predictions with the novelty guard "
                                                                      "(the benchmark's) or without")
    p.add_argument("--vertex-share", type=float, default=None, metavar="S",
                   help="completion's vertex share (meshseq.inbetween; default the run's)")
    args = p.parse_args()
    spec = generalize.frames_spec(args.spec)[0]
    block = score_frames(args.run, spec, args.first, args.stop, args.guard == "on", args.vertex_share)
    guard = "" if args.guard == "on" else ", guard off"
    print(generalize.line(f"{Path(args.run).name} frames {args.first}-{args.stop}{guard}", block), flush=True)
    if args.out:
        Path(args.out).write_text(json.dumps(block, indent=1))


if __name__ == "__main__":
    main()
