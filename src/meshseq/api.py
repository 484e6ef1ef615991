"""``meshseq.load(RUN)``: a trained model for notebooks and scripts.

    m = meshseq.load("runs/horse")          # a run folder (newest checkpoint) or a checkpoint folder
    x = m.features(vertices)                # (T, V, 3) -> scaled ACAP features (T, V, 9)
    mu = m.encode(x)                        # (T, V, 9) -> (T, latent)
    s = m.initial_state(1, "forward")
    s, x1 = m.step(s, x[:1])                # G(s, X) -> (s', X + dX)
    frames = m.rollout(x[:1], 20)           # (1, 21, V, 9), free running
    verts = m.vertices(frames[0])           # back to (21, V, 3) vertices

Arrays in, arrays out: numpy inputs give numpy outputs, torch inputs give torch outputs. Features
are in the model's scaled space ([-0.95, 0.95]); ``features``/``vertices`` convert to and from
meshes (ACAP extraction against the reference mesh stored with the model, and reconstruction).
"""

from __future__ import annotations

import os

import numpy as np

from meshseq import checkpoint as ckpt
from meshseq.checkpoint_schema import feature_options
from meshseq.errors import MeshseqError
from meshseq.model_config import ModelConfig


def _to_torch(x, device):
    """``(tensor on device, whether x was numpy)``."""
    import torch

    if isinstance(x, torch.Tensor):
        return x.to(device=device, dtype=torch.float32), False
    return torch.as_tensor(np.asarray(x), dtype=torch.float32, device=device), True


def _check_finite(frames: np.ndarray, what: str) -> None:
    """MeshseqError naming the first frame of ``frames`` ``(T, ...)`` with a NaN or infinity."""
    if np.isfinite(np.sum(frames)):  # one pass, no temporaries: finite unless some value is not (or it overflowed)
        return
    ok = np.isfinite(frames.reshape(len(frames), -1)).all(axis=1) if frames.ndim > 1 else np.isfinite(frames)
    if not ok.all():
        t = int(np.flatnonzero(~ok)[0])
        raise MeshseqError(f"the model's output is not finite ({what} of frame {t} of {len(frames)}): "
                           "it diverged on this input")


def _back(t, as_numpy: bool):
    return t.detach().cpu().numpy() if as_numpy else t


