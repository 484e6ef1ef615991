"""Training options: ``TrainConfig`` (every field documented in its docstring), the named recipes
(``RECIPES``), their validation, and ``--config FILE.toml`` (``config_from_toml``).

Why the default recipe departs from the paper, decision by decision with the measurements behind
each: docs/method.md, "The departures of the default recipe" and "Measured and left out".
"""

from __future__ import annotations

import difflib
import re
from dataclasses import asdict, dataclass, fields
from pathlib import Path

import numpy as np

from meshseq.data.windows import check_holdout, check_validation
from meshseq.errors import MeshseqError
from meshseq.model_config import is_finite_number

PRECISIONS = ("float32", "bf16")

STEP_SCALES = ("none", "data")
#: ``fc_lr``: how the big FC weight (encoder V*9 -> L, tied to the decoder) learns on meshes whose
#: fan-in V * 9 exceeds ``fc_lr_fan_in``, with ``f = min(1, fc_lr_fan_in / (V * 9))``:
#: ``fan-in`` scales its Adam learning rate by f (both of its uses learn slower); ``encoder`` keeps
#: one rate and scales the encoder's share of its gradient by f (``BDLSTM.encoder_grad_scale``: the
#: encoder, whose output moves by up to rate x fan-in per step, is slowed; the decoder, fan-in L,
#: is not); ``none``: one rate, the plain gradient (the paper).
FC_LRS = ("fan-in", "encoder", "none")
#: The FC fan-in at which the recipe study chose lr = 1e-3 (the 1,000-vertex body set): the
#: ``fc_lr_fan_in`` of runs stored before the option.
FC_REFERENCE_FAN_IN = 9000
#: ``kl_scale``: ``vertices`` multiplies w_kl by ``V / KL_REFERENCE_VERTICES`` (see ``kl_weight``);
#: ``none``: w_kl as given (the paper).
KL_SCALES = ("vertices", "none")
#: ``feedback_grad``: ``full`` backpropagates through the generated frames fed back into the
#: encoder (the paper: one computation graph over the roll-out); ``stop`` treats each fed-back frame
#: as a constant input (``BDLSTM.rollout``), so the gradient no longer loops through the mesh
#: features; it still flows through the LSTM state and the residual ``X + dX``.
FEEDBACK_GRADS = ("full", "stop")
#: The mesh size at which the recipe study chose w_kl = 0.1 (the 1,000-vertex body set).
KL_REFERENCE_VERTICES = 1000
#: ``grad_clip``: the gradient's norm is clipped at ``grad_clip`` times the median norm of the last
#: ``GRAD_CLIP_HISTORY`` iterations (unclipped norms), once ``GRAD_CLIP_WARMUP`` are known.
GRAD_CLIP_HISTORY = 100
GRAD_CLIP_WARMUP = 10
#: ``ema_decay``: the averaging weight of iteration t is ``min(ema_decay, (1 + t) / (EMA_WARMUP + t))``,
#: so the first iterations are not averaged with the random initial weights (see ``average_decay``).
EMA_WARMUP = 10
#: ``window_fit``: ``batch`` shortens the window until the training part holds a batch of
#: different windows (``meshseq.data.windows.fitted_window``); ``none`` trains on the window given.
WINDOW_FITS = ("batch", "none")
#: Fields added to TrainConfig after runs were stored without them: the value that reproduces
#: those runs (TrainConfig.from_dict fills it in when a stored config lacks the field).
LEGACY_TRAIN_DEFAULTS = {"fc_lr": "none", "w_motion": 0.0, "kl_scale": "none", "logvar_max": None,
                         "grad_clip": None, "adam_beta2": 0.999, "ema_decay": None,
                         "mu_max": None, "feedback_grad": "full", "tempo_augment": 0.0,
                         "fc_lr_fan_in": FC_REFERENCE_FAN_IN, "w_vertex": 0.0, "validation": 0.0,
                         "speed_augment": 1.0, "window_fit": "none",
                         "placement_jitter": 0.0, "placement": "centroid", "rollback": False}


def is_positive_integer(x) -> bool:
    """An int (numpy integers too) >= 1, not a bool and not a float: what a count option may hold."""
    return isinstance(x, (int, np.integer)) and not isinstance(x, bool) and x >= 1


