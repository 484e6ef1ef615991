"""The generator's architecture (``ModelConfig``, stored in every checkpoint's JSON) and its checks,
without torch: what a checkpoint's reader and the numpy inference path (``meshseq.numpy_net``)
need; ``meshseq.model`` builds the torch module from it."""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, fields

import numpy as np

from meshseq.errors import MeshseqError

VARIANTS = ("bd", "std-bd", "uni")
CONV_IMPLS = ("gather", "sparse")
#: the command-line options of ModelConfig fields (``meshseq train``), named in messages about them
MODEL_OPTIONS = {"variant": "--variant", "conv_impl": "--conv", "latent": "--latent",
                 "lstm_layers": "--lstm-layers", "conv_layers": "--conv-layers"}


@dataclass
class ModelConfig:
    """Architecture of the generator; stored in every checkpoint's JSON.

    ``latent`` is both the VAE latent width and the LSTM width (the decoder FC is the encoder FC
    transposed, so the LSTM output must have the latent width).

    ``step_scale`` (None = the paper: ``X_t+1 = X_t + dX``): per-channel factors ``(C,)`` so that
    ``X_t+1 = X_t + step_scale * dX``; training sets them to the spread of the data's frame-to-frame
    changes, so the decoder works in units of a typical step (see ``meshseq.train``).

    ``input_norm`` (False = the paper): the encoder sees ``(X - offset) / spread`` instead of
    ``X``, with ``offset`` ``(V, C)`` the mean training frame and ``spread`` ``(C,)`` the RMS of the
    training frames around it per channel (buffers ``input_offset``/``input_spread``, set by
    training with ``set_input_norm`` and stored with the weights): the frames then differ by O(1)
    at the encoder's input, not by the few hundredths they differ by in the scaled space.

    ``logvar_max`` (None = the paper: unbounded): the VAE head's log-variance is clamped to at
    most this, so the sampling noise ``exp(logvar / 2)`` never exceeds ``exp(logvar_max / 2)``
    (0: the prior's unit spread; see ``meshseq.train.RECIPES`` for why).

    ``mu_max`` (None = the paper: unbounded): the VAE head's mean is squashed softly into
    ``(-mu_max, mu_max)``, ``mu = mu_max * tanh(m / mu_max)`` (``m``: the head's output), so a
    coherent Adam step on the large encoder FC cannot throw the latent far outside the prior's range.
    """

    n_vertices: int
    channels: int = 9
    conv_layers: int = 3
    latent: int = 128
    lstm_layers: int = 3
    variant: str = "bd"
    conv_impl: str = "sparse"
    init_state: float = 0.1
    step_scale: list[float] | None = None
    input_norm: bool = False
    logvar_max: float | None = None
    mu_max: float | None = None

    def __post_init__(self):
        ModelConfig.check_options(self.__dict__)
        if self.step_scale is not None:
            self.step_scale = [float(v) for v in self.step_scale]

    def to_dict(self) -> dict:
        return asdict(self)

    @staticmethod
    def check_options(options: dict) -> None:
        """MeshseqError (naming the command-line option) unless ``options`` (fields; ``n_vertices``
        may be left out) make a valid config; for checking before any work starts."""
        known = {f.name for f in fields(ModelConfig)}
        unknown = set(options) - known
        if unknown:
            raise MeshseqError(f"unknown model options {sorted(unknown)}")
        defaults = {f.name: f.default for f in fields(ModelConfig)}
        problem = _model_config_problem({**defaults, "n_vertices": 1, **options})
        if problem:
            field, value, expected = problem
            raise MeshseqError(f"{MODEL_OPTIONS.get(field, 'model option ' + field)} {value!r}: {expected}")

    @staticmethod
    def from_dict(d: dict, source: str = "stored model config") -> "ModelConfig":
        """The config stored by :meth:`to_dict` (a checkpoint's ``model``). Its problems are
        reported as stored fields of ``source`` (``source: model.variant ...``), not as
        command-line options nobody gave."""
        if not isinstance(d, dict):
            raise MeshseqError(f"{source}: model config must be a JSON object, got {type(d).__name__}")
        known = {f.name for f in fields(ModelConfig)}
        unknown = set(d) - known
        if unknown:
            raise MeshseqError(f"{source}: model config has unknown keys {sorted(unknown)} (newer meshseq?)")
        if "n_vertices" not in d:
            raise MeshseqError(f"{source}: model config has no n_vertices")
        defaults = {f.name: f.default for f in fields(ModelConfig) if f.name != "n_vertices"}
        problem = _model_config_problem({**defaults, **d})
        if problem:
            field, value, expected = problem
            raise MeshseqError(f"{source}: stored field model.{field} = {value!r}: {expected}")
        return ModelConfig(**d)


