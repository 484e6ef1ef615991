"""Checkpoints: safetensors for tensors, JSON for everything else; atomic; never unpickled.

A run folder ``RUN`` holds ``RUN/checkpoints/ITERATION/`` (zero-padded) folders, each with

* ``model.safetensors``: ``model.<name>`` weights of the generator (with ``ema_decay``: their
  moving average, the delivered model), ``reference.vertices``
  ``(V, 3)`` float64 and ``reference.faces`` ``(F, 3)`` int64 (the mesh the features refer to, so
  features can be turned back into vertices without the training data), and ``novelty.latents``
  ``(N, L)`` float32 (the delivered model's latent means of the training frames: prediction's
  novelty guard, ``meshseq.novelty``; runs stored before it lack it) and ``novelty.steps`` alike
  (each one's latent step from the training frame before it; runs stored before them lack them);
* ``model.json``: format, iteration, model config, training config, feature scaling, mesh
  topology hash, data set names and splits, the novelty reference's step, frame count and whether
  it keeps the steps, and the SHA-256 of ``model.safetensors``;
* ``state.safetensors``: Adam moments ``optim.<param name>.<key>``, the torch CPU generator state
  ``rng.torch`` (uint8) and, on CUDA, ``rng.cuda``; under DistributedDataParallel every other
  process's as ``rng.torch.rank<R>`` / ``rng.cuda.rank<R>`` (each rank draws its own noise);
  with ``ema_decay``, ``train.<param name>``: the weights training continues from;
* ``state.json``: Adam step counts and hyper-parameters, the numpy bit-generator state (common to
  all ranks), Python's ``random`` state, the number of processes and the SHA-256 of
  ``state.safetensors``.

Reading goes through :func:`load_folder` only, which checks everything against
``meshseq.checkpoint_schema`` (JSON fields and types, tensor names, shapes, dtypes, finite
values): a damaged or edited checkpoint is one MeshseqError naming the file and the field. A run's
newest usable checkpoint is :func:`load_latest`; damaged ones never count toward ``keep``.

A run trained with a validation block (``meshseq train --validation``) also keeps
``RUN/checkpoints/best/``: a checkpoint like the others (the one with the lowest validation error
so far; its model.json records ``validation: {error, iteration}``), never pruned and never what
``--resume`` continues from.

A checkpoint folder is written under a temporary name and renamed into place
(``meshseq.io.atomic_output``) after its files are flushed to disk, so a run killed at any moment
leaves complete checkpoints only (plus, perhaps, a ``.tmp-*`` folder that the next save removes).
``model.*`` alone is what ``meshseq.load`` needs: a shareable model.
"""

from __future__ import annotations

import hashlib
import json
import os
import random
import re
import shutil
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from meshseq.checkpoint_schema import FORMAT, FORMAT_VERSION
from meshseq.errors import MeshseqError, MeshseqWarning
from meshseq.io import atomic_output
from meshseq.mesh import topology_hash
from meshseq.model_config import ModelConfig
from meshseq.novelty import NoveltyReference

MODEL_TENSORS, MODEL_META = "model.safetensors", "model.json"
STATE_TENSORS, STATE_META = "state.safetensors", "state.json"
_DIR_RE = re.compile(r"^\d{8}$")
BEST = "best"  # the folder of a run's best checkpoint on its validation block
#: what ``load_folder`` builds the generator as: the torch module, or numpy inference (no torch)
BACKENDS = ("torch", "numpy")


def is_checkpoint_name(name: str) -> bool:
    """Whether ``name`` is a checkpoint folder's name (the zero-padded iteration)."""
    return bool(_DIR_RE.match(name))


def checkpoint_root(run_dir: str | os.PathLike) -> Path:
    return Path(run_dir) / "checkpoints"


def _write_bytes(path: Path, data: bytes) -> None:
    with open(path, "wb") as fh:
        fh.write(data)
        fh.flush()
        os.fsync(fh.fileno())


def _write_json(path: Path, obj: dict) -> None:
    _write_bytes(path, (json.dumps(obj, indent=1, sort_keys=True) + "\n").encode())


def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def _fsync_dir(path: Path) -> None:
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def _contiguous(tensors: dict) -> dict:
    return {k: v.detach().contiguous().cpu() for k, v in tensors.items()}