@dataclass
class TrainConfig:
    """Training options; stored in every checkpoint's JSON. Every field can be set in
    ``meshseq train --config FILE.toml`` (top-level keys, see ``config_from_toml``); the command
    line sets the first group. Defaults are the ``default`` recipe's (``RECIPES``; the paper's
    values in brackets where they differ).

    Command line (``meshseq train --help``):
        iterations: training iterations (the paper: 7000). window: frames per training window.
        batch: windows per iteration (over all processes). seed: weights, windows, sampling noise.
        validation: fraction of every data set's training frames kept out as a validation block
        (``meshseq.data.windows.split_frames``); every ``eval_every`` iterations the prediction
        error there is measured and the best checkpoint kept as ``RUN/checkpoints/best`` (0: none).
        precision: ``float32``, or ``bf16`` (autocast the training step; float32 master weights).

    Data:
        stride: take every stride-th frame. holdout: fraction of every data set held out (one
        block); holdout_at: where it starts (``start``, ``end`` or a fraction). speed_augment R:
        play every window at a random speed in [1/R, R] (log-uniform, linear interpolation of
        frames; 1 = off). tempo_augment S: play a share S of the windows with a changing tempo
        (holds, slow-downs to a stop, speed-ups; ``WindowSampler.sample_at_tempos``; 0 = off).
        scaling: feature scaling to [-0.95, 0.95] fitted on the training frames
        (``two-group``, ``per-channel``, ``robust``). consistency: rotation consistency of the ACAP
        features (``acap.CONSISTENCY_MODES``: ``temporal``, ``temporal-mst``, ...). window_fit: ``batch`` shortens the window until the
        training frames hold a batch of different windows (never below 16 frames while that
        fits) [``none``: the window as given]. placement_jitter J (0.1 [0]): on a mesh of several
        parts, shift each part's placement channels in every training window by a random offset
        (normal, std J in scaled units, one per part and window; ``losses.jittered_placement``).
        placement (``anchor`` [``centroid``]): what a part's placement channels measure it from
        (``acap.parts.PLACEMENT_MODES``: its anchor, the largest part's vertex nearest it, or the
        mesh's centroid).

    Loss (``meshseq.training.losses``):
        w_rec, w_bd, w_kl, w_l2 (1, 0.5, 0.1, 0 [0.1]): weights of L_rec, L_bd, L_KL, L_2 (the sum
        of squared weights). w_motion (20 [0]): L_motion, generated frame-to-frame change against
        the truth's, in size. w_vertex (1 [0]): L_vertex (``meshseq.vertex_loss``), generated
        frames reconstructed to vertices against the truth's; vertex_frames: frames of each chain
        it reconstructs (evenly spaced, the last always). kl_scale: ``vertices`` multiplies w_kl
        by vertices / 1000 [``none``]. given G: each iteration draws 1..G teacher-forced first
        frames per chain (1: free-running chains). sample: sample z during training (True).

    Model and optimiser:
        lr: Adam's learning rate; adam_beta2: its second-moment decay (0.999). input_norm: centre
        and scale the encoder's input on the training frames [False]. step_scale: ``none``
        (X' = X + dX) or ``data`` (dX in units of the RMS frame change). fc_lr: how the big FC
        weight learns on meshes with fan-in V x 9 over fc_lr_fan_in (f = min(1, fc_lr_fan_in /
        (V x 9))): ``encoder`` scales the encoder's share of its gradient by f, ``fan-in`` its
        learning rate, [``none``] neither. logvar_max (0 [none]): clamp of the encoder's
        log-variance. mu_max (none): soft squash of the latent mean into (-X, X). grad_clip
        (none): clip the gradient norm at X times the median of the last 100. rollback (True
        [False]): a loss blow-up (``optim.blown_up``) sends training back to weights at least 100
        iterations older, at half the learning rate (three times at most). ema_decay
        (0.99 [none]): checkpoints deliver a moving average of the weights. feedback_grad:
        ``full`` backpropagates through the frames fed back into the encoder, ``stop`` does not.

    Logging: eval_every (held-out loss and validation every K iterations; 0: at the end),
    checkpoint_every (and at the end), log_every (metrics rows), keep (checkpoints kept).
    """

    iterations: int = 7000
    window: int = 32
    window_fit: str = "batch"
    batch: int = 8
    stride: int = 1
    seed: int = 0
    lr: float = 1e-3
    adam_beta2: float = 0.999
    w_rec: float = 1.0
    w_bd: float = 0.5
    w_kl: float = 0.1
    w_l2: float = 0.0
    w_motion: float = 20.0
    w_vertex: float = 1.0
    vertex_frames: int = 4
    holdout: float = 0.2
    holdout_at: str = "end"
    validation: float = 0.0
    speed_augment: float = 1.0
    tempo_augment: float = 0.0
    placement_jitter: float = 0.1
    placement: str = "anchor"
    scaling: str = "two-group"
    consistency: str = "temporal-mst"  # acap.DEFAULT_CONSISTENCY (a test checks they agree)
    given: int = 1
    step_scale: str = "none"
    input_norm: bool = True
    fc_lr: str = "encoder"
    fc_lr_fan_in: int = FC_REFERENCE_FAN_IN
    kl_scale: str = "vertices"
    logvar_max: float | None = 0.0
    mu_max: float | None = None
    grad_clip: float | None = None
    rollback: bool = True
    ema_decay: float | None = 0.99
    feedback_grad: str = "full"
    sample: bool = True
    eval_every: int = 100
    checkpoint_every: int = 500
    log_every: int = 10
    keep: int = 2
    precision: str = "float32"

    def __post_init__(self):
        """MeshseqError naming the first bad field: its command-line flag (``--window``) where it has
        one, else its name (``fc_lr``), as a ``--config`` file sets it."""
        for name in ("iterations", "window", "batch"):
            if int(getattr(self, name)) < 1:
                raise MeshseqError(f"--{name} {getattr(self, name)}: expected a positive integer")
        if int(self.stride) < 1:
            raise MeshseqError(f"stride {self.stride}: expected a positive integer")
        if int(self.window) < 2:
            raise MeshseqError(f"--window {self.window}: a window needs at least 2 frames")
        check_holdout(self.holdout, self.holdout_at)
        check_validation(self.validation)
        for name in ("eval_every", "checkpoint_every", "log_every"):
            if int(getattr(self, name)) < 0:
                raise MeshseqError(f"{name} {getattr(self, name)}: expected >= 0")
        for name in ("w_rec", "w_bd", "w_kl", "w_l2", "w_motion", "w_vertex"):
            if not float(getattr(self, name)) >= 0:
                raise MeshseqError(f"loss weight {name}={getattr(self, name)} must be >= 0")
        if not is_positive_integer(self.vertex_frames):
            raise MeshseqError(f"vertex_frames {self.vertex_frames!r}: expected a positive integer")
        if self.window_fit not in WINDOW_FITS:
            raise MeshseqError(f"window_fit {self.window_fit!r}: expected one of {', '.join(WINDOW_FITS)}")
        if not (is_finite_number(self.speed_augment) and self.speed_augment >= 1):
            raise MeshseqError(f"speed_augment {self.speed_augment!r}: expected a number >= 1 (1 = off)")
        if not (is_finite_number(self.tempo_augment) and 0 <= self.tempo_augment <= 1):
            raise MeshseqError(f"tempo_augment {self.tempo_augment!r}: expected a share in [0, 1] (0 = off)")
        from meshseq.acap.parts import PLACEMENT_MODES
        from meshseq.acap.rotations import CONSISTENCY_MODES

        if self.consistency not in CONSISTENCY_MODES:
            raise MeshseqError(f"consistency {self.consistency!r}: expected one of {', '.join(CONSISTENCY_MODES)}")
        if self.placement not in PLACEMENT_MODES:
            raise MeshseqError(f"placement {self.placement!r}: expected one of {', '.join(PLACEMENT_MODES)}")
        if not (is_finite_number(self.placement_jitter) and self.placement_jitter >= 0):
            raise MeshseqError(f"placement_jitter {self.placement_jitter!r}: expected a number >= 0 (0 = off)")
        if self.tempo_augment > 0 and self.speed_augment > 1:
            raise MeshseqError("tempo_augment and speed_augment: choose one of the two augmentations")
        if not float(self.lr) > 0:
            raise MeshseqError(f"lr {self.lr}: expected a positive number")
        if not (is_finite_number(self.adam_beta2) and 0 <= self.adam_beta2 < 1):
            raise MeshseqError(f"adam_beta2 {self.adam_beta2!r}: expected a number in [0, 1)")
        if not 1 <= int(self.given) < int(self.window):
            raise MeshseqError(f"given {self.given}: expected 1 <= given < --window ({self.window})")
        if self.step_scale not in STEP_SCALES:
            raise MeshseqError(f"step_scale {self.step_scale!r}: expected one of {', '.join(STEP_SCALES)}")
        if self.fc_lr not in FC_LRS:
            raise MeshseqError(f"fc_lr {self.fc_lr!r}: expected one of {', '.join(FC_LRS)}")
        if not is_positive_integer(self.fc_lr_fan_in):
            raise MeshseqError(f"fc_lr_fan_in {self.fc_lr_fan_in!r}: expected a positive integer")
        if self.logvar_max is not None and not is_finite_number(self.logvar_max):
            raise MeshseqError(f"logvar_max {self.logvar_max!r}: expected a number")
        if self.mu_max is not None and not (is_finite_number(self.mu_max) and self.mu_max > 0):
            raise MeshseqError(f"mu_max {self.mu_max!r}: expected a positive number or none")
        if self.grad_clip is not None and not (is_finite_number(self.grad_clip) and self.grad_clip > 0):
            raise MeshseqError(f"grad_clip {self.grad_clip!r}: expected a positive number or none")
        if not isinstance(self.rollback, (bool, np.bool_)):
            raise MeshseqError(f"rollback {self.rollback!r}: expected true or false")
        if self.ema_decay is not None and not (is_finite_number(self.ema_decay) and 0 < self.ema_decay < 1):
            raise MeshseqError(f"ema_decay {self.ema_decay!r}: expected a number in (0, 1) or none")
        if self.feedback_grad not in FEEDBACK_GRADS:
            raise MeshseqError(f"feedback_grad {self.feedback_grad!r}: expected one of {', '.join(FEEDBACK_GRADS)}")
        if self.kl_scale not in KL_SCALES:
            raise MeshseqError(f"kl_scale {self.kl_scale!r}: expected one of {', '.join(KL_SCALES)}")
        if self.precision not in PRECISIONS:
            raise MeshseqError(f"--precision {self.precision!r}: expected one of {', '.join(PRECISIONS)}")

    def to_dict(self) -> dict:
        return asdict(self)

    @staticmethod
    def from_dict(d: dict) -> "TrainConfig":
        known = {f.name for f in fields(TrainConfig)}
        return TrainConfig(**(LEGACY_TRAIN_DEFAULTS | {k: v for k, v in d.items() if k in known}))



