"""Training: splits and windows, losses, the loop, the CLI and the notebook API."""

from __future__ import annotations

import csv
import gc
import math

import numpy as np
import pytest
import torch

import meshseq
from conftest import training_data
from meshseq import acap
from meshseq.cli import main
from meshseq.data.synthetic import twisting_limb
from meshseq.data.windows import WindowSampler, heldout_rows, split_frames, window_starts
from meshseq.errors import MeshseqError
from meshseq.io import save_sequence
from meshseq.train import (TrainConfig, WindowLoss, freeze_setup_objects, load_training_data, train,
                           window_losses)

SMALL = {"latent": 16, "lstm_layers": 2}


pytestmark = pytest.mark.usefixtures("one_torch_thread")


def limb_data(frames=40, seed=0):
    seq = twisting_limb(frames=frames, rings=10, segments=8, seed=seed)
    return seq, training_data(seq)


# -- splits and windows ------------------------------------------------------------------------


def test_split_holds_out_one_contiguous_block():
    s = split_frames(50, 0.2)
    assert s.heldout == (40, 50) and s.train == ((0, 40),)
    s = split_frames(50, 0.2, at="start")
    assert s.heldout == (0, 10) and s.train == ((10, 50),)
    s = split_frames(50, 0.2, at="0.5")
    assert s.heldout == (25, 35) and s.train == ((0, 25), (35, 50))
    assert set(s.train_frames()) == set(range(50)) - set(range(25, 35))
    assert split_frames(50, 0.0).heldout == (50, 50)
    with pytest.raises(MeshseqError, match="--holdout"):
        split_frames(50, 1.5)
    with pytest.raises(MeshseqError, match="--holdout-at"):
        split_frames(50, 0.2, at="middle")


def test_windows_stay_inside_training_segments_and_respect_stride():
    splits = [split_frames(50, 0.2, at="0.5"), split_frames(30, 0.2)]
    sampler = WindowSampler(splits, ["a", "b"], window=5, stride=2)
    rows = sampler.rows(np.arange(len(sampler.starts)))
    assert rows.shape == (len(sampler.starts), 5)
    assert np.all(np.diff(rows, axis=1) == 2)
    held = set(range(25, 35)) | {50 + f for f in range(24, 30)}
    assert not held & set(rows.ravel().tolist())
    # every valid window is there: segment (0,25): starts 0..16; (35,50): 35..41; b (0,24): 0..15
    assert len(sampler.starts) == 17 + 7 + 16
    assert rows[:, 0].min() == 0 and rows[-1, 0] == 50 + 15
    rng = np.random.default_rng(0)
    assert sampler.sample(rng, 8).shape == (8, 5)
    with pytest.raises(MeshseqError, match="--window 30"):
        WindowSampler(splits, ["a", "b"], window=30, stride=1)
    assert window_starts([(0, 0, 3)], window=4).shape == (0, 2)


def test_heldout_windows_come_from_the_heldout_block():
    splits = [split_frames(50, 0.2)]
    rows = heldout_rows(splits, window=32)
    assert rows.shape[1] == 10 and rows.min() >= 40 and rows.max() <= 49
    assert heldout_rows([split_frames(50, 0.0)], window=8).size == 0


# -- losses ------------------------------------------------------------------------------------


def test_window_losses_by_hand():
    X = torch.zeros(1, 3, 2, 9)
    X[0, :, 0, 0] = torch.tensor([0.0, 1.0, 2.0])
    f = X.clone()
    f[0, 2, 0, 0] = 3.0  # forward chain misses X_3 by 1
    b = X.flip(1).clone()
    b[0, 2, 1, 1] = 2.0  # backward chain misses X_1 by 2 (its 3rd frame)
    out = {"forward": f, "backward": b, "mu": torch.zeros(2, 2, 4), "logvar": torch.zeros(2, 2, 4)}
    t = window_losses(out, X)
    assert t["rec"].item() == pytest.approx((0 + 1) / 2 + (0 + 4) / 2)
    # L_bd pairs S^f_i with S^b_{n+1-i}: frame 3 differs by 1, frame 1 by 2 (squared 4)
    assert t["bd"].item() == pytest.approx((4 + 0 + 1) / 3)
    assert t["kl"].item() == pytest.approx(0.0)
    out["mu"] = torch.ones(2, 2, 4)
    assert window_losses(out, X)["kl"].item() == pytest.approx(0.5 * 4)
    out["backward"] = None
    t = window_losses(out, X)
    assert t["rec"].item() == pytest.approx(0.5) and t["bd"].item() == 0.0


