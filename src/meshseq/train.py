"""Training the BD-LSTM: losses, the loop, metrics, checkpoints, resume, distributed data parallel.

The loss of a batch of ground-truth windows ``X`` ``(B, n, V, 9)`` (scaled features), with
``S^f`` the forward chain's frames and ``S^b`` the backward chain's (own order, ``S^b_1 = X_n``)::

    L_rec = mean_windows mean_{i=2..n} ( ||S^f_i - X_i||^2 + ||S^b_i - X_{n+1-i}||^2 )
    L_bd  = mean_windows mean_{i=1..n}   ||S^f_i - S^b_{n+1-i}||^2
    L_KL  = mean_windows mean_steps sum_latent KL(N(mu, sigma^2) || N(0, 1))
    L_2   = sum of squares of every weight matrix (biases excluded; tied weights counted once)
    L     = w_rec L_rec + w_bd L_bd + w_kl L_KL + w_l2 L_2      (paper 1, 0.5, 0.1, 0.1; default L_2 off)

and ``+ w_motion L_motion + w_vertex L_vertex`` (not in the paper, whose recipe has both at 0; the
default recipe: 20 and 1; see ``motion_loss``, ``meshseq.vertex_loss`` and ``RECIPES``).

The recipes (``RECIPES``: ``paper`` and ``default``) and why the default departs from the paper
are documented beside ``RECIPES``.

``||.||^2`` sums over vertices and the 9 channels of one frame (the paper's sums over frames
become means, so the weights do not depend on the window length). ``uni`` has no backward chain:
its L_rec has the forward term only and L_bd = 0.

The loop is a plain loop: sample windows (numpy generator), one batched forward of both chains,
backward, Adam step; log every ``log_every`` iterations (rich progress bar, ``RUN/metrics.csv``,
TensorBoard events in ``RUN/tensorboard`` when the ``tensorboard`` package is installed),
held-out loss every ``eval_every``, a checkpoint every ``checkpoint_every`` and at the end.

Distributed: started by ``torchrun`` (env ``RANK``/``WORLD_SIZE``/``MASTER_ADDR``...), every
process joins a process group (NCCL on CUDA, Gloo on CPU) and trains a
``DistributedDataParallel`` copy; all ranks draw the same global batch of ``batch`` windows and
each takes its ``batch / world_size`` share, so a step sees the same windows as a single process
would. Rank 0 writes metrics and checkpoints, which hold every rank's generator state, so a
resume repeats a multi-process run bit for bit (on CPU).

Divergence: every iteration checks the weighted loss terms, their total and the gradient norm
for NaN/infinity before the update (one host synchronisation; under DDP one all-reduce of the
flag); the first non-finite value stops training with a MeshseqError naming the iteration and the
term, and the last good checkpoint stays the newest.
"""

from __future__ import annotations

import collections
import contextlib
import csv
import gc
import io as _io
import math
import os
import random
import sys
import time
from dataclasses import asdict, dataclass, fields, replace
from pathlib import Path

import numpy as np
import torch
from torch import nn

from meshseq import checkpoint as ckpt
from meshseq.data.windows import (Split, WindowSampler, check_holdout, check_validation, fitted_window,
                                  heldout_rows, split_frames)
from meshseq.errors import MeshseqError
from meshseq.kernels import frame_errors, frame_errors_of_frames, keep_freed_memory
from meshseq.mesh import Topology, topology_hash
from meshseq.model import BDLSTM, ModelConfig, is_finite_number

PRECISIONS = ("float32", "bf16")
METRIC_FIELDS = ("iteration", "seconds", "loss", "rec", "bd", "kl", "l2", "motion", "vertex", "latent_spread",
                 "latent_rms", "latent_sigma", "grad_norm", "clipped", "heldout_rec", "heldout_bd",
                 "validation")


STEP_SCALES = ("none", "data")
#: ``fc_lr``: how the big FC weight (encoder V*9 -> L, tied to the decoder) learns on meshes whose
#: fan-in V * 9 exceeds ``fc_lr_fan_in``, with ``f = min(1, fc_lr_fan_in / (V * 9))``:
#: ``fan-in`` scales its Adam learning rate by f (both of its uses learn slower); ``encoder`` keeps
#: one rate and scales the encoder's share of its gradient by f (``BDLSTM.encoder_grad_scale``: the
#: encoder, whose output moves by up to rate x fan-in per step, is slowed; the decoder, fan-in L,
#: is not); ``none``: one rate, the plain gradient (the paper).
FC_LRS = ("fan-in", "encoder", "none")
#: The FC fan-in at which the recipe study chose lr = 1e-3 (the 1,000-vertex body set): the
#: ``fc_lr_fan_in`` of runs stored before the option.
FC_REFERENCE_FAN_IN = 9000
#: ``kl_scale``: ``vertices`` multiplies w_kl by ``V / KL_REFERENCE_VERTICES`` (see ``kl_weight``);
#: ``none``: w_kl as given (the paper).
KL_SCALES = ("vertices", "none")
#: ``feedback_grad``: ``full`` backpropagates through the generated frames fed back into the
#: encoder (the paper: one computation graph over the roll-out); ``stop`` treats each fed-back frame
#: as a constant input (``BDLSTM.rollout``), so the gradient no longer loops through the mesh
#: features; it still flows through the LSTM state and the residual ``X + dX``.
FEEDBACK_GRADS = ("full", "stop")
#: The mesh size at which the recipe study chose w_kl = 0.1 (the 1,000-vertex body set).
KL_REFERENCE_VERTICES = 1000
#: ``grad_clip``: the gradient's norm is clipped at ``grad_clip`` times the median norm of the last
#: ``GRAD_CLIP_HISTORY`` iterations (unclipped norms), once ``GRAD_CLIP_WARMUP`` are known.
GRAD_CLIP_HISTORY = 100
GRAD_CLIP_WARMUP = 10
#: ``ema_decay``: the averaging weight of iteration t is ``min(ema_decay, (1 + t) / (EMA_WARMUP + t))``,
#: so the first iterations are not averaged with the random initial weights (see ``average_decay``).
EMA_WARMUP = 10
#: ``window_fit``: ``batch`` shortens the window until the training part holds a batch of
#: different windows (``meshseq.data.windows.fitted_window``); ``none`` trains on the window given.
WINDOW_FITS = ("batch", "none")
#: Fields added to TrainConfig after runs were stored without them: the value that reproduces
#: those runs (TrainConfig.from_dict fills it in when a stored config lacks the field).
LEGACY_TRAIN_DEFAULTS = {"fc_lr": "none", "w_motion": 0.0, "kl_scale": "none", "logvar_max": None,
                         "grad_clip": None, "adam_beta2": 0.999, "ema_decay": None,
                         "mu_max": None, "feedback_grad": "full",
                         "fc_lr_fan_in": FC_REFERENCE_FAN_IN, "w_vertex": 0.0, "validation": 0.0,
                         "speed_augment": 1.0, "window_fit": "none"}

def is_positive_integer(x) -> bool:
    """An int (numpy integers too) >= 1, not a bool and not a float: what a count option may hold."""
    return isinstance(x, (int, np.integer)) and not isinstance(x, bool) and x >= 1


