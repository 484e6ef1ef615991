"""What a checkpoint must hold: its JSON and its tensors, checked in one place on every load.

``meshseq.checkpoint`` reads a checkpoint only through these checks, so an edited, truncated or
foreign file is one ``MeshseqError`` naming the file and the field, e.g.
``RUN/checkpoints/00000004/model.json: model.latent: expected an integer, got "16"``, never a
traceback from deep inside torch or numpy, and never a model that trains to NaN.

* :func:`check_model_meta` / :func:`check_state_meta`: JSON types by the schemas below
  (``int``; ``float`` = any finite number; ``str``; ``bool``; dicts of fixed keys, ``Opt`` for
  keys older checkpoints lack; lists; ``Each`` for dicts of any keys), then the values as the
  configs check them (``ModelConfig``, ``TrainConfig``), the scaling (a minimum below a maximum per channel),
  the splits, the optimizer's hyper-parameters and the RNG states.
* :func:`check_model_tensors` / :func:`check_state_tensors`: the names, shapes and dtypes the
  model described by the JSON has, finite values, faces inside the vertex range.
"""

from __future__ import annotations

import json
import math
import random
from dataclasses import MISSING, fields
from pathlib import Path

import numpy as np

from meshseq.errors import MeshseqError

#: acap.CONSISTENCY_MODES, kept here so that reading a checkpoint's schema imports no mesh code (a
#: test checks they agree)
CONSISTENCY_MODES = ("temporal-mst", "temporal", "spatial", "greedy")
#: the rotation consistency and placement of checkpoints stored before model.json named theirs
UNNAMED_CONSISTENCY, UNNAMED_PLACEMENT = "temporal", "centroid"

#: what a checkpoint's model.json says it is (``format``) and the newest version this meshseq reads
FORMAT = "meshseq-bdlstm-checkpoint"
FORMAT_VERSION = 1
#: the training frames' latents (``meshseq.novelty``), with ``novelty`` in model.json; optional
NOVELTY_LATENTS = "novelty.latents"
#: each of those latents' step from the training frame before it, with ``novelty.steps`` true; optional
NOVELTY_STEPS = "novelty.steps"


class CheckpointError(MeshseqError):
    """A checkpoint file does not match its schema (a MeshseqError naming file and field)."""

    def __init__(self, file: Path | str, field: str, message: str):
        super().__init__(f"{file}: {field}: {message}" if field else f"{file}: {message}")


class Opt:
    """A dict key that may be absent (written by later meshseq versions than format 1's first)."""

    def __init__(self, spec):
        self.spec = spec


class Each:
    """A dict of any keys whose values all match ``spec``."""

    def __init__(self, spec):
        self.spec = spec


_KINDS = {int: "an integer", float: "a finite number", str: "a string", bool: "true or false",
          None: "null", dict: "an object", list: "a list"}


def _show(value) -> str:
    text = json.dumps(value) if isinstance(value, (int, float, str, bool, type(None))) else type(value).__name__
    text = {"dict": "an object", "list": "a list"}.get(text, text)
    return text if len(text) <= 40 else text[:37] + "..."


def _matches(value, kind) -> bool:
    if kind is None:
        return value is None
    if kind is float:
        return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
    if kind is int:
        return isinstance(value, int) and not isinstance(value, bool)
    return isinstance(value, kind)


def check(value, spec, file, field: str = "") -> None:
    """CheckpointError unless ``value`` (parsed JSON) matches ``spec``; ``field`` is its dotted path."""
    if isinstance(spec, tuple):  # any of
        for alternative in spec:
            try:
                return check(value, alternative, file, field)
            except CheckpointError:
                pass
        kinds = " or ".join(_KINDS[list if isinstance(k, list) else k] for k in spec)
        raise CheckpointError(file, field, f"expected {kinds}, got {_show(value)}")
    elif isinstance(spec, list):
        if not isinstance(value, list):
            raise CheckpointError(file, field, f"expected a list, got {_show(value)}")
        for i, item in enumerate(value):
            check(item, spec[0], file, f"{field}[{i}]")
    elif isinstance(spec, Each):
        if not isinstance(value, dict):
            raise CheckpointError(file, field, f"expected an object, got {_show(value)}")
        for key, item in value.items():
            check(item, spec.spec, file, f"{field}.{key}" if field else key)
    elif isinstance(spec, dict):
        if not isinstance(value, dict):
            raise CheckpointError(file, field, f"expected an object, got {_show(value)}")
        for key, sub in spec.items():
            name = f"{field}.{key}" if field else key
            if key not in value:
                if isinstance(sub, Opt):
                    continue
                raise CheckpointError(file, name, "missing")
            check(value[key], sub.spec if isinstance(sub, Opt) else sub, file, name)
    elif spec is not object and not _matches(value, spec):
        raise CheckpointError(file, field, f"expected {_KINDS[spec]}, got {_show(value)}")


