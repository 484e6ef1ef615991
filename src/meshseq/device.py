"""The torch device a command runs on (``--device``)."""

from __future__ import annotations

import torch

from meshseq.errors import MeshseqError


def resolve_device(device: str) -> torch.device:
    """``auto`` (CUDA if available), ``cpu``, ``cuda`` or ``cuda:N`` -> a torch device; a one-line
    MeshseqError for CUDA where there is none or an unknown name."""
    if device == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if device.startswith("cuda") and not torch.cuda.is_available():
        raise MeshseqError(f"--device {device}: CUDA is not available here (torch {torch.__version__})")
    try:
        return torch.device(device)
    except RuntimeError:
        raise MeshseqError(f"--device {device!r}: expected auto, cpu, cuda or cuda:N") from None