def save_checkpoint(
    run_dir: str | os.PathLike,
    iteration: int,
    model_tensors: dict,
    model_meta: dict,
    state_tensors: dict,
    state_meta: dict,
    keep: int = 2,
    name: str | None = None,
) -> Path:
    """Write ``RUN/checkpoints/<iteration>/`` atomically; keep the newest ``keep`` checkpoints.

    Returns the checkpoint folder. An existing folder of the same iteration is replaced. Only
    complete, undamaged checkpoints count toward ``keep`` (a damaged one is left alone), and a
    non-finite tensor is refused (MeshseqError) before anything is written. ``name`` (e.g.
    ``BEST``): write ``RUN/checkpoints/<name>/`` instead, replacing it, and prune nothing.
    """
    import torch
    from safetensors.torch import save

    for what, tensors in (("model", model_tensors), ("training state", state_tensors)):
        for key, t in tensors.items():
            if t.is_floating_point() and not bool(torch.isfinite(t).all()):
                raise MeshseqError(f"not writing checkpoint {int(iteration)}: {what} tensor {key} is not finite")
    root = checkpoint_root(run_dir)
    root.mkdir(parents=True, exist_ok=True)
    for pattern in (".tmp-*", ".old-*"):  # left by a killed run
        for stale in root.glob(pattern):
            shutil.rmtree(stale, ignore_errors=True)
    final = root / (name or f"{int(iteration):08d}")
    with atomic_output(final, force=True) as tmp:
        tmp.mkdir()
        _write_bytes(tmp / MODEL_TENSORS, save(_contiguous(model_tensors)))
        meta = dict(model_meta, format=FORMAT, format_version=FORMAT_VERSION, iteration=int(iteration))
        meta["sha256"] = _sha256(tmp / MODEL_TENSORS)
        _write_json(tmp / MODEL_META, meta)
        _write_bytes(tmp / STATE_TENSORS, save(_contiguous(state_tensors)))
        smeta = dict(state_meta, iteration=int(iteration), sha256=_sha256(tmp / STATE_TENSORS))
        _write_json(tmp / STATE_META, smeta)
        _fsync_dir(tmp)
    _fsync_dir(root)
    if name:
        return final
    kept = [f for f in list_checkpoints(run_dir) if f == final or is_valid(f)]
    for old in kept[:-keep] if keep > 0 else []:
        if old != final:
            # rename first (atomic), then delete: a kill mid-delete must not leave a partial
            # folder under a checkpoint's name
            doomed = root / f".old-{old.name}-{os.getpid()}"
            os.replace(old, doomed)
            shutil.rmtree(doomed, ignore_errors=True)
    return final


def add_model_meta(folder: str | os.PathLike, fields: dict) -> None:
    """Add ``fields`` to the model.json of checkpoint ``folder`` (replaced atomically; its tensors, and
    so their SHA-256, untouched): what training fits from the finished model."""
    from meshseq.checkpoint_schema import check_model_meta

    path = Path(folder) / MODEL_META
    meta = {**_read_json(path), **fields}
    check_model_meta(meta, path)
    with atomic_output(path, force=True) as tmp:
        _write_json(tmp, meta)


def list_checkpoints(run_dir: str | os.PathLike) -> list[Path]:
    """Checkpoint folders of a run, oldest first (by iteration)."""
    root = checkpoint_root(run_dir)
    if not root.is_dir():
        return []
    return sorted(p for p in root.iterdir() if p.is_dir() and _DIR_RE.match(p.name))


def _read_json(path: Path):
    try:
        return json.loads(path.read_text())
    except FileNotFoundError:
        raise MeshseqError(f"{path}: missing (not a meshseq checkpoint)") from None
    except (json.JSONDecodeError, UnicodeDecodeError, RecursionError) as err:
        raise MeshseqError(f"{path}: not valid JSON ({' '.join(str(err).split())})") from None
    except OSError as err:
        raise MeshseqError(f"{path}: cannot read ({err.strerror or err})") from None


def _read_tensors(path: Path, meta: dict, meta_name: str, backend: str = "torch") -> dict:
    """The tensors of ``path`` (torch tensors, or numpy arrays for ``backend="numpy"``) if its
    SHA-256 is the one ``meta`` (already schema-checked) records."""
    if backend == "numpy":
        from safetensors.numpy import load_file
    else:
        from safetensors.torch import load_file
    if not path.is_file():
        raise MeshseqError(f"{path}: missing")
    if meta["sha256"] != _sha256(path):
        raise MeshseqError(f"{path}: contents do not match the SHA-256 in {meta_name}")
    try:
        return load_file(str(path))
    except Exception as err:  # SafetensorError, or OSError / ValueError / others from a damaged header
        first = (str(err).splitlines() or [type(err).__name__])[0]
        raise MeshseqError(f"{path}: not a safetensors file ({first})") from None