#: The TrainConfig fields a recipe sets (``RECIPES``).
RECIPE_OPTIONS = ("w_rec", "w_bd", "w_kl", "w_l2", "w_motion", "w_vertex", "given", "step_scale", "input_norm", "fc_lr",
                  "fc_lr_fan_in", "kl_scale", "logvar_max", "mu_max", "grad_clip", "rollback", "ema_decay",
                  "feedback_grad", "window_fit")
#: Named recipes (``meshseq train --recipe``): values of the fields in ``RECIPE_OPTIONS``. ``paper``: the
#: paper's recipe read literally (L_rec + 0.5 L_bd + 0.1 (L_KL + L_2), free-running chains, the
#: encoder fed the scaled features as they are). ``default``: TrainConfig's defaults, each departure
#: measured by controlled runs (docs/method.md, "The departures of the default recipe").
RECIPES = {
    "paper": {"w_rec": 1.0, "w_bd": 0.5, "w_kl": 0.1, "w_l2": 0.1, "w_motion": 0.0, "w_vertex": 0.0, "given": 1,
              "step_scale": "none", "input_norm": False, "fc_lr": "none", "fc_lr_fan_in": FC_REFERENCE_FAN_IN,
              "kl_scale": "none", "logvar_max": None, "grad_clip": None, "rollback": False, "ema_decay": None,
              "mu_max": None, "feedback_grad": "full", "window_fit": "none"},
    "default": {name: TrainConfig.__dataclass_fields__[name].default for name in RECIPE_OPTIONS},
}


