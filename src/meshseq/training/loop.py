"""The training loop: ``train`` (or resume) a BD-LSTM on ``TrainingData``.

The loop is a plain loop: sample windows (numpy generator), one batched forward of both chains,
backward, Adam step; log every ``log_every`` iterations (rich progress bar, ``RUN/metrics.csv``,
TensorBoard events in ``RUN/tensorboard`` when the ``tensorboard`` package is installed),
held-out loss every ``eval_every``, a checkpoint every ``checkpoint_every`` and at the end.
Processes, run folder and metrics: ``meshseq.training.run``; the objective:
``meshseq.training.losses``; the options: ``meshseq.training.config``.

Divergence: every iteration checks the weighted loss terms, their total and the gradient norm
for NaN/infinity before the update (one host synchronisation; under DDP one all-reduce of the
flag); the first non-finite value stops training with a MeshseqError naming the iteration and the
term, and the last good checkpoint stays the newest; with ``rollback``, once the run has gone 100
iterations, such a value or a loss that blows up (``optim.blown_up``) sends training back to a copy
of its state kept in memory, at half the learning rate, instead. A run that never blows up is the
same bit for bit.
"""

from __future__ import annotations

import collections
import copy
import gc
import os
import random
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch import nn

from meshseq import checkpoint as ckpt
from meshseq.checkpoint_schema import NOVELTY_LATENTS, NOVELTY_STEPS
from meshseq.data.windows import Split, WindowSampler, heldout_rows, split_frames
from meshseq.errors import MeshseqError
from meshseq.mesh import Topology, topology_hash
from meshseq.model import BDLSTM, ModelConfig
from meshseq.novelty import NoveltyReference, reference_latents
from meshseq.training.config import GRAD_CLIP_HISTORY, TrainConfig
from meshseq.training.data import TrainingData, fit_window, step_spread, training_windows
from meshseq.training.losses import WindowLoss, make_vertex_loss, reconstructed_vertices, window_losses
from meshseq.training.optim import (LOSS_HISTORY, MAX_ROLLBACKS, SNAPSHOT_EVERY, autocast, average_decay, blown_up,
                                    can_go_back, clip_threshold, copy_weights, divergence, fused_adam, grad_norm,
                                    parameter_groups, scale_gradients, update_average, weights_swapped)
from meshseq.training.run import (Dist, Metrics, freeze_setup_objects, prepare_run_dir, progress_bar, resume_point,
                                  start_processes, stderr_log, terms_text)

#: iterations before the collapse check starts (the latent needs a few hundred to organise)
COLLAPSE_AFTER = 200