# --------------------------------------------------------------------------------------------
# model.json

#: options added after format version 1 was first written: optional (the dataclass default)
ADDED_LATER = {"given", "step_scale", "input_norm", "sample", "precision", "vertex_frames"}  # and train.LEGACY_TRAIN_DEFAULTS
_ANNOTATIONS = {"int": int, "float": float, "str": str, "bool": bool, "list[float] | None": ([float], None),
                "float | None": (float, None)}


def config_schema(cls) -> dict:
    """The JSON schema of a config dataclass (``ModelConfig``, ``TrainConfig``) from its fields."""
    from meshseq.training.config import LEGACY_TRAIN_DEFAULTS  # added later, with the value older runs had

    added_later = ADDED_LATER | set(LEGACY_TRAIN_DEFAULTS)
    schema = {}
    for f in fields(cls):
        spec = _ANNOTATIONS[f.type]
        spec = spec if isinstance(spec, list | tuple) else (spec,)
        schema[f.name] = Opt(spec) if f.name in added_later and f.default is not MISSING else spec
    return schema


_SPLIT = {"n_frames": int, "train": [[int]], "heldout": [int], "validation": Opt([int])}
_DATASET = {"name": str, "source": str, "n_frames": int, "split": _SPLIT}
_SCALING = {"mode": str, "minimum": [float], "maximum": [float]}
_TOPOLOGY = {"hash": str, "n_vertices": int, "n_faces": int}


def model_meta_schema() -> dict:
    from meshseq.model_config import ModelConfig
    from meshseq.training.config import TrainConfig

    return {
        "format": str, "format_version": int, "iteration": int, "sha256": str,
        "model": config_schema(ModelConfig), "train": config_schema(TrainConfig),
        "scaling": _SCALING, "topology": _TOPOLOGY, "datasets": [_DATASET],
        "features": Opt({"consistency": Opt(str), "reference": Opt(str), "placement": Opt(str)}),
        "validation": Opt({"error": float, "iteration": int}),
        "novelty": Opt({"step": float, "frames": int, "steps": Opt(bool)}),
        "completion": Opt({"vertex_share": float, "scores": Opt(Each(float))}),
        "prediction": Opt({"carry": float, "scores": Opt(Each(float))}),
    }


def check_model_meta(meta, file: Path, iteration: int | None = None) -> None:
    """CheckpointError unless ``meta`` (model.json parsed) is a model.json this meshseq can use.

    ``iteration``: the one the folder's name says, if it is a checkpoint folder.
    """
    from meshseq.acap.parts import CHANNEL_COUNTS
    from meshseq.acap.scaling import SCALING_MODES
    from meshseq.model_config import ModelConfig
    from meshseq.training.config import TrainConfig

    if not isinstance(meta, dict) or meta.get("format") != FORMAT:
        raise CheckpointError(file, "", f"not a {FORMAT} file")
    check(meta, model_meta_schema(), file)
    if meta["format_version"] > FORMAT_VERSION:
        raise CheckpointError(file, "format_version",
                              f"{meta['format_version']} is newer than this meshseq ({FORMAT_VERSION})")
    _check_iteration(meta, file, iteration)
    ModelConfig.from_dict(meta["model"], source=str(file))  # names the file and the stored field
    try:
        TrainConfig.from_dict(meta["train"])
    except MeshseqError as err:
        raise CheckpointError(file, "train", str(err)) from None
    model, topo = meta["model"], meta["topology"]
    channels = model["channels"]
    if channels not in CHANNEL_COUNTS:
        raise CheckpointError(file, "model.channels", f"{channels}: ACAP features have 9 channels (12 with the "
                              "placement channels of a multi-part mesh)")
    if topo["n_vertices"] != model["n_vertices"] or topo["n_vertices"] < 1 or topo["n_faces"] < 1:
        raise CheckpointError(file, "topology", f"{topo['n_vertices']} vertices, {topo['n_faces']} faces, but the "
                              f"model has {model['n_vertices']} vertices")
    sc = meta["scaling"]
    if sc["mode"] not in SCALING_MODES:
        raise CheckpointError(file, "scaling.mode", f"{sc['mode']!r}: expected one of {', '.join(SCALING_MODES)}")
    lo, hi = np.asarray(sc["minimum"], dtype=np.float64), np.asarray(sc["maximum"], dtype=np.float64)
    if lo.shape != (channels,) or hi.shape != (channels,):
        raise CheckpointError(file, "scaling", f"expected {channels} minima and {channels} maxima, got {lo.size} "
                              f"and {hi.size}")
    if not np.all(hi > lo):
        c = int(np.argmin(hi > lo))
        raise CheckpointError(file, "scaling", f"channel {c}: maximum {hi[c]} is not above minimum {lo[c]}")
    if not meta["datasets"]:
        raise CheckpointError(file, "datasets", "empty")
    for i, d in enumerate(meta["datasets"]):
        _check_split(d, file, f"datasets[{i}]")
    consistency, placement = feature_options(meta)
    if consistency not in CONSISTENCY_MODES:
        raise CheckpointError(file, "features.consistency",
                              f"{consistency!r}: expected one of {', '.join(CONSISTENCY_MODES)}")
    nov = meta.get("novelty")
    if nov is not None and not (nov["step"] > 0 and math.isfinite(nov["step"]) and nov["frames"] >= 1):
        raise CheckpointError(file, "novelty", f"step {nov['step']} and frames {nov['frames']}: expected a positive "
                              "step and at least one frame")
    if placement not in ("centroid", "anchor"):  # acap.parts.PLACEMENT_MODES
        raise CheckpointError(file, "features.placement", f"{placement!r}: expected centroid or anchor")
    share = meta.get("completion", {}).get("vertex_share", 0.0)
    if not 0.0 <= share <= 1.0:
        raise CheckpointError(file, "completion.vertex_share", f"{share}: expected a share from 0 to 1")
    carry = meta.get("prediction", {}).get("carry", 0.0)
    if not 0.0 <= carry < 1.0:
        raise CheckpointError(file, "prediction.carry", f"{carry}: expected a share in [0, 1)")


