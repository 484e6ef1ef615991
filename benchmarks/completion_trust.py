"""Completion as the generalisation benchmark scores a block, with completion's trust in the chains
changed: which completion misses come from chains that are right but not trusted (method.md, "What
the generalisation benchmark leaves unmet").

    python benchmarks/completion_trust.py RUN SPEC[@FIRST,STOP] ... [--rules default,always,pace=0.5]

For each sequence (frames ``[FIRST, STOP)``, by default the whole sequence: the benchmark's block)
and rule, ours at the benchmark's gaps of 5 / 10 / 20 / 30 frames (8 starts, ``CONTEXT`` frames
given around the keys) with ACAP and vertex interpolation beside it, and ours over the better of the
two. The rules: ``default`` (``synthesize.context_trust``), ``always`` (every gap's chains keep
their own motion), ``never`` (none does: the anchored weight everywhere) and ``pace=P`` (the default
with the slowest trusted pace P instead of ``synthesize.PACE_TRUST``).
"""

from __future__ import annotations

import argparse
import contextlib
import functools
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import generalize  # noqa: E402  (a sibling script: its gaps and the shared data folder)


def trust_rule(name: str):
    """The ``context_trust`` that a rule name stands for; SystemExit naming it if there is none."""
    import meshseq.synthesize as syn

    if name == "default":
        return syn.context_trust
    if name in ("always", "never"):
        def fixed(model, before, key_a, after, key_b, **_) -> np.ndarray:
            return np.full(len(key_a), name == "always")
        return fixed
    if name.startswith("pace="):
        try:
            return functools.partial(syn.context_trust, pace_trust=float(name[len("pace="):]))
        except ValueError:
            pass
    raise SystemExit(f"--rules: {name!r}: expected default, always, never or pace=P")


@contextlib.contextmanager
def trusting(rule):
    """Completion trusts the chains by ``rule`` (a ``context_trust``) inside the block."""
    import meshseq.synthesize as syn

    saved, syn.context_trust = syn.context_trust, rule
    try:
        yield
    finally:
        syn.context_trust = saved


def block_errors(model, verts: np.ndarray, feats: np.ndarray, lo: int, hi: int, rule) -> dict[str, dict]:
    """The benchmark's completion figures of block ``[lo, hi)`` (ours, ``linear``, ``linear_vertices``
    per gap, as ``evaluate.completion_errors`` gives them) with the chains trusted by ``rule``."""
    from meshseq.evaluate import completion_errors
    from meshseq.synthesize import CONTEXT

    gaps = generalize.block_gaps(lo, hi)
    with trusting(rule):
        return completion_errors(model, verts, feats, lo, hi, gaps, ["ours", "linear", "linear_vertices"],
                                 samples=1, context=CONTEXT)


def main() -> None:
    import meshseq
    from meshseq.io import load_sequence

    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("run")
    p.add_argument("specs", nargs="+", help="sequences, each optionally SPEC@FIRST,STOP (a file in the shared "
                                            "data folder may be named alone)")
    p.add_argument("--rules", default="default,always,never", help="comma-separated: default, always, never, pace=P")
    p.add_argument("--vertex-share", type=float, default=None, metavar="S",
                   help="completion's vertex share (meshseq.inbetween; default the run's, fitted on its training "
                        "frames as the benchmark fits it where the run was stored without)")
    args = p.parse_args()
    rules = {name: trust_rule(name) for name in args.rules.split(",")}
    model = meshseq.load(args.run)
    generalize.ensure_vertex_share(model, *generalize.training_specs(model))
    if args.vertex_share is not None:
        model.vertex_share = args.vertex_share
    for spec in args.specs:
        path, frames = generalize.frames_spec(spec)
        verts = load_sequence(path).vertices.astype(np.float64)
        lo, hi = frames or (0, len(verts))
        feats = model.features(verts)
        for name, rule in rules.items():
            res = block_errors(model, verts, feats, lo, hi, rule)
            cells = [f"gap {g}: {r['ours']:.1f} / {r['linear']:.1f} / {r['linear_vertices']:.1f} = "
                     f"{r['ours'] / min(r['linear'], r['linear_vertices']):.3f}" for g, r in res.items()]
            print(f"{Path(path).name} {lo}-{hi} {name}: " + "  ".join(cells), flush=True)


if __name__ == "__main__":
    main()