def train(
    data: TrainingData,
    run_dir: str | os.PathLike,
    config: TrainConfig | None = None,
    model_options: dict | None = None,
    device: str = "auto",
    resume: bool = False,
    force: bool = False,
    progress: bool = True,
    log=stderr_log,
) -> dict:
    """Train (or resume training) a BD-LSTM on ``data``; write metrics and checkpoints to ``run_dir``.

    Args:
        data: features of the data sets (see :func:`load_training_data`).
        config: training options (default ``TrainConfig()``). On resume the stored options are
            used, except ``iterations``, which may extend the run.
        model_options: ``ModelConfig`` fields other than ``n_vertices`` (variant, latent, ...).
        device: ``auto`` (CUDA if available), ``cpu``, ``cuda`` or ``cuda:N``.
        resume: continue from the newest usable checkpoint in ``run_dir``; MeshseqError if there
            is none (a resume never starts over; its stored options are used).
        force: start over in a non-empty ``run_dir`` (removes the checkpoints, metrics and
            TensorBoard events training wrote there, nothing else).
    The finished checkpoint's model.json also gets ``prediction``: the carried velocity fitted on the
    training frames (``meshseq.carry``; once, by the main process).

    Raises:
        MeshseqError: bad options or data, nothing to resume, or divergence: a non-finite loss
            term or gradient stops training before the update, naming the iteration and the
            term; checkpoints are written only with finite weights.
    Returns:
        ``{"iteration", "checkpoint", "loss", "heldout_rec", "model"}`` after the last iteration
        (``model``: the trained ``BDLSTM``, with the weight average when ``ema_decay`` is set:
        what the checkpoints deliver); with ``validation`` also ``"best"``: ``{"error",
        "iteration", "checkpoint"}``, the checkpoint with the lowest validation error
        (``RUN/checkpoints/best``; errors are measured every ``eval_every`` iterations and at the last).
    """
    config = config or TrainConfig()
    run_dir = Path(run_dir)
    dev, dist_info = start_processes(device)
    is_main = dist_info.rank == 0
    log = log if (is_main and log) else (lambda msg: None)
    ModelConfig.check_options(model_options or {})  # before the run folder is created
    if resume and force:
        raise MeshseqError("--resume and --force: choose one (--resume continues RUN, --force starts it over)")
    found = resume_point(run_dir) if resume else None
    splits = None
    if found is None:  # options the data cannot meet fail before --force removes anything
        splits = [split_frames(len(f), config.holdout, config.holdout_at, config.validation) for f in data.features]
        if config.window_fit == "batch":
            config = fit_window(config, splits, log)
        WindowSampler(splits, data.names, config.window, config.stride)
    if is_main:
        prepare_run_dir(run_dir, resume, force)
    if dist_info.active:
        torch.distributed.barrier()

    setup = _Setup.of(data, config, model_options, found, splits, dist_info.world, main=is_main)
    config = setup.config
    if is_main and setup.topology.n_components > 1:
        log(f"the mesh has {setup.topology.n_components} separate parts: where each sits relative to the others "
            "is learned as three extra feature channels")
    frames = torch.from_numpy(np.concatenate(setup.scaled).astype(np.float32)).to(dev)  # (sum T, V, 9)
    torch.manual_seed(config.seed)
    random.seed(config.seed)
    np_rng = np.random.default_rng(config.seed)
    st = _State.start(setup, data, found, dev, dist_info, np_rng, log)
    validating = is_main and config.validation > 0  # the main process measures the validation blocks
    truth = reconstructed_vertices(data) if (config.w_vertex > 0 or validating) else None
    objective = _objective(st.model, data, setup, dev, dist_info, frames, truth)
    validate = validation_scorer(st.model, st.params, st.average, data, setup.scaling, setup.splits,
                                 setup.scaled, truth, dev) if validating else None
    best = ckpt.best_validation(run_dir) if (validate and found is not None) else None
    if best is not None and best["iteration"] > st.start:  # written after the checkpoint we resume from
        best = None
    saver = _Saver(run_dir, data, setup, st, np_rng, dev, dist_info)
    sampler = WindowSampler(setup.splits, data.names, config.window, config.stride)
    eval_rows = heldout_rows(setup.splits, config.window, config.stride)

    monitor = _Monitor(run_dir, config, st, frames, eval_rows, validate, best, saver, progress, log) if is_main else None
    share = config.batch // dist_info.world
    mine = slice(dist_info.rank * share, (dist_info.rank + 1) * share)
    last: dict = {"iteration": st.start, "checkpoint": str(found.folder) if found else None, "loss": None,
                  "heldout_rec": None}
    frozen = freeze_setup_objects()
    try:
        for it in range(st.start + 1, config.iterations + 1):
            windows, rows = training_windows(frames, sampler, np_rng, config, mine)
            given = 1 if config.given <= 1 else int(np_rng.integers(1, config.given + 1))
            total, terms, norm = st.step(objective, windows, rows, given, it, last["checkpoint"])
            if _every(config.log_every, it, config.iterations):
                last["loss"] = float(total.detach())  # this process's share of the batch
            if monitor is not None:
                last["heldout_rec"] = monitor.watch(it, last["loss"], terms, norm, last["heldout_rec"])
            if _every(config.checkpoint_every, it, config.iterations):
                last["checkpoint"] = saver.checkpoint(it) or last["checkpoint"]
            last["iteration"] = it
        if st.start >= config.iterations and is_main:
            log(f"{run_dir}: already at iteration {st.start} (>= --iterations {config.iterations}); nothing to do")
    finally:
        if frozen:
            gc.unfreeze()
        if monitor is not None:
            monitor.close()
        if dist_info.started_here:
            torch.distributed.destroy_process_group()
    if is_main and last["checkpoint"] is not None and data.vertices is not None:
        carry_fit(last["checkpoint"], data, setup)
    best = monitor.best if monitor is not None else None
    if st.average is not None:  # return what the checkpoints deliver
        copy_weights(st.params, st.average)
    last["model"] = st.model
    if best is not None:
        last["best"] = {**best, "checkpoint": str(ckpt.best_folder(run_dir))}
        log(f"best validation error {best['error']:.1f} (x 1e-4) at iteration {best['iteration']}: "
            f"{ckpt.best_folder(run_dir)}")
    return last