# -- the loop ----------------------------------------------------------------------------------


def read_metrics(run):
    with open(run / "metrics.csv", newline="") as fh:
        return list(csv.DictReader(fh))


def training_rec(model, data, run) -> float:
    """Deterministic L_rec (z = mu) over every training window of ``data``'s first data set."""
    scaling = meshseq.load(run).scaling
    x = torch.from_numpy(scaling.apply(data.features[0]).astype(np.float32))
    sampler = WindowSampler([split_frames(len(x), 0.2)], ["limb"], 8)
    w = x[torch.from_numpy(sampler.rows(np.arange(len(sampler.starts))))]
    with torch.no_grad():
        return window_losses(model(w, sample=False), w)["rec"].item()


def test_loss_decreases_on_a_generated_sequence(tmp_path):
    _, data = limb_data()
    cfg = TrainConfig(iterations=1, window=8, batch=4, eval_every=50, checkpoint_every=0, log_every=1, lr=2e-3)
    first = train(data, tmp_path / "one", cfg, SMALL, device="cpu", progress=False, log=None)
    before = training_rec(first["model"], data, tmp_path / "one")
    cfg.iterations = 200
    result = train(data, tmp_path / "run", cfg, SMALL, device="cpu", progress=False, log=None)
    after = training_rec(result["model"], data, tmp_path / "run")
    assert after < 0.7 * before
    rows = read_metrics(tmp_path / "run")
    assert [int(r["iteration"]) for r in rows] == list(range(1, 201))
    held = [float(r["heldout_rec"]) for r in rows if r["heldout_rec"]]
    assert len(held) == 4 and np.all(np.isfinite(held))  # at 50, 100, 150, 200
    assert result["iteration"] == 200 and (tmp_path / "run" / "checkpoints" / "00000200").is_dir()


@pytest.mark.parametrize("variant", ["std-bd", "uni"])
def test_other_variants_train(tmp_path, variant):
    _, data = limb_data(frames=24)
    cfg = TrainConfig(iterations=3, window=6, batch=2, eval_every=0, checkpoint_every=0, log_every=1, w_kl=0.0)
    train(data, tmp_path / "run", cfg, dict(SMALL, variant=variant), device="cpu", progress=True, log=None)
    rows = read_metrics(tmp_path / "run")
    assert len(rows) == 3
    assert all(float(r["kl"]) >= 0 for r in rows)
    if variant == "uni":
        assert all(float(r["bd"]) == 0.0 for r in rows) and rows[-1]["heldout_bd"] == ""


def test_training_freezes_the_setup_objects_for_the_collector_and_unfreezes_after(tmp_path, monkeypatch):
    """The objects alive before the first iteration are exempt from the cyclic collector while
    training runs (``freeze_setup_objects``) and given back after, also when training fails."""
    assert gc.get_freeze_count() == 0
    seen = []
    real_step = torch.optim.Adam.step

    def step(self, *a, **kw):
        seen.append(gc.get_freeze_count())
        return real_step(self, *a, **kw)

    monkeypatch.setattr(torch.optim.Adam, "step", step)
    _, data = limb_data(frames=24)
    cfg = TrainConfig(iterations=2, window=6, batch=2, eval_every=0, checkpoint_every=0, log_every=0, w_kl=0.0)
    train(data, tmp_path / "run", cfg, SMALL, device="cpu", progress=False, log=None)
    assert len(seen) == 2 and min(seen) > 10_000  # modules, tensors, the libraries' objects
    assert gc.get_freeze_count() == 0
    gc.disable()
    try:
        assert not freeze_setup_objects() and gc.get_freeze_count() == 0  # collector off: nothing to do
    finally:
        gc.enable()


