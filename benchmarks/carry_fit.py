"""The carried velocity's fit (``meshseq.carry``) on any run: the scores training stores, for a run
stored before it or for other shares (method.md, "5. Synthesis").

    python benchmarks/carry_fit.py RUN [--carries 0,0.3,0.6]

Over the training segments of RUN (as its checkpoint names them; their files must be readable
where it says), as ``meshseq.carry.fit_carry`` scores them: 3 given frames, a start every 4 frames
inside each segment, ours with each carry over zero velocity at h5 / h10 / h15 (centroid-aligned,
errors summed over every start before the ratio), their mean, and the share the fit picks.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from generalize import training_segments  # noqa: E402  (a sibling script)


def main(argv: list[str] | None = None) -> None:
    import meshseq
    from meshseq.carry import CARRIES, carry_errors, choose_carry

    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("run", help="a trained run")
    p.add_argument("--carries", default=",".join(f"{c:g}" for c in CARRIES),
                   help="carried-velocity shares to score, ascending (the fit's by default)")
    args = p.parse_args(argv)
    carries = [float(c) for c in args.carries.split(",")]
    model = meshseq.load(args.run)
    ours, zero = carry_errors(model, training_segments(model), carries)
    ratios = ours / np.maximum(zero, 1e-300)
    print(f"{args.run}: its training segments, u3, ours over zero velocity at h5 / h10 / h15, mean")
    for c, r in zip(carries, ratios):
        print(f"  carry {c:<4g} " + " / ".join(f"{x:.3f}" for x in r) + f"   {r.mean():.3f}", flush=True)
    print(f"  fitted: {choose_carry(ratios.mean(axis=1), carries):g}; stored: "
          f"{model.meta.get('prediction', {}).get('carry', 'none')}")


if __name__ == "__main__":
    main()