def _every(k: int, it: int, iterations: int) -> bool:
    """Whether iteration ``it`` is one of every ``k``-th (0: none) or the last."""
    return bool(k and it % k == 0 or it == iterations)


@dataclass
class _Setup:
    """What a run trains with: options, model config, scaling and splits (stored ones on a resume,
    fitted on ``data`` otherwise), and the scaled features ``[(T_d, V, C)]`` float64 (C = 9, or 12 on a
    mesh of several parts: ``meshseq.acap.parts``)."""

    config: TrainConfig
    model_config: ModelConfig
    scaling: object
    splits: list[Split]
    scaled: list[np.ndarray]
    topology: Topology
    completion: dict | None = None  # model.json's ``completion``: the fitted vertex share (meshseq.inbetween)

    @staticmethod
    def of(data: TrainingData, config: TrainConfig, model_options: dict | None, found, splits, world: int,
           main: bool = True) -> "_Setup":
        from meshseq.acap import Scaling
        from meshseq.acap.parts import CHANNEL_COUNTS

        faces, V = data.faces, data.n_vertices
        topo = Topology.from_faces(faces, V)
        C = data.features[0].shape[-1] if data.features[0].ndim == 3 else 9  # 12: ACAP and placement channels
        for name, f in zip(data.names, data.features):
            if f.ndim != 3 or f.shape[1:] != (V, C) or C not in CHANNEL_COUNTS:
                raise MeshseqError(f"{name}: features must have shape (T, {V}, 9) (or 12 channels with the "
                                   f"placement of a multi-part mesh, all data sets alike), got {f.shape}")
        if found is not None:
            meta = found.meta
            ckpt.check_topology(meta, faces, V, what="the training data")
            if [d["source"] for d in meta["datasets"]] != data.sources:
                raise MeshseqError(f"--resume: {found.folder} was trained on "
                                   f"{[d['source'] for d in meta['datasets']]}, not {data.sources}")
            iterations = config.iterations
            config = TrainConfig.from_dict(meta["train"])
            config.iterations = iterations
            model_config = ModelConfig.from_dict(meta["model"])
            if model_config.channels != C:
                raise MeshseqError(f"--resume: {found.folder} was trained on features of {model_config.channels} "
                                   f"channels, the data have {C}")
            scaling = Scaling.from_dict(meta["scaling"])
            splits = [Split.from_dict(d["split"]) for d in meta["datasets"]]
        else:
            model_config = ModelConfig(n_vertices=V, **((model_options or {}) | {"channels": C}))
            train_feats = np.concatenate([f[s.train_frames()] for f, s in zip(data.features, splits)])
            if len(train_feats) == 0:
                raise MeshseqError(f"--holdout {config.holdout}: leaves no training frames")
            scaling = Scaling.fit(train_feats, mode=config.scaling)
            model_config.input_norm = bool(config.input_norm)
            model_config.logvar_max = None if config.logvar_max is None else float(config.logvar_max)
            model_config.mu_max = None if config.mu_max is None else float(config.mu_max)
        if data.consistency != config.consistency:
            stored = f"{found.folder} was trained on" if found is not None else "--consistency asks for"
            raise MeshseqError(f"{stored} {config.consistency} features; the data were extracted with "
                               f"{data.consistency} rotation consistency")
        if C > 9 and data.placement != config.placement:
            raise MeshseqError(f"placement {config.placement}: the data's placement channels were extracted with "
                               f"{data.placement}")
        scaled = [scaling.apply(f) for f in data.features]  # (T_d, V, 9) float64 each
        if found is None and config.step_scale == "data":
            model_config.step_scale = [float(v) for v in step_spread(scaled, splits, config.stride)]
        if config.batch % world:
            raise MeshseqError(f"--batch {config.batch} must be a multiple of the number of processes ({world})")
        completion = found.meta.get("completion") if found is not None else None
        if completion is None and data.vertices is not None and main:  # rank 0 writes model.json
            completion = completion_fit(data, splits, config.placement)
        return _Setup(config, model_config, scaling, splits, scaled, topo, completion)


