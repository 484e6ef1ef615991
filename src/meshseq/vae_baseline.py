"""The mesh-VAE baseline of the paper's tables (``vae_latent``: linear extrapolation in the latent
space of a mesh VAE trained on the same features; it stands in for Tan et al., CVPR 2018, which used
another feature). Read through ``meshseq.baselines`` (``baselines.train_vae`` etc.), whose other
baselines are numpy only.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import torch
from torch import nn

from meshseq.mesh import Topology
from meshseq.model import BDLSTM, ModelConfig

#: how ``train_vae`` sets the FC weight's learning rate (``vae_param_groups``), stored with a cached VAE
VAE_FC_LR = "fan-in"
VAE_NOTE = "vae_latent: latent extrapolation of a mesh VAE on ACAP features, standing in for Tan et al. 2018"


class MeshVAE(nn.Module):
    """A mesh-convolutional VAE on single frames ``(B, V, C)``: the generator's own encoder
    (conv + FC + VAE head) and tied decoder, trained to output the frame itself rather than a
    change. (The wrapped generator's LSTM is unused.) With ``config.input_norm`` (``train_vae``'s
    default) it encodes and decodes frames normalised as the generator's input is (centred on the
    mean training frame, divided by each channel's spread): without it the frames of a sequence
    differ by a few hundredths of the scaled range and the VAE reconstructs their mean."""

    def __init__(self, config: ModelConfig, topology: Topology):
        super().__init__()
        self.config = config
        self.net = BDLSTM(config, topology)

    def normalise(self, x: torch.Tensor) -> torch.Tensor:
        """``(B, V, C)`` frames -> the same normalised (identity without ``input_norm``)."""
        if not self.config.input_norm:
            return x
        return (x - self.net.input_offset[:, :, 0].t()) / self.net.input_spread.view(1, 1, -1)

    def encode(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``(B, V, C)`` -> ``(mu, logvar)`` each ``(B, L)``."""
        return self.net.encode(x)

    def decode_normalised(self, z: torch.Tensor) -> torch.Tensor:
        """``(B, L)`` -> normalised frames ``(B, V, C)`` (what training fits)."""
        return self.net.decode(z)

    def decode(self, z: torch.Tensor) -> torch.Tensor:
        """``(B, L)`` -> frames ``(B, V, C)``."""
        out = self.net.decode(z)
        if not self.config.input_norm:
            return out
        return out * self.net.input_spread.view(1, 1, -1) + self.net.input_offset[:, :, 0].t()


def vae_param_groups(vae: MeshVAE, lr: float) -> list[dict]:
    """Adam's parameter groups: the big FC weight (fan-in V x C, tied to the decoder) at ``lr x
    min(1, 9000 / (V x C))`` (``meshseq.train.fc_lr_factor``, the generator's ``fc_lr = "fan-in"``
    rule), everything else at ``lr``. At one rate for every weight, horse-gallop's VAE (fan-in
    75,879, 1000 iterations) ran away: training reconstruction error 5,832 against 82 for one
    frame-to-frame change, log-variance -182, predictions 25 x worse than standing still; with
    the factor (0.119) its reconstruction error is 35.
    """
    from meshseq.training.config import FC_REFERENCE_FAN_IN, fc_lr_factor

    fc = vae.net.fc.weight
    factor = fc_lr_factor(fc.shape[1], VAE_FC_LR, FC_REFERENCE_FAN_IN)
    return [{"params": [p for p in vae.parameters() if p is not fc], "lr": lr},
            {"params": [fc], "lr": lr * factor}]