def test_several_data_sets_with_one_connectivity(tmp_path):
    a = twisting_limb(frames=20, rings=8, segments=6, seed=0)
    b = twisting_limb(frames=16, rings=8, segments=6, seed=1, twist_turns=0.5)
    c = twisting_limb(frames=16, rings=9, segments=6)
    for name, s in (("a", a), ("b", b), ("c", c)):
        save_sequence(s, tmp_path / f"{name}.npz")
    data = load_training_data([str(tmp_path / "a.npz"), str(tmp_path / "b.npz")])
    assert [len(f) for f in data.features] == [20, 16]
    np.testing.assert_allclose(data.reference, a.vertices[0])
    # the second data set's features refer to the first data set's first frame
    np.testing.assert_allclose(data.features[1], acap.extract(b.vertices, b.faces, reference=a.vertices[0]))
    with pytest.raises(MeshseqError, match="c.npz: connectivity differs"):
        load_training_data([str(tmp_path / "a.npz"), str(tmp_path / "c.npz")])
    cfg = TrainConfig(iterations=2, window=6, batch=2, eval_every=1, checkpoint_every=0)
    train(data, tmp_path / "run", cfg, SMALL, device="cpu", progress=False, log=None)
    m = meshseq.load(tmp_path / "run")
    assert [d["n_frames"] for d in m.meta["datasets"]] == [20, 16]
    assert m.meta["datasets"][1]["split"]["heldout"] == [13, 16]


def test_cli_train_then_load_and_use_the_model(tmp_path, capsys):
    seq, _ = limb_data(frames=30)
    save_sequence(seq, tmp_path / "limb.npz")
    run = tmp_path / "run"
    config = tmp_path / "run.toml"
    config.write_text("checkpoint_every = 2\nstride = 2\n[model]\nlstm_layers = 1\n")
    argv = ["train", str(tmp_path / "limb.npz"), "--out", str(run), "--iterations", "4", "--window", "6",
            "--batch", "2", "--latent", "16", "--config", str(config), "--no-progress",
            "--device", "auto", "--variant", "bd", "--seed", "3"]
    assert main(argv) == 0
    assert "trained to iteration 4" in capsys.readouterr().out
    assert sorted(p.name for p in (run / "checkpoints").iterdir()) == ["00000002", "00000004"]
    # nothing overwritten without --resume/--force
    assert main(argv) == 2
    assert "already exists" in capsys.readouterr().err
    assert main(argv + ["--force"]) == 0

    m = meshseq.load(run)
    assert m.iteration == 4 and m.config.latent == 16 and m.meta["train"]["stride"] == 2
    x = m.features(seq.vertices[:5])
    assert x.shape == (5, seq.n_vertices, 9) and x.dtype == np.float32
    assert np.abs(x).max() <= 0.95 + 1e-5  # scaled like the training frames (first 24 of 30 contain these)
    mu = m.encode(x)
    assert mu.shape == (5, 16) and isinstance(mu, np.ndarray)
    assert m.decode(mu).shape == (5, seq.n_vertices, 9)
    s = m.initial_state(2)
    s2, x1 = m.step(s, x[:2])
    assert x1.shape == (2, seq.n_vertices, 9) and s2[0].shape == (1, 2, 16)
    h = m.net.lstm(torch.from_numpy(mu[:2])[None], s)[0][0].detach()
    np.testing.assert_allclose(x1, x[:2] + m.decode(h.numpy()), atol=1e-5)
    frames = m.rollout(torch.from_numpy(x[:1]), 3, direction="backward")
    assert isinstance(frames, torch.Tensor) and frames.shape == (1, 4, seq.n_vertices, 9)
    v = m.vertices(x)
    assert v.shape == (5, seq.n_vertices, 3)
    # the reference mesh travels with the model: the first frame comes back (up to translation)
    ref = seq.vertices[0] - seq.vertices[0].mean(0)
    assert np.abs(v[0] - v[0].mean(0) - ref).max() < 1e-4 * np.ptp(ref)