def completion_fit(data: TrainingData, splits: list[Split], placement: str) -> dict:
    """``meshseq.inbetween.fit_vertex_share`` on the training segments of ``data`` (its loaded frames)."""
    from meshseq.acap import Reconstructor
    from meshseq.inbetween import fit_vertex_share

    solver = Reconstructor(data.reference, data.faces, placement=placement)
    segments = [(f[a:b], np.asarray(v[a:b], dtype=np.float64))
                for f, v, split in zip(data.features, data.vertices, splits) for a, b in split.train]
    return fit_vertex_share(segments, solver.solve)


def carry_fit(folder: str, data: TrainingData, setup: "_Setup") -> None:
    """``meshseq.carry.fit_carry`` of the checkpoint ``folder`` (the finished model) on the training
    segments of ``data`` (its loaded frames), added to its model.json as ``prediction`` (once)."""
    import json

    import meshseq
    from meshseq.carry import fit_carry

    if "prediction" in json.loads((Path(folder) / ckpt.MODEL_META).read_text()):
        return  # a resumed run with nothing left to train, fitted already: its weights are not read
    model = meshseq.load(folder)
    segments = [(f[a:b].astype(np.float32), np.asarray(v[a:b], dtype=np.float64))
                for f, v, split in zip(setup.scaled, data.vertices, setup.splits) for a, b in split.train]
    ckpt.add_model_meta(folder, {"prediction": fit_carry(model, segments)})