def fc_lr_factor(fan_in: int, fc_lr: str, reference: int = FC_REFERENCE_FAN_IN) -> float:
    """The factor on the FC weight's learning rate: ``min(1, reference / fan_in)`` with
    ``fc_lr = "fan-in"``, else 1."""
    return min(1.0, reference / fan_in) if fc_lr == "fan-in" else 1.0


# --------------------------------------------------------------------------------------------
# --config FILE.toml

#: ModelConfig options a config file may set in its ``[model]`` table (the command line sets
#: ``variant`` and ``latent``)
MODEL_KEYS = ("variant", "latent", "lstm_layers", "conv_layers", "conv_impl")
_KINDS = {"int": (int,), "float": (int, float), "str": (str,), "bool": (bool,), "float | None": (int, float)}
_SAYS = {"int": "an integer", "float": "a number", "str": "a string", "bool": "true or false",
         "float | None": 'a number or "none"'}


def _checked_value(file: str, key: str, value, kind: str):
    """``value`` of TOML key ``key`` as TrainConfig's field of annotation ``kind`` holds it."""
    if kind == "float | None" and isinstance(value, str) and value.lower() == "none":
        return None
    if isinstance(value, bool) and kind != "bool" or not isinstance(value, _KINDS[kind]):
        raise MeshseqError(f"{file}: {key}: expected {_SAYS[kind]}, got {value!r}")
    return float(value) if kind in ("float", "float | None") else value


