"""Report: how much of the [-0.95, 0.95] range a frame-to-frame change uses, per scaling mode.

For each sequence (default: the shared pcow, crane, horse-gallop) the features are extracted
(``--consistency``, default temporal), scaled with ``two-group`` and ``per-channel`` (fitted on all
frames), and the per-frame change |x'_{t+1} - x'_t| is reported relative to the range 1.9: mean
and 99.9th percentile, for the rotation channels (0-2) and the stretch channels (3-8), with the
rotation channels' fitted span. ``wrapped`` rows wrap each rotation log to norm <= pi first
(principal logs, which adds 2 pi jumps back), to show what wrapping accumulated angles would do.

    python benchmarks/acap_scaling.py [DATA ...] [--consistency temporal]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from meshseq.acap import CONSISTENCY_MODES, Scaling, extract

SHARED = Path(__file__).resolve().parent.parent.parent / "shared" / "data"


def wrap(feats: np.ndarray) -> np.ndarray:
    out = feats.copy()
    r = out[..., :3]
    n = np.linalg.norm(r, axis=-1, keepdims=True)
    k = np.round(n / (2 * np.pi))
    out[..., :3] = r * np.divide(n - 2 * np.pi * k, n, out=np.ones_like(n), where=n > 0)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("data", nargs="*")
    ap.add_argument("--consistency", default="temporal", choices=CONSISTENCY_MODES)
    args = ap.parse_args()
    paths = args.data or [SHARED / f"{n}.npz" for n in ("pcow", "crane", "horse-gallop")]
    print("| data | features | scaling | rot span (rad) | rot step mean | rot step p99.9 | S step mean | S step p99.9 |")
    print("|---|---|---|---|---|---|---|---|")
    for path in paths:
        d = np.load(path)
        feats = extract(d["vertices"].astype(np.float64), d["faces"], consistency=args.consistency)
        for label, x in ((args.consistency, feats), ("wrapped", wrap(feats))):
            for mode in ("two-group", "per-channel"):
                s = Scaling.fit(x, mode)
                step = np.abs(np.diff(s.apply(x), axis=0)) / 1.9
                rot, st = step[..., :3], step[..., 3:]
                span = s.maximum[:3] - s.minimum[:3]
                span_txt = f"{span[0]:.2f}" if mode == "two-group" else "/".join(f"{v:.2f}" for v in span)
                print(f"| {Path(path).stem} | {label} | {mode} | {span_txt} | {rot.mean():.2e} |"
                      f" {np.percentile(rot, 99.9):.3f} | {st.mean():.2e} | {np.percentile(st, 99.9):.3f} |",
                      flush=True)


if __name__ == "__main__":
    main()