class _State:
    """The model, its optimiser, the weight average, the gradient-norm and loss histories of a run,
    its snapshots (``rollback``), and ``step``: one iteration's update."""

    def __init__(self, model: BDLSTM, config: TrainConfig, dev: torch.device, dist_info: Dist):
        self.model, self.config, self.dist_info = model, config, dist_info
        groups = parameter_groups(model, config)
        self.names = [n for g in groups for n in g["names"]]  # in the optimizer's order
        self.optimizer = torch.optim.Adam([{k: v for k, v in g.items() if k != "names"} for g in groups],
                                          lr=config.lr, betas=(0.9, float(config.adam_beta2)),
                                          fused=fused_adam(dev))
        self.start = 0
        self.own_rng = False
        self.grad_history = collections.deque(maxlen=GRAD_CLIP_HISTORY)  # the last unclipped gradient norms
        self.params = list(model.parameters())
        self.param_names = [n for n, _ in model.named_parameters()]
        self.average = None
        self.clipped = 0  # iterations whose gradient was clipped since the last metrics row
        self.loss_history = collections.deque(maxlen=LOSS_HISTORY)  # the last losses, blow-ups left out
        self.snapshots = collections.deque(maxlen=2)  # (iteration, weights, average, optimizer, gradient norms)
        self.rollbacks = 0
        self.log = lambda msg: None
        checked = [k for k in ("rec", "bd", "kl", "l2", "motion", "vertex") if getattr(config, f"w_{k}") != 0]
        self.checked = checked
        self.checked_names = [f"the loss term {k}" for k in checked] + ["the total loss", "the gradient norm"]

    @staticmethod
    def start(setup: _Setup, data: TrainingData, found, dev, dist_info: Dist, np_rng, log) -> "_State":
        """A fresh model (seeded by the caller) or the stored one, its optimiser and average, with
        the training state of ``found`` (a resume) restored."""
        config = setup.config
        if found is None:
            model = BDLSTM(setup.model_config, setup.topology)
            if setup.model_config.input_norm:
                model.set_input_norm(np.concatenate([x[s.train_frames()] for x, s in zip(setup.scaled, setup.splits)]))
        else:
            model = found.net  # the stored weights, checked against the stored config
        st = _State(model.to(dev), config, dev, dist_info)
        if found is not None:
            st.restore(found, np_rng, log)
        # with ema_decay, checkpoints deliver the average (model tensors) and carry the weights
        # training continues from in the training state (train.<name>)
        if config.ema_decay is not None:
            st.average = [p.detach().clone() for p in st.params]  # fresh: the initial weights; resume: the stored average
            if found is not None:
                raw = ckpt.training_weights(found.state_tensors)
                if set(raw) != set(st.param_names):
                    raise MeshseqError(f"--resume: {found.folder}: the training state lacks the weights (train.*) "
                                       "behind its weight average (ema_decay)")
                copy_weights(st.params, [raw[n] for n in st.param_names])
        st.log = log
        if config.rollback:
            st.take_snapshot(st.start)
        if dist_info.rank > 0 and not st.own_rng:
            # different sampling noise per rank (the windows stay common)
            torch.manual_seed(config.seed + 7919 * dist_info.rank + st.start)
        return st

    def restore(self, found, np_rng: np.random.Generator, log) -> None:
        """The optimiser, generators, gradient history and iteration of checkpoint ``found``."""
        smeta, stensors = found.state_meta, found.state_tensors
        self.grad_history.extend(smeta.get("grad_norms", []))
        self.loss_history.extend(smeta.get("losses", []))
        self.rollbacks = int(smeta.get("rollbacks", 0))
        ckpt.load_optimizer_state(self.optimizer, self.names, stensors, smeta["optimizer"])
        self.own_rng = ckpt.set_rng_state(stensors, smeta, self.dist_info.rank)
        np_rng.bit_generator.state = smeta["numpy_rng"]
        self.start = int(found.meta["iteration"])
        log(f"resumed {found.folder} at iteration {self.start} (with its stored options; "
            f"--iterations {self.config.iterations})")
        stored_world = int(smeta.get("world_size", 1))
        if stored_world < self.dist_info.world:
            log(f"the checkpoint was written by {stored_world} process(es), not {self.dist_info.world}: the sampling "
                f"noise of processes {stored_world}.. is reseeded (the run is not repeated bit for bit)")

    def step(self, objective, windows, rows, given: int, it: int, last_checkpoint: str | None):
        """One iteration on ``windows``: forward, backward, the finiteness check, clipping, Adam's
        update and the average's. Returns ``(total, terms, gradient norm)``."""
        config = self.config
        self.optimizer.zero_grad(set_to_none=True)
        with autocast(windows.device, config.precision):
            total, terms = objective(windows, sample=config.sample, given=given, rows=rows)
        total.backward()
        # one finiteness check per iteration, before the update: the weighted loss terms, the
        # total and the norm of all gradients (after DDP's all-reduce, so common to all ranks)
        health = torch.stack([terms[k].float() for k in self.checked] + [total.detach().float(),
                                                                         grad_norm(self.params).float()])
        finite = torch.isfinite(health).all().to(torch.int32)
        if self.dist_info.active:
            torch.distributed.all_reduce(finite, op=torch.distributed.ReduceOp.MIN)
        values = health.tolist()
        loss, norm = values[-2], values[-1]
        if not bool(finite):
            if not (config.rollback and can_go_back(self.loss_history)):
                raise MeshseqError(divergence(it, self.checked_names, health.cpu(), config.lr, last_checkpoint))
            self.roll_back(it, "is not finite")
            return total, terms, norm
        if config.rollback and self.blown_up(loss):
            self.roll_back(it, f"blew up to {loss:.4g} ({loss / float(np.median(self.loss_history)):.0f} times the "
                                f"median of the last {len(self.loss_history)} iterations)")
            return total, terms, norm
        self.loss_history.append(loss)
        limit = clip_threshold(self.grad_history, config.grad_clip)
        self.grad_history.append(norm)
        if limit is not None and norm > limit:
            scale_gradients(self.params, limit / norm)
            self.clipped += 1
        self.optimizer.step()
        if self.average is not None:
            update_average(self.average, self.params, average_decay(config.ema_decay, it))
        if config.rollback and it % SNAPSHOT_EVERY == 0:
            self.take_snapshot(it)
        return total, terms, norm

    def blown_up(self, loss: float) -> bool:
        """``optim.blown_up`` of this process's loss, true on every process if on any."""
        flag = blown_up(loss, self.loss_history)
        if not self.dist_info.active:
            return flag
        t = torch.tensor(int(flag), device=self.params[0].device)
        torch.distributed.all_reduce(t, op=torch.distributed.ReduceOp.MAX)
        return bool(t)

    def take_snapshot(self, it: int) -> None:
        """Keep a copy of the weights, their average, Adam's state and the gradient norms of iteration ``it``."""
        average = None if self.average is None else [a.clone() for a in self.average]
        self.snapshots.append((it, [p.detach().clone() for p in self.params], average,
                               copy.deepcopy(self.optimizer.state_dict()), list(self.grad_history)))

    def roll_back(self, it: int, what: str) -> None:
        """Iteration ``it``'s loss blew up or is not finite (``what`` says which): restore the older
        snapshot kept, halve every learning rate and go on (the windows drawn from here on differ
        from the first attempt's); a MeshseqError after ``MAX_ROLLBACKS`` times. (A run resumed
        fewer than 100 iterations before goes back to its resume point.)"""
        self.rollbacks += 1
        if self.rollbacks > MAX_ROLLBACKS:
            raise MeshseqError(f"training diverged at iteration {it}: the loss {what}, the {self.rollbacks}th time "
                               f"after going back {MAX_ROLLBACKS} times, each at half the learning rate; try a "
                               f"smaller lr than {self.config.lr:g} (lr = ... in --config FILE.toml)")
        at, params, average, optimizer, grads = self.snapshots[0]
        copy_weights(self.params, params)
        if average is not None:
            copy_weights(self.average, average)
        self.optimizer.load_state_dict(copy.deepcopy(optimizer))
        for group in self.optimizer.param_groups:
            group["lr"] *= 0.5
        self.grad_history.clear()
        self.grad_history.extend(grads)
        self.snapshots.clear()
        self.take_snapshot(it)
        lr = self.optimizer.param_groups[0]["lr"]
        self.log(f"iteration {it}: the loss {what}; training went back to the weights of iteration {at} and goes "
                 f"on at half the learning rate ({lr:g})")


