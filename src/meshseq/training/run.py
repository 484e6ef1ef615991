"""What surrounds the loop: the processes (torchrun's distributed data parallel), the run folder
(``--force``, ``--resume``), metrics (``RUN/metrics.csv``, TensorBoard) and the progress bar.

Distributed: started by ``torchrun`` (env ``RANK``/``WORLD_SIZE``/``MASTER_ADDR``...), every
process joins a process group (NCCL on CUDA, Gloo on CPU) and trains a
``DistributedDataParallel`` copy; all ranks draw the same global batch of ``batch`` windows and
each takes its ``batch / world_size`` share, so a step sees the same windows as a single process
would. Rank 0 writes metrics and checkpoints, which hold every rank's generator state, so a
resume repeats a multi-process run bit for bit (on CPU).
"""

from __future__ import annotations

import csv
import gc
import io as _io
import os
import sys
from dataclasses import dataclass
from pathlib import Path

import torch

from meshseq import checkpoint as ckpt
from meshseq.device import resolve_device
from meshseq.errors import MeshseqError
from meshseq.kernels import keep_freed_memory

METRIC_FIELDS = ("iteration", "seconds", "loss", "rec", "bd", "kl", "l2", "motion", "vertex", "latent_spread",
                 "latent_rms", "latent_sigma", "grad_norm", "clipped", "heldout_rec", "heldout_bd",
                 "validation")



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



def start_processes(device: str) -> tuple[torch.device, Dist]:
    """The device this process trains on and its place among torchrun's processes (``Dist()``
    alone): under torchrun on CUDA each process takes the GPU of its local rank."""
    dev = resolve_device(device)
    dist_info = init_distributed(dev)
    if dev.type == "cuda" and dist_info.active:
        dev = torch.device("cuda", dist_info.local_rank)
        torch.cuda.set_device(dev)
    if dev.type == "cpu":
        keep_freed_memory()  # reuse freed step-sized blocks instead of page-faulting fresh ones
    return dev, dist_info


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



def prepare_run_dir(run_dir: Path, resume: bool, force: bool) -> None:
    """Make ``run_dir`` ready for a run: MeshseqError if it holds one and neither ``resume`` nor
    ``force`` is given; ``force`` removes what training wrote there (``remove_run_outputs``)."""
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
        raise _resume_error(run_dir, err) from None


def resume_meta(run_dir: Path) -> dict:
    """model.json of the run ``--resume`` continues (``checkpoint.latest_meta``: its model and feature
    options, the weights not read); the same MeshseqError as ``resume_point`` if there is none."""
    try:
        return ckpt.latest_meta(run_dir)
    except MeshseqError as err:
        raise _resume_error(run_dir, err) from None


def _resume_error(run_dir: Path, err: MeshseqError) -> MeshseqError:
    hint = ("leave out --resume to start a new run" if not ckpt.list_checkpoints(run_dir)
            else "use --force without --resume to start over")
    return MeshseqError(f"--resume: {err}; {hint}")


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



def stderr_log(msg: str) -> None:
    print(f"meshseq: {msg}", file=sys.stderr)



def terms_text(row: dict) -> str:
    keys = ("loss", "rec", "bd", "kl", "l2", "latent_spread", "heldout_rec")
    return " ".join(f"{k}={row[k]:.4g}" for k in keys if row.get(k) is not None)


def progress_bar(total: int):
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