def read_toml(path: str | Path) -> dict:
    """The table of a TOML file; a one-line MeshseqError if it is missing or not TOML."""
    try:
        import tomllib
    except ImportError:  # Python 3.10
        try:
            import tomli as tomllib
        except ImportError:
            raise MeshseqError(f"--config {path}: reading TOML needs Python >= 3.11 or the tomli package "
                               "(pip install tomli)") from None
    try:
        with open(path, "rb") as fh:
            return tomllib.load(fh)
    except OSError as err:
        raise MeshseqError(f"--config {path}: {err.strerror or err}") from None
    except tomllib.TOMLDecodeError as err:
        raise MeshseqError(f"--config {path}: not valid TOML: {err}") from None


def config_from_toml(path: str | Path, base: dict | None = None) -> tuple[dict, dict]:
    """``(train, model)`` options of a ``--config`` file: its top-level keys are TrainConfig fields
    (documented in TrainConfig's docstring), its ``[model]`` table ModelConfig options
    (``MODEL_KEYS``). Each value is checked against ``base`` (TrainConfig fields it overrides, e.g. a
    recipe's), so an unknown key or a bad value is one MeshseqError naming the file and the key::

        # run.toml
        w_motion = 10.0
        ema_decay = "none"      # a number or "none" for the optional ones
        eval_every = 50
        [model]
        lstm_layers = 2
    """
    return config_from_table(read_toml(path), str(path), base)


def config_from_table(table: dict, file: str, base: dict | None = None) -> tuple[dict, dict]:
    """``config_from_toml`` of a table already read (``file``: what error messages name)."""
    kinds = {f.name: f.type for f in fields(TrainConfig)}
    train, model = {}, {}
    for key, value in table.items():
        if key == "model" and isinstance(value, dict):
            model = _model_table(file, value)
        elif key not in kinds:
            close = difflib.get_close_matches(key, list(kinds) + ["model"], n=1)
            hint = f"did you mean {close[0]}? " if close else ""
            raise MeshseqError(f"{file}: {key}: not a training option ({hint}the options are TrainConfig's fields, "
                               "documented in meshseq.training.config.TrainConfig)")
        else:
            train[key] = _checked_value(file, key, value, kinds[key])
            try:
                TrainConfig(**{**(base or {}), key: train[key]})
            except MeshseqError as err:
                raise MeshseqError(f"{file}: {key}: {_without_flag(err, key)}") from None
    return train, model


def _without_flag(err: MeshseqError, key: str = "") -> str:
    """A config check's message without the flag or field name it starts with (``--window 1: ...``,
    ``lr -1: ...`` -> ``1: ...``, ``-1: ...``): the file's key names the option."""
    return re.sub(rf"^(--[a-z0-9-]+|{re.escape(key)}) " if key else r"^--[a-z0-9-]+ ", "", str(err))


def _model_table(file: str, table: dict) -> dict:
    """The ``[model]`` table of a config file, checked by ``ModelConfig.check_options``."""
    from meshseq.model_config import ModelConfig

    for key, value in table.items():
        if key not in MODEL_KEYS:
            raise MeshseqError(f"{file}: model.{key}: not a model option (known: {', '.join(MODEL_KEYS)})")
        try:
            ModelConfig.check_options({key: value})
        except MeshseqError as err:
            raise MeshseqError(f"{file}: model.{key}: {_without_flag(err)}") from None
    return dict(table)