@dataclass
class TrainConfig:
    """Training options; stored in every checkpoint's JSON."""

    iterations: int = 7000
    window: int = 32
    window_fit: str = "batch"  # the default recipe (RECIPES): shorten the window to a batch of starts; paper "none"
    batch: int = 8
    stride: int = 1
    seed: int = 0
    lr: float = 1e-3
    adam_beta2: float = 0.999  # Adam's second-moment decay (the paper: TensorFlow's default, 0.999)
    w_rec: float = 1.0
    w_bd: float = 0.5
    w_kl: float = 0.1
    w_l2: float = 0.0  # the default recipe (RECIPES, below); the paper: 0.1
    w_motion: float = 20.0  # the default recipe (RECIPES); the paper has no such term (0)
    w_vertex: float = 1.0  # L_vertex (meshseq.vertex_loss): the default recipe (RECIPES); the paper: 0
    vertex_frames: int = 4  # frames of each chain that L_vertex reconstructs (meshseq.vertex_loss)
    holdout: float = 0.2
    holdout_at: str = "end"
    validation: float = 0.0  # training frames kept out to choose the best checkpoint on (split_frames); off in both recipes
    speed_augment: float = 1.0  # windows played at speeds in [1/R, R] (WindowSampler.sample_at_speeds); 1 = off
    scaling: str = "two-group"
    consistency: str = "temporal"
    given: int = 1
    step_scale: str = "none"
    input_norm: bool = True  # the default recipe (RECIPES); the paper: False
    fc_lr: str = "encoder"  # the default recipe (RECIPES); the paper: "none"
    fc_lr_fan_in: int = FC_REFERENCE_FAN_IN  # the fan-in from which fc_lr acts (FC_LRS)
    kl_scale: str = "vertices"  # the default recipe (RECIPES); the paper: "none"
    logvar_max: float | None = 0.0  # the default recipe (RECIPES); the paper: None (unbounded)
    mu_max: float | None = None  # off in both recipes (measured on horse-gallop: see RECIPES)
    grad_clip: float | None = None  # off in both recipes (measured on horse-gallop: see RECIPES)
    ema_decay: float | None = 0.99  # the default recipe (RECIPES): checkpoints deliver a moving average; paper: None
    feedback_grad: str = "full"  # both recipes (the paper); "stop": see FEEDBACK_GRADS
    sample: bool = True
    eval_every: int = 100
    checkpoint_every: int = 500
    log_every: int = 10
    keep: int = 2
    precision: str = "float32"

    def __post_init__(self):
        for name in ("iterations", "window", "batch", "stride"):
            if int(getattr(self, name)) < 1:
                raise MeshseqError(f"--{name} {getattr(self, name)}: expected a positive integer")
        if int(self.window) < 2:
            raise MeshseqError(f"--window {self.window}: a window needs at least 2 frames")
        check_holdout(self.holdout, self.holdout_at)
        check_validation(self.validation)
        for name in ("eval_every", "checkpoint_every", "log_every"):
            if int(getattr(self, name)) < 0:
                raise MeshseqError(f"--{name.replace('_', '-')} {getattr(self, name)}: expected >= 0")
        for name in ("w_rec", "w_bd", "w_kl", "w_l2", "w_motion", "w_vertex"):
            if not float(getattr(self, name)) >= 0:
                raise MeshseqError(f"loss weight {name}={getattr(self, name)} must be >= 0")
        if not is_positive_integer(self.vertex_frames):
            raise MeshseqError(f"--vertex-frames {self.vertex_frames!r}: expected a positive integer")
        if self.window_fit not in WINDOW_FITS:
            raise MeshseqError(f"--window-fit {self.window_fit!r}: expected one of {', '.join(WINDOW_FITS)}")
        if not (is_finite_number(self.speed_augment) and self.speed_augment >= 1):
            raise MeshseqError(f"--speed-augment {self.speed_augment!r}: expected a number >= 1 (1 = off)")
        if not float(self.lr) > 0:
            raise MeshseqError(f"--lr {self.lr}: expected a positive number")
        if not (is_finite_number(self.adam_beta2) and 0 <= self.adam_beta2 < 1):
            raise MeshseqError(f"--adam-beta2 {self.adam_beta2!r}: expected a number in [0, 1)")
        if not 1 <= int(self.given) < int(self.window):
            raise MeshseqError(f"--given {self.given}: expected 1 <= given < --window ({self.window})")
        if self.step_scale not in STEP_SCALES:
            raise MeshseqError(f"--step-scale {self.step_scale!r}: expected one of {', '.join(STEP_SCALES)}")
        if self.fc_lr not in FC_LRS:
            raise MeshseqError(f"--fc-lr {self.fc_lr!r}: expected one of {', '.join(FC_LRS)}")
        if not is_positive_integer(self.fc_lr_fan_in):
            raise MeshseqError(f"--fc-lr-fan-in {self.fc_lr_fan_in!r}: expected a positive integer")
        if self.logvar_max is not None and not is_finite_number(self.logvar_max):
            raise MeshseqError(f"--logvar-max {self.logvar_max!r}: expected a number")
        if self.mu_max is not None and not (is_finite_number(self.mu_max) and self.mu_max > 0):
            raise MeshseqError(f"--mu-max {self.mu_max!r}: expected a positive number or none")
        if self.grad_clip is not None and not (is_finite_number(self.grad_clip) and self.grad_clip > 0):
            raise MeshseqError(f"--grad-clip {self.grad_clip!r}: expected a positive number or none")
        if self.ema_decay is not None and not (is_finite_number(self.ema_decay) and 0 < self.ema_decay < 1):
            raise MeshseqError(f"--ema-decay {self.ema_decay!r}: expected a number in (0, 1) or none")
        if self.feedback_grad not in FEEDBACK_GRADS:
            raise MeshseqError(f"--feedback-grad {self.feedback_grad!r}: expected one of {', '.join(FEEDBACK_GRADS)}")
        if self.kl_scale not in KL_SCALES:
            raise MeshseqError(f"--kl-scale {self.kl_scale!r}: expected one of {', '.join(KL_SCALES)}")
        if self.precision not in PRECISIONS:
            raise MeshseqError(f"--precision {self.precision!r}: expected one of {', '.join(PRECISIONS)}")

    def to_dict(self) -> dict:
        return asdict(self)

    @staticmethod
    def from_dict(d: dict) -> "TrainConfig":
        known = {f.name for f in fields(TrainConfig)}
        return TrainConfig(**(LEGACY_TRAIN_DEFAULTS | {k: v for k, v in d.items() if k in known}))


