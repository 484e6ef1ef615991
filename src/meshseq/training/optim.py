"""The optimiser's side of an iteration: Adam's parameter groups, the step's precision, gradient
norms and clipping, the weights' moving average (``ema_decay``), the blow-up test (``rollback``) and
the divergence message."""

from __future__ import annotations

import contextlib
import math

import numpy as np
import torch

from meshseq.model import BDLSTM
from meshseq.training.config import EMA_WARMUP, GRAD_CLIP_WARMUP, TrainConfig, fc_lr_factor


def autocast(device: torch.device, precision: str):
    """The training step's precision: ``bf16`` = autocast to bfloat16 (float32 master weights and
    optimizer; the roll-out's big FC products run in bfloat16, the mesh convolutions stay float32)."""
    return torch.autocast(device.type, dtype=torch.bfloat16, enabled=precision == "bf16")



def fused_adam(device) -> bool:
    """Adam's update as one fused pass per tensor (CPU and CUDA) instead of about eight passes of
    ``foreach`` operators over the parameters and moments (the FC weight's four 39 MB tensors on
    the horse): the same arithmetic, read and written once."""
    return torch.device(device).type in ("cpu", "cuda")



def parameter_groups(model: BDLSTM, config: TrainConfig) -> list[dict]:
    """Adam's parameter groups: ``[{"params", "names"(, "lr")}]``; with ``fc_lr="fan-in"`` and a
    mesh over 1,000 vertices the FC weight gets its own, smaller rate (see ``RECIPES``)."""
    named = list(model.named_parameters())
    factor = fc_lr_factor(model.fc.weight.shape[1], config.fc_lr, config.fc_lr_fan_in)
    if factor == 1.0:
        return [{"params": [p for _, p in named], "names": [n for n, _ in named]}]
    rest = [(n, p) for n, p in named if n != "fc.weight"]
    return [{"params": [p for _, p in rest], "names": [n for n, _ in rest]},
            {"params": [model.fc.weight], "names": ["fc.weight"], "lr": config.lr * factor}]



def grad_norm(parameters) -> torch.Tensor:
    """The 2-norm of all gradients together, a 0-d tensor (no host synchronisation)."""
    grads = [p.grad for p in parameters if p.grad is not None]
    if hasattr(torch.nn.utils, "get_total_norm"):  # torch >= 2.6
        return torch.nn.utils.get_total_norm(grads)
    return torch.linalg.vector_norm(torch.stack([torch.linalg.vector_norm(g) for g in grads]))


def clip_threshold(history, factor: float | None) -> float | None:
    """The norm a gradient is clipped at: ``factor`` times the median of ``history`` (the last
    iterations' unclipped gradient norms), or None (no clipping) without a factor or while fewer
    than ``GRAD_CLIP_WARMUP`` norms are known. The median ignores the outliers it guards against."""
    if factor is None or len(history) < GRAD_CLIP_WARMUP:
        return None
    return float(factor) * float(np.median(np.asarray(history, dtype=np.float64)))


def scale_gradients(parameters, scale: float) -> None:
    """Multiply every gradient of ``parameters`` by ``scale`` in place."""
    grads = [p.grad for p in parameters if p.grad is not None]
    if grads:
        torch._foreach_mul_(grads, scale)


def average_decay(ema_decay: float, iteration: int) -> float:
    """The weight of the old average at ``iteration`` (1-based): ``min(ema_decay, (1 + t) /
    (EMA_WARMUP + t))``, TensorFlow's ``num_updates`` rule: early averages follow the weights
    closely instead of remembering the random initialisation for ~1 / (1 - ema_decay) iterations."""
    return min(float(ema_decay), (1.0 + iteration) / (EMA_WARMUP + iteration))


#: ``rollback``: a loss above ``BLOWUP`` times the median of the last ``LOSS_HISTORY`` iterations'
#: (once ``SNAPSHOT_EVERY`` are known) is a blow-up; training keeps a copy of its state every
#: ``SNAPSHOT_EVERY`` iterations and goes back to the older of the last two, at most
#: ``MAX_ROLLBACKS`` times. Against the median of the 20 metrics rows before (every 10th iteration),
#: default-recipe runs of 2,000 iterations peaked at 2.1x (the body set) and 3.5x (pcow); the
#: multi-part body set recovered from a spike of 9x, then blew up without recovering (a loss of
#: about 100, then 28,840 and millions: 41,821x).
BLOWUP = 100.0
LOSS_HISTORY = 200
SNAPSHOT_EVERY = 100
MAX_ROLLBACKS = 3


def can_go_back(history) -> bool:
    """Whether a run with ``history`` (its last iterations' losses) knows enough iterations
    (``SNAPSHOT_EVERY``) for the blow-up test and to go back to a snapshot."""
    return len(history) >= SNAPSHOT_EVERY


def blown_up(loss: float, history) -> bool:
    """Whether an iteration's ``loss`` is a blow-up: above ``BLOWUP`` times the median of
    ``history`` (the last iterations' losses, blow-ups left out), once ``can_go_back``."""
    if not can_go_back(history):
        return False
    return loss > BLOWUP * float(np.median(np.asarray(history, dtype=np.float64)))


def update_average(average: list[torch.Tensor], parameters: list[torch.Tensor], decay: float) -> None:
    """``average <- decay * average + (1 - decay) * parameters`` in place (lists of like tensors)."""
    with torch.no_grad():
        for a, p in zip(average, parameters):
            a.lerp_(p.detach(), 1.0 - decay)


def copy_weights(parameters: list[torch.Tensor], values: list[torch.Tensor]) -> None:
    """Copy ``values`` into ``parameters`` in place (lists of like tensors; no autograd)."""
    with torch.no_grad():
        for p, v in zip(parameters, values):
            p.copy_(v)


@contextlib.contextmanager
def weights_swapped(parameters: list[torch.Tensor], weights: list[torch.Tensor] | None):
    """Run the body with ``weights`` copied into ``parameters``, then restore them bit for bit
    (``weights`` None: nothing changes)."""
    if weights is None:
        yield
        return
    kept = [p.detach().clone() for p in parameters]
    copy_weights(parameters, weights)
    try:
        yield
    finally:
        copy_weights(parameters, kept)


def divergence(it: int, names: list[str], values: torch.Tensor, lr: float, last_checkpoint: str | None) -> str:
    """The one-line error for a non-finite loss term or gradient norm; ``values`` ``(len(names),)``."""
    bad = [(n, v) for n, v in zip(names, values.tolist()) if not math.isfinite(v)]
    what = f"{bad[0][0]} is {bad[0][1]}" if bad else "another process's loss is not finite"
    kept = f"the last good checkpoint is {last_checkpoint}" if last_checkpoint else "no checkpoint was written"
    return (f"training diverged at iteration {it}: {what}; stopped before updating the weights ({kept}); "
            f"try a smaller lr than {lr:g} (lr = ... in --config FILE.toml)")