def _objective(model: BDLSTM, data: TrainingData, setup: _Setup, dev, dist_info: Dist, frames, truth):
    """The ``WindowLoss`` of the run (wrapped by DistributedDataParallel under torchrun)."""
    config = setup.config
    vertex_loss = make_vertex_loss(data, setup.scaled, setup.splits, setup.scaling, config, dev, truth)
    if vertex_loss is not None and config.speed_augment <= 1 and config.tempo_augment <= 0:
        vertex_loss.cache_targets(frames)  # the truth's vertices of every training frame, once
    labels = setup.topology.component_labels if setup.model_config.channels > 9 else None
    objective = WindowLoss(model, config, vertex_loss, labels)
    if dist_info.active:
        objective = nn.parallel.DistributedDataParallel(
            objective,
            device_ids=[dev.index] if dev.type == "cuda" else None,
            broadcast_buffers=False,
        )
    return objective


def heldout_losses(st: _State, frames: torch.Tensor, eval_rows: np.ndarray) -> dict:
    """``{"heldout_rec"(, "heldout_bd")}`` of the model as a checkpoint delivers it on the held-out
    windows (rows ``eval_rows`` of the stacked frames); {} without any."""
    if len(eval_rows) == 0:
        return {}
    model = st.model
    model.eval()
    with torch.no_grad(), weights_swapped(st.params, st.average):  # what a checkpoint delivers
        w = frames[torch.from_numpy(eval_rows).to(frames.device)]
        terms = window_losses(model(w, sample=False), w)
    model.train()
    out = {"heldout_rec": float(terms["rec"])}
    if model.config.variant != "uni":
        out["heldout_bd"] = float(terms["bd"])
    return out


def novelty_reference(st: _State, setup: _Setup, dev) -> NoveltyReference:
    """The training frames' latents (``meshseq.novelty``) of the model as a checkpoint delivers it."""
    model = st.model
    segments = [x[a:b] for x, split in zip(setup.scaled, setup.splits) for a, b in split.train if b - a > 0]

    def encode(frames: np.ndarray) -> np.ndarray:
        return model.encode(torch.from_numpy(np.asarray(frames, dtype=np.float32)).to(dev))[0].cpu().numpy()

    model.eval()
    with torch.no_grad(), weights_swapped(st.params, st.average):
        reference = reference_latents(encode, segments)
    model.train()
    return reference