#: Named training recipes: values of the TrainConfig options in ``RECIPE_OPTIONS``.
#:
#: ``paper``: the paper's recipe read literally (method.md 3): L_rec + 0.5 L_bd + 0.1 (L_KL + L_2),
#: L_2 the sum of squared weights, chains free-running from one frame, the encoder fed the scaled
#: features as they are.
#:
#: ``default`` (TrainConfig's defaults) departs from it in the ways below, each measured by controlled runs (same seed, data and
#: budget; ``benchmarks/recipe_study.py``, docs/results.md "Why the model froze"): on 16 body
#: sequences (1,000 vertices, 8 x 32 frames, 600 iterations), validation error at horizon 15
#: after 1 given frame (x 1e-4; zero velocity 1030):
#:
#: * ``w_l2 = 0`` (paper 0.1). With 9.2 million FC weights tied between encoder and decoder, 0.1
#:   times their sum of squares outweighs L_rec (900 against 10 at the start) and Adam shrinks
#:   the FC toward zero: the latent's spread over frames falls to 4e-6, KL to 0.005 nats, and the
#:   roll-out freezes (paper recipe: 1052, worse than zero velocity). Without L_2: 834.
#: * ``input_norm = True`` (paper: no normalisation). The scaled features of two frames differ by
#:   a few hundredths (the [-0.95, 0.95] range is spent on the accumulated angles), so the
#:   encoder's output hardly depends on the frame (latent spread 0.006 against the sampling
#:   noise's 1) and the LSTM learns from noise. Centring every vertex-channel on the mean
#:   training frame and dividing by the spread around it (encoder input only; the output is
#:   still the change in the scaled space) gives a latent spread of 0.19 and 442 (0.43 x zero
#:   velocity), with KL alive at 2.5 nats.
#: * ``fc_lr = "fan-in"`` (paper: one learning rate). Adam moves every weight by about lr per
#:   step, so one step moves the FC's output (the latent, before its VAE head) by up to lr times
#:   the fan-in V * 9: 9 on the body set, 76 on horse-gallop (8,431 vertices), where training
#:   blew up at iteration 9 (KL 1e5, then an infinite gradient norm) with lr 1e-3, and was still
#:   unstable with lr 3.6e-4 for every weight. Scaling the FC weight's rate alone by
#:   ``min(1, 9000 / (V * 9))`` (the fan-in where lr = 1e-3 was chosen) trains horse stably
#:   (L_rec 714 -> 470 in 40 iterations) and leaves meshes up to 1,000 vertices unchanged.
#:   Since 2026-12-02 the default is ``fc_lr = "encoder"``: the same factor on the encoder's share
#:   of the FC weight's gradient only, one rate for the weight. The weight is tied, and ``fan-in``
#:   slowed its decoder use (fan-in L = 128) as much as its encoder use; on horse-gallop
#:   (seed 0, 300 iterations, window 29) the one training window's L_rec fell to 0.22 of zero
#:   velocity's against 0.44 with ``fan-in``, with no loss spike in 310 iterations (``fan-in``: 2),
#:   and from the window's first frame the prediction error at h10 was 0.42 x the best baseline
#:   against 0.84. On crane's validation blocks (400 iterations, one seed) it was within the
#:   run-to-run spread: h15 after 1 / 3 given frames 3505 / 3618 against 3372 / 3378, rigid 2050
#:   against 2133, free-running validation L_rec 4920 against 5458. Identical at <= 1,000 vertices.
#:   A 10 x smaller FC rate (``fc_lr_fan_in = 900``) cost the body set 40% (validation h15 690
#:   against 489 after 1 given frame) and did not stop horse's spikes.
#:
#: * ``w_motion = 10`` (paper: no such term). Roll-outs trained by squared error alone slow down
#:   after a few steps: the mean of the futures a model cannot tell apart (direction and phase of
#:   a periodic motion) moves less than any one of them. Measured on the validation blocks, the
#:   free roll-outs move at 20% of the truth's feature change (Fig. 3) and, on the training
#:   windows themselves, at 24% of the truth's frame-to-frame speed, so it is the objective, not
#:   generalisation. ``motion_loss`` (the size of each generated change against the truth's,
#:   blind to its direction) with weight 10: motion 95% and 92% of the truth's (two seeds), error
#:   at h15 after 1 given frame 495 and 490 (default without it: 425 and 489; zero velocity
#:   1030), after 3 given frames 534 and 499 (413 and 467). Weight 1 changed nothing (motion 21%).
#:   Since 2026-12-02 the default is 20, with the vertex term below (the same rule: the smallest
#:   weight that keeps the motion level within 30% on both seeds; 10 gave 0.65 on seed 0).
#: * ``w_vertex = 1`` (paper: no such term; ``meshseq.vertex_loss``). The feature loss weighs
#:   every vertex and channel alike, the vertex error does not: on horse-gallop a 4 x better
#:   feature fit gave no better vertex error. L_vertex reconstructs 4 frames of each chain to
#:   vertices (the evaluation's linear solve, differentiable) and compares them with the truth's,
#:   in units where standing still costs as much as in L_rec. Body-set validation blocks, h15 at
#:   600 iterations (u1 / u3 / u3 rigid), seed 0: 396 / 407 / 388 against 470 / 480 / 437, motion
#:   0.84 (default 1.03); seed 1: 489 / 483 / 456 against 470 / 513 / 450, motion 0.72 (0.97).
#:   horse-gallop, 300 iterations, ours over the best baseline from the untrained starts of its
#:   training frames (u1 h10 / h15, u3 h10 / h15): 1.15 / 0.76 / 1.17 / 0.67 against 1.31 / 0.95 /
#:   1.47 / 1.05 (with w_motion 10: 0.94 / 0.70 / 1.03 / 0.57). crane validation blocks, 400
#:   iterations: 3509 / 3663 / 2106 against 3505 / 3618 / 2050, motion 0.69 against 0.63 (with
#:   w_motion 10: 3300 / 3385 / 2046). Cost: +13% per iteration on the body set, ~+15% on horse.
#:
#: Two guards for meshes larger than the body set, where the four choices above ran away on
#: horse-gallop (8,431 vertices: iteration 822 in one run, a KL of 5,388 nats at iteration 160 in
#: another; docs/recipe_study.md "Large meshes: the latent runs away"). ``kl_scale`` is exactly
#: w_kl on the 1,000-vertex body set; ``logvar_max`` acts there too (some dimensions ask for more
#: noise than the prior's) and was no worse on its validation blocks (h15 after 1 given frame 447
#: against 487 without it, 600 iterations, one seed). With both, horse-gallop trained 1000
#: iterations without running away, but with one loss spike (L_rec 150 -> 4,985 at 750, back by
#: 1000): not solved by these guards.
#:
#: * ``kl_scale = "vertices"`` (paper: one w_kl). L_rec sums over V x 9 values, L_KL over the
#:   latent, so with one w_kl the KL's pull per unit of reconstruction error falls as 1 / V. On
#:   horse-gallop with one w_kl the latent mean grew to an RMS of 5.9 (KL 2,300 nats at iteration
#:   160, with the noise bounded); with w_kl x V / 1000 it stayed below 1.5 (KL <= 170 nats) over
#:   the same 240 iterations.
#: * ``logvar_max = 0`` (paper: unbounded). The motion term rewards roll-outs that move, and a
#:   noisier z moves them: on horse-gallop a few latent dimensions' noise ran away (mean spread
#:   1.02 -> 1.98, KL 250 -> 5,388 nats, L_rec 337 -> 2,005 between iterations 150 and 170), as
#:   in the no-kl ablation on the body set. The noise is bounded at the prior's (sigma <= 1).
#:
#: Measured and left out: ``step_scale = "data"`` (decoder output in units of the RMS frame
#: change) learns slower (held-out L_rec 6.5 against 4.3 at 600 iterations); a deterministic
#: latent (no noise, no KL) changed little without the normalisation (864 against 834).
#: Against horse-gallop's loss spikes (L_rec 150 -> 4,985 at iteration 750 with the default
#: recipe; docs/recipe_study.md "Loss spikes on horse-gallop"), each one run of seed 0:
#: ``grad_clip = 3`` (clipped 15% of the iterations, L_rec still rose 500 -> 917 while 7 of 10
#: were clipped: under Adam a clipped gradient leaves the step about as large), ``lr = 5e-4``
#: (slower, L_rec 530 against 328 at 400, and a spike to 1,408), ``adam_beta2 = 0.99`` (mildest:
#: worst 984; spikes remain; on the body set 20% worse at 600 iterations). None removes them;
#: all three stay options, off in both recipes. Without the motion term (``w_motion = 0``) the
#: horse trained smoothly after one early spike (median gradient norm 14 x smaller): the motion
#: term, which rewards roll-outs that move, is what drives the spikes. ``mu_max = 3`` (the latent
#: mean squashed into the prior's range; one run of seed 0 to 230): the latent still jumped (spread
#: 0.28 -> 1.13) and L_rec spiked to 1,023: off in both recipes.
#:
#: * ``ema_decay = 0.99`` (paper: the last weights). Checkpoints deliver the moving average of the
#:   weights (training itself is unchanged; the training weights travel in the training state).
#:   Body-set validation blocks, h15 after 1 / 3 given frames at 600 iterations: seed 0 452 / 437
#:   against 447 / 460, seed 1 452 / 468 against 509 / 534; better in 7 of 8 checkpoints (150-600,
#:   two seeds), worse only at 150 of seed 1 (warm-up); motion 0.75-0.95 of the truth's. It does not
#:   remove horse-gallop's spikes: at their peak the average is 2-10 x better, during recovery it
#:   lags (docs/recipe_study.md "A moving average of the weights").
#:
#: * ``window_fit = "batch"`` (paper: the window as given; its data sets are long). A window is
#:   shortened until the training part holds at least a batch of different windows
#:   (``meshseq.data.windows.fitted_window``; never below 16 frames while that fits); it changes
#:   only short sequences: of this repository's sets only horse-gallop, whose 29 training frames
#:   hold one window of 32 (paper.py trained it on that one window of 29) and 8 of 22. Rule and
#:   threshold written before the run (docs/recipe_study.md "How much data a sequence set needs"):
#:   horse-gallop at 1000 iterations, mean of the 8 prediction ratios (ours over the best
#:   baseline, h10/h15, u1/u3, raw and rigid) 1.46 with one window, **0.30** with 8 (0.19-0.36,
#:   all 8 below 1; u1 h10 0.32 against 1.30-2.05), completion gap 10 0.83 -> 0.51, motion level
#:   0.56 -> 0.86 of the truth's. The same pattern on body data: one jumping-jacks cycle trained
#:   from 1 start 0.462, from 9 starts 0.136.
RECIPE_OPTIONS = ("w_rec", "w_bd", "w_kl", "w_l2", "w_motion", "w_vertex", "given", "step_scale", "input_norm", "fc_lr",
                  "fc_lr_fan_in", "kl_scale", "logvar_max", "mu_max", "grad_clip", "ema_decay", "feedback_grad",
                  "window_fit")
RECIPES = {
    "paper": {"w_rec": 1.0, "w_bd": 0.5, "w_kl": 0.1, "w_l2": 0.1, "w_motion": 0.0, "w_vertex": 0.0, "given": 1,
              "step_scale": "none", "input_norm": False, "fc_lr": "none", "fc_lr_fan_in": FC_REFERENCE_FAN_IN,
              "kl_scale": "none", "logvar_max": None, "grad_clip": None, "ema_decay": None, "mu_max": None,
              "feedback_grad": "full", "window_fit": "none"},
    "default": {name: TrainConfig.__dataclass_fields__[name].default for name in RECIPE_OPTIONS},
}


