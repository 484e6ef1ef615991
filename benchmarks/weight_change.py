"""How far each weight tensor moved between two checkpoints of a run: norms of the training
weights at the first, of the change, the change relative to the weights, and its largest entry.

    python benchmarks/weight_change.py RUN ITERATION_A ITERATION_B

Reads the training weights (``train.<name>`` in the training state, present when the run averages
its weights with ``--ema-decay``; otherwise the model tensors, which are then the same weights).
"""

from __future__ import annotations

import argparse


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("run")
    p.add_argument("a", type=int)
    p.add_argument("b", type=int)
    args = p.parse_args()

    import torch

    from meshseq import checkpoint as ckpt

    torch.set_num_threads(1)

    def weights(iteration: int) -> dict:
        loaded = ckpt.load_folder(ckpt.checkpoint_root(args.run) / f"{iteration:08d}", with_state=True)
        return ckpt.training_weights(loaded.state_tensors) or {n: p.detach() for n, p in loaded.net.named_parameters()}

    wa, wb = weights(args.a), weights(args.b)
    print(f"{args.run}: iterations {args.a} -> {args.b}")
    print("| weights | shape | norm at first | norm of the change | relative | largest entry of the change |")
    print("|---|---|---|---|---|---|")
    for name in sorted(wa):
        x, d = wa[name], wb[name] - wa[name]
        rel = float(d.norm() / x.norm().clamp_min(1e-12))
        print(f"| {name} | {tuple(x.shape)} | {float(x.norm()):.3f} | {float(d.norm()):.3f} | {rel:.3f} | "
              f"{float(d.abs().max()):.4f} |")


if __name__ == "__main__":
    main()