class _Saver:
    """Checkpoints of a run: ``save`` writes one (rank 0), ``checkpoint`` gathers every rank's
    generator state first (every rank calls it)."""

    def __init__(self, run_dir: Path, data: TrainingData, setup: _Setup, st: _State, np_rng: np.random.Generator,
                 dev, dist_info: Dist):
        self.run_dir, self.data, self.setup, self.st = run_dir, data, setup, st
        self.np_rng, self.dev, self.dist_info = np_rng, dev, dist_info
        self.datasets_meta = [
            {"name": n, "source": s, "n_frames": int(len(f)), "split": sp.to_dict()}
            for n, s, f, sp in zip(data.names, data.sources, data.features, setup.splits)
        ]
        faces, V = data.faces, data.n_vertices
        self.topo_meta = {"hash": topology_hash(faces, V), "n_vertices": V, "n_faces": int(len(faces))}

    def save(self, iteration: int, rng_t: dict, name: str | None = None, extra: dict | None = None) -> Path:
        st, setup, data = self.st, self.setup, self.data
        tensors = {f"model.{k}": v for k, v in st.model.state_dict().items()}
        if st.average is not None:
            tensors.update({f"model.{n}": a for n, a in zip(st.param_names, st.average)})
        tensors["reference.vertices"] = torch.from_numpy(np.asarray(data.reference, dtype=np.float64))
        tensors["reference.faces"] = torch.from_numpy(np.asarray(data.faces, dtype=np.int64))
        novelty = novelty_reference(st, setup, self.dev)
        tensors[NOVELTY_LATENTS] = torch.from_numpy(novelty.latents)
        tensors[NOVELTY_STEPS] = torch.from_numpy(novelty.steps)
        meta = {
            "model": setup.model_config.to_dict(),
            "train": setup.config.to_dict(),
            "scaling": setup.scaling.to_dict(),
            "topology": self.topo_meta,
            "datasets": self.datasets_meta,
            "features": {"reference": "first frame of data set 0", "consistency": setup.config.consistency,
                         "placement": setup.config.placement},
            "torch_version": torch.__version__,
            "world_size": self.dist_info.world,
            "novelty": {"step": novelty.step, "frames": int(len(novelty.latents)), "steps": True},
            **({"completion": setup.completion} if setup.completion is not None else {}),
            **(extra or {}),
        }
        opt_t, opt_meta = ckpt.optimizer_state(st.optimizer, st.names)
        _, rng_meta = ckpt.rng_state()
        state_meta = {"optimizer": opt_meta, "numpy_rng": self.np_rng.bit_generator.state, "world_size": self.dist_info.world,
                      "grad_norms": list(st.grad_history), "losses": list(st.loss_history),
                      "rollbacks": st.rollbacks, **rng_meta}
        raw_t = {f"train.{n}": p for n, p in zip(st.param_names, st.params)} if st.average is not None else {}
        return ckpt.save_checkpoint(self.run_dir, iteration, tensors, meta, {**opt_t, **rng_t, **raw_t}, state_meta,
                                    setup.config.keep, name)

    def checkpoint(self, iteration: int) -> str | None:
        """Write the checkpoint of ``iteration`` (rank 0; its folder, None on other ranks)."""
        rng_t = self.gather_rng()
        folder = str(self.save(iteration, rng_t)) if self.dist_info.rank == 0 else None
        if self.dist_info.active:
            torch.distributed.barrier()
        return folder

    def gather_rng(self) -> dict:
        """Every process's torch (and CUDA) generator state, named by rank (every rank calls this)."""
        own, _ = ckpt.rng_state()
        if not self.dist_info.active:
            return own
        out = {}
        for name, t in own.items():
            t = t.to(self.dev)  # NCCL gathers CUDA tensors only
            parts = [torch.empty_like(t) for _ in range(self.dist_info.world)]
            torch.distributed.all_gather(parts, t)
            out.update({ckpt.rng_key(name.split(".")[1], r): part.cpu() for r, part in enumerate(parts)})
        return out


