"""meshseq installed as a user of a package index gets it: a wheel, installed non-editable.

One test, about two minutes (most of it compiling the C++ kernels once, from the wheel's files):

1. builds the wheel from a copy of the project (pyproject.toml, README.md, src/; offline:
   ``pip wheel --no-deps --no-build-isolation --no-index``) and checks that it carries every file
   of ``src/meshseq/csrc`` (the kernels' sources and the header they include);
2. installs it, ``--no-deps``, into a fresh virtual environment whose dependencies (torch, numpy,
   ...) are borrowed from the running one by a ``.pth`` line (its site-packages folder as a plain
   path: the running environment's editable ``meshseq`` is not put on the path);
3. from a folder outside the repository, with ``TORCH_EXTENSIONS_DIR`` empty, checks that
   ``import meshseq`` is the installed copy and that a ``meshseq train`` step runs the compiled
   ``meshseq::`` operators (torch's profiler sees them), built from the installed ``csrc``.

Nothing here skips: a missing compiler, ninja or file fails the test.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import sysconfig
import zipfile
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parent.parent

#: run by the installed environment's python, from outside the repository: argv[1] the data,
#: argv[2] the run folder; prints one JSON line
CHILD = r"""
import json, sys
from torch.profiler import ProfilerActivity, profile
import meshseq, meshseq.cli, meshseq.kernels as kernels
with profile(activities=[ProfilerActivity.CPU]) as prof:
    status = meshseq.cli.main(["train", sys.argv[1], "--out", sys.argv[2], "--iterations", "2",
                               "--threads", "1", "--no-progress"])
print(json.dumps({"meshseq": meshseq.__file__, "csrc": str(kernels._CSRC), "status": status,
                  "compiled": kernels._cpu_kernels,
                  "ops": sorted({e.key for e in prof.key_averages() if e.key.startswith("meshseq::")})}))
"""


def _copy_project(dest: Path) -> Path:
    """What a source distribution holds: pyproject.toml, README.md and src/ (no caches)."""
    dest.mkdir()
    for name in ("pyproject.toml", "README.md"):
        shutil.copy2(REPO_ROOT / name, dest / name)
    shutil.copytree(REPO_ROOT / "src", dest / "src", ignore=shutil.ignore_patterns("__pycache__", "*.egg-info"))
    return dest


def _run(cmd: list, **kw) -> subprocess.CompletedProcess:
    proc = subprocess.run([str(c) for c in cmd], capture_output=True, text=True, **kw)
    assert proc.returncode == 0, f"{' '.join(map(str, cmd))} failed ({proc.returncode}):\n{proc.stdout}\n{proc.stderr}"
    return proc


def _build_wheel(tmp: Path) -> Path:
    """The project's wheel (built offline with this environment's setuptools)."""
    project = _copy_project(tmp / "project")
    _run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "--no-index",
          "--quiet", project, "-w", tmp / "wheel"])
    (wheel,) = (tmp / "wheel").glob("meshseq-*.whl")
    return wheel


def _fresh_venv(tmp: Path) -> tuple[Path, Path]:
    """A new virtual environment that sees this one's packages but not its meshseq: (python, site-packages)."""
    venv = tmp / "venv"
    _run([sys.executable, "-m", "venv", "--without-pip", venv])
    python = venv / "bin" / "python"
    site = Path(_run([python, "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"]).stdout.strip())
    # a plain path: the .pth files in it (this environment's editable meshseq) are not read
    (site / "borrowed-dependencies.pth").write_text(sysconfig.get_paths()["purelib"] + "\n")
    import ninja  # the build tool pip would have installed beside the console script (a dependency)

    (venv / "bin" / "ninja").symlink_to(Path(ninja.BIN_DIR) / "ninja")
    return python, site


def test_wheel_installs_and_trains_on_the_compiled_kernels(tmp_path):
    from meshseq.data.synthetic import twisting_limb
    from meshseq.io import save_sequence

    wheel = _build_wheel(tmp_path)
    shipped = set(zipfile.ZipFile(wheel).namelist())
    csrc = sorted(p.name for p in (REPO_ROOT / "src" / "meshseq" / "csrc").iterdir() if p.is_file())
    missing = [name for name in csrc if f"meshseq/csrc/{name}" not in shipped]
    assert not missing, f"the wheel lacks csrc files the kernels need: {missing}"

    python, site = _fresh_venv(tmp_path)
    _run([sys.executable, "-m", "pip", "--python", python, "install", "--no-deps", "--no-index",
          "--ignore-installed", "--quiet", wheel])
    assert (site / "meshseq" / "csrc" / "simd.h").is_file()

    work = tmp_path / "work"  # the working folder: outside the repository
    assert not work.is_relative_to(REPO_ROOT)
    work.mkdir()
    save_sequence(twisting_limb(frames=30, rings=8, segments=6), work / "limb.npz")
    env = {k: v for k, v in os.environ.items()
           if k not in ("PYTHONPATH", "PYTHONHOME", "PYTHONSTARTUP", "MESHSEQ_CPU_KERNELS", "VIRTUAL_ENV")}
    extensions = tmp_path / "torch_extensions"
    env.update(TORCH_EXTENSIONS_DIR=str(extensions), OMP_NUM_THREADS="1",
               PATH=f"{python.parent}{os.pathsep}{env.get('PATH', '')}")

    help_text = _run([python.parent / "meshseq", "--help"], cwd=work, env=env).stdout
    assert "train" in help_text
    out = _run([python, "-c", CHILD, "limb.npz", "run"], cwd=work, env=env, timeout=900).stdout
    report = json.loads(out.strip().splitlines()[-1])

    assert Path(report["meshseq"]).is_relative_to(site), f"imported {report['meshseq']}, not the installed copy"
    assert Path(report["csrc"]) == site / "meshseq" / "csrc"
    assert report["status"] == 0 and (work / "run").is_dir()
    assert report["compiled"] is True, "the kernels were not built: training fell back to the torch-op path"
    assert {"meshseq::conv_forward", "meshseq::lstm_forward"} <= set(report["ops"]), report["ops"]
    (ninja_file,) = extensions.glob("meshseq_kernels-*/build.ninja")
    assert f"{site}/meshseq/csrc/mesh_conv.cpp" in ninja_file.read_text(), "not compiled from the installed sources"