# --------------------------------------------------------------------------------------------
# losses


def kl_divergence(mu: torch.Tensor, logvar: torch.Tensor) -> torch.Tensor:
    """KL(N(mu, exp(logvar)) || N(0, I)) summed over the last axis, averaged over the rest."""
    return (-0.5 * (1.0 + logvar - mu.square() - logvar.exp())).sum(-1).mean()


def kl_weight(w_kl: float, n_vertices: int, kl_scale: str) -> float:
    """The weight on L_KL: ``w_kl``, times ``n_vertices / KL_REFERENCE_VERTICES`` with
    ``kl_scale="vertices"``.

    L_rec, L_bd and L_motion are sums over the V x 9 feature values of a frame, L_KL a sum over
    the latent: with one w_kl, the KL's pull per unit of reconstruction falls as 1 / V, so a mesh
    8.4 times the body set's (horse-gallop) trains a nearly unregularised latent. Scaling w_kl
    with V keeps the ratio the body set was tuned at (exactly w_kl there).
    """
    return float(w_kl) * (n_vertices / KL_REFERENCE_VERTICES if kl_scale == "vertices" else 1.0)


class _SquaredNorm(torch.autograd.Function):
    """``sum(p^2)`` as one pass: the dot product of each row with itself (one batched matmul),
    the rows' sums added; backward ``2 g p``, the same values as autograd's ``p.square().sum()``
    (which wrote and read the square: 10.6 against 4.0 ms forward + backward for the horse's
    39 MB FC weight). Row by row, the sum keeps ``square().sum()``'s accuracy (a single dot of
    all 9.7 million values was off by 8e-5 relative; rows: 4e-7)."""

    @staticmethod
    @torch.autocast("cpu", enabled=False)
    @torch.autocast("cuda", enabled=False)
    def forward(ctx, p):  # float32 under --precision bf16 too (a sum of 9.7 million squares)
        ctx.save_for_backward(p)
        rows = p.reshape(p.shape[0] if p.dim() else 1, 1, -1)
        return torch.bmm(rows, rows.transpose(1, 2)).sum()

    @staticmethod
    def backward(ctx, g):
        (p,) = ctx.saved_tensors
        return p * (2 * g)


def squared_norm(p: torch.Tensor) -> torch.Tensor:
    """``p.square().sum()`` (L_2's term for one weight) in one pass; see ``_SquaredNorm``."""
    return _SquaredNorm.apply(p)


def has_backward_chains(out: dict) -> bool:
    """Whether ``BDLSTM.forward``'s output (or a dict like it) has backward chains, without making
    a ``RolloutOutput`` stack its frames to say so."""
    return out.get("backward", True) is not None  # a RolloutOutput with backward chains has no key yet


def output_frame_errors(out: dict, windows: torch.Tensor, steps: bool = False) -> torch.Tensor:
    """``kernels.frame_errors`` of ``BDLSTM.forward``'s output: from its vertex-major ``frames`` when
    it has them (no stacked copy), otherwise from its stacked chains."""
    if "frames" in out:
        return frame_errors_of_frames(out["frames"], windows, steps=steps)
    chains = out["forward"] if out["backward"] is None else torch.cat([out["forward"], out["backward"]])
    return frame_errors(chains, windows, steps=steps)


def window_losses(out: dict, windows: torch.Tensor, errors: torch.Tensor | None = None) -> dict:
    """Loss terms (unweighted) of ``BDLSTM.forward``'s output for ground truth ``(B, n, V, C)``.

    ``errors``: ``output_frame_errors`` of the output, when already computed."""
    # (3 or 6, B, n): rec forward, rec backward, bd per frame (then the step sizes)
    e = output_frame_errors(out, windows) if errors is None else errors
    rec = e[0, :, 1:].mean()  # the first frames are the given ones
    if has_backward_chains(out):
        rec = rec + e[1, :, 1:].mean()
        bd = e[2].mean()
    else:
        bd = e.new_zeros(())
    kl = kl_divergence(out["mu"], out["logvar"]) if out["mu"].numel() else e.new_zeros(())
    return {"rec": rec, "bd": bd, "kl": kl, **latent_health(out["mu"], out["logvar"])}


def motion_loss(out: dict, windows: torch.Tensor, errors: torch.Tensor | None = None) -> torch.Tensor:
    """L_motion: how far each generated frame-to-frame change is from the truth's in size,
    ``mean_windows mean_{i=2..n} (||S_i - S_{i-1}|| - ||X_i - X_{i-1}||)^2`` over both chains.

    Blind to the direction of the change, so it penalises a roll-out that slows down (the
    squared-error optimum under phase uncertainty) without asking for the right phase.
    ``errors``: ``output_frame_errors(..., steps=True)`` of the output, when already computed.
    """
    e = output_frame_errors(out, windows, steps=True) if errors is None else errors
    true_speed = e[5, :, 1:].sqrt()  # (B, n - 1); the backward chain's truth runs in reverse: flip
    loss = (e[3, :, 1:].add(1e-12).sqrt() - true_speed).square().mean()
    if has_backward_chains(out):
        loss = loss + (e[4, :, 1:].add(1e-12).sqrt() - true_speed.flip(1)).square().mean()
    return loss


def latent_health(mu: torch.Tensor, logvar: torch.Tensor) -> dict:
    """Detached diagnostics of the VAE head's output ``mu``, ``logvar`` ``(..., L)``: which part of
    the KL moves. ``latent_spread`` (see below), ``latent_rms`` the root mean square of ``mu``,
    ``latent_sigma`` the mean posterior standard deviation ``exp(logvar / 2)`` (the prior's: 1).
    """
    if not mu.numel():
        return {"latent_spread": mu.new_zeros(())}
    return {"latent_spread": latent_spread(mu), "latent_rms": mu.detach().square().mean().sqrt(),
            "latent_sigma": logvar.detach().mul(0.5).exp().mean()}


def latent_spread(mu: torch.Tensor) -> torch.Tensor:
    """How much the latent mean varies with the frame: the standard deviation of ``mu``
    ``(..., L)`` over all frames and chains, averaged over the latent dimensions (detached).

    Near 0 (next to the prior's 1), z carries nothing about the frame: the latent has collapsed.
    """
    m = mu.detach().reshape(-1, mu.shape[-1])
    return m.std(0).mean() if m.shape[0] > 1 else m.new_zeros(())


class WindowLoss(nn.Module):
    """The whole training objective as one module (what DistributedDataParallel wraps).

    ``forward(windows (B, n, V, C))`` -> ``(total, terms)``: one roll-out of both chains and the
    weighted loss; terms are detached scalars for logging.
    """

    def __init__(self, model: BDLSTM, config: TrainConfig, vertex_loss: nn.Module | None = None):
        super().__init__()
        self.model = model
        self.weights = {"rec": config.w_rec, "bd": config.w_bd, "l2": config.w_l2, "motion": config.w_motion,
                        "kl": kl_weight(config.w_kl, model.config.n_vertices, config.kl_scale),
                        "vertex": config.w_vertex}
        if config.w_vertex > 0 and vertex_loss is None:
            raise ValueError("w_vertex > 0 needs a VertexLoss (meshseq.vertex_loss)")
        self.vertex_loss = vertex_loss if config.w_vertex > 0 else None
        self.feedback_grad = config.feedback_grad == "full"
        # how the tied FC weight's gradient is formed in this objective's roll-outs (fc_lr "encoder")
        model.encoder_grad_scale = encoder_grad_scale(model.fc.weight.shape[1], config)

    def forward(self, windows: torch.Tensor, sample: bool = True, given: int = 1, rows: torch.Tensor | None = None):
        """``rows`` ``(B, n)``: the stacked training frames the windows are (L_vertex then reads the
        truth's vertices from its cache, ``VertexLoss.cache_targets``), or None."""
        out = self.model(windows, sample=sample, given=given, feedback_grad=self.feedback_grad)
        motion = self.weights["motion"] > 0
        errors = output_frame_errors(out, windows, steps=motion)  # one pass for all these terms
        terms = window_losses(out, windows, errors)
        if motion:
            terms["motion"] = motion_loss(out, windows, errors)
        if self.vertex_loss is not None:
            # only the picked frames of the chains, stacked: (B or 2B, k, V, C)
            picked = out.frames_at(self.vertex_loss.picks(windows.shape[1]))
            B = windows.shape[0]
            terms["vertex"] = self.vertex_loss.of_picked(picked[:B], windows, rows)
            if has_backward_chains(out):
                back_rows = None if rows is None else rows.flip(1)
                terms["vertex"] = terms["vertex"] + self.vertex_loss.of_picked(picked[B:], windows.flip(1), back_rows)
        terms["l2"] = sum(squared_norm(p) for p in self.model.weight_parameters())
        total = sum(self.weights[k] * v for k, v in terms.items() if self.weights.get(k, 0) != 0)
        return total, {k: v.detach() for k, v in terms.items()}


