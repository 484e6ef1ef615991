"""How far apart a run's training sequences lie in its latent space, next to other sequences'
novelty: could the guard's ramp be scaled by the training set's own spread? (method.md, "What the
generalisation benchmark leaves unmet").

    python benchmarks/novelty_spread.py RUN [SPEC ...]

For each training sequence of RUN (its training frames only): the median and 90th percentile of its
frames' distance to the nearest latent of the other training sequences (leave one sequence out), in
the run's typical latent steps; then for each SPEC the median and 10th percentile of its frames'
novelty against the whole reference (``novelty.novelty``, what the guard reads).
"""

from __future__ import annotations

import argparse

import numpy as np


def training_latents(model) -> list[tuple[str, np.ndarray]]:
    """``[(spec, (N_i, L) latent means of its training frames)]`` for each of the run's data sets."""
    from meshseq.data.windows import Split
    from meshseq.io import load_sequence

    out = []
    for d in model.meta["datasets"]:
        split = Split.from_dict(d["split"])
        feats = model.features(load_sequence(d["source"]).vertices.astype(np.float64))
        segments = [feats[a:b] for a, b in split.train if b - a > 1]
        out.append((d["source"], np.concatenate([model.encode(s) for s in segments])))
    return out


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("run", help="a trained run (its training sequences must be readable where it says)")
    p.add_argument("specs", nargs="*", metavar="SPEC", help="other sequences (FILE or FILE:NAME)")
    args = p.parse_args(argv)
    import meshseq
    from meshseq import novelty
    from meshseq.io import load_sequence

    model = meshseq.load(args.run)
    train = training_latents(model)
    medians = []
    for i, (spec, z) in enumerate(train):
        rest = novelty.NoveltyReference(np.concatenate([t for j, (_, t) in enumerate(train) if j != i]),
                                        model.novelty.step)
        d = novelty.novelty(z, rest)
        medians.append(np.median(d))
        print(f"training, left out  {spec}: median {np.median(d):.2f}  p90 {np.percentile(d, 90):.2f}")
    print(f"training, left out: median over sequences {np.median(medians):.2f}, "
          f"range {min(medians):.2f}-{max(medians):.2f}")
    for spec in args.specs:
        n = novelty.novelty(model.encode(model.features(load_sequence(spec).vertices.astype(np.float64))),
                            model.novelty)
        print(f"other               {spec}: median {np.median(n):.2f}  p10 {np.percentile(n, 10):.2f}", flush=True)


if __name__ == "__main__":
    main()
