"""Does prediction keep the pace of its given frames? Checkpoints on sequences with holds,
slow-downs to a stop and speed-ups.

For every start (every ``--every`` frames) it gives 3 frames and predicts 15, and reports, binned
by the given frames' motion level over the sequence's mean step (still < 0.1, slow < 0.5, steady
< 1.5, fast), the mean level of the given frames, of the truth that follows and of the prediction,
their correlation over all starts, the level predicted from a pose held still (3 copies of one
frame), and prediction errors x 1e-4 against zero velocity and linear extrapolation.

    meshseq make-bodies --subjects female_fit,male_heavy,female_old,male_slim \
        --motions punch,shake_arms,jumping_jacks,walk --frames 160 --vertices 1000 --tempo varied \
        -o bodies1k_varied.h5
    python benchmarks/pace.py RUN_OR_CHECKPOINT... --data bodies1k_varied.h5 --every 8
"""

from __future__ import annotations

import argparse
import json

import numpy as np


def sequences(spec: str) -> list[str]:
    if spec.endswith(".h5"):
        import h5py

        with h5py.File(spec, "r") as fh:
            return [f"{spec}:{k}" for k in sorted(fh.keys()) if k != "faces"]
    return [spec]


def evaluate(path: str, specs: list[str], every: int, horizon: int = 15) -> dict:
    import meshseq
    from meshseq.evaluate import prediction_errors
    from meshseq.io import load_sequence
    from meshseq.pace import pace_levels, pace_table, step_levels

    model = meshseq.load(path)
    levels = {"given": [], "truth": [], "ours": []}
    hold = []
    errs: dict = {}
    typical = []
    for spec in specs:
        seq = load_sequence(spec)
        v = seq.vertices.astype(np.float64)
        feats = model.features(v)
        med = float(np.mean(step_levels(v)))  # the mean: a sequence may hold still half the time
        starts = np.arange(0, len(v) - 3 - horizon, every)
        lv = pace_levels(model, v, feats, starts, 3, horizon)
        for k in levels:
            levels[k].append(lv[k] / med)
        hv = pace_levels(model, v, feats, starts[::4], 3, horizon, hold=True)
        hold.append(hv["ours"] / med)
        typical.append(med)
        for u in (1, 3):
            r = prediction_errors(model, v, feats, 0, len(v), u, [5, 10, 15],
                                  ["ours", "zero_velocity", "linear_acap"], every=every)
            for m, res in r.items():
                for key in ("centroid", "rigid"):
                    for h, e in res[key].items():
                        errs.setdefault((m, u, key, h), []).append(e)
    levels = {k: np.concatenate(v) for k, v in levels.items()}
    table = pace_table(levels, 1.0)
    corr = float(np.corrcoef(levels["given"], levels["ours"])[0, 1])
    errors = {f"{m} u{u} {key} h{h}": float(np.mean(e)) for (m, u, key, h), e in errs.items()}
    return {"checkpoint": str(path), "iteration": model.iteration, "pace": table, "corr_given_ours": corr,
            "corr_given_truth": float(np.corrcoef(levels["given"], levels["truth"])[0, 1]),
            "hold_level": float(np.mean(np.concatenate(hold))), "errors": errors}


def main() -> None:
    p = argparse.ArgumentParser()
    p.add_argument("runs", nargs="+")
    p.add_argument("--data", nargs="+", required=True)
    p.add_argument("--every", type=int, default=4)
    p.add_argument("--json", default=None)
    args = p.parse_args()
    specs = [s for d in args.data for s in sequences(d)]
    out = []
    for run in args.runs:
        r = evaluate(run, specs, args.every)
        out.append(r)
        print(f"== {run} (iteration {r['iteration']}): corr(given, ours) {r['corr_given_ours']:.2f} "
              f"(truth {r['corr_given_truth']:.2f}); from a held pose: {r['hold_level']:.3f} of the mean step")
        for row in r["pace"]:
            print(f"  {row['bin']:7s} n={row['starts']:4d} given {row['given']:.2f} truth {row['truth']:.2f} "
                  f"ours {row['ours']:.2f}  ours/truth {row['ours_over_truth']:.2f}")
        e = r["errors"]
        for u in (1, 3):
            for key in ("centroid", "rigid"):
                cells = "  ".join(f"h{h} {e[f'ours u{u} {key} h{h}']:.0f}/{e[f'zero_velocity u{u} {key} h{h}']:.0f}/"
                                  f"{e[f'linear_acap u{u} {key} h{h}']:.0f}" for h in (5, 10, 15))
                print(f"  u{u} {key:8s} ours/zero/linear: {cells}")
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(out, fh, indent=1)


if __name__ == "__main__":
    main()
