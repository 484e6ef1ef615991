"""Benchmark: seconds to generate a body set (Anny subjects x motions x frames at V vertices).

Default: the issue's line, 10 subjects x 7 motions x 120 frames at 3,000 vertices, written to a
temporary HDF5 file (what ``meshseq make-bodies`` does). Anny's load time (its one-off cache
build on a new machine, under a second afterwards) is reported separately and not counted.

    python benchmarks/bodies_speed.py [--subjects 10] [--motions all] [--frames 120] [--vertices 3000]
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path

os.environ.setdefault("HF_HUB_OFFLINE", "1")

from meshseq.data import bodies  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--subjects", default="10")
    ap.add_argument("--motions", default="all")
    ap.add_argument("--frames", type=int, default=120)
    ap.add_argument("--vertices", type=int, default=3000)
    args = ap.parse_args()

    t0 = time.perf_counter()
    bodies.body_model()
    load = time.perf_counter() - t0
    t0 = time.perf_counter()
    bodies.body_template(args.vertices)
    template = time.perf_counter() - t0

    subjects = bodies.resolve_subjects(args.subjects)
    motions = bodies.resolve_motions(args.motions)
    n_seq = len(subjects) * len(motions)
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "bodies.h5"
        t0 = time.perf_counter()
        bodies.make_body_set(out, subjects=args.subjects, motions=motions, frames=args.frames,
                             vertices=args.vertices)
        total = time.perf_counter() - t0
        size = out.stat().st_size
    frames = n_seq * args.frames
    print(f"anny load {load:.2f} s, template ({args.vertices} vertices) {template:.2f} s (not counted)")
    print(f"bodies: {len(subjects)} subjects x {len(motions)} motions x {args.frames} frames at "
          f"{args.vertices} vertices: {total:.1f} s ({frames / total:.0f} frames/s, "
          f"{total / n_seq:.2f} s per sequence, {size / 1e6:.0f} MB)")


if __name__ == "__main__":
    main()