# --------------------------------------------------------------------------------------------
# data


@dataclass
class TrainingData:
    """Raw ACAP features of one or more data sets sharing one connectivity.

    ``features[d]`` ``(T_d, V, 9)`` float64; ``reference`` ``(V, 3)`` the mesh the features
    refer to (first frame of the first data set); ``faces`` ``(F, 3)`` int64.
    """

    names: list[str]
    sources: list[str]
    features: list[np.ndarray]
    faces: np.ndarray
    reference: np.ndarray
    consistency: str = "temporal"  # the rotation consistency the features were extracted with

    @property
    def n_vertices(self) -> int:
        return int(self.reference.shape[0])


def load_training_data(specs: list[str], consistency: str = "temporal") -> TrainingData:
    """Load sequences (``meshseq.io.load_sequence``) and extract features against one reference.

    MeshseqError if the data sets do not share one connectivity.
    """
    from meshseq import acap
    from meshseq.io import load_sequence

    if not specs:
        raise MeshseqError("no training data given")
    seqs = [load_sequence(s) for s in specs]
    first = seqs[0]
    for spec, s in zip(specs[1:], seqs[1:]):
        if s.n_vertices != first.n_vertices or s.faces.shape != first.faces.shape or not np.array_equal(
            s.faces, first.faces
        ):
            raise MeshseqError(
                f"{spec}: connectivity differs from {specs[0]} ({s.n_vertices} vertices, {s.n_faces} faces "
                f"vs {first.n_vertices} vertices, {first.n_faces} faces); data sets trained together "
                "must share one mesh connectivity"
            )
    reference = first.vertices[0].copy()
    feats = [acap.extract(s.vertices, s.faces, reference=reference, consistency=consistency) for s in seqs]
    return TrainingData([s.name for s in seqs], [str(sp) for sp in specs], feats, first.faces, reference, consistency)


def step_spread(scaled: list[np.ndarray], splits: list[Split], stride: int = 1) -> np.ndarray:
    """Root mean square per channel ``(C,)`` of the frame-to-frame changes ``X_{t+stride} - X_t`` of
    scaled features ``[(T_d, V, C)]`` inside the training segments (the ``data`` step scale).

    Channels that never change get the mean of the others (or 1), so every factor is positive.
    """
    sums, count = 0.0, 0
    for x, split in zip(scaled, splits):
        for a, b in split.train:
            seg = np.asarray(x[a:b], dtype=np.float64)
            if len(seg) > stride:
                d = seg[stride:] - seg[:-stride]
                sums = sums + np.square(d).sum(axis=(0, 1))
                count += d.shape[0] * d.shape[1]
    if count == 0:
        raise MeshseqError(f"--step-scale data: no training segment is longer than --stride {stride}")
    rms = np.sqrt(np.asarray(sums) / count)
    good = rms > 1e-8
    return np.where(good, rms, rms[good].mean() if good.any() else 1.0)


def autocast(device: torch.device, precision: str):
    """The training step's precision: ``bf16`` = autocast to bfloat16 (float32 master weights and
    optimizer; the roll-out's big FC products run in bfloat16, the mesh convolutions stay float32)."""
    return torch.autocast(device.type, dtype=torch.bfloat16, enabled=precision == "bf16")


def freeze_setup_objects() -> bool:
    """Exempt the objects that exist before the first iteration (imported libraries, the model, the
    data: about 300,000) from the cyclic garbage collector's later passes, which otherwise walk all
    of them at every full collection (measured on the horse: 1.12 -> 1.09 s an iteration, A/B in
    one process); objects made later are collected as usual. Undone by ``gc.unfreeze()``. False
    (nothing done) when the collector is off."""
    if not gc.isenabled():
        return False
    gc.collect()
    gc.freeze()
    return True


def fused_adam(device) -> bool:
    """Adam's update as one fused pass per tensor (CPU and CUDA) instead of about eight passes of
    ``foreach`` operators over the parameters and moments (the FC weight's four 39 MB tensors on
    the horse): the same arithmetic, read and written once."""
    return torch.device(device).type in ("cpu", "cuda")


def resolve_device(device: str) -> torch.device:
    if device == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if device.startswith("cuda") and not torch.cuda.is_available():
        raise MeshseqError(f"--device {device}: CUDA is not available here (torch {torch.__version__})")
    try:
        return torch.device(device)
    except RuntimeError:
        raise MeshseqError(f"--device {device!r}: expected auto, cpu, cuda or cuda:N") from None


# --------------------------------------------------------------------------------------------
# distributed


@dataclass
class Dist:
    rank: int = 0
    world: int = 1
    local_rank: int = 0
    started_here: bool = False

    @property
    def active(self) -> bool:
        return self.world > 1


def init_distributed(device: torch.device) -> Dist:
    """Join the process group torchrun describes (env RANK, WORLD_SIZE); a no-op otherwise."""
    import torch.distributed as dist

    if "RANK" not in os.environ or "WORLD_SIZE" not in os.environ:
        return Dist()
    world = int(os.environ["WORLD_SIZE"])
    rank = int(os.environ["RANK"])
    local = int(os.environ.get("LOCAL_RANK", rank))
    if world <= 1:
        return Dist(rank, world, local)
    started = False
    if not dist.is_initialized():
        dist.init_process_group(backend="nccl" if device.type == "cuda" else "gloo")
        started = True
    return Dist(rank, world, local, started)


# --------------------------------------------------------------------------------------------
# metrics


class Metrics:
    """``RUN/metrics.csv`` (always) and TensorBoard events (if the package is installed)."""

    def __init__(self, run_dir: Path, start_iteration: int, log=None):
        self.path = run_dir / "metrics.csv"
        kept = []
        if start_iteration > 0 and self.path.is_file():
            # keep the rows up to the checkpoint; rows after it (and a torn last line) are redone
            with open(self.path, newline="") as fh:
                for row in csv.DictReader(fh):
                    try:
                        if int(row["iteration"]) <= start_iteration and None not in row.values():
                            kept.append(row)
                    except (TypeError, ValueError, KeyError):
                        pass
        text = _io.StringIO()
        w = csv.DictWriter(text, METRIC_FIELDS, lineterminator="\n")
        w.writeheader()
        w.writerows({k: r.get(k, "") for k in METRIC_FIELDS} for r in kept)
        tmp = self.path.with_name(".tmp-metrics.csv")
        tmp.write_text(text.getvalue())
        os.replace(tmp, self.path)
        self.fh = open(self.path, "a", newline="")
        self.writer = csv.DictWriter(self.fh, METRIC_FIELDS, lineterminator="\n")
        self.tb = None
        try:
            from torch.utils.tensorboard import SummaryWriter
        except ImportError:
            if log:
                log(f"tensorboard is not installed: metrics go to {self.path} only "
                    "(pip install 'meshseq[train]' for TensorBoard events)")
        else:
            self.tb = SummaryWriter(log_dir=str(run_dir / "tensorboard"), purge_step=start_iteration + 1)

    def write(self, row: dict) -> None:
        self.writer.writerow({k: ("" if row.get(k) is None else row.get(k)) for k in METRIC_FIELDS})
        self.fh.flush()
        if self.tb is not None:
            for k, v in row.items():
                if k not in ("iteration", "seconds") and v is not None and v != "":
                    self.tb.add_scalar(k.replace("heldout_", "heldout/"), float(v), row["iteration"])

    def close(self) -> None:
        self.fh.close()
        if self.tb is not None:
            self.tb.close()


# --------------------------------------------------------------------------------------------
# the loop


def _prepare_run_dir(run_dir: Path, resume: bool, force: bool) -> None:
    if run_dir.exists() and not run_dir.is_dir():
        raise MeshseqError(f"--out {run_dir}: exists and is not a folder")
    if run_dir.is_dir() and any(run_dir.iterdir()) and not resume:
        if not force:
            raise MeshseqError(f"--out {run_dir}: already exists and is not empty (use --resume to continue it "
                               "or --force to start over)")
        remove_run_outputs(run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)