class Model:
    """A trained BD-LSTM generator with its reference mesh and feature scaling.

    Attributes:
        net: the ``BDLSTM`` torch module (eval mode), or a ``meshseq.numpy_net.NumpyNet``
            (``backend`` ``numpy``: no torch; arrays in and out are numpy, nothing is sampled).
        engine: what synthesis runs (``meshseq.torch_net``'s interface): ``TorchNet(net)`` or ``net``.
        config: its ``ModelConfig``; ``meta``: the checkpoint's JSON.
        reference: ``(V, 3)`` float64 reference vertices; ``faces``: ``(F, 3)`` int64.
        scaling: the ``meshseq.acap.Scaling`` fitted on the training frames.
        novelty: the training frames' latents (``meshseq.novelty.NoveltyReference``), which
            prediction's guard measures given frames against; None for runs stored without.

    ``vertex_share``: how far completion's line between two keys moves on toward the straight lines
    between the keys' vertices (``meshseq.inbetween``), fitted on the training frames; 0 for runs
    stored without it. ``carry``: the share of the given frames' velocity prediction carries into
    the roll-out (``meshseq.carry``), fitted on the training frames; ``synthesize.CARRY`` for runs
    stored without it.
    """

    def __init__(self, net, meta: dict, reference: np.ndarray, faces: np.ndarray, device,
                 reconstructor=None, novelty=None):
        from meshseq import synthesize
        from meshseq.acap import Scaling
        from meshseq.numpy_net import NumpyNet

        self.backend = "numpy" if isinstance(net, NumpyNet) else "torch"
        if self.backend == "numpy":
            self.net = self.engine = net
            self.device = "cpu"
        else:
            import torch

            from meshseq.torch_net import TorchNet

            self.net = net.eval()
            self.device = torch.device(device)
            self.engine = TorchNet(self.net, self.device)
        self.meta = meta
        self.config: ModelConfig = net.config
        self.reference = reference
        self.faces = faces
        self.scaling = Scaling.from_dict(meta["scaling"])
        # the rotation consistency of its features (acap.CONSISTENCY_MODES) and what a multi-part
        # model's placement channels measure from (acap.parts.PLACEMENT_MODES)
        self.consistency, self.placement = feature_options(meta)
        self._reconstructor = reconstructor  # an acap.Reconstructor of (reference, faces); made when first needed
        self.novelty = novelty  # meshseq.novelty.NoveltyReference of the training frames, or None
        self.vertex_share = float(meta.get("completion", {}).get("vertex_share", 0.0))
        self.carry = float(meta.get("prediction", {}).get("carry", synthesize.CARRY))

    def __repr__(self) -> str:
        c = self.config
        return (f"meshseq.Model(variant={c.variant!r}, vertices={c.n_vertices}, latent={c.latent}, "
                f"lstm_layers={c.lstm_layers}, iteration={self.meta.get('iteration')})")

    @property
    def iteration(self) -> int:
        return int(self.meta["iteration"])

    # -- meshes <-> features ------------------------------------------------------------------

    def check_mesh(self, faces: np.ndarray, n_vertices: int, what: str = "the mesh") -> None:
        """MeshseqError unless the connectivity is the one the model was trained on."""
        ckpt.check_topology(self.meta, faces, n_vertices, what)

    def features(self, vertices: np.ndarray, faces: np.ndarray | None = None) -> np.ndarray:
        """Vertices ``(T, V, 3)`` -> scaled features ``(T, V, C)`` float32 (against the reference; C = 9,
        or 12 for a model of a multi-part mesh, whose last three place the parts: ``acap.parts``)."""
        from meshseq import acap

        v = np.asarray(vertices, dtype=np.float64)
        if v.ndim == 2:
            v = v[None]
        if faces is not None:
            self.check_mesh(np.asarray(faces), v.shape[1])
        elif v.shape[1] != self.config.n_vertices:
            raise MeshseqError(f"vertices have {v.shape[1]} vertices, the model expects {self.config.n_vertices}")
        f = acap.extract(v, self.faces, reference=self.reference, consistency=self.consistency,
                         placement=self.config.channels > 9, placement_mode=self.placement)
        return self.scaling.apply(f).astype(np.float32)

    def vertices(self, x) -> np.ndarray:
        """Scaled features ``(T, V, C)`` -> vertices ``(T, V, 3)`` (centroid at the origin; the parts of a
        multi-part mesh where the features' placement channels put them).

        MeshseqError if a frame's features or vertices are not finite (a diverged roll-out), so
        nothing downstream writes or measures NaN frames.
        """
        from meshseq import acap

        if self._reconstructor is None:
            self._reconstructor = acap.Reconstructor(self.reference, self.faces, placement=self.placement)
        x = x.detach().cpu().numpy() if hasattr(x, "detach") else np.asarray(x)  # (a torch tensor)
        _check_finite(x, "features")
        v = self._reconstructor.solve(x, scaling=self.scaling)
        _check_finite(v, "vertices")
        return v

    # -- the network --------------------------------------------------------------------------

    def encode(self, x):
        """Scaled features ``(..., V, 9)`` -> latent means ``mu`` ``(..., latent)``."""
        if self.backend == "numpy":
            f = np.asarray(x, dtype=np.float32)
            return self.net.encode(f.reshape(-1, *f.shape[-2:])).reshape(*f.shape[:-2], -1)
        import torch

        t, as_np = _to_torch(x, self.device)
        lead = t.shape[:-2]
        with torch.no_grad():
            mu, _ = self.net.encode(t.reshape(-1, *t.shape[-2:]))
        return _back(mu.reshape(*lead, -1), as_np)

    def decode(self, h):
        """LSTM outputs / latent codes ``(..., latent)`` -> frame changes ``dX`` ``(..., V, 9)``."""
        if self.backend == "numpy":
            z = np.asarray(h, dtype=np.float32)
            d = self.net.decode(z.reshape(-1, z.shape[-1]))
            return d.reshape(*z.shape[:-1], *d.shape[-2:])
        import torch

        t, as_np = _to_torch(h, self.device)
        lead = t.shape[:-1]
        with torch.no_grad():
            d = self.net.decode(t.reshape(-1, t.shape[-1]))
        return _back(d.reshape(*lead, *d.shape[-2:]), as_np)

    def initial_state(self, batch: int = 1, direction: str = "forward", value: float | None = None):
        """``(h, c)``, each ``(layers, batch, latent)`` torch tensors (numpy arrays on the numpy
        backend): +0.1 forward, -0.1 backward."""
        if direction not in ("forward", "backward"):
            raise MeshseqError(f"direction {direction!r}: expected 'forward' or 'backward'")
        fwd = direction == "forward"
        if self.backend == "numpy":
            h, c = self.net.initial_state(batch if fwd else 0, 0 if fwd else batch)
        else:
            h, c = self.net.initial_state(batch if fwd else 0, 0 if fwd else batch, self.device)
        if value is not None:  # (torch tensors or numpy arrays)
            h[...] = value
            c[...] = value
        return h, c

    def step(self, state, x, direction: str = "forward", sample: bool = False):
        """G(s, X) -> (s', X + dX) for frames ``(B, V, 9)``; ``direction`` picks the LSTM (std-bd)."""
        if self.backend == "numpy":
            f = np.asarray(x, dtype=np.float32)
            batch = f[None] if f.ndim == 2 else f
            state, nxt = self.net.step(state, batch, len(batch) if direction == "forward" else 0, sample)
            return state, nxt[0] if f.ndim == 2 else nxt
        import torch

        t, as_np = _to_torch(x, self.device)
        single = t.dim() == 2
        if single:
            t = t[None]
        n_forward = t.shape[0] if direction == "forward" else 0
        with torch.no_grad():
            state, nxt, _, _ = self.net.step(state, t, sample=sample, n_forward=n_forward)
        nxt = nxt[0] if single else nxt
        return state, _back(nxt, as_np)

    def _check_sampling(self, sample: bool) -> None:
        """One line where sampling is asked of the numpy backend (it has no VAE sampling)."""
        if sample and self.backend == "numpy":
            raise MeshseqError("drawing the VAE latent (sampled predictions) needs the torch model: "
                               "load it with meshseq.load(run) (backend torch)")

    def rollout(self, first, steps: int, direction: str = "forward", state=None, sample: bool = False):
        """Free-running frames ``(B, steps + 1, V, 9)`` from ``first`` ``(B, V, 9)``."""
        if self.backend == "numpy":
            self._check_sampling(sample)
            f = np.asarray(first, dtype=np.float32)
            state = self.initial_state(len(f), direction) if state is None else state
            return self.net.rollout(f, int(steps), state, len(f) if direction == "forward" else 0)[0]
        import torch

        t, as_np = _to_torch(first, self.device)
        if state is None:
            state = self.initial_state(t.shape[0], direction)
        n_forward = t.shape[0] if direction == "forward" else 0
        with torch.no_grad():
            frames, _, _, _ = self.net.rollout(t, int(steps), state, sample=sample, n_forward=n_forward)
        return _back(frames, as_np)


    # -- synthesis (see meshseq.synthesize) ---------------------------------------------------

    def predict(self, frames, n_frames: int, sample: bool = False, pace: str = "given",
                guard: bool = True, carry: float | None = None) -> np.ndarray:
        """Continue a motion.

        ``frames``: given vertices ``(U, V, 3)`` -> vertices ``(U + n, V, 3)``: the given frames
        (exactly), then ``n`` generated ones continuing from the last; or scaled features
        ``(U, V, 9)`` -> the generated features ``(n, V, 9)``. ``pace``, ``guard`` (the novelty
        guard; False: the roll-out alone) and ``carry`` (None: the model's own, ``carry``; 0: the
        model's steps as they are): see ``meshseq.synthesize.predict``.
        """
        from meshseq import synthesize

        f = np.asarray(frames)
        c = self.config.channels
        if f.ndim != 3 or f.shape[-1] not in (3, c) or f.shape[1] != self.config.n_vertices:
            raise MeshseqError(f"frames must be (U, {self.config.n_vertices}, 3) vertices or (U, "
                               f"{self.config.n_vertices}, {c}) scaled features, got shape {f.shape}")
        if f.shape[-1] == c:
            return synthesize.predict(self, f, n_frames, sample=sample, pace=pace, guard=guard, carry=carry)
        given = np.asarray(f, dtype=np.float64)
        feats = self.features(given)
        gen = synthesize.predict(self, feats, n_frames, sample=sample, pace=pace, guard=guard, carry=carry)
        return synthesize.assemble_vertices(self, np.concatenate([feats, gen]),
                                            {i: given[i] for i in range(len(given))})

    def sample(self, frames, n_frames: int, samples: int = 4, seed: int = 0) -> np.ndarray:
        """Several continuations of a motion, each drawing the VAE latent at every step.

        ``frames``: given vertices ``(U, V, 3)`` -> ``(samples, U + n, V, 3)`` vertices: the given
        frames (exactly), then ``n`` generated ones; ``seed`` makes the draws repeatable.
        """
        from meshseq import synthesize

        self._check_sampling(True)
        f = np.asarray(frames, dtype=np.float64)
        if f.ndim != 3 or f.shape[-1] != 3 or f.shape[1] != self.config.n_vertices:
            raise MeshseqError(f"frames must be (U, {self.config.n_vertices}, 3) vertices, got shape {f.shape}")
        feats = self.features(f)
        if self.backend == "torch":
            import torch

            torch.manual_seed(int(seed))
        gen = synthesize.predict(self, np.repeat(feats[None], int(samples), 0), n_frames, sample=True)
        return synthesize.assemble_vertices(self, np.concatenate([np.repeat(feats[None], len(gen), 0), gen], 1),
                                            {i: f[i] for i in range(len(f))})

    def complete(self, keyframes, lengths, samples: int = 1, seed: int | None = None,
                 before=None, after=None) -> np.ndarray:
        """Fill the gaps between keyframes ``(K, V, 3)`` (vertices).

        ``lengths``: frames to generate between consecutive keys (one int for all gaps, or K-1).
        ``before`` / ``after``: vertices ``(U, V, 3)`` of the frames just before the first key and
        just after the last, if there are any (``meshseq complete`` gives 7 of DATA's): one
        completion warms its chains up on them and keeps their own motion where they are
        trustworthy (``meshseq.synthesize.context_trust``).
        Returns ``(samples, T, V, 3)`` vertices passing exactly through every key
        (``T = K + sum(lengths)``); several samples come from random initial states (and use the
        keys alone).
        """
        from meshseq import synthesize

        keys = np.asarray(keyframes, dtype=np.float64)
        if keys.ndim == 3 and keys.shape[-1] == self.config.channels:
            raise MeshseqError(f"keyframes: Model.complete takes vertices (K, V, 3), got features {keys.shape}; "
                               "complete features with meshseq.synthesize.complete")
        if keys.ndim != 3 or len(keys) < 2 or keys.shape[-1] != 3:
            raise MeshseqError(f"keyframes must be (K >= 2, V, 3) vertices, got shape {keys.shape}")
        if keys.shape[1] != self.config.n_vertices:
            raise MeshseqError(f"keyframes have {keys.shape[1]} vertices, the model expects {self.config.n_vertices}")
        gaps = [int(lengths)] * (len(keys) - 1) if np.ndim(lengths) == 0 else [int(g) for g in lengths]
        if len(gaps) != len(keys) - 1:
            raise MeshseqError(f"lengths: expected one number or {len(keys) - 1}, got {len(gaps)}")
        around = [None if c is None else np.asarray(c, dtype=np.float64) for c in (before, after)]
        for name, c in zip(("before", "after"), around):
            if c is not None and (c.ndim != 3 or c.shape[1:] != keys.shape[1:]):
                raise MeshseqError(f"{name} must be (U, {keys.shape[1]}, 3) vertices, got shape {c.shape}")
        return synthesize.complete_keyframes(self, keys, gaps, samples=samples, seed=0 if seed is None else seed,
                                             before=around[0], after=around[1])