def is_finite_number(x) -> bool:
    """A finite int or float (numpy floats too), not a bool: what a numeric option may hold."""
    return (isinstance(x, (int, float, np.floating)) and not isinstance(x, bool)
            and math.isfinite(x))


def _model_config_problem(values: dict) -> tuple[str, object, str] | None:
    """``(field, value, what was expected)`` of the first invalid ModelConfig field; None if valid."""
    def is_int(x):
        return isinstance(x, (int, np.integer)) and not isinstance(x, (bool, np.bool_))

    if values["variant"] not in VARIANTS:
        return "variant", values["variant"], f"expected one of {', '.join(VARIANTS)}"
    if values["conv_impl"] not in CONV_IMPLS:
        return "conv_impl", values["conv_impl"], f"expected one of {', '.join(CONV_IMPLS)}"
    for name in ("n_vertices", "channels", "conv_layers", "latent", "lstm_layers"):
        if not is_int(values[name]) or values[name] < 1:
            return name, values[name], "expected an integer of at least 1"
    if not isinstance(values["init_state"], (int, float, np.floating)) or not math.isfinite(values["init_state"]):
        return "init_state", values["init_state"], "expected a number"
    if not isinstance(values["input_norm"], (bool, np.bool_)):
        return "input_norm", values["input_norm"], "expected true or false"
    if values["logvar_max"] is not None and not is_finite_number(values["logvar_max"]):
        return "logvar_max", values["logvar_max"], "expected a number or null"
    mu_max = values["mu_max"]
    if mu_max is not None and not (is_finite_number(mu_max) and mu_max > 0):
        return "mu_max", mu_max, "expected a positive number or null"
    scale = values["step_scale"]
    if scale is not None:
        try:
            a = np.asarray(scale, dtype=np.float64)
        except (TypeError, ValueError):
            a = np.zeros(0)
        if a.shape != (values["channels"],) or not (np.isfinite(a) & (a > 0)).all():
            return "step_scale", scale, f"expected {values['channels']} positive numbers"
    return None


def tensor_shapes(config: ModelConfig) -> dict[str, tuple[int, ...]]:
    """``{name: shape}`` of every tensor a ``BDLSTM`` of ``config`` stores (its ``state_dict``, all
    float32): what a checkpoint's ``model.<name>`` entries must be (``checkpoint_schema``) and what
    ``meshseq.numpy_net`` reads (tests/test_numpy_net.py checks it against the torch module)."""
    C, L, V, K = config.channels, config.latent, config.n_vertices, config.conv_layers
    shapes: dict[str, tuple[int, ...]] = {}
    for k in range(K):
        shapes[f"convs.{k}.weight"] = (2 * C, C)
        shapes[f"convs.{k}.bias"] = (C,)
    shapes.update({"fc.weight": (L, V * C), "fc.bias": (L,), "fc_mu.weight": (L, L), "fc_mu.bias": (L,),
                   "fc_logvar.weight": (L, L), "fc_logvar.bias": (L,), "dec_fc_bias": (V * C,)})
    shapes.update({f"dec_conv_bias.{k}": (C,) for k in range(K)})
    for lstm in ("lstm", "lstm_backward") if config.variant == "std-bd" else ("lstm",):
        for k in range(config.lstm_layers):
            shapes.update({f"{lstm}.weight_ih_l{k}": (4 * L, L), f"{lstm}.weight_hh_l{k}": (4 * L, L),
                           f"{lstm}.bias_ih_l{k}": (4 * L,), f"{lstm}.bias_hh_l{k}": (4 * L,)})
    if config.input_norm:
        shapes.update({"input_offset": (C, V, 1), "input_spread": (C, 1, 1)})
    return shapes