def remove_run_outputs(run_dir: Path) -> None:
    """What ``--force`` deletes: the files training writes in ``run_dir`` (checkpoint folders,
    metrics.csv, TensorBoard event files), nothing else; folders left empty are removed."""
    import shutil

    root = ckpt.checkpoint_root(run_dir)
    if root.is_dir():
        for p in root.iterdir():
            if p.is_dir() and (ckpt.is_checkpoint_name(p.name) or p.name == ckpt.BEST
                               or p.name.startswith((".tmp-", ".old-"))):
                shutil.rmtree(p)
    for name in ("metrics.csv", ".tmp-metrics.csv"):
        (run_dir / name).unlink(missing_ok=True)
    for events in (run_dir / "tensorboard").glob("events.out.tfevents.*"):
        events.unlink()
    for folder in (root, run_dir / "tensorboard"):
        if folder.is_dir() and not any(folder.iterdir()):
            folder.rmdir()


def resume_point(run_dir: Path) -> "ckpt.Loaded":
    """The checkpoint ``--resume`` continues from; MeshseqError (never a fresh start) if none is usable."""
    try:
        return ckpt.load_latest(run_dir, with_state=True)
    except MeshseqError as err:
        hint = ("leave out --resume to start a new run" if not ckpt.list_checkpoints(run_dir)
                else "use --force without --resume to start over")
        raise MeshseqError(f"--resume: {err}; {hint}") from None


def fc_lr_factor(fan_in: int, fc_lr: str, reference: int = FC_REFERENCE_FAN_IN) -> float:
    """The factor on the FC weight's learning rate: ``min(1, reference / fan_in)`` with
    ``fc_lr = "fan-in"``, else 1."""
    return min(1.0, reference / fan_in) if fc_lr == "fan-in" else 1.0


def reconstructed_vertices(data: TrainingData) -> tuple[object, list[np.ndarray]]:
    """``(Reconstructor of the training reference, [(T_d, V, 3)] centred vertices of every frame)``:
    the truth as the features reconstruct it (no reconstruction error in what is compared)."""
    from meshseq.acap import Reconstructor

    rec = Reconstructor(data.reference, data.faces)
    return rec, [rec.solve(f) for f in data.features]  # centred (align.place)


def make_vertex_loss(data: TrainingData, scaled: list[np.ndarray], splits: list[Split], scaling,
                     config: TrainConfig, device: torch.device, truth=None):
    """The ``VertexLoss`` of a run (None when ``w_vertex`` is 0): the training reference's torch
    reconstruction and the unit calibrated on the training frames (``meshseq.vertex_loss``).
    ``truth``: ``reconstructed_vertices(data)`` if already computed."""
    if config.w_vertex <= 0:
        return None
    from meshseq.acap.torch_reconstruct import TorchReconstructor
    from meshseq.vertex_loss import VertexLoss, vertex_unit

    rec, verts = truth or reconstructed_vertices(data)
    unit = vertex_unit(scaled, verts, [s.train for s in splits])
    return VertexLoss(TorchReconstructor(rec, device=device), scaling, unit, config.vertex_frames)


def encoder_grad_scale(fan_in: int, config: TrainConfig) -> float:
    """The factor on the encoder's share of the FC weight's gradient: ``min(1, fc_lr_fan_in /
    fan_in)`` with ``fc_lr = "encoder"``, else 1."""
    return min(1.0, config.fc_lr_fan_in / fan_in) if config.fc_lr == "encoder" else 1.0


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


def fit_window(config: TrainConfig, splits: list[Split], log=lambda msg: None) -> TrainConfig:
    """``config`` with its window shortened by ``fitted_window`` to the training segments of
    ``splits`` (the same config when it already fits); says so through ``log``."""
    lengths = [b - a for s in splits for a, b in s.train]
    window = fitted_window(lengths, config.window, config.batch, config.stride)
    if window == config.window:
        return config
    if not config.given < window:
        raise MeshseqError(f"--given {config.given}: the training frames hold only windows of {window} frames "
                           f"(--window {config.window} shortened to a batch of {config.batch} starts); "
                           "use a smaller --given or --window-fit none")
    log(f"--window {config.window}: the training frames hold fewer than a batch ({config.batch}) of different "
        f"windows of {config.window} frames; training on windows of {window} frames (--window-fit none keeps "
        f"{config.window})")
    return replace(config, window=window)


def gather_frames(frames: torch.Tensor, rows: torch.Tensor) -> torch.Tensor:
    """``frames[rows]``: ``(T, ...)`` frames at indices ``rows`` (any shape) -> ``rows.shape + (...)``,
    as one ``index_select`` (a row copy each: 5.4 against 10.8 ms for advanced indexing, 8 x 32
    frames of the horse)."""
    return frames.index_select(0, rows.reshape(-1)).view(*rows.shape, *frames.shape[1:])


def training_windows(frames: torch.Tensor, sampler: WindowSampler, rng: np.random.Generator,
                     config: TrainConfig, share: slice = slice(None)) -> tuple[torch.Tensor, torch.Tensor | None]:
    """This process's ``share`` of one iteration's ``(batch, window, V, 9)`` windows of the
    stacked ``(T, V, 9)`` frames (every process draws the whole batch, so the generators stay in
    step); with ``speed_augment > 1`` played at random speeds (``WindowSampler.sample_at_speeds``),
    each frame the linear interpolation of the two frames around its position.
    Returns ``(windows, rows)``, ``rows`` ``(batch, window)`` the frames' indices (None for windows
    played at other speeds: their frames are interpolations)."""
    def rows(r: np.ndarray) -> torch.Tensor:
        return gather_frames(frames, torch.from_numpy(r[share]).to(frames.device))

    if config.speed_augment <= 1:
        r = sampler.sample(rng, config.batch)
        return rows(r), torch.from_numpy(r[share])
    before, after, weight = sampler.sample_at_speeds(rng, config.batch, config.speed_augment)
    w = torch.from_numpy(weight[share]).to(frames.device, frames.dtype)[..., None, None]
    return torch.lerp(rows(before), rows(after), w), None


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
            f"try a smaller --lr than {lr:g}")


def _stderr(msg: str) -> None:
    print(f"meshseq: {msg}", file=sys.stderr)


