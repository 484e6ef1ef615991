"""Table: spurious 2 pi jumps in time of ACAP rotation logs, before (greedy) and after (temporal).

A spurious jump is a consecutive-frame step of a vertex's three rotation channels longer than pi
while the rotation itself changes by less than pi/2 (meshseq.acap.diagnostics.branch_jumps).
Rows: the shared data sets (../shared/data, or files given as arguments) and the synthetic hard
cases of meshseq.data.rotation_cases. Columns per consistency mode: spurious jumps, vertices hit,
largest log norm.

    python benchmarks/acap_jumps.py [DATA ...] [--modes greedy temporal] [--no-synthetic]
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from meshseq.acap import CONSISTENCY_MODES, extract
from meshseq.acap.diagnostics import feature_jumps

SHARED = Path(__file__).resolve().parent.parent.parent / "shared" / "data"
DEFAULT_DATA = [SHARED / f"{n}.npz" for n in ("pcow", "crane", "horse-gallop")]


def rows(args):
    from meshseq.io import load_sequence

    for path in args.data or DEFAULT_DATA:
        seq = load_sequence(str(path))
        yield Path(path).stem, seq.vertices, seq.faces
    if args.synthetic:
        from meshseq.data.rotation_cases import cases

        for name, seq in cases().items():
            yield f"synthetic:{name}", seq.vertices, seq.faces


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("data", nargs="*", help="sequences (default: pcow, crane, horse-gallop from ../shared/data)")
    ap.add_argument("--modes", nargs="+", default=["greedy", "temporal"], choices=CONSISTENCY_MODES)
    ap.add_argument("--no-synthetic", dest="synthetic", action="store_false")
    args = ap.parse_args()
    head = f"| {'data':28s} | {'frames x vertices':17s} |" + "".join(
        f" {m}: jumps | vertices hit | max log norm | s |" for m in args.modes)
    print(head)
    print("|" + "---|" * (2 + 4 * len(args.modes)))
    for name, v, f in rows(args):
        cells = [f"| {name:28s} | {f'{v.shape[0]} x {v.shape[1]}':17s} |"]
        for mode in args.modes:
            t0 = time.perf_counter()
            feats = extract(np.asarray(v, dtype=np.float64), f, consistency=mode)
            seconds = time.perf_counter() - t0
            j = feature_jumps(feats)
            cells.append(f" {j['spurious_jumps']} | {j['spurious_jump_vertices']} |"
                         f" {j['largest_log_norm']:.2f} | {seconds:.2f} |")
        print("".join(cells), flush=True)


if __name__ == "__main__":
    main()