def test_cli_errors_are_one_line(tmp_path, capsys):
    assert main(["train", str(tmp_path / "missing.npz"), "--out", str(tmp_path / "run")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("meshseq: error:") and "missing.npz" in err and err.count("\n") == 1
    seq, _ = limb_data(frames=10)
    save_sequence(seq, tmp_path / "limb.npz")
    # (the default recipe would shorten the window to the data: window_fit = "none" keeps it)
    (tmp_path / "as-given.toml").write_text('window_fit = "none"\n')
    assert main(["train", str(tmp_path / "limb.npz"), "--out", str(tmp_path / "run"), "--window", "32",
                 "--config", str(tmp_path / "as-given.toml")]) == 2
    assert "--window 32" in capsys.readouterr().err
    assert main(["train", str(tmp_path / "limb.npz"), "--out", str(tmp_path / "run"), "--batch", "0"]) == 2
    assert "--batch 0" in capsys.readouterr().err
    with pytest.raises(SystemExit) as exit_info:  # argparse rejects a bad choice itself
        main(["train", str(tmp_path / "limb.npz"), "--out", str(tmp_path / "run"), "--variant", "bi"])
    assert exit_info.value.code == 2 and "--variant" in capsys.readouterr().err
    if not torch.cuda.is_available():
        assert main(["train", str(tmp_path / "limb.npz"), "--out", str(tmp_path / "run"), "--device", "cuda"]) == 2
        assert "CUDA is not available" in capsys.readouterr().err


def test_tensorboard_events_when_installed_and_one_note_when_not(tmp_path, monkeypatch):
    import sys
    import types

    _, data = limb_data(frames=20)
    cfg = TrainConfig(iterations=4, window=6, batch=2, eval_every=2, checkpoint_every=0, log_every=1)
    notes = []
    monkeypatch.setitem(sys.modules, "torch.utils.tensorboard", None)  # import fails
    train(data, tmp_path / "a", cfg, SMALL, device="cpu", progress=False, log=notes.append)
    assert len([n for n in notes if "tensorboard is not installed" in n]) == 1
    assert not (tmp_path / "a" / "tensorboard").exists()

    scalars = []

    class FakeWriter:
        def __init__(self, log_dir, purge_step):
            scalars.append(("init", log_dir, purge_step))

        def add_scalar(self, tag, value, step):
            scalars.append((tag, value, step))

        def close(self):
            scalars.append(("close",))

    monkeypatch.setitem(sys.modules, "torch.utils.tensorboard", types.SimpleNamespace(SummaryWriter=FakeWriter))
    train(data, tmp_path / "b", cfg, SMALL, device="cpu", progress=False, log=None)
    assert scalars[0] == ("init", str(tmp_path / "b" / "tensorboard"), 1) and scalars[-1] == ("close",)
    tags = {s[0] for s in scalars[1:-1]}
    assert {"loss", "rec", "bd", "kl", "l2", "heldout/rec", "heldout/bd"} <= tags
    assert sorted({s[2] for s in scalars[1:-1] if s[0] == "heldout/rec"}) == [2, 4]


# -- precision and the GPU path ----------------------------------------------------------------


def test_bf16_precision_trains_close_to_float32(tmp_path):
    _, data = limb_data(frames=30)
    cfg = dict(iterations=3, window=6, batch=3, eval_every=3, log_every=1)
    f32 = train(data, tmp_path / "f32", TrainConfig(**cfg), SMALL, device="cpu", progress=False, log=None)
    bf16 = train(data, tmp_path / "bf16", TrainConfig(precision="bf16", **cfg), SMALL, device="cpu",
                 progress=False, log=None)
    assert math.isfinite(bf16["loss"]) and abs(bf16["loss"] - f32["loss"]) <= 0.05 * abs(f32["loss"])
    assert all(p.dtype == torch.float32 for p in bf16["model"].parameters())  # float32 master weights
    with pytest.raises(MeshseqError, match="precision"):
        TrainConfig(precision="fp8")


@pytest.mark.skipif(not torch.cuda.is_available(),
                    reason="no CUDA GPU on this machine: the GPU training path is untested here")
@pytest.mark.parametrize("precision", ["float32", "bf16"])
def test_cuda_trains_and_resumes(tmp_path, precision):
    _, data = limb_data(frames=30)
    cfg = dict(window=6, batch=3, eval_every=2, checkpoint_every=2, log_every=1, precision=precision)
    one = train(data, tmp_path / "a", TrainConfig(iterations=4, **cfg), SMALL, device="cuda", progress=False,
                log=None)
    train(data, tmp_path / "b", TrainConfig(iterations=2, **cfg), SMALL, device="cuda", progress=False, log=None)
    two = train(data, tmp_path / "b", TrainConfig(iterations=4, **cfg), SMALL, device="cuda", resume=True,
                progress=False, log=None)
    assert two["iteration"] == 4 and math.isfinite(one["loss"])
    assert next(one["model"].parameters()).device.type == "cuda"
    sa, sb = one["model"].state_dict(), two["model"].state_dict()
    for k in sa:  # CUDA reductions (sparse products, atomics) need not repeat bit for bit
        torch.testing.assert_close(sa[k], sb[k], atol=1e-5, rtol=1e-4, msg=k)
    # the same roll-out on CPU and on CUDA gives the same loss
    model = one["model"]
    w = 0.1 * torch.randn(2, 5, model.config.n_vertices, 9)
    with torch.no_grad():
        gpu = WindowLoss(model, TrainConfig(w_vertex=0.0))(w.cuda(), sample=False)[0].item()
        cpu = WindowLoss(model.cpu(), TrainConfig(w_vertex=0.0))(w, sample=False)[0].item()
    assert abs(gpu - cpu) <= 1e-4 * abs(cpu)


# -- divergence (issue 13.1) -------------------------------------------------------------------


def test_divergence_stops_with_one_line_and_keeps_the_last_good_checkpoint(tmp_path, capsys):
    from meshseq import checkpoint as ckpt

    seq, _ = limb_data(frames=30)
    save_sequence(seq, tmp_path / "limb.npz")
    run = tmp_path / "run"
    (tmp_path / "run.toml").write_text("checkpoint_every = 1\nlog_every = 1\nkeep = 3\nlr = 1e6\n"
                                       "[model]\nlstm_layers = 1\n")
    argv = ["train", str(tmp_path / "limb.npz"), "--out", str(run), "--iterations", "20", "--window", "6",
            "--batch", "2", "--latent", "16", "--config", str(tmp_path / "run.toml"), "--no-progress"]
    assert main(argv) == 2
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if line.startswith("meshseq: error:")]
    assert len(lines) == 1 and "Traceback" not in err, err
    message = lines[0]
    assert "training diverged at iteration" in message and "a smaller lr" in message
    bad_it = int(message.split("iteration ")[1].split(":")[0])
    assert any(term in message for term in ("the loss term", "the total loss", "the gradient norm"))
    folders = ckpt.list_checkpoints(run)
    assert folders and int(folders[-1].name) == bad_it - 1 and str(folders[-1]) in message
    for folder in folders:  # every checkpoint written is finite and loads
        assert ckpt.is_valid(folder)
    rows = read_metrics(run)
    assert [int(r["iteration"]) for r in rows] == list(range(1, bad_it))
    assert all(math.isfinite(float(r["loss"])) for r in rows)
    # the last good checkpoint is a working model
    assert meshseq.load(run).iteration == bad_it - 1


def test_non_finite_gradient_is_caught_before_the_update(tmp_path, monkeypatch):
    from meshseq.training import loop as train_module

    _, data = limb_data(frames=24)
    real = train_module.grad_norm
    calls = []

    def poisoned(params):
        calls.append(1)
        return real(params) * (float("inf") if len(calls) == 3 else 1.0)

    monkeypatch.setattr(train_module, "grad_norm", poisoned)
    cfg = TrainConfig(iterations=5, window=6, batch=2, eval_every=0, checkpoint_every=1, log_every=1)
    with pytest.raises(MeshseqError, match=r"diverged at iteration 3: the gradient norm is inf") as info:
        train(data, tmp_path / "run", cfg, SMALL, device="cpu", progress=False, log=None)
    assert "00000002" in str(info.value)
    before = meshseq.load(tmp_path / "run").net.state_dict()
    assert meshseq.load(tmp_path / "run").iteration == 2 and all(torch.isfinite(v).all() for v in before.values())


def test_loaders_refuse_non_finite_weights_and_commands_write_no_non_finite_output(tmp_path, capsys, monkeypatch):
    import json

    from safetensors.torch import load_file, save_file

    from meshseq import checkpoint as ckpt

    seq, data = limb_data(frames=24)
    save_sequence(seq, tmp_path / "limb.npz")
    run = tmp_path / "run"
    train(data, run, TrainConfig(iterations=2, window=6, batch=2, checkpoint_every=0), SMALL, device="cpu",
          progress=False, log=None)
    folder = ckpt.list_checkpoints(run)[-1]
    out = tmp_path / "out.npz"
    common = [str(run), str(tmp_path / "limb.npz"), "-o", str(out)]
    # a finite model whose roll-out is not finite: predict and complete write nothing
    from meshseq import synthesize

    monkeypatch.setattr(synthesize, "predict", lambda model, feats, n, **kw: np.full((n,) + feats.shape[1:], np.nan))
    assert main(["predict", *common, "--frames", "3"]) == 2
    err = capsys.readouterr().err
    # 3 given frames (predict's default) and 3 generated: the first generated one is frame 3 of 6
    assert err.count("\n") == 1 and "not finite" in err and "frame 3 of 6" in err and not out.exists()
    monkeypatch.undo()
    real_complete = synthesize.complete

    def nan_complete(*args, **kwargs):
        c = real_complete(*args, **kwargs)
        c.frames[:, 2] = np.nan
        return c

    monkeypatch.setattr(synthesize, "complete", nan_complete)
    assert main(["complete", *common, "--keyframes", "0,6"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "not finite" in err and not out.exists()
    monkeypatch.undo()
    # NaN weights (a checkpoint of an older meshseq): refused by every loader
    tensors = load_file(str(folder / "model.safetensors"))
    tensors["model.fc.weight"][:] = float("nan")
    save_file(tensors, str(folder / "model.safetensors"))
    meta = json.loads((folder / "model.json").read_text())
    meta["sha256"] = ckpt._sha256(folder / "model.safetensors")
    (folder / "model.json").write_text(json.dumps(meta))
    with pytest.raises(MeshseqError, match="model.fc.weight: non-finite values"):
        meshseq.load(folder)
    for argv in (["predict", *common], ["complete", *common, "--keyframes", "0,6"],
                 ["evaluate", str(run), str(tmp_path / "limb.npz"), "--gaps", "none", "--methods", "ours"]):
        assert main(argv) == 2
        err = capsys.readouterr().err
        lines = [line for line in err.splitlines() if line.startswith("meshseq: error:")]
        assert len(lines) == 1 and "model.fc.weight: non-finite values" in lines[0] and "Traceback" not in err
        assert not out.exists()


def test_squared_norm_is_the_sum_of_squares_with_autograds_gradient():
    from meshseq.train import squared_norm

    torch.manual_seed(0)
    for shape in [(128, 3000), (18, 9), (512, 128)]:
        p = (torch.randn(*shape) * 0.01 + 0.003).requires_grad_()
        ref = p.square().sum()
        value = squared_norm(p)
        assert float(value.detach()) == pytest.approx(float(p.detach().double().square().sum()), rel=1e-6)
        (g,) = torch.autograd.grad(3.0 * value, p)
        (g_ref,) = torch.autograd.grad(3.0 * ref, p)
        assert torch.equal(g, g_ref)
    with torch.autocast("cpu", dtype=torch.bfloat16):  # stays float32 under --precision bf16
        assert squared_norm(p).dtype == torch.float32


def test_gather_frames_is_advanced_indexing():
    from meshseq.train import gather_frames

    frames = torch.randn(10, 7, 9)
    rows = torch.tensor([[3, 4, 5], [9, 8, 7]])
    assert torch.equal(gather_frames(frames, rows), frames[rows])


# -- the command surface: a short --help, everything else in --config FILE.toml -----------------


def _train_args(*argv):
    from meshseq.cli import build_parser

    return build_parser().parse_args(["train", "DATA", "--out", "RUN", *argv])


def test_train_help_is_short_and_shows_what_users_set(capsys):
    with pytest.raises(SystemExit):
        main(["train", "--help"])
    text = capsys.readouterr().out
    assert len(text.splitlines()) <= 60, text
    for flag in ("--out", "--iterations", "--variant", "--window", "--batch", "--latent", "--device", "--threads",
                 "--seed", "--resume", "--force", "--validation", "--precision", "--recipe", "--config"):
        assert flag in text, flag
    assert "--w-motion" not in text and "--lstm-layers" not in text  # in --config now


def test_config_file_sits_between_the_recipe_and_the_command_line(tmp_path):
    from meshseq.cli.train_cmds import train_options
    from meshseq.train import RECIPES

    config = tmp_path / "run.toml"
    config.write_text('window = 12\nw_motion = 3.0\nema_decay = "none"\neval_every = 7\n'
                      '[model]\nlstm_layers = 2\nconv_impl = "gather"\n')
    cfg, model = train_options(_train_args("--recipe", "paper", "--config", str(config), "--window", "6",
                                           "--latent", "8"))
    assert cfg.window == 6 and cfg.w_motion == 3.0 and cfg.ema_decay is None and cfg.eval_every == 7
    assert cfg.w_l2 == RECIPES["paper"]["w_l2"] == 0.1 and cfg.input_norm is False  # the rest: the recipe's
    assert model == {"lstm_layers": 2, "conv_impl": "gather", "latent": 8}
    cfg, model = train_options(_train_args())
    assert cfg == TrainConfig() and model == {}
    # an integer where a number is expected is that number
    config.write_text("lr = 1\n")
    assert train_options(_train_args("--config", str(config)))[0].lr == 1.0


@pytest.mark.parametrize("text, message", [
    ("w_motoin = 1\n", "w_motoin: not a training option (did you mean w_motion?"),
    ('lr = "fast"\n', "lr: expected a number, got 'fast'"),
    ("window = 6.5\n", "window: expected an integer, got 6.5"),
    ("input_norm = 1\n", "input_norm: expected true or false, got 1"),
    ("adam_beta2 = 1.5\n", "adam_beta2: 1.5: expected a number in [0, 1)"),
    ('fc_lr = "fast"\n', "fc_lr: 'fast': expected one of fan-in, encoder, none"),
    ('consistency = "bfs"\n', "consistency: 'bfs': expected one of temporal-mst, temporal, spatial, greedy"),
    ("[model]\nlayers = 2\n", "model.layers: not a model option"),
    ("[model]\nlatent = 0\n", "model.latent: 0: expected an integer of at least 1"),
    ("lr = \n", "not valid TOML"),
])
def test_config_file_errors_are_one_line_naming_the_file_and_key(text, message, tmp_path, capsys):
    config = tmp_path / "bad.toml"
    config.write_text(text)
    assert main(["train", str(tmp_path / "missing.npz"), "--out", str(tmp_path / "run"), "--config",
                 str(config)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and f"{config}" in err and message in err, err
    assert not (tmp_path / "run").exists()
    assert main(["train", "x.npz", "--out", str(tmp_path / "run"), "--config", str(tmp_path / "none.toml")]) == 2
    assert "none.toml" in capsys.readouterr().err


# -- blow-ups (rollback) -----------------------------------------------------------------------


def test_a_blow_up_is_a_loss_far_above_the_median_of_enough_iterations_before():
    from meshseq.training.optim import BLOWUP, SNAPSHOT_EVERY, blown_up

    history = [1.0, 3.0] * (SNAPSHOT_EVERY // 2)  # median 2
    assert blown_up(2.0 * BLOWUP + 1e-6, history)
    assert not blown_up(2.0 * BLOWUP, history)  # a spike, however large, up to the limit
    assert not blown_up(1e9, history[:-1])  # too few iterations known yet


def poisoned_loss(monkeypatch, bad_calls, factor=1e6):
    """WindowLoss whose total is multiplied by ``factor`` on the calls numbered in ``bad_calls`` (1-based)."""
    from meshseq.training import loop

    calls = []

    class Poisoned(loop.WindowLoss):
        def forward(self, *args, **kwargs):
            total, terms = super().forward(*args, **kwargs)
            calls.append(1)
            return (total * factor if len(calls) in bad_calls else total), terms

    monkeypatch.setattr(loop, "WindowLoss", Poisoned)


@pytest.fixture
def short_snapshots(monkeypatch):
    """Snapshots (and the history a blow-up needs) every 4 iterations instead of 100."""
    from meshseq.training import loop, optim

    monkeypatch.setattr(optim, "SNAPSHOT_EVERY", 4)
    monkeypatch.setattr(loop, "SNAPSHOT_EVERY", 4)


def test_snapshots_leave_a_run_that_never_blows_up_unchanged(tmp_path, short_snapshots):
    _, data = limb_data(frames=24)
    weights = []
    for rollback in (True, False):
        cfg = TrainConfig(iterations=12, window=6, batch=2, eval_every=0, checkpoint_every=0, rollback=rollback)
        train(data, tmp_path / str(rollback), cfg, SMALL, device="cpu", progress=False, log=None)
        weights.append(meshseq.load(tmp_path / str(rollback)).net.state_dict())
    assert all(torch.equal(weights[0][k], weights[1][k]) for k in weights[0])


def test_a_blow_up_goes_back_to_a_snapshot_at_half_the_learning_rate(tmp_path, monkeypatch, short_snapshots):
    from meshseq.training.run import resume_point

    _, data = limb_data(frames=24)
    poisoned_loss(monkeypatch, {10})
    said = []
    cfg = TrainConfig(iterations=14, window=6, batch=2, eval_every=0, checkpoint_every=0, log_every=1)
    out = train(data, tmp_path / "run", cfg, SMALL, device="cpu", progress=False, log=said.append)
    assert out["iteration"] == 14
    lines = [s for s in said if "blew up" in s]
    assert len(lines) == 1 and "iteration 10:" in lines[0] and "weights of iteration 4" in lines[0], said
    found = resume_point(tmp_path / "run")
    groups = found.state_meta["optimizer"]["param_groups"]
    assert [g["lr"] for g in groups] == [cfg.lr / 2] * len(groups)
    assert found.state_meta["rollbacks"] == 1
    assert all(torch.isfinite(v).all() for v in meshseq.load(tmp_path / "run").net.state_dict().values())
    rows = read_metrics(tmp_path / "run")
    assert float(rows[9]["loss"]) > 1e4 * float(rows[8]["loss"])  # the blow-up is in the metrics, as it happened


def test_training_that_keeps_blowing_up_stops_with_one_line(tmp_path, monkeypatch, short_snapshots):
    _, data = limb_data(frames=24)
    poisoned_loss(monkeypatch, set(range(9, 100)))
    cfg = TrainConfig(iterations=30, window=6, batch=2, eval_every=0, checkpoint_every=0)
    with pytest.raises(MeshseqError, match=r"diverged at iteration 12: the loss blew up to .* the 4th time"):
        train(data, tmp_path / "run", cfg, SMALL, device="cpu", progress=False, log=None)


def test_a_loss_that_is_not_finite_goes_back_too_once_a_snapshot_is_old_enough(tmp_path, monkeypatch,
                                                                               short_snapshots):
    _, data = limb_data(frames=24)
    poisoned_loss(monkeypatch, {10}, factor=float("nan"))
    said = []
    cfg = TrainConfig(iterations=12, window=6, batch=2, eval_every=0, checkpoint_every=0)
    assert train(data, tmp_path / "run", cfg, SMALL, device="cpu", progress=False, log=said.append)["iteration"] == 12
    assert [s for s in said if "not finite" in s] == [
        "iteration 10: the loss is not finite; training went back to the weights of iteration 4 and goes on at "
        f"half the learning rate ({cfg.lr / 2:g})"]
    assert all(torch.isfinite(v).all() for v in meshseq.load(tmp_path / "run").net.state_dict().values())