def train(
    data: TrainingData,
    run_dir: str | os.PathLike,
    config: TrainConfig | None = None,
    model_options: dict | None = None,
    device: str = "auto",
    resume: bool = False,
    force: bool = False,
    progress: bool = True,
    log=_stderr,
) -> dict:
    """Train (or resume training) a BD-LSTM on ``data``; write metrics and checkpoints to ``run_dir``.

    Args:
        data: features of the data sets (see :func:`load_training_data`).
        config: training options (default ``TrainConfig()``). On resume the stored options are
            used, except ``iterations``, which may extend the run.
        model_options: ``ModelConfig`` fields other than ``n_vertices`` (variant, latent, ...).
        device: ``auto`` (CUDA if available), ``cpu``, ``cuda`` or ``cuda:N``.
        resume: continue from the newest usable checkpoint in ``run_dir``; MeshseqError if there
            is none (a resume never starts over; its stored options are used).
        force: start over in a non-empty ``run_dir`` (removes the checkpoints, metrics and
            TensorBoard events training wrote there, nothing else).
    Raises:
        MeshseqError: bad options or data, nothing to resume, or divergence: a non-finite loss
            term or gradient stops training before the update, naming the iteration and the
            term; checkpoints are written only with finite weights.
    Returns:
        ``{"iteration", "checkpoint", "loss", "heldout_rec", "model"}`` after the last iteration
        (``model``: the trained ``BDLSTM``, with the weight average when ``ema_decay`` is set:
        what the checkpoints deliver); with ``validation`` also ``"best"``: ``{"error",
        "iteration", "checkpoint"}``, the checkpoint with the lowest validation error
        (``RUN/checkpoints/best``; errors are measured every ``eval_every`` iterations and at the last).
    """
    from meshseq.acap import Scaling

    config = config or TrainConfig()
    run_dir = Path(run_dir)
    dev = resolve_device(device)
    dist_info = init_distributed(dev)
    if dev.type == "cuda" and dist_info.active:
        dev = torch.device("cuda", dist_info.local_rank)
        torch.cuda.set_device(dev)
    is_main = dist_info.rank == 0
    if dev.type == "cpu":
        keep_freed_memory()  # reuse freed step-sized blocks instead of page-faulting fresh ones
    log = log if (is_main and log) else (lambda msg: None)
    ModelConfig.check_options(model_options or {})  # before the run folder is created
    if resume and force:
        raise MeshseqError("--resume and --force: choose one (--resume continues RUN, --force starts it over)")
    found = resume_point(run_dir) if resume else None
    if found is None:  # options the data cannot meet fail before --force removes anything
        splits = [split_frames(len(f), config.holdout, config.holdout_at, config.validation) for f in data.features]
        if config.window_fit == "batch":
            config = fit_window(config, splits, log)
        WindowSampler(splits, data.names, config.window, config.stride)
    if is_main:
        _prepare_run_dir(run_dir, resume, force)
    if dist_info.active:
        torch.distributed.barrier()

    faces, V = data.faces, data.n_vertices
    topo = Topology.from_faces(faces, V)
    for name, f in zip(data.names, data.features):
        if f.ndim != 3 or f.shape[1:] != (V, 9):
            raise MeshseqError(f"{name}: features must have shape (T, {V}, 9), got {f.shape}")

    if found is not None:
        meta = found.meta
        ckpt.check_topology(meta, faces, V, what="the training data")
        if [d["source"] for d in meta["datasets"]] != data.sources:
            raise MeshseqError(
                f"--resume: {found.folder} was trained on {[d['source'] for d in meta['datasets']]}, not {data.sources}"
            )
        iterations = config.iterations
        config = TrainConfig.from_dict(meta["train"])
        config.iterations = iterations
        model_config = ModelConfig.from_dict(meta["model"])
        scaling = Scaling.from_dict(meta["scaling"])
        splits = [Split.from_dict(d["split"]) for d in meta["datasets"]]
    else:
        model_config = ModelConfig(n_vertices=V, **(model_options or {}))
        train_feats = np.concatenate([f[s.train_frames()] for f, s in zip(data.features, splits)])
        if len(train_feats) == 0:
            raise MeshseqError(f"--holdout {config.holdout}: leaves no training frames")
        scaling = Scaling.fit(train_feats, mode=config.scaling)
        model_config.input_norm = bool(config.input_norm)
        model_config.logvar_max = None if config.logvar_max is None else float(config.logvar_max)
        model_config.mu_max = None if config.mu_max is None else float(config.mu_max)

    if data.consistency != config.consistency:
        stored = f"{found.folder} was trained on" if found is not None else "--consistency asks for"
        raise MeshseqError(f"{stored} {config.consistency} features; the data were extracted with "
                           f"{data.consistency} rotation consistency")
    scaled = [scaling.apply(f) for f in data.features]  # (T_d, V, 9) float64 each
    if found is None and config.step_scale == "data":
        model_config.step_scale = [float(v) for v in step_spread(scaled, splits, config.stride)]
    if config.batch % dist_info.world:
        raise MeshseqError(f"--batch {config.batch} must be a multiple of the number of processes ({dist_info.world})")
    sampler = WindowSampler(splits, data.names, config.window, config.stride)
    eval_rows = heldout_rows(splits, config.window, config.stride)
    frames = torch.from_numpy(np.concatenate(scaled).astype(np.float32)).to(dev)  # (sum T, V, 9)

    torch.manual_seed(config.seed)
    random.seed(config.seed)
    np_rng = np.random.default_rng(config.seed)
    if found is None:
        model = BDLSTM(model_config, topo)
        if model_config.input_norm:
            model.set_input_norm(np.concatenate([x[s.train_frames()] for x, s in zip(scaled, splits)]))
    else:
        model = found.net  # the stored weights, checked against the stored config
    model = model.to(dev)
    groups = parameter_groups(model, config)
    names = [n for g in groups for n in g["names"]]  # in the optimizer's order
    optimizer = torch.optim.Adam([{k: v for k, v in g.items() if k != "names"} for g in groups],
                                 lr=config.lr, betas=(0.9, float(config.adam_beta2)),
                                 fused=fused_adam(dev))
    start = 0
    own_rng = False
    grad_history = collections.deque(maxlen=GRAD_CLIP_HISTORY)  # the last unclipped gradient norms
    if found is not None:
        smeta, stensors = found.state_meta, found.state_tensors
        grad_history.extend(smeta.get("grad_norms", []))
        ckpt.load_optimizer_state(optimizer, names, stensors, smeta["optimizer"])
        own_rng = ckpt.set_rng_state(stensors, smeta, dist_info.rank)
        np_rng.bit_generator.state = smeta["numpy_rng"]
        start = int(meta["iteration"])
        log(f"resumed {found.folder} at iteration {start} (with its stored options; --iterations {config.iterations})")
        stored_world = int(smeta.get("world_size", 1))
        if stored_world < dist_info.world:
            log(f"the checkpoint was written by {stored_world} process(es), not {dist_info.world}: the sampling "
                f"noise of processes {stored_world}.. is reseeded (the run is not repeated bit for bit)")
    params = list(model.parameters())
    param_names = [n for n, _ in model.named_parameters()]
    # with ema_decay, checkpoints deliver the average (model tensors) and carry the weights
    # training continues from in the training state (train.<name>)
    average = None
    if config.ema_decay is not None:
        average = [p.detach().clone() for p in params]  # a fresh run: the initial weights; a resume: the stored average
        if found is not None:
            raw = ckpt.training_weights(found.state_tensors)
            if set(raw) != set(param_names):
                raise MeshseqError(f"--resume: {found.folder}: the training state lacks the weights (train.*) "
                                   "behind its weight average (ema_decay)")
            copy_weights(params, [raw[n] for n in param_names])
    if dist_info.rank > 0 and not own_rng:
        # different sampling noise per rank (the windows stay common)
        torch.manual_seed(config.seed + 7919 * dist_info.rank + start)

    validating = is_main and config.validation > 0  # the main process measures the validation blocks
    truth = reconstructed_vertices(data) if (config.w_vertex > 0 or validating) else None
    vertex_loss = make_vertex_loss(data, scaled, splits, scaling, config, dev, truth)
    if vertex_loss is not None and config.speed_augment <= 1:
        vertex_loss.cache_targets(frames)  # the truth's vertices of every training frame, once
    objective = WindowLoss(model, config, vertex_loss)
    if dist_info.active:
        objective = nn.parallel.DistributedDataParallel(
            objective,
            device_ids=[dev.index] if dev.type == "cuda" else None,
            broadcast_buffers=False,
        )

    datasets_meta = [
        {"name": n, "source": s, "n_frames": int(len(f)), "split": sp.to_dict()}
        for n, s, f, sp in zip(data.names, data.sources, data.features, splits)
    ]
    topo_meta = {"hash": topology_hash(faces, V), "n_vertices": V, "n_faces": int(len(faces))}

    def save(iteration: int, rng_t: dict, name: str | None = None, extra: dict | None = None) -> Path:
        tensors = {f"model.{k}": v for k, v in model.state_dict().items()}
        if average is not None:
            tensors.update({f"model.{n}": a for n, a in zip(param_names, average)})
        tensors["reference.vertices"] = torch.from_numpy(np.asarray(data.reference, dtype=np.float64))
        tensors["reference.faces"] = torch.from_numpy(np.asarray(faces, dtype=np.int64))
        meta = {
            "model": model_config.to_dict(),
            "train": config.to_dict(),
            "scaling": scaling.to_dict(),
            "topology": topo_meta,
            "datasets": datasets_meta,
            "features": {"reference": "first frame of data set 0", "consistency": config.consistency},
            "torch_version": torch.__version__,
            "world_size": dist_info.world,
            **(extra or {}),
        }
        opt_t, opt_meta = ckpt.optimizer_state(optimizer, names)
        _, rng_meta = ckpt.rng_state()
        state_meta = {"optimizer": opt_meta, "numpy_rng": np_rng.bit_generator.state, "world_size": dist_info.world,
                      "grad_norms": list(grad_history), **rng_meta}
        raw_t = {f"train.{n}": p for n, p in zip(param_names, params)} if average is not None else {}
        return ckpt.save_checkpoint(run_dir, iteration, tensors, meta, {**opt_t, **rng_t, **raw_t}, state_meta,
                                    config.keep, name)

    def gather_rng() -> dict:
        """Every process's torch (and CUDA) generator state, named by rank (every rank calls this)."""
        own, _ = ckpt.rng_state()
        if not dist_info.active:
            return own
        out = {}
        for name, t in own.items():
            t = t.to(dev)  # NCCL gathers CUDA tensors only
            parts = [torch.empty_like(t) for _ in range(dist_info.world)]
            torch.distributed.all_gather(parts, t)
            out.update({ckpt.rng_key(name.split(".")[1], r): part.cpu() for r, part in enumerate(parts)})
        return out

    def evaluate() -> dict:
        if len(eval_rows) == 0:
            return {}
        model.eval()
        with torch.no_grad(), weights_swapped(params, average):  # what a checkpoint delivers
            w = frames[torch.from_numpy(eval_rows).to(dev)]
            terms = window_losses(model(w, sample=False), w)
        model.train()
        out = {"heldout_rec": float(terms["rec"])}
        if model_config.variant != "uni":
            out["heldout_bd"] = float(terms["bd"])
        return out

    validate = None
    if validating:
        validate = validation_scorer(model, params, average, data, scaling, splits, scaled, truth, dev)
    best = ckpt.best_validation(run_dir) if (validate and found is not None) else None
    if best is not None and best["iteration"] > start:  # written after the checkpoint we resume from
        best = None

    metrics = Metrics(run_dir, start, log) if is_main else None
    share = config.batch // dist_info.world
    lo, hi = dist_info.rank * share, (dist_info.rank + 1) * share
    bar = _progress_bar(config.iterations - start) if (is_main and progress) else None
    last: dict = {"iteration": start, "checkpoint": str(found.folder) if found else None, "loss": None,
                  "heldout_rec": None}
    t0 = time.perf_counter()
    collapse_warned = False
    clipped = 0  # iterations whose gradient was clipped since the last metrics row
    checked = [k for k in ("rec", "bd", "kl", "l2", "motion", "vertex") if getattr(config, f"w_{k}") != 0]
    checked_names = [f"the loss term {k}" for k in checked] + ["the total loss", "the gradient norm"]
    frozen = freeze_setup_objects()
    try:
        if bar is not None:
            bar.start()
            task = bar.add_task("train", total=config.iterations, completed=start, terms="")
        for it in range(start + 1, config.iterations + 1):
            windows, rows = training_windows(frames, sampler, np_rng, config, slice(lo, hi))
            given = 1 if config.given <= 1 else int(np_rng.integers(1, config.given + 1))
            optimizer.zero_grad(set_to_none=True)
            with autocast(dev, config.precision):
                total, terms = objective(windows, sample=config.sample, given=given, rows=rows)
            total.backward()
            # one finiteness check per iteration, before the update: the weighted loss terms, the
            # total and the norm of all gradients (after DDP's all-reduce, so common to all ranks)
            health = torch.stack([terms[k].float() for k in checked] + [total.detach().float(),
                                                                        grad_norm(params).float()])
            finite = torch.isfinite(health).all().to(torch.int32)
            if dist_info.active:
                torch.distributed.all_reduce(finite, op=torch.distributed.ReduceOp.MIN)
            if not bool(finite):
                raise MeshseqError(divergence(it, checked_names, health.cpu(), config.lr, last["checkpoint"]))
            norm = float(health[-1])
            limit = clip_threshold(grad_history, config.grad_clip)
            grad_history.append(norm)
            if limit is not None and norm > limit:
                scale_gradients(params, limit / norm)
                clipped += 1
            optimizer.step()
            if average is not None:
                update_average(average, params, average_decay(config.ema_decay, it))

            row = None
            if config.log_every and it % config.log_every == 0 or it == config.iterations:
                last["loss"] = float(total.detach())  # this process's share of the batch
            if is_main and (config.log_every and it % config.log_every == 0 or it == config.iterations):
                row = {"iteration": it, "seconds": round(time.perf_counter() - t0, 3), "loss": float(total.detach())}
                row.update({k: float(v) for k, v in terms.items()})
                row["grad_norm"] = norm
                row["clipped"], clipped = clipped, 0
            if is_main and (config.eval_every and it % config.eval_every == 0 or it == config.iterations):
                row = row or {"iteration": it, "seconds": round(time.perf_counter() - t0, 3)}
                row.update(evaluate())
                last["heldout_rec"] = row.get("heldout_rec")
                if validate is not None:
                    row["validation"] = validate()
                    if best is None or row["validation"] < best["error"]:
                        best = {"error": row["validation"], "iteration": it}
                        save(it, ckpt.rng_state()[0], ckpt.BEST, {"validation": best})
                if not collapse_warned and it >= COLLAPSE_AFTER and "latent_spread" in row:
                    message = collapse_warning(row.get("kl"), row["latent_spread"], config.w_kl)
                    if message:
                        log(f"warning at iteration {it}: {message}")
                        collapse_warned = True
            if row is not None:
                metrics.write(row)
                if bar is not None:
                    bar.update(task, terms=_terms_text(row))
            if bar is not None:
                bar.update(task, completed=it)
            if config.checkpoint_every and it % config.checkpoint_every == 0 or it == config.iterations:
                rng_t = gather_rng()
                if is_main:
                    last["checkpoint"] = str(save(it, rng_t))
                if dist_info.active:
                    torch.distributed.barrier()
            last["iteration"] = it
        if start >= config.iterations and is_main:
            log(f"{run_dir}: already at iteration {start} (>= --iterations {config.iterations}); nothing to do")
    finally:
        if frozen:
            gc.unfreeze()
        if bar is not None:
            bar.stop()
        if metrics is not None:
            metrics.close()
        if dist_info.started_here:
            torch.distributed.destroy_process_group()
    if average is not None:  # return what the checkpoints deliver
        copy_weights(params, average)
    last["model"] = model
    if best is not None:
        last["best"] = {**best, "checkpoint": str(ckpt.best_folder(run_dir))}
        log(f"best validation error {best['error']:.1f} (x 1e-4) at iteration {best['iteration']}: "
            f"{ckpt.best_folder(run_dir)}")
    return last