@dataclass
class Loaded:
    """A checkpoint that passed every check of ``meshseq.checkpoint_schema``.

    ``folder``; ``meta``: model.json; ``net``: a CPU ``BDLSTM`` holding the stored weights;
    ``reference`` ``(V, 3)`` float64 and ``faces`` ``(F, 3)`` int64: the stored mesh;
    ``state_meta``/``state_tensors``: state.json and state.safetensors (None unless asked for);
    ``novelty``: the training frames' latents (``meshseq.novelty``), None for a run stored without.
    """

    folder: Path
    meta: dict
    net: object
    reference: np.ndarray
    faces: np.ndarray
    state_meta: dict | None = None
    state_tensors: dict | None = None
    novelty: NoveltyReference | None = None

    def __repr__(self) -> str:
        return f"Loaded({str(self.folder)!r}, iteration={self.meta['iteration']})"


def load_folder(folder: str | os.PathLike, with_state: bool = False, backend: str = "torch") -> Loaded:
    """Load and check one checkpoint folder (the model part; the training state too if asked).

    ``backend``: ``torch`` (``net`` a CPU ``BDLSTM``) or ``numpy`` (``net`` a
    ``meshseq.numpy_net.NumpyNet``, and torch is not imported; the model part only).
    MeshseqError (one line naming the file and field) if anything is missing, damaged or not
    what the JSON describes, or if a weight is not finite.
    """
    from meshseq import checkpoint_schema as schema

    if backend not in BACKENDS or (with_state and backend != "torch"):
        raise ValueError(f"load_folder: backend {backend!r} (with_state={with_state})")
    folder = Path(folder)
    iteration = int(folder.name) if _DIR_RE.match(folder.name) else None
    meta = _read_json(folder / MODEL_META)
    schema.check_model_meta(meta, folder / MODEL_META, iteration)
    tensors = _read_tensors(folder / MODEL_TENSORS, meta, MODEL_META, backend)
    schema.check_reference(tensors, meta, folder / MODEL_TENSORS)
    schema.check_model_tensors(tensors, meta, folder / MODEL_TENSORS)
    reference = np.asarray(tensors["reference.vertices"])
    faces = np.asarray(tensors["reference.faces"])
    weights = {k[len("model."):]: v for k, v in tensors.items() if k.startswith("model.")}
    net = _build_net(ModelConfig.from_dict(meta["model"], source=str(folder / MODEL_META)), weights, faces,
                     backend)
    loaded = Loaded(folder, meta, net, reference, faces)
    if meta.get("novelty") is not None:
        def array(key: str) -> np.ndarray | None:
            return np.ascontiguousarray(np.asarray(tensors[key]), dtype=np.float32) if key in tensors else None

        loaded.novelty = NoveltyReference(array(schema.NOVELTY_LATENTS), float(meta["novelty"]["step"]),
                                          array(schema.NOVELTY_STEPS))
    if with_state:
        smeta = _read_json(folder / STATE_META)
        schema.check_state_meta(smeta, folder / STATE_META, meta["iteration"])
        stensors = _read_tensors(folder / STATE_TENSORS, smeta, STATE_META)
        schema.check_state_tensors(stensors, smeta, dict(net.named_parameters()), folder / STATE_TENSORS)
        loaded.state_meta, loaded.state_tensors = smeta, stensors
    return loaded


def _build_net(config: ModelConfig, weights: dict, faces: np.ndarray, backend: str):
    """The generator of ``config`` holding ``weights`` (checked): a ``BDLSTM`` or a ``NumpyNet``."""
    from meshseq.mesh import Topology

    topology = Topology.from_faces(faces, config.n_vertices)
    if backend == "numpy":
        from meshseq.numpy_net import NumpyNet, ring_matrix

        return NumpyNet(config, weights, ring_matrix(topology))
    import torch

    from meshseq.model import BDLSTM

    # the random initial weights are overwritten below: draw them from a forked generator, so
    # loading (e.g. checking an older checkpoint while training) leaves the caller's noise alone
    with torch.random.fork_rng(devices=[]):
        net = BDLSTM(config, topology)
    net.load_state_dict(weights)
    return net


