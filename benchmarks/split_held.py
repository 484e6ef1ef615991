"""A body set with one sequence's start shown to training: the controlled run of "what if training
had seen the first part of this performance" (method.md, "What the generalisation benchmark leaves
unmet").

    python benchmarks/split_held.py bodies1k.h5 male_slim_jumping_jacks 60 -o bodies1k_jjseen.h5
    python benchmarks/generalize.py --sets bodies --bodies bodies1k_jjseen.h5 --bodies-name bodies-jjseen \\
        --hold-subject held

Copies every sequence of a ``meshseq make-bodies`` file but SEQUENCE, which becomes two:
``seen_MOTION`` (its frames before FRAME, trained on) and ``held_MOTION`` (the rest, held out with
``--hold-subject held`` and scored whole).
"""

from __future__ import annotations

import argparse
from pathlib import Path


def main() -> None:
    import h5py

    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("bodies")
    p.add_argument("sequence")
    p.add_argument("frame", type=int, help="the first held-out frame")
    p.add_argument("-o", "--out", required=True)
    args = p.parse_args()
    if Path(args.out).exists():
        raise SystemExit(f"{args.out} exists")
    with h5py.File(args.bodies, "r") as src, h5py.File(args.out, "w") as dst:
        if args.sequence not in src:
            raise SystemExit(f"{args.bodies}: no sequence {args.sequence!r}")
        dst.attrs.update(dict(src.attrs))
        for name in src:
            if name != args.sequence:
                src.copy(name, dst, name=name)
                continue
            seq = src[name]
            motion = seq.attrs["motion"]
            frames = seq[...]  # (V, 3, T), as make-bodies stores it
            for part, cut in ((f"seen_{motion}", slice(0, args.frame)), (f"held_{motion}", slice(args.frame, None))):
                dst.create_dataset(part, data=frames[:, :, cut]).attrs.update(dict(seq.attrs))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
