"""How smooth in time each part's rotation logs are under each rotation consistency (method.md,
"Meshes of several parts": the smallest-turn walk).

    python benchmarks/log_steps.py SPEC ... [--reference SPEC] [--consistency temporal,temporal-mst]

For every sequence, part (connected component, the largest first) and consistency: the share of
vertex-frames whose log lies past pi (on a 2 pi shell), the share of log steps between consecutive
frames longer than 0.3 rad where the rotation itself turned by less than 0.1 rad (steps the shell
makes, not motion), and the mean log step in radians. ``--reference``: extract against frame 0 of
that sequence (as training does against its first data set's); default each sequence's own first
frame.
"""

from __future__ import annotations

import argparse

import numpy as np

#: a log step longer than this (radians) ...
LONG_STEP = 0.3
#: ... where the rotation turned by less than this is the shell's doing, not motion
SMALL_TURN = 0.1


def log_step_stats(logs: np.ndarray, labels: np.ndarray) -> list[dict]:
    """Per part ``c`` (``labels == c``, ``(V,)``) of rotation logs ``(T, V, 3)``: ``shell`` (share of
    vertex-frames with ``|log| > pi``), ``shell_steps`` (share of steps longer than :data:`LONG_STEP`
    turning less than :data:`SMALL_TURN`) and ``mean_step`` (radians)."""
    from meshseq.acap.rotations import relative_angles

    norm = np.linalg.norm(logs, axis=-1)
    step = np.linalg.norm(np.diff(logs, axis=0), axis=-1)
    turn = relative_angles(logs)
    out = []
    for c in range(labels.max() + 1):
        m = labels == c
        out.append({"vertices": int(m.sum()), "shell": float((norm[:, m] > np.pi).mean()),
                    "shell_steps": float(((step[:, m] > LONG_STEP) & (turn[:, m] < SMALL_TURN)).mean()),
                    "mean_step": float(step[:, m].mean())})
    return out


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("specs", nargs="+", metavar="SPEC", help="sequences (FILE or FILE:NAME)")
    p.add_argument("--reference", help="extract against frame 0 of this sequence")
    p.add_argument("--consistency", default="temporal,temporal-mst")
    args = p.parse_args(argv)
    from meshseq.acap import extract
    from meshseq.acap.diagnostics import rotation_logs
    from meshseq.io import load_sequence
    from meshseq.mesh import Topology

    reference = load_sequence(args.reference).vertices[0] if args.reference else None
    for spec in args.specs:
        seq = load_sequence(spec)
        labels = Topology.from_faces(seq.faces, seq.n_vertices).component_labels
        order = np.argsort(-np.bincount(labels), kind="stable")  # the largest part first
        labels = np.argsort(order)[labels]
        print(f"{spec}: per part (vertices): on the shell / steps the shell makes / mean log step (rad)")
        for mode in args.consistency.split(","):
            f = extract(seq.vertices, seq.faces, reference=reference, consistency=mode)
            stats = log_step_stats(rotation_logs(f[..., :9]), labels)
            print(f"  {mode:13s} " + "   ".join(f"({s['vertices']}) {s['shell']:.3f} / {s['shell_steps']:.4f} / "
                                                f"{s['mean_step']:.3f}" for s in stats), flush=True)


if __name__ == "__main__":
    main()