def is_valid(folder: Path) -> bool:
    """Whether ``folder`` is a complete, undamaged checkpoint (model and training state)."""
    try:
        load_folder(folder, with_state=True)
    except MeshseqError:
        return False
    return True


def load_latest(run_dir: str | os.PathLike, with_state: bool = False, backend: str = "torch") -> Loaded:
    """The newest usable checkpoint of a run; a damaged newer one is skipped with a warning.

    MeshseqError if the run has no checkpoint, or none is usable (naming the newest's problem).
    """
    loaded, skipped = _newest(run_dir, lambda folder: load_folder(folder, with_state, backend))
    for err in skipped:
        warnings.warn(f"damaged checkpoint skipped: {err}", MeshseqWarning)
    return loaded


def latest_meta(run_dir: str | os.PathLike) -> dict:
    """The checked model.json of a run's newest checkpoint whose model.json reads (the weights are not
    read: every checkpoint of a run stores the same model, mesh and feature options, so this is what
    a run is, not which checkpoint ``load_latest`` would pick). MeshseqError if there is none."""
    from meshseq import checkpoint_schema as schema

    def read(folder: Path) -> dict:
        meta = _read_json(folder / MODEL_META)
        schema.check_model_meta(meta, folder / MODEL_META, int(folder.name))
        return meta

    return _newest(run_dir, read)[0]


def _newest(run_dir: str | os.PathLike, read):
    """``(read(folder), problems)``: ``read`` of a run's newest checkpoint folder it succeeds on, and
    the MeshseqErrors of the newer ones it failed on; MeshseqError if the run has no checkpoint or
    ``read`` fails on every one (naming the newest's problem)."""
    folders = list_checkpoints(run_dir)
    if not folders:
        raise MeshseqError(f"{run_dir}: no checkpoint in {checkpoint_root(run_dir)}")
    problems = []
    for folder in reversed(folders):
        try:
            return read(folder), problems
        except MeshseqError as err:
            problems.append(err)
    raise MeshseqError(f"{run_dir}: every checkpoint is damaged (the newest: {problems[0]})")


def best_folder(run_dir: str | os.PathLike) -> Path:
    """Where a run keeps its best checkpoint on its validation block (it may not exist)."""
    return checkpoint_root(run_dir) / BEST


def best_validation(run_dir: str | os.PathLike) -> dict | None:
    """``{"error", "iteration"}`` of a run's best checkpoint, or None if it has none (a damaged
    one is warned about and counts as none: the next validation writes a new one)."""
    folder = best_folder(run_dir)
    if not folder.exists():
        return None
    try:
        meta = load_folder(folder).meta
    except MeshseqError as err:
        warnings.warn(f"damaged best checkpoint ignored: {err}", MeshseqWarning)
        return None
    return meta.get("validation")


def latest_checkpoint(run_dir: str | os.PathLike) -> Path | None:
    """The newest complete checkpoint folder of a run (a damaged newer one is skipped, with a
    warning), or None if there is none."""
    try:
        return load_latest(run_dir, with_state=True).folder
    except MeshseqError:
        return None


def load(path: str | os.PathLike, backend: str = "torch") -> Loaded:
    """The model part of a checkpoint folder, or of a run folder's newest usable checkpoint
    (``backend``: see ``load_folder``)."""
    p = Path(path)
    if (p / MODEL_META).is_file():
        return load_folder(p, backend=backend)
    if not p.exists():
        raise MeshseqError(f"{p}: no such run or checkpoint folder")
    return load_latest(p, backend=backend)


def resolve(path: str | os.PathLike) -> Path:
    """A run folder (-> its latest usable checkpoint) or a checkpoint folder -> the checkpoint folder."""
    p = Path(path)
    return p if (p / MODEL_META).is_file() else load(p).folder


def check_topology(meta: dict, faces: np.ndarray, n_vertices: int, what: str = "the mesh") -> None:
    """MeshseqError unless ``faces``/``n_vertices`` have the connectivity the checkpoint was trained on."""
    topo = meta["topology"]
    got = topology_hash(faces, n_vertices)
    if got != topo["hash"]:
        raise MeshseqError(
            f"{what} has another connectivity than the checkpoint's mesh "
            f"({n_vertices} vertices, {len(faces)} faces, hash {got}; the checkpoint expects "
            f"{topo['n_vertices']} vertices, {topo['n_faces']} faces, hash {topo['hash']})"
        )