def feature_options(meta: dict) -> tuple[str, str]:
    """``(consistency, placement)``: the rotation consistency and part placement a checkpoint's
    features were extracted with (model.json's ``features``; ``UNNAMED_*`` where it names none)."""
    features = meta.get("features", {})
    return features.get("consistency", UNNAMED_CONSISTENCY), features.get("placement", UNNAMED_PLACEMENT)


def _check_iteration(meta: dict, file, iteration: int | None) -> None:
    if meta["iteration"] < 0 or (iteration is not None and meta["iteration"] != iteration):
        raise CheckpointError(file, "iteration", f"{meta['iteration']} does not match the folder name ({iteration})")


def _check_split(d: dict, file, field: str) -> None:
    n, s = d["n_frames"], d["split"]
    spans = [("train", span) for span in s["train"]] + [("heldout", s["heldout"])]
    spans += [("validation", s["validation"])] if "validation" in s else []
    for name, span in spans:
        if len(span) != 2 or not 0 <= span[0] <= span[1] <= n:
            raise CheckpointError(file, f"{field}.split.{name}", f"{span}: expected [start, stop] inside 0..{n}")
    if s["n_frames"] != n or n < 1:
        raise CheckpointError(file, f"{field}.split.n_frames", f"{s['n_frames']}: expected {n} (the data set's frames)")


# --------------------------------------------------------------------------------------------
# state.json

_GROUP = Each((int, float, str, bool, None, list))
_STATE = {
    "iteration": int, "sha256": str,
    "optimizer": {"scalars": Each(Each(float)), "param_groups": [_GROUP]},
    "numpy_rng": dict,
    "python_random": Opt(list),
    "world_size": Opt(int),
    "grad_norms": Opt([float]),
    "losses": Opt([float]),
    "rollbacks": Opt(int),
}