def load(run: str | os.PathLike, device: str = "cpu", backend: str = "torch") -> Model:
    """Load a trained model from a run folder (its newest usable checkpoint) or a checkpoint folder.

    ``backend``: ``torch`` (the ``BDLSTM`` module on ``device``) or ``numpy`` (CPU inference
    without torch, ``meshseq.numpy_net``: what ``meshseq predict`` / ``complete`` use on CPU;
    ``device`` must then be ``cpu`` or ``auto``).
    Reads safetensors and JSON only (nothing is unpickled), checked by
    ``meshseq.checkpoint_schema``: a damaged or edited checkpoint, or one with non-finite
    weights, is a one-line MeshseqError naming the file and field.
    """
    if backend == "numpy":
        if device not in ("cpu", "auto"):
            raise MeshseqError(f"--device {device}: the numpy inference runs on the CPU (device cpu or auto)")
        loaded = ckpt.load(run, backend="numpy")
        return Model(loaded.net, loaded.meta, loaded.reference.astype(np.float64), loaded.faces.astype(np.int64),
                     "cpu", novelty=loaded.novelty)
    from meshseq.device import resolve_device

    dev = resolve_device(device)
    loaded = ckpt.load(run)
    return Model(loaded.net.to(dev), loaded.meta, loaded.reference.astype(np.float64),
                 loaded.faces.astype(np.int64), dev, novelty=loaded.novelty)