def train_vae(frames: np.ndarray, topology: Topology, latent: int = 128, iterations: int = 3000,
              batch: int = 16, lr: float = 1e-3, kl_weight: float = 1e-3, seed: int = 0,
              device: str | torch.device = "cpu", patience: int = 300) -> MeshVAE:
    """Fit a ``MeshVAE`` to scaled training frames ``(N, V, C)`` (reconstruction + KL), on
    normalised frames (``MeshVAE``), until the reconstruction error has not improved by 1% for
    ``patience`` iterations, or ``iterations`` at most.

    The big FC weight (fan-in V x C, tied to the decoder) learns at ``lr x min(1, 9000 / (V x C))``
    (``vae_param_groups``).
    """
    torch.manual_seed(seed)
    rng = np.random.default_rng(seed)
    x_all = torch.as_tensor(np.asarray(frames), dtype=torch.float32, device=device)
    config = ModelConfig(n_vertices=x_all.shape[1], channels=x_all.shape[2], latent=latent, lstm_layers=1,
                         variant="uni", input_norm=True)
    vae = MeshVAE(config, topology)
    vae.net.set_input_norm(np.asarray(frames))
    vae = vae.to(device)
    opt = torch.optim.Adam(vae_param_groups(vae, lr), lr=lr)
    best, since, smooth = np.inf, 0, None
    for _ in range(iterations):
        x = x_all[torch.as_tensor(rng.integers(0, len(x_all), size=min(batch, len(x_all))), device=device)]
        mu, logvar = vae.encode(x)
        z = mu + torch.exp(0.5 * logvar) * torch.randn_like(mu)
        rec = ((vae.decode_normalised(z) - vae.normalise(x)) ** 2).sum(dim=(1, 2)).mean()
        kl = -0.5 * (1 + logvar - mu.pow(2) - logvar.exp()).sum(dim=1).mean()
        loss = rec + kl_weight * kl
        opt.zero_grad()
        loss.backward()
        opt.step()
        smooth = rec.item() if smooth is None else 0.98 * smooth + 0.02 * rec.item()
        if smooth < 0.99 * best:
            best, since = smooth, 0
        else:
            since += 1
            if since >= patience:
                break
    return vae.eval()


def vae_latent(vae: MeshVAE, given: np.ndarray, n_frames: int) -> np.ndarray:
    """``(B, U, V, C)`` -> ``(B, n, V, C)``: linear extrapolation of the latent means, decoded."""
    g = torch.as_tensor(np.asarray(given), dtype=torch.float32, device=next(vae.parameters()).device)
    bsz, u = g.shape[:2]
    with torch.no_grad():
        mu, _ = vae.encode(g.reshape(bsz * u, *g.shape[2:]))
        mu = mu.view(bsz, u, -1)
        vel = mu[:, -1] - mu[:, -2] if u >= 2 else torch.zeros_like(mu[:, -1])
        k = torch.arange(1, n_frames + 1, dtype=mu.dtype, device=mu.device)[None, :, None]
        z = mu[:, -1:] + k * vel[:, None]
        out = vae.decode(z.reshape(bsz * n_frames, -1)).view(bsz, n_frames, *g.shape[2:])
    return out.cpu().numpy()


def save_vae(vae: MeshVAE, folder: str | Path, info: dict) -> None:
    """Weights (safetensors) and config + ``info`` (JSON) into ``folder``, atomically."""
    from safetensors.torch import save_file

    from meshseq.io import atomic_output

    with atomic_output(Path(folder), force=True) as tmp:
        tmp.mkdir()
        save_file({k: v.detach().cpu().contiguous() for k, v in vae.state_dict().items()}, str(tmp / "vae.safetensors"))
        (tmp / "vae.json").write_text(json.dumps({"config": vae.config.to_dict(), **info}, indent=2))


def load_vae(folder: str | Path, topology: Topology, device="cpu") -> tuple[MeshVAE, dict]:
    """Inverse of ``save_vae`` (safetensors and JSON only: nothing unpickled).

    MeshseqError (one line naming the file) if the files are damaged, do not match each other or
    hold non-finite weights.
    """
    from safetensors import SafetensorError
    from safetensors.torch import load_file

    from meshseq import checkpoint_schema as schema
    from meshseq.errors import MeshseqError

    folder = Path(folder)
    try:
        meta = json.loads((folder / "vae.json").read_text())
        tensors = load_file(str(folder / "vae.safetensors"))
    except (OSError, ValueError, SafetensorError) as err:
        raise MeshseqError(f"{folder}: damaged VAE baseline ({str(err).splitlines()[0]})") from None
    schema.check(meta, {"config": schema.config_schema(ModelConfig)}, folder / "vae.json")
    config = ModelConfig.from_dict(meta["config"], source=str(folder / "vae.json"))
    vae = MeshVAE(config, topology)
    schema.check_like(tensors, vae.state_dict(), folder / "vae.safetensors", exact=True)
    vae.load_state_dict(tensors)
    return vae.to(device).eval(), meta