# --------------------------------------------------------------------------------------------
# optimizer and RNG state <-> (tensors, JSON)


def optimizer_state(optimizer: torch.optim.Optimizer, names: list[str]) -> tuple[dict, dict]:
    """Flatten an optimizer's state: tensors ``optim.<name>.<key>`` and JSON (scalars, groups).

    ``names[i]`` is the name of the optimizer's i-th parameter (in param_groups order).
    """
    import torch

    sd = optimizer.state_dict()
    tensors, scalars = {}, {}
    for idx, st in sd["state"].items():
        name = names[idx]
        for key, val in st.items():
            if torch.is_tensor(val) and val.dim() > 0:
                tensors[f"optim.{name}.{key}"] = val
            else:
                scalars.setdefault(name, {})[key] = float(val.item() if torch.is_tensor(val) else val)
    groups = [{k: v for k, v in g.items() if k != "params"} | {"params": [names[i] for i in g["params"]]}
              for g in sd["param_groups"]]
    return tensors, {"scalars": scalars, "param_groups": groups}


def load_optimizer_state(optimizer: torch.optim.Optimizer, names: list[str], tensors: dict, meta: dict) -> None:
    """Inverse of :func:`optimizer_state` (tensors moved to each parameter's device)."""
    import torch

    index = {n: i for i, n in enumerate(names)}
    params = [p for g in optimizer.param_groups for p in g["params"]]
    state: dict = {}
    for key, val in tensors.items():
        if not key.startswith("optim."):
            continue
        name, sub = key[len("optim.") :].rsplit(".", 1)
        if name not in index:
            raise MeshseqError(f"optimizer state names unknown parameter {name!r}")
        state.setdefault(index[name], {})[sub] = val.to(params[index[name]].device)
    for name, sc in meta["scalars"].items():
        for sub, val in sc.items():
            # torch keeps Adam's step as a float32 tensor (on CPU unless capturable/fused)
            state.setdefault(index[name], {})[sub] = torch.tensor(val, dtype=torch.float32)
    groups = []
    for g in meta["param_groups"]:
        g = dict(g)
        g["params"] = [index[n] for n in g["params"]]
        if "betas" in g:
            g["betas"] = tuple(g["betas"])
        groups.append(g)
    optimizer.load_state_dict({"state": state, "param_groups": groups})


def training_weights(state_tensors: dict) -> dict:
    """The weights training continues from, stored as ``train.<name>`` in the training state
    behind a weight average (``ema_decay``): ``{name: tensor}``, empty for runs without one."""
    return {k[len("train."):]: v for k, v in state_tensors.items() if k.startswith("train.")}


def rng_key(kind: str, rank: int = 0) -> str:
    """Tensor name of a generator state (``kind`` torch or cuda): ``rng.torch`` for rank 0 and
    single-process runs, ``rng.torch.rank<R>`` for the other processes of a distributed run."""
    return f"rng.{kind}" if rank == 0 else f"rng.{kind}.rank{rank}"


def rng_state() -> tuple[dict, dict]:
    """Torch (CPU, and CUDA if initialised) generator states as tensors; Python's as JSON."""
    import torch

    tensors = {"rng.torch": torch.get_rng_state()}
    if torch.cuda.is_available() and torch.cuda.is_initialized():
        tensors["rng.cuda"] = torch.cuda.get_rng_state()
    version, internal, gauss = random.getstate()
    return tensors, {"python_random": [version, list(internal), gauss]}


def set_rng_state(tensors: dict, meta: dict, rank: int = 0) -> bool:
    """Restore this process's generators (``rank``'s torch and CUDA states, Python's); False if
    the checkpoint has no torch state for ``rank`` (it was written by fewer processes)."""
    import torch

    if "python_random" in meta:
        version, internal, gauss = meta["python_random"]
        random.setstate((version, tuple(internal), gauss))
    if rng_key("torch", rank) not in tensors:
        return False
    torch.set_rng_state(tensors[rng_key("torch", rank)].cpu())
    if rng_key("cuda", rank) in tensors and torch.cuda.is_available():
        torch.cuda.set_rng_state(tensors[rng_key("cuda", rank)].cpu())
    return True