def validation_scorer(model: BDLSTM, params, average, data: TrainingData, scaling, splits: list[Split],
                      scaled: list[np.ndarray], truth, device: torch.device):
    """``score() -> float``: ``meshseq.evaluate.validation_error`` of the model as a checkpoint
    would deliver it (the weight average, when kept) on every data set's validation block.

    ``truth``: ``reconstructed_vertices(data)``.
    """
    from meshseq.api import Model
    from meshseq.evaluate import validation_error

    rec, vertices = truth
    blocks = [s.validation for s in splits]
    delivered = Model(model, {"scaling": scaling.to_dict()}, data.reference, data.faces, device, rec)
    model.train()  # Model() switched it to eval mode

    def score() -> float:
        model.eval()
        try:
            with torch.no_grad(), weights_swapped(params, average):
                return validation_error(delivered, vertices, scaled, blocks)
        finally:
            model.train()

    return score


#: iterations before the collapse check starts (the latent needs a few hundred to organise)
COLLAPSE_AFTER = 200


def collapse_warning(kl: float | None, spread: float, w_kl: float) -> str | None:
    """A one-line warning if the latent has collapsed to the prior, else None.

    Collapse: the latent mean hardly varies with the frame (``spread`` < 0.01, against the
    prior's unit spread) or, with a KL term, the KL is below 0.01 nats: z then tells the LSTM
    nothing about the current frame and roll-outs freeze.
    """
    if spread < 1e-2 or (w_kl > 0 and kl is not None and kl < 1e-2):
        return (f"the latent has collapsed to the prior (KL {0.0 if kl is None else kl:.3g} nats, "
                f"latent spread {spread:.3g}): z carries little about the frame and roll-outs will "
                "freeze; the paper's recipe does this (L_2 shrinks the tied FC), see --recipe")
    return None


def _terms_text(row: dict) -> str:
    keys = ("loss", "rec", "bd", "kl", "l2", "latent_spread", "heldout_rec")
    return " ".join(f"{k}={row[k]:.4g}" for k in keys if row.get(k) is not None)


def _progress_bar(total: int):
    from rich.progress import (
        BarColumn,
        MofNCompleteColumn,
        Progress,
        TextColumn,
        TimeElapsedColumn,
        TimeRemainingColumn,
    )

    class _Rate(TextColumn):
        def render(self, task):
            speed = task.finished_speed or task.speed
            from rich.text import Text

            return Text("?" if speed is None else (f"{speed:.2f} it/s" if speed >= 1 else f"{1 / speed:.2f} s/it"))

    return Progress(
        TextColumn("[bold]{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        _Rate(""),
        TimeElapsedColumn(),
        TextColumn("ETA"),
        TimeRemainingColumn(),
        TextColumn("{task.fields[terms]}"),
        transient=False,
    )