def check_state_meta(meta, file: Path, iteration: int | None = None) -> None:
    """CheckpointError unless ``meta`` (state.json parsed) holds usable optimizer and RNG states."""
    check(meta, _STATE, file)
    _check_iteration(meta, file, iteration)
    groups = meta["optimizer"]["param_groups"]
    if len(groups) not in (1, 2):  # one rate, or the FC weight's own (TrainConfig.fc_lr)
        raise CheckpointError(file, "optimizer.param_groups", f"expected one or two parameter groups, "
                              f"got {len(groups)}")
    need = {"params": [str], "lr": float, "betas": [float], "eps": float, "weight_decay": float}
    for i, g in enumerate(groups):
        where = f"optimizer.param_groups[{i}]"
        check(g, need, file, where)
        if not g["lr"] > 0:
            raise CheckpointError(file, f"{where}.lr", f"{g['lr']}: expected a positive number")
        if len(g["betas"]) != 2 or not all(0 <= b < 1 for b in g["betas"]):
            raise CheckpointError(file, f"{where}.betas", f"{g['betas']}: expected two numbers in [0, 1)")
        if not g["eps"] > 0 or g["weight_decay"] < 0:
            raise CheckpointError(file, where, f"eps {g['eps']} must be > 0, weight_decay {g['weight_decay']} >= 0")
        for key, val in g.items():
            if key not in need and not isinstance(val, (bool, type(None))):
                raise CheckpointError(file, f"{where}.{key}", f"expected true, false or null, got {_show(val)}")
    for name, scalars in meta["optimizer"]["scalars"].items():
        if any(v < 0 for v in scalars.values()):
            raise CheckpointError(file, f"optimizer.scalars.{name}", "negative step count")
    bit_generator = np.random.PCG64()
    try:
        bit_generator.state = meta["numpy_rng"]
    except (TypeError, ValueError, KeyError, OverflowError) as err:
        raise CheckpointError(file, "numpy_rng", f"not a numpy PCG64 state ({err})") from None
    if "python_random" in meta:
        try:
            version, internal, gauss = meta["python_random"]
            random.Random().setstate((version, tuple(internal), gauss))
        except (TypeError, ValueError, OverflowError) as err:
            raise CheckpointError(file, "python_random", f"not a Python random state ({err})") from None


# --------------------------------------------------------------------------------------------
# tensors


def _dtype_name(t) -> str:
    """``float32``, ``int64``, ... of a torch tensor or a numpy array (or a ``tensor_spec``)."""
    return str(t.dtype).removeprefix("torch.")


class TensorSpec:
    """The shape and dtype a stored tensor must have (``check_like``'s expectations)."""

    def __init__(self, shape: tuple[int, ...], dtype: str):
        self.shape, self.dtype = tuple(shape), dtype


def check_like(tensors: dict, expected: dict, file, exact: bool = False) -> None:
    """CheckpointError unless ``tensors`` (torch tensors or numpy arrays) has ``expected``'s names,
    shapes and dtypes (``expected``: tensors, arrays or ``TensorSpec``), finite values (floating
    point) and, if ``exact``, no other tensors."""
    missing = sorted(set(expected) - set(tensors))
    if missing:
        more = f" (and {len(missing) - 1} more)" if len(missing) > 1 else ""
        raise CheckpointError(file, "", f"the file lacks tensor {missing[0]}{more}")
    for name, want in expected.items():
        got = tensors[name]
        if _dtype_name(got) != _dtype_name(want) or tuple(got.shape) != tuple(want.shape):
            raise CheckpointError(file, name, f"{got.dtype} {tuple(got.shape)}, expected {want.dtype} "
                                  f"{tuple(want.shape)} (the model its JSON describes)")
    extra = sorted(set(tensors) - set(expected))
    if exact and extra:
        raise CheckpointError(file, extra[0], "unexpected tensor (not part of the model its JSON describes)")
    _check_finite({k: tensors[k] for k in expected}, file)


def _all_finite(t) -> bool:
    """Whether every value is finite: the minimum and maximum are (NaN propagates through both), one
    pass without ``isfinite``'s full-size mask (8x faster on a crane model's FC weight)."""
    if isinstance(t, np.ndarray):
        return bool(np.isfinite(t.min()) & np.isfinite(t.max()))
    import torch

    lo, hi = torch.aminmax(t)
    return bool(torch.isfinite(lo) & torch.isfinite(hi))


def _check_finite(tensors: dict, file) -> None:
    for name, t in tensors.items():
        floating = _dtype_name(t).startswith(("float", "bfloat"))
        if floating and math.prod(t.shape) and not _all_finite(t):
            raise CheckpointError(file, name, "non-finite values (NaN or infinity): the run diverged; use an "
                                  "earlier checkpoint")


def check_reference(tensors: dict, meta: dict, file: Path) -> None:
    """CheckpointError unless model.safetensors holds the reference mesh of ``meta`` (model.json):
    ``reference.vertices`` ``(V, 3)`` float64, finite, and ``reference.faces`` ``(F, 3)`` int64
    in ``0..V-1`` with the stored connectivity hash."""
    from meshseq.mesh import topology_hash

    topo = meta["topology"]
    V, F = topo["n_vertices"], topo["n_faces"]
    want = {"reference.vertices": TensorSpec((V, 3), "float64"), "reference.faces": TensorSpec((F, 3), "int64")}
    check_like(tensors, want, file)
    faces = tensors["reference.faces"]
    if int(faces.min()) < 0 or int(faces.max()) >= V:
        raise CheckpointError(file, "reference.faces", f"vertex numbers outside 0..{V - 1}")
    if topology_hash(np.asarray(faces), V) != topo["hash"]:
        raise CheckpointError(file, "reference.faces", f"connectivity hash differs from topology.hash {topo['hash']} "
                              "in model.json")


