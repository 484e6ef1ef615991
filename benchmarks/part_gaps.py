"""How much each part's placement moves over a sequence, measured from the mesh's centroid and from
the part's anchor vertex (``meshseq.acap.parts.PLACEMENT_MODES``): the mean distance of each frame's
gap from the sequence's mean gap, x 1e-4 of the data's units. What the model has to predict of a
part's place is that motion; a part that rides on the body barely moves from its anchor.

    python benchmarks/part_gaps.py bodies1k_parts.h5:male_slim_walk bodies1k_parts.h5:female_old_punch
"""

from __future__ import annotations

import argparse

import numpy as np


def gap_motion(vertices: np.ndarray, faces: np.ndarray, mode: str) -> np.ndarray:
    """``(C,)``: each part's mean distance from its mean gap under ``mode`` (frame 0 the reference)."""
    from meshseq.acap.parts import part_anchors, part_gaps
    from meshseq.mesh import Topology

    topo = Topology.from_faces(faces, vertices.shape[1])
    anchors = part_anchors(vertices[0], topo) if mode == "anchor" else None
    gaps = part_gaps(vertices, topo, anchors)  # (T, C, 3)
    return np.linalg.norm(gaps - gaps.mean(axis=0), axis=-1).mean(axis=0)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("specs", nargs="+", help="sequences (meshseq.io.load_sequence specs)")
    args = p.parse_args()
    from meshseq.acap.parts import body_part
    from meshseq.io import load_sequence
    from meshseq.mesh import Topology

    for spec in args.specs:
        seq = load_sequence(spec)
        v = seq.vertices.astype(np.float64)
        topo = Topology.from_faces(seq.faces, seq.n_vertices)
        counts = np.bincount(topo.component_labels)
        moves = {mode: gap_motion(v, seq.faces, mode) for mode in ("centroid", "anchor")}
        parts = [c for c in range(topo.n_components) if c != body_part(topo)]
        print(f"{spec}: " + " | ".join(f"part {c} ({counts[c]} vertices): from the centroid "
                                       f"{moves['centroid'][c] * 1e4:.0f}, from its anchor {moves['anchor'][c] * 1e4:.0f}"
                                       for c in parts))


if __name__ == "__main__":
    main()
