"""Validation-block errors of checkpoints beside the baselines' (``meshseq train --validation``).

    python benchmarks/validation_errors.py RUN/checkpoints/best RUN/checkpoints/00001000 ...

For each checkpoint (or run folder: its newest checkpoint), the figure training logs as
``validation`` (``meshseq.evaluate.validation_error``: centroid-aligned error x 1e-4 over horizons
1..15 after 1 and 3 given frames on every data set's validation block), and the same figure for
zero velocity and linear ACAP extrapolation, so a run's validation curve can be read against
standing still. Only the validation blocks are predicted (the given frames may be training
frames); the held-out block is never read.
"""

from __future__ import annotations

import argparse

BASELINES = ("zero_velocity", "linear_acap")


def main(argv=None) -> int:
    import meshseq
    from meshseq.data.windows import Split
    from meshseq.evaluate import validation_error
    from meshseq.train import load_training_data, reconstructed_vertices

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("checkpoints", nargs="+", help="checkpoint or run folders (one run's, or runs on the same data)")
    args = ap.parse_args(argv)
    cache = {}
    for path in args.checkpoints:
        model = meshseq.load(path)
        sets = model.meta["datasets"]
        splits = [Split.from_dict(d["split"]) for d in sets]
        if any(s.validation is None for s in splits):
            raise SystemExit(f"{path}: trained without a validation block (meshseq train --validation)")
        sources = tuple(d["source"] for d in sets)
        if sources not in cache:
            data = load_training_data(list(sources), model.meta["features"].get("consistency", "temporal"))
            cache[sources] = (data, reconstructed_vertices(data)[1])
        data, vertices = cache[sources]
        feats = [model.scaling.apply(f) for f in data.features]
        blocks = [s.validation for s in splits]
        figures = {m: validation_error(model, vertices, feats, blocks, method=m) for m in ("ours",) + BASELINES}
        print(f"{path} (iteration {model.iteration}): " + ", ".join(f"{m} {e:.1f}" for m, e in figures.items())
              + f"; ours / best baseline {figures['ours'] / min(figures[m] for m in BASELINES):.3f}", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