class _Monitor:
    """What the main process watches: a metrics row every ``log_every`` iterations (``RUN/metrics.csv``,
    TensorBoard, the progress bar), the held-out losses and validation error every ``eval_every``
    (keeping the best checkpoint), and the latent's collapse."""

    def __init__(self, run_dir: Path, config: TrainConfig, st: _State, frames: torch.Tensor, eval_rows: np.ndarray,
                 validate, best: dict | None, saver: _Saver, progress: bool, log):
        self.config, self.st, self.frames, self.eval_rows = config, st, frames, eval_rows
        self.validate, self.best, self.saver, self.log = validate, best, saver, log
        self.metrics = Metrics(run_dir, st.start, log)
        self.bar = progress_bar(config.iterations - st.start) if progress else None
        self.t0 = time.perf_counter()
        self.collapse_warned = False
        if self.bar is not None:
            self.bar.start()
            self.task = self.bar.add_task("train", total=config.iterations, completed=st.start, terms="")

    def watch(self, it: int, loss: float | None, terms: dict, norm: float, heldout_rec: float | None) -> float | None:
        """Record iteration ``it`` (``loss``: its total, ``terms``: the loss terms, ``norm``: the
        gradient norm); returns the latest held-out L_rec."""
        config, st = self.config, self.st
        row = None
        if _every(config.log_every, it, config.iterations):
            row = {"iteration": it, "seconds": round(time.perf_counter() - self.t0, 3), "loss": loss,
                   **{k: float(v) for k, v in terms.items()}, "grad_norm": norm, "clipped": st.clipped}
            st.clipped = 0
        if _every(config.eval_every, it, config.iterations):
            row = row or {"iteration": it, "seconds": round(time.perf_counter() - self.t0, 3)}
            row.update(heldout_losses(st, self.frames, self.eval_rows))
            heldout_rec = row.get("heldout_rec")
            if self.validate is not None:
                row["validation"] = self.validate()
                if self.best is None or row["validation"] < self.best["error"]:
                    self.best = {"error": row["validation"], "iteration": it}
                    self.saver.save(it, ckpt.rng_state()[0], ckpt.BEST, {"validation": self.best})
            if not self.collapse_warned and it >= COLLAPSE_AFTER and "latent_spread" in row:
                message = collapse_warning(row.get("kl"), row["latent_spread"], config.w_kl)
                if message:
                    self.log(f"warning at iteration {it}: {message}")
                    self.collapse_warned = True
        if row is not None:
            self.metrics.write(row)
            if self.bar is not None:
                self.bar.update(self.task, terms=terms_text(row))
        if self.bar is not None:
            self.bar.update(self.task, completed=it)
        return heldout_rec

    def close(self) -> None:
        if self.bar is not None:
            self.bar.stop()
        self.metrics.close()


def validation_scorer(model: BDLSTM, params, average, data: TrainingData, scaling, splits: list[Split],
                      scaled: list[np.ndarray], truth, device: torch.device):
    """``score() -> float``: ``meshseq.evaluate.validation_error`` of the model as a checkpoint
    would deliver it (the weight average, when kept) on every data set's validation block.

    ``truth``: ``reconstructed_vertices(data)``.
    """
    from meshseq.api import Model
    from meshseq.evaluate import validation_error

    rec, vertices = truth
    blocks = [s.validation for s in splits]
    delivered = Model(model, {"scaling": scaling.to_dict()}, data.reference, data.faces, device, rec)
    model.train()  # Model() switched it to eval mode

    def score() -> float:
        model.eval()
        try:
            with torch.no_grad(), weights_swapped(params, average):
                return validation_error(delivered, vertices, scaled, blocks)
        finally:
            model.train()

    return score


def collapse_warning(kl: float | None, spread: float, w_kl: float) -> str | None:
    """A one-line warning if the latent has collapsed to the prior, else None.

    Collapse: the latent mean hardly varies with the frame (``spread`` < 0.01, against the
    prior's unit spread) or, with a KL term, the KL is below 0.01 nats: z then tells the LSTM
    nothing about the current frame and roll-outs freeze.
    """
    if spread < 1e-2 or (w_kl > 0 and kl is not None and kl < 1e-2):
        return (f"the latent has collapsed to the prior (KL {0.0 if kl is None else kl:.3g} nats, "
                f"latent spread {spread:.3g}): z carries little about the frame and roll-outs will "
                "freeze; the paper's recipe does this (L_2 shrinks the tied FC), see --recipe")
    return None
