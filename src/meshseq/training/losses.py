"""The training objective: loss terms of a roll-out and ``WindowLoss``, the module DDP wraps.

The loss of a batch of ground-truth windows ``X`` ``(B, n, V, 9)`` (scaled features), with
``S^f`` the forward chain's frames and ``S^b`` the backward chain's (own order, ``S^b_1 = X_n``)::

    L_rec = mean_windows mean_{i=2..n} ( ||S^f_i - X_i||^2 + ||S^b_i - X_{n+1-i}||^2 )
    L_bd  = mean_windows mean_{i=1..n}   ||S^f_i - S^b_{n+1-i}||^2
    L_KL  = mean_windows mean_steps sum_latent KL(N(mu, sigma^2) || N(0, 1))
    L_2   = sum of squares of every weight matrix (biases excluded; tied weights counted once)
    L     = w_rec L_rec + w_bd L_bd + w_kl L_KL + w_l2 L_2      (paper 1, 0.5, 0.1, 0.1; default L_2 off)

and ``+ w_motion L_motion + w_vertex L_vertex`` (not in the paper, whose recipe has both at 0; the
default recipe: 20 and 1; see ``motion_loss``, ``meshseq.vertex_loss`` and
``meshseq.training.config.RECIPES``).

``||.||^2`` sums over vertices and the 9 channels of one frame (the paper's sums over frames
become means, so the weights do not depend on the window length). ``uni`` has no backward chain:
its L_rec has the forward term only and L_bd = 0.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import nn

from meshseq.data.windows import Split
from meshseq.kernels import frame_errors, frame_errors_of_frames
from meshseq.model import BDLSTM
from meshseq.training.config import KL_REFERENCE_VERTICES, TrainConfig
from meshseq.training.data import TrainingData


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

    def __init__(self, model: BDLSTM, config: TrainConfig, vertex_loss: nn.Module | None = None,
                 part_labels: np.ndarray | None = None):
        """``part_labels`` ``(V,)``: each vertex's part, on a model with placement channels (what
        ``placement_jitter`` shifts part by part); None otherwise."""
        super().__init__()
        self.model = model
        self.weights = {"rec": config.w_rec, "bd": config.w_bd, "l2": config.w_l2, "motion": config.w_motion,
                        "kl": kl_weight(config.w_kl, model.config.n_vertices, config.kl_scale),
                        "vertex": config.w_vertex}
        if config.w_vertex > 0 and vertex_loss is None:
            raise ValueError("w_vertex > 0 needs a VertexLoss (meshseq.vertex_loss)")
        self.vertex_loss = vertex_loss if config.w_vertex > 0 else None
        self.feedback_grad = config.feedback_grad == "full"
        self.placement_jitter = float(config.placement_jitter) if model.config.channels > 9 else 0.0
        if self.placement_jitter > 0 and part_labels is None:
            raise ValueError("placement_jitter > 0 needs the parts' labels (part_labels)")
        self.part_labels = None if part_labels is None else torch.as_tensor(  # on the model's device, once
            np.asarray(part_labels), dtype=torch.long, device=model.fc.weight.device)
        # how the tied FC weight's gradient is formed in this objective's roll-outs (fc_lr "encoder")
        model.encoder_grad_scale = encoder_grad_scale(model.fc.weight.shape[1], config)

    def forward(self, windows: torch.Tensor, sample: bool = True, given: int = 1, rows: torch.Tensor | None = None):
        """``rows`` ``(B, n)``: the stacked training frames the windows are (L_vertex then reads the
        truth's vertices from its cache, ``VertexLoss.cache_targets``), or None."""
        truth, shift = windows, None  # L_vertex compares with the unshifted truth
        if self.placement_jitter > 0 and self.training:
            windows, shift = jittered_placement(windows, self.part_labels, self.placement_jitter)
        out = self.model(windows, sample=sample, given=given, feedback_grad=self.feedback_grad)
        motion = self.weights["motion"] > 0
        errors = output_frame_errors(out, windows, steps=motion)  # one pass for all these terms
        terms = window_losses(out, windows, errors)
        if motion:
            terms["motion"] = motion_loss(out, windows, errors)
        if self.vertex_loss is not None:
            # only the picked frames of the chains, stacked: (B or 2B, k, V, C)
            picked = out.frames_at(self.vertex_loss.picks(windows.shape[1]))
            if shift is not None:  # the truth's vertices sit where the unshifted channels put the parts
                picked = unjittered(picked, shift)
            B = windows.shape[0]
            terms["vertex"] = self.vertex_loss.of_picked(picked[:B], truth, rows)
            if has_backward_chains(out):
                back_rows = None if rows is None else rows.flip(1)
                terms["vertex"] = terms["vertex"] + self.vertex_loss.of_picked(picked[B:], truth.flip(1), back_rows)
        terms["l2"] = sum(squared_norm(p) for p in self.model.weight_parameters())
        total = sum(self.weights[k] * v for k, v in terms.items() if self.weights.get(k, 0) != 0)
        return total, {k: v.detach() for k, v in terms.items()}



def jittered_placement(windows: torch.Tensor, labels: torch.Tensor, std: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Windows ``(B, n, V, 12)`` with each part's placement channels shifted by one random offset
    per window (normal, ``std`` in scaled units), and the shift ``(B, V, 3)``.

    The held-out subject's parts sit elsewhere than the training subjects' (a strap on a slimmer
    body); shifted at random, a part's absolute placement says nothing of the motion, so the model
    learns to move the parts from where the given frames put them.
    """
    labels = labels.to(windows.device)
    n_parts = int(labels.max()) + 1
    offsets = torch.randn(windows.shape[0], n_parts, 3, device=windows.device, dtype=windows.dtype) * std
    shift = offsets[:, labels]  # (B, V, 3)
    return windows + nn.functional.pad(shift, (9, 0))[:, None], shift  # zeros on the 9 ACAP channels


def unjittered(frames: torch.Tensor, shift: torch.Tensor) -> torch.Tensor:
    """Frames ``(B or 2B, k, V, 12)`` of jittered windows with the placement shift ``(B, V, 3)`` taken
    back (the backward chains, rows B.., share their windows' shift)."""
    reps = frames.shape[0] // shift.shape[0]
    return frames - nn.functional.pad(shift, (9, 0)).repeat(reps, 1, 1)[:, None]


def encoder_grad_scale(fan_in: int, config: TrainConfig) -> float:
    """The factor on the encoder's share of the FC weight's gradient: ``min(1, fc_lr_fan_in /
    fan_in)`` with ``fc_lr = "encoder"``, else 1."""
    return min(1.0, config.fc_lr_fan_in / fan_in) if config.fc_lr == "encoder" else 1.0



def reconstructed_vertices(data: TrainingData) -> tuple[object, list[np.ndarray]]:
    """``(Reconstructor of the training reference, [(T_d, V, 3)] centred vertices of every frame)``:
    the truth as the features reconstruct it (no reconstruction error in what is compared)."""
    from meshseq.acap import Reconstructor

    rec = Reconstructor(data.reference, data.faces, placement=data.placement)
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

