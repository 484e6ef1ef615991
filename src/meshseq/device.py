"""The device a command runs on (``--device``), and whether its inference needs torch at all."""

from __future__ import annotations

import os
import sys

from meshseq.errors import MeshseqError

#: ``MESHSEQ_INFERENCE=torch`` runs ``predict`` and ``complete`` on the torch model on CPU too
#: (default there: ``meshseq.numpy_net``, which does not import torch)
INFERENCE_ENV = "MESHSEQ_INFERENCE"


def resolve_device(device: str):
    """``auto`` (CUDA if available), ``cpu``, ``cuda`` or ``cuda:N`` -> a torch device; a one-line
    MeshseqError for CUDA where there is none or an unknown name."""
    import torch

    if device == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if device.startswith("cuda") and not torch.cuda.is_available():
        raise MeshseqError(f"--device {device}: CUDA is not available here (torch {torch.__version__})")
    try:
        return torch.device(device)
    except RuntimeError:
        raise MeshseqError(f"--device {device!r}: expected auto, cpu, cuda or cuda:N") from None


def gpu_driver_absent() -> bool:
    """True where torch could find no GPU, known without importing it: macOS (no CUDA), or Linux
    without an NVIDIA driver (``/proc/driver/nvidia/version``, ``/dev/nvidiactl``) or a ROCm one
    (``/dev/kfd``). False (perhaps a GPU: ask torch) elsewhere."""
    if sys.platform == "darwin":
        return True
    if sys.platform.startswith("linux"):
        return not any(os.path.exists(p) for p in ("/proc/driver/nvidia/version", "/dev/nvidiactl", "/dev/kfd"))
    return False


def inference_backend(device: str) -> str:
    """``numpy`` where a synthesis command's ``--device`` means this CPU (``cpu``, or ``auto`` with
    no GPU driver) and ``MESHSEQ_INFERENCE`` does not ask for ``torch``; else ``torch``."""
    if os.environ.get(INFERENCE_ENV, "").strip().lower() == "torch":
        return "torch"
    if device == "cpu" or (device == "auto" and gpu_driver_absent()):
        return "numpy"
    return "torch"


def inference_setup(device: str) -> str:
    """``inference_backend(device)``, and for ``numpy`` one BLAS thread per caller, set before numpy
    loads (``OPENBLAS_NUM_THREADS``, unless already set): numpy's and scipy's OpenBLAS each keep
    a pool of spinning threads, and on 2 cores the two pools starve each other (the crane
    ``complete`` took over 25 s, pcow's ``predict`` 5.1 s against 1.5 s with one thread). The
    numpy inference splits its own work over threads (``meshseq.numpy_net``)."""
    backend = inference_backend(device)
    if backend == "numpy" and "numpy" not in sys.modules:
        os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
    return backend