def check_model_tensors(tensors: dict, meta: dict, file: Path) -> None:
    """CheckpointError unless model.safetensors holds ``model.<name>`` for every tensor of the model
    ``meta`` (model.json, checked) describes (``model_config.tensor_shapes``, float32), finite,
    besides the reference mesh (:func:`check_reference`) and, where model.json has ``novelty``,
    ``novelty.latents`` ``(frames, latent)`` float32 (and ``novelty.steps`` alike where ``novelty.steps``
    is true); nothing else."""
    from meshseq.model_config import ModelConfig, tensor_shapes

    config = ModelConfig.from_dict(meta["model"], source=str(file))
    want = {f"model.{k}": TensorSpec(shape, "float32") for k, shape in tensor_shapes(config).items()}
    want.update({k: tensors[k] for k in ("reference.vertices", "reference.faces")})  # checked before
    if meta.get("novelty") is not None:
        want[NOVELTY_LATENTS] = TensorSpec((meta["novelty"]["frames"], config.latent), "float32")
        if meta["novelty"].get("steps", False):
            want[NOVELTY_STEPS] = want[NOVELTY_LATENTS]
    check_like(tensors, want, file, exact=True)


def _check_like_parameter(t, params: dict, name: str, file: Path, key: str, what: str) -> None:
    """CheckpointError unless ``name`` is a parameter and ``t`` has its dtype and shape."""
    if name not in params:
        raise CheckpointError(file, key, f"{what} of an unknown parameter")
    p = params[name]
    if t.dtype != p.dtype or t.shape != p.shape:
        raise CheckpointError(file, key, f"{t.dtype} {tuple(t.shape)}, expected {p.dtype} {tuple(p.shape)} "
                              "(its parameter)")


def check_state_tensors(tensors: dict, meta: dict, params: dict, file: Path) -> None:
    """CheckpointError unless state.safetensors holds Adam moments ``optim.<param>.<key>`` shaped
    like the parameters ``params`` (name -> tensor) for exactly the parameters with step counts in
    ``meta`` (state.json), finite, valid torch generator states ``rng.torch[.rankR]`` and, behind a
    weight average (``ema_decay``), the weights training continues from, ``train.<param>``, for
    every parameter."""
    import torch

    scalars = meta["optimizer"]["scalars"]
    listed = [n for g in meta["optimizer"]["param_groups"] for n in g["params"]]
    if sorted(listed) != sorted(params) or len(set(listed)) != len(listed):
        raise CheckpointError(file.with_name("state.json"), "optimizer.param_groups",
                              "do not list each of the model's parameters once")
    moments: dict = {}
    for key, t in tensors.items():
        if key.startswith("optim."):
            name, _, sub = key[len("optim."):].rpartition(".")
            _check_like_parameter(t, params, name, file, key, "moments")
            moments.setdefault(name, set()).add(sub)
        elif key.startswith("train."):  # the weights training continues from (behind a weight average)
            _check_like_parameter(t, params, key[len("train."):], file, key, "weights")
        elif key == "rng.torch" or key.startswith("rng.torch.rank"):
            try:
                torch.Generator().set_state(t)
            except (RuntimeError, TypeError) as err:
                raise CheckpointError(file, key, f"not a torch generator state ({str(err).splitlines()[0]})") from None
        elif key == "rng.cuda" or key.startswith("rng.cuda.rank"):
            if t.dtype != torch.uint8 or t.dim() != 1:
                raise CheckpointError(file, key, "not a CUDA generator state")
        else:
            raise CheckpointError(file, key, "unexpected tensor")
    if "rng.torch" not in tensors:
        raise CheckpointError(file, "", "lacks tensor rng.torch")
    if set(moments) != set(scalars):
        odd = sorted(set(moments) ^ set(scalars))[0]
        raise CheckpointError(file, f"optim.{odd}", "moments and step count do not come together (state.json)")
    weights = {k for k in tensors if k.startswith("train.")}
    if weights and len(weights) != len(params):
        missing = sorted(set(params) - {k[len("train."):] for k in weights})[0]
        raise CheckpointError(file, f"train.{missing}", "missing (the training weights come for every parameter or none)")
    _check_finite({k: v for k, v in tensors.items() if k.startswith(("optim.", "train."))}, file)
