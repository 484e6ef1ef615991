"""What a weight average delivers: a run's training loss at every checkpoint, for the delivered
model and for the weights training continues from.

For each checkpoint of a ``meshseq train`` run, the free-running loss terms (``z = mu``, no
sampling noise, 1 given frame: L_rec, L_bd) on the run's own training windows, evenly spaced over
its training part (at most ``--windows`` of them; the held-out frames are never used), of

- ``delivered``: the model the checkpoint holds (``meshseq.load``, what predict and evaluate use),
- ``training``: the weights training continues from, stored beside it when the run averages its
  weights (``--ema-decay``; otherwise the two are the same weights and only one column is printed).

    python benchmarks/average_study.py RUN DATA [DATA ...] [--windows 16] [--threads 2]

DATA: what the run was trained on (the same specs as ``meshseq train``).
"""

from __future__ import annotations

import argparse
import sys

import numpy as np


def training_rows(meta: dict, max_windows: int) -> np.ndarray:
    """Up to ``max_windows`` evenly spaced training windows ``(N, window)`` (rows of the stacked frames)."""
    from meshseq.data.windows import Split, WindowSampler

    splits = [Split.from_dict(d["split"]) for d in meta["datasets"]]
    train = meta["train"]
    sampler = WindowSampler(splits, [d["name"] for d in meta["datasets"]], train["window"], train["stride"])
    picks = np.unique(np.linspace(0, len(sampler.starts) - 1, num=max_windows).round().astype(np.int64))
    return sampler.rows(picks)


def checkpoint_losses(loaded, frames, rows: np.ndarray) -> dict:
    """``{"delivered": {rec, bd}, "training": {rec, bd} or None}`` of one loaded checkpoint
    (``checkpoint.load_folder(..., with_state=True)``)."""
    import torch

    from meshseq import checkpoint as ckpt
    from meshseq.train import copy_weights, window_losses

    net = loaded.net.eval()
    windows = frames[torch.from_numpy(rows)]

    def losses() -> dict:
        with torch.no_grad():
            terms = window_losses(net(windows, sample=False), windows)
        return {"rec": float(terms["rec"]), "bd": float(terms["bd"])}

    out = {"delivered": losses(), "training": None}
    raw = ckpt.training_weights(loaded.state_tensors)
    if raw:
        names, params = zip(*net.named_parameters())
        copy_weights(list(params), [raw[n] for n in names])
        out["training"] = losses()
    return out


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("run")
    p.add_argument("data", nargs="+")
    p.add_argument("--windows", type=int, default=16, help="training windows evaluated (evenly spaced)")
    p.add_argument("--threads", type=int, default=2)
    args = p.parse_args()

    import torch

    from meshseq import checkpoint as ckpt
    from meshseq.acap import Scaling
    from meshseq.errors import MeshseqError
    from meshseq.train import load_training_data

    torch.set_num_threads(args.threads)
    folders = ckpt.list_checkpoints(args.run)
    if not folders:
        sys.exit(f"average_study: {args.run}: no checkpoint")
    meta = ckpt.load_folder(folders[-1]).meta
    data = load_training_data(args.data, consistency=meta["train"]["consistency"])
    if [d["source"] for d in meta["datasets"]] != data.sources:
        sys.exit(f"average_study: {args.run} was trained on {[d['source'] for d in meta['datasets']]}, "
                 f"not {data.sources}")
    scaling = Scaling.from_dict(meta["scaling"])
    frames = torch.from_numpy(np.concatenate([scaling.apply(f) for f in data.features]).astype(np.float32))
    rows = training_rows(meta, args.windows)
    decay = meta["train"].get("ema_decay")
    print(f"{args.run}: {len(rows)} training window(s) of {rows.shape[1]} frames; ema_decay {decay}")
    print("| iteration | delivered L_rec | delivered L_bd | training-weights L_rec | training-weights L_bd |")
    print("|---|---|---|---|---|")
    for folder in folders:  # each loaded (and checked) once; a damaged one is named and skipped
        try:
            loaded = ckpt.load_folder(folder, with_state=True)
        except MeshseqError as err:
            print(f"| {folder.name} | skipped: {err} | | | |", flush=True)
            continue
        r = checkpoint_losses(loaded, frames, rows)
        d, t = r["delivered"], r["training"] or {"rec": float("nan"), "bd": float("nan")}
        print(f"| {int(folder.name)} | {d['rec']:.1f} | {d['bd']:.1f} | {t['rec']:.1f} | {t['bd']:.1f} |", flush=True)


if __name__ == "__main__":
    main()
