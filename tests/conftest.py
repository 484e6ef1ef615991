"""Shared pytest fixtures.

``shared_data`` locates the team's real data folder (``../shared/data`` relative to the repo
root, or ``$MESHSEQ_SHARED_DATA``). A test that needs it FAILS (never skips) when it is missing.
"""

from __future__ import annotations

import contextlib
import importlib.util
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

REPO_ROOT = Path(__file__).resolve().parent.parent


def shared_data_dir() -> Path:
    """Path of the shared data folder; ``pytest.fail`` with a clear message if it is missing."""
    override = os.environ.get("MESHSEQ_SHARED_DATA")
    path = Path(override) if override else REPO_ROOT.parent / "shared" / "data"
    if not path.is_dir():
        pytest.fail(
            f"shared data folder not found: {path} (set MESHSEQ_SHARED_DATA to the folder holding "
            "horse-gallop.npz, crane.npz, pcow.npz)",
            pytrace=False,
        )
    return path


def shared_file(name: str) -> Path:
    """Path of one file in the shared data folder, e.g. ``shared_file("crane.npz")``; fails if missing."""
    path = shared_data_dir() / name
    if not path.is_file():
        pytest.fail(f"shared data file not found: {path}", pytrace=False)
    return path


@pytest.fixture
def shared_data() -> Path:
    """The shared data folder (``../shared/data``); the test fails if it is missing."""
    return shared_data_dir()


def benchmark_script(name: str):
    """The module of ``benchmarks/NAME.py`` (its sibling scripts importable, as when it runs)."""
    folder = str(REPO_ROOT / "benchmarks")
    if folder not in sys.path:
        sys.path.insert(0, folder)
    spec = importlib.util.spec_from_file_location(f"{name}_benchmark", REPO_ROOT / "benchmarks" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@contextlib.contextmanager
def torch_threads(n: int = 1):
    """Run the block on ``n`` torch threads, then restore the previous count."""
    import torch

    before = torch.get_num_threads()
    torch.set_num_threads(n)
    try:
        yield
    finally:
        torch.set_num_threads(before)


@pytest.fixture
def one_torch_thread():
    """Tiny models run fastest, and steadiest on a shared machine, on one torch thread."""
    with torch_threads(1):
        yield


def training_data(seq, features=None):
    """``TrainingData`` of one sequence: its ACAP features (extracted unless given), its first
    frame as the reference mesh."""
    from meshseq import acap
    from meshseq.train import TrainingData

    feats = acap.extract(seq.vertices, seq.faces) if features is None else features
    return TrainingData([seq.name], [seq.source], [feats], seq.faces, seq.vertices[0])


def run_blender(client: Path, args: list[str], timeout: float, extra_env: dict | None = None) -> str:
    """Run ``client`` in headless Blender (``-b --factory-startup``) with ``args`` after ``--``;
    returns its stdout. The test FAILS if Blender is missing or the client does not print
    BLENDER_CLIENT_OK.

    Blender runs its own Python with Debian's numpy: this test run's virtual environment (an
    activated venv's PATH, VIRTUAL_ENV, PYTHONPATH) is kept out of it, or it imports the venv's numpy.
    """
    exe = shutil.which("blender")
    if exe is None:
        pytest.fail("blender is not installed (Debian package blender); run tools/install_test_deps.sh",
                    pytrace=False)
    env = {k: v for k, v in os.environ.items() if k not in ("VIRTUAL_ENV", "PYTHONPATH", "PYTHONHOME")}
    venv = os.environ.get("VIRTUAL_ENV")
    if venv:
        env["PATH"] = os.pathsep.join(p for p in env.get("PATH", "").split(os.pathsep)
                                      if not p.startswith(venv))
    env.update(extra_env or {})
    proc = subprocess.run([exe, "-b", "--factory-startup", "--python-exit-code", "1", "--python", str(client),
                           "--", *args], capture_output=True, text=True, timeout=timeout, env=env)
    assert proc.returncode == 0 and "BLENDER_CLIENT_OK" in proc.stdout, proc.stdout[-3000:] + proc.stderr[-3000:]
    return proc.stdout
