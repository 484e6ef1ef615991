"""Checkpoints: safetensors for tensors, JSON for everything else; atomic; never unpickled.

A run folder ``RUN`` holds ``RUN/checkpoints/ITERATION/`` (zero-padded) folders, each with

* ``model.safetensors``: ``model.<name>`` weights of the generator, ``reference.vertices``
  ``(V, 3)`` float64 and ``reference.faces`` ``(F, 3)`` int64 (the mesh the features refer to, so
  features can be turned back into vertices without the training data);
* ``model.json``: format, iteration, model config, training config, feature scaling, mesh
  topology hash, data set names and splits, and the SHA-256 of ``model.safetensors``;
* ``state.safetensors``: Adam moments ``optim.<param name>.<key>``, the torch CPU generator state
  ``rng.torch`` (uint8) and, on CUDA, ``rng.cuda``;
* ``state.json``: Adam step counts and hyper-parameters, the numpy bit-generator state, Python's
  ``random`` state and the SHA-256 of ``state.safetensors``.

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
from pathlib import Path

import numpy as np
import torch
from safetensors.torch import load_file, save

from meshseq.errors import MeshseqError, MeshseqWarning
from meshseq.io import atomic_output
from meshseq.mesh import topology_hash

FORMAT = "meshseq-bdlstm-checkpoint"
FORMAT_VERSION = 1
MODEL_TENSORS, MODEL_META = "model.safetensors", "model.json"
STATE_TENSORS, STATE_META = "state.safetensors", "state.json"
_DIR_RE = re.compile(r"^\d{8}$")


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
) -> Path:
    """Write ``RUN/checkpoints/<iteration>/`` atomically; keep the newest ``keep`` checkpoints.

    Returns the checkpoint folder. An existing folder of the same iteration is replaced.
    """
    root = checkpoint_root(run_dir)
    root.mkdir(parents=True, exist_ok=True)
    for pattern in (".tmp-*", ".old-*"):  # left by a killed run
        for stale in root.glob(pattern):
            shutil.rmtree(stale, ignore_errors=True)
    final = root / f"{int(iteration):08d}"
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
    for old in list_checkpoints(run_dir)[:-keep] if keep > 0 else []:
        if old != final:
            # rename first (atomic), then delete: a kill mid-delete must not leave a partial
            # folder under a checkpoint's name
            doomed = root / f".old-{old.name}-{os.getpid()}"
            os.replace(old, doomed)
            shutil.rmtree(doomed, ignore_errors=True)
    return final


def list_checkpoints(run_dir: str | os.PathLike) -> list[Path]:
    """Checkpoint folders of a run, oldest first (by iteration)."""
    root = checkpoint_root(run_dir)
    if not root.is_dir():
        return []
    return sorted(p for p in root.iterdir() if p.is_dir() and _DIR_RE.match(p.name))


def _read_meta(folder: Path, meta_name: str, tensor_name: str) -> dict:
    try:
        meta = json.loads((folder / meta_name).read_text())
    except FileNotFoundError:
        raise MeshseqError(f"{folder / meta_name}: missing (not a meshseq checkpoint)") from None
    except (json.JSONDecodeError, UnicodeDecodeError, RecursionError) as err:
        raise MeshseqError(f"{folder / meta_name}: not valid JSON ({' '.join(str(err).split())})") from None
    except OSError as err:
        raise MeshseqError(f"{folder / meta_name}: cannot read ({err.strerror or err})") from None
    if not isinstance(meta, dict):
        raise MeshseqError(f"{folder / meta_name}: expected a JSON object, found {type(meta).__name__}")
    if not (folder / tensor_name).is_file():
        raise MeshseqError(f"{folder / tensor_name}: missing")
    if meta.get("sha256") != _sha256(folder / tensor_name):
        raise MeshseqError(f"{folder / tensor_name}: contents do not match the SHA-256 in {meta_name}")
    return meta


def is_valid(folder: Path) -> bool:
    try:
        _read_meta(folder, MODEL_META, MODEL_TENSORS)
        _read_meta(folder, STATE_META, STATE_TENSORS)
    except MeshseqError:
        return False
    return True


def latest_checkpoint(run_dir: str | os.PathLike) -> Path | None:
    """The newest complete checkpoint folder of a run (a damaged newer one is skipped, with a warning)."""
    for folder in reversed(list_checkpoints(run_dir)):
        if is_valid(folder):
            return folder
        warnings.warn(f"{folder}: damaged checkpoint skipped", MeshseqWarning)
    return None


def resolve(path: str | os.PathLike) -> Path:
    """A run folder (-> its latest checkpoint) or a checkpoint folder -> the checkpoint folder."""
    p = Path(path)
    if (p / MODEL_META).is_file():
        return p
    if not p.exists():
        raise MeshseqError(f"{p}: no such run or checkpoint folder")
    found = latest_checkpoint(p)
    if found is None:
        raise MeshseqError(f"{p}: no complete checkpoint in {checkpoint_root(p)}")
    return found


def read_model(path: str | os.PathLike, device="cpu") -> tuple[dict, dict]:
    """``(meta, tensors)`` of the model part of a checkpoint (run folder or checkpoint folder)."""
    folder = resolve(path)
    meta = _read_meta(folder, MODEL_META, MODEL_TENSORS)
    if meta.get("format") != FORMAT:
        raise MeshseqError(f"{folder / MODEL_META}: not a {FORMAT} file")
    version = meta.get("format_version", 0)
    if not isinstance(version, int) or isinstance(version, bool):
        raise MeshseqError(f"{folder / MODEL_META}: format_version {version!r} is not an integer")
    if version > FORMAT_VERSION:
        raise MeshseqError(f"{folder / MODEL_META}: format version {meta['format_version']} is newer than this meshseq")
    return meta, _load_tensors(folder / MODEL_TENSORS, device)


def read_state(folder: str | os.PathLike, device="cpu") -> tuple[dict, dict]:
    """``(meta, tensors)`` of the training-state part of a checkpoint folder."""
    folder = Path(folder)
    meta = _read_meta(folder, STATE_META, STATE_TENSORS)
    return meta, _load_tensors(folder / STATE_TENSORS, device)


def _load_tensors(path: Path, device) -> dict:
    """The tensors of a safetensors file; MeshseqError (one line) if it cannot be parsed."""
    try:
        return load_file(str(path), device=str(device))
    except Exception as err:  # safetensors' SafetensorError, or OSError / ValueError from a damaged header
        raise MeshseqError(f"{path}: cannot read safetensors ({type(err).__name__}: "
                           f"{' '.join(str(err).split())}); damaged checkpoint?") from None


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


def rng_state() -> tuple[dict, dict]:
    """Torch (CPU, and CUDA if initialised) generator states as tensors; Python's as JSON."""
    tensors = {"rng.torch": torch.get_rng_state()}
    if torch.cuda.is_available() and torch.cuda.is_initialized():
        tensors["rng.cuda"] = torch.cuda.get_rng_state()
    version, internal, gauss = random.getstate()
    return tensors, {"python_random": [version, list(internal), gauss]}


def set_rng_state(tensors: dict, meta: dict) -> None:
    torch.set_rng_state(tensors["rng.torch"].cpu())
    if "rng.cuda" in tensors and torch.cuda.is_available():
        torch.cuda.set_rng_state(tensors["rng.cuda"].cpu())
    if "python_random" in meta:
        version, internal, gauss = meta["python_random"]
        random.setstate((version, tuple(internal), gauss))
