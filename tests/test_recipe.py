"""Training recipe: teacher-forced warm-up, the step scale, recipes and the collapse warning."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from conftest import training_data
from meshseq import acap
from meshseq.data.synthetic import twisting_limb
from meshseq.data.windows import split_frames
from meshseq.errors import MeshseqError
from meshseq.mesh import Topology
from meshseq.model import BDLSTM, ModelConfig
from meshseq.train import (
    RECIPE_OPTIONS,
    RECIPES,
    TrainConfig,
    WindowLoss,
    collapse_warning,
    latent_spread,
    motion_loss,
    step_spread,
    train,
)

pytestmark = pytest.mark.usefixtures("one_torch_thread")
SMALL = {"latent": 16, "lstm_layers": 2}


def limb():
    seq = twisting_limb(frames=40, rings=10, segments=8, seed=0)
    feats = acap.extract(seq.vertices, seq.faces)
    return seq, feats


def tiny_cli(folder, options: str = "", name: str = "tiny") -> list[str]:
    """A one-iteration ``meshseq train`` on a tiny model (CLI option tests): its flags and a
    ``--config`` file (``folder/NAME.toml``) holding ``options`` (TOML lines of TrainConfig fields)."""
    config = folder / f"{name}.toml"
    config.write_text(f"eval_every = 0\n{options}\n[model]\nlstm_layers = 1\n")
    return ["--iterations", "1", "--window", "6", "--batch", "2", "--latent", "8", "--no-progress",
            "--config", str(config)]


def stored_configs(run):
    """``(train, model)`` configs of the first checkpoint of ``run``."""
    import json

    meta = json.loads(next((run / "checkpoints").iterdir()).joinpath("model.json").read_text())
    return meta["train"], meta["model"]


def small_model(seq, variant="bd", step_scale=None, seed=0):
    torch.manual_seed(seed)
    cfg = ModelConfig(n_vertices=seq.n_vertices, variant=variant, step_scale=step_scale, **SMALL)
    return BDLSTM(cfg, Topology.from_faces(seq.faces, seq.n_vertices))


def twin_models(seq, **option):
    """Two small models with the same weights: one with the model ``option``, one without."""
    torch.manual_seed(0)
    topo = Topology.from_faces(seq.faces, seq.n_vertices)
    bounded = BDLSTM(ModelConfig(n_vertices=seq.n_vertices, **option, **SMALL), topo)
    free = BDLSTM(ModelConfig(n_vertices=seq.n_vertices, **SMALL), topo)
    free.load_state_dict(bounded.state_dict())
    return bounded, free


@pytest.mark.parametrize("variant", ["bd", "std-bd", "uni"])
def test_given_frames_are_teacher_forced_then_the_chains_run_free(variant):
    seq, feats = limb()
    net = small_model(seq, variant).eval()
    x = torch.from_numpy(acap.Scaling.fit(feats).apply(feats)).float()
    windows = torch.stack([x[0:10], x[5:15]])  # (B=2, n=10, V, 9)
    B, n, given = 2, 10, 3
    with torch.no_grad():
        out = net(windows, sample=False, given=given)
        # the same by single steps: true frames 0..given-1 in, then the chain's own frames
        nb = 0 if variant == "uni" else B
        chains = windows if variant == "uni" else torch.cat([windows, windows.flip(1)])
        state = net.initial_state(B, nb)
        frames = [chains[:, 0]]
        cur = chains[:, 0]
        for t in range(n - 1):
            inp = chains[:, t] if t < given else cur
            state, cur, _, _ = net.step(state, inp, n_forward=B)
            frames.append(cur)
        ref = torch.stack(frames, 1)
    torch.testing.assert_close(out["forward"], ref[:B], rtol=1e-5, atol=1e-6)
    if variant != "uni":
        torch.testing.assert_close(out["backward"], ref[B:], rtol=1e-5, atol=1e-6)
    assert out["mu"].shape == (n - 1, len(chains), SMALL["latent"])
    # given=1 is the paper's free-running chain, and differs from the warm-up
    with torch.no_grad():
        free = net(windows, sample=False, given=1)["forward"]
    assert not torch.allclose(free[:, 3:], out["forward"][:, 3:])


def test_step_scale_multiplies_the_decoded_change_per_channel():
    seq, feats = limb()
    plain = small_model(seq, step_scale=None).eval()
    scale = [2.0] * 3 + [0.5] * 6
    scaled = small_model(seq, step_scale=scale).eval()
    scaled.load_state_dict(plain.state_dict())
    x = torch.from_numpy(acap.Scaling.fit(feats).apply(feats[:2])).float()
    with torch.no_grad():
        s0 = plain.initial_state(2)
        _, a, _, _ = plain.step(s0, x)
        _, b, _, _ = scaled.step(s0, x)
    torch.testing.assert_close(b - x, (a - x) * torch.tensor(scale), rtol=1e-5, atol=1e-7)
    with pytest.raises(MeshseqError, match="step_scale"):
        ModelConfig(n_vertices=5, step_scale=[1.0, 2.0])
    with pytest.raises(MeshseqError, match="step_scale"):
        ModelConfig(n_vertices=5, step_scale=[1.0] * 8 + [0.0])


def test_step_spread_is_the_rms_change_inside_training_segments():
    rng = np.random.default_rng(0)
    T, V = 30, 4
    steps = np.array([0.1, 0.2, 0.3, 0, 0, 0, 0, 0, 0.4])
    x = np.cumsum(np.broadcast_to(steps, (T, V, 9)), axis=0) + 0 * rng.normal(size=(T, V, 9))
    x[25:] += 100.0  # inside the held-out block: a jump there must not count
    split = split_frames(T, 0.2)  # held out 24..29
    rms = step_spread([x], [split])
    np.testing.assert_allclose(rms[[0, 1, 2, 8]], [0.1, 0.2, 0.3, 0.4])
    np.testing.assert_allclose(rms[3:8], np.mean([0.1, 0.2, 0.3, 0.4]))  # still channels: the mean
    np.testing.assert_allclose(step_spread([x], [split], stride=2)[0], 0.2)


def test_latent_spread_and_collapse_warning():
    mu = torch.zeros(5, 4, 8)
    assert float(latent_spread(mu)) == 0.0
    assert collapse_warning(0.0, 0.0, 0.1) is not None
    assert "collapsed" in collapse_warning(0.001, 0.5, 0.1)
    assert collapse_warning(0.001, 0.5, 0.0) is None  # no KL term: the spread decides
    alive = torch.randn(5, 4, 8, generator=torch.Generator().manual_seed(0))
    assert 0.7 < float(latent_spread(alive)) < 1.3
    assert collapse_warning(3.0, float(latent_spread(alive)), 0.1) is None


def test_latent_health_separates_the_mean_from_the_noise_and_is_logged(tmp_path):
    import csv

    from meshseq.train import latent_health

    g = torch.Generator().manual_seed(0)
    mu = 3.0 * torch.randn(6, 4, 16, generator=g)
    logvar = torch.full((6, 4, 16), 2.0 * np.log(0.5))
    logvar[..., 0] = 2.0 * np.log(8.5)  # one dimension's noise ran away
    h = latent_health(mu, logvar)
    assert float(h["latent_rms"]) == pytest.approx(float(mu.square().mean().sqrt()))
    assert float(h["latent_sigma"]) == pytest.approx((15 * 0.5 + 8.5) / 16)
    assert float(h["latent_spread"]) == pytest.approx(float(latent_spread(mu)))
    # training writes them, with the motion term and the gradient norm, to metrics.csv
    seq, feats = limb()
    cfg = TrainConfig(iterations=4, window=8, batch=2, eval_every=0, log_every=2, checkpoint_every=0)
    train(training_data(seq, feats), tmp_path / "run", cfg, SMALL, progress=False, log=None)
    with open(tmp_path / "run" / "metrics.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert [r["iteration"] for r in rows] == ["2", "4"]
    for key in ("motion", "latent_rms", "latent_sigma", "grad_norm"):
        assert all(float(r[key]) > 0 for r in rows), key
    assert all(float(r["latent_sigma"]) <= 1.0 for r in rows)  # the default recipe's logvar_max = 0


def test_training_warns_when_the_latent_collapses(tmp_path, monkeypatch):
    import meshseq.training.loop as tr

    seq, feats = limb()
    data = training_data(seq, feats)
    monkeypatch.setattr(tr, "COLLAPSE_AFTER", 0)
    messages = []
    # an overwhelming L_2 crushes the tied FC at once: the latent carries nothing
    cfg = TrainConfig(iterations=20, window=8, batch=2, eval_every=10, log_every=10, checkpoint_every=0,
                      w_l2=1e4, lr=1e-2, holdout=0.2)
    train(data, tmp_path / "run", cfg, SMALL, progress=False, log=messages.append)
    assert any("collapsed" in m for m in messages), messages
    messages.clear()
    cfg = TrainConfig(iterations=20, window=8, batch=2, eval_every=10, log_every=10, checkpoint_every=0,
                      w_l2=0.0, w_kl=0.0, holdout=0.2)
    train(data, tmp_path / "run2", cfg, SMALL, progress=False, log=messages.append)
    assert not any("collapsed" in m for m in messages), messages


def test_given_option_is_checked_and_recipes_are_known_options():
    with pytest.raises(MeshseqError, match="given"):
        TrainConfig(given=0)
    with pytest.raises(MeshseqError, match="given"):
        TrainConfig(window=8, given=8)
    with pytest.raises(MeshseqError, match="step_scale"):
        TrainConfig(step_scale="big")
    for name, recipe in RECIPES.items():
        TrainConfig(**recipe)  # every recipe is valid
        assert set(recipe) == set(RECIPE_OPTIONS)  # and sets every recipe option
    assert RECIPES["paper"]["w_l2"] == 0.1 and RECIPES["paper"]["given"] == 1
    assert RECIPES["paper"]["step_scale"] == "none"
    default = TrainConfig()
    assert all(getattr(default, k) == v for k, v in RECIPES["default"].items())


def test_step_scale_data_is_stored_and_reloaded(tmp_path):
    import meshseq

    seq, feats = limb()
    data = training_data(seq, feats)
    cfg = TrainConfig(iterations=2, window=8, batch=2, eval_every=0, checkpoint_every=0, step_scale="data", given=3)
    train(data, tmp_path / "run", cfg, SMALL, progress=False, log=None)
    model = meshseq.load(tmp_path / "run")
    scale = model.config.step_scale
    assert scale is not None and len(scale) == 9 and all(v > 0 for v in scale)
    scaled = model.scaling.apply(feats)
    split = split_frames(len(feats), 0.2)
    np.testing.assert_allclose(scale, step_spread([scaled], [split]), rtol=1e-6)


def test_cli_recipe_names_match_the_library():
    from meshseq.cli.train_cmds import RECIPE_NAMES

    assert set(RECIPE_NAMES) == set(RECIPES)


def test_input_norm_standardises_the_encoder_input_and_is_stored(tmp_path):
    import meshseq

    seq, feats = limb()
    data = training_data(seq, feats)
    cfg = TrainConfig(iterations=2, window=8, batch=2, eval_every=0, checkpoint_every=0, input_norm=True)
    train(data, tmp_path / "run", cfg, SMALL, progress=False, log=None)
    model = meshseq.load(tmp_path / "run")
    assert model.config.input_norm
    scaled = model.scaling.apply(feats[:32])  # the training frames (20% held out)
    offset = model.net.input_offset[:, :, 0].T.numpy()  # (V, 9)
    np.testing.assert_allclose(offset, scaled.mean(0), rtol=1e-5, atol=1e-6)
    z = (scaled - offset) / model.net.input_spread[:, 0, 0].numpy()
    np.testing.assert_allclose(np.sqrt(np.square(z).mean(axis=(0, 1))), 1.0, rtol=1e-4)
    # the encoder sees the normalised frames: equal to a plain encoder fed them by hand
    x = torch.from_numpy(scaled[:3]).float()
    plain = BDLSTM(ModelConfig(**{**model.config.to_dict(), "input_norm": False}),
                   Topology.from_faces(seq.faces, seq.n_vertices))
    plain.load_state_dict({k: v for k, v in model.net.state_dict().items() if not k.startswith("input_")})
    with torch.no_grad():
        mu_a, _ = model.net.encode(x)
        mu_b, _ = plain.encode(torch.from_numpy(z[:3]).float())
    torch.testing.assert_close(mu_a, mu_b, rtol=1e-4, atol=1e-5)


def test_cli_recipe_sets_the_options_and_flags_override(tmp_path):
    from meshseq.cli import main
    from meshseq.io import save_sequence

    seq, _ = limb()
    data = tmp_path / "limb.npz"
    save_sequence(seq, data)
    common, stored = tiny_cli(tmp_path), stored_configs

    assert main(["train", str(data), "--out", str(tmp_path / "p"), "--recipe", "paper", *common]) == 0
    train_opts, model_opts = stored(tmp_path / "p")
    assert train_opts["w_l2"] == 0.1 and train_opts["input_norm"] is False and model_opts["input_norm"] is False
    assert main(["train", str(data), "--out", str(tmp_path / "d"), *common]) == 0
    train_opts, model_opts = stored(tmp_path / "d")
    assert train_opts["w_l2"] == RECIPES["default"]["w_l2"] and model_opts["input_norm"] is True
    assert main(["train", str(data), "--out", str(tmp_path / "o"), "--recipe", "paper",
                 *tiny_cli(tmp_path, "input_norm = true\nw_l2 = 0.5\ngiven = 2", "o")]) == 0
    train_opts, model_opts = stored(tmp_path / "o")
    assert train_opts["w_l2"] == 0.5 and train_opts["given"] == 2 and model_opts["input_norm"] is True
    assert train_opts["w_kl"] == 0.1  # the rest from the paper's recipe


def test_fc_learning_rate_scales_with_the_fan_in():
    """fc_lr="fan-in": the FC weight's Adam rate is lr * min(1, 9000 / (V * 9)); every other
    parameter keeps lr; "none" (the paper) is one group."""
    import meshseq.train as T

    seq, _ = limb()
    net = small_model(seq)
    fan_in = net.fc.weight.shape[1]  # vertices x 9, under the reference 9000
    cfg = TrainConfig(lr=2e-3, fc_lr="fan-in")
    assert fan_in == seq.n_vertices * 9 < 9000 and T.fc_lr_factor(fan_in, "fan-in") == 1.0 and T.fc_lr_factor(90000, "fan-in") == pytest.approx(0.1)
    assert T.fc_lr_factor(90000, "none") == 1.0
    [one] = T.parameter_groups(net, cfg)  # below the reference: one rate
    assert one["names"] == [n for n, _ in net.named_parameters()] and "lr" not in one
    rest, fc = T.parameter_groups(net, TrainConfig(lr=2e-3, fc_lr="fan-in", fc_lr_fan_in=fan_in // 4))  # as if 4x
    assert fc["names"] == ["fc.weight"] and fc["params"][0] is net.fc.weight
    assert fc["lr"] == pytest.approx(2e-3 * (fan_in // 4) / fan_in)
    assert "fc.weight" not in rest["names"] and len(rest["params"]) == len(list(net.parameters())) - 1
    assert len(T.parameter_groups(net, TrainConfig(lr=2e-3, fc_lr="none"))) == 1
    with pytest.raises(MeshseqError, match="fc_lr"):
        TrainConfig(fc_lr="small")
    for bad in (0, -5, 2.5, True, "900"):
        with pytest.raises(MeshseqError, match="fc_lr_fan_in"):
            TrainConfig(fc_lr_fan_in=bad)
    # a config stored before the options existed reproduces its run: one rate, the reference 9000
    stored = TrainConfig().to_dict()
    del stored["fc_lr"], stored["fc_lr_fan_in"]
    assert TrainConfig.from_dict(stored).fc_lr == "none"
    assert TrainConfig.from_dict(stored).fc_lr_fan_in == T.FC_REFERENCE_FAN_IN == 9000


@pytest.mark.parametrize("fc_lr", ["fan-in", "encoder"])
def test_two_learning_rates_train_as_set_and_resume_bit_for_bit(tmp_path, fc_lr):
    import json

    seq, feats = limb()
    fan_in = seq.n_vertices * 9
    data = training_data(seq, feats)
    cfg = dict(window=6, batch=2, eval_every=0, checkpoint_every=3, log_every=1, lr=1e-3, fc_lr_fan_in=fan_in // 4,
               fc_lr=fc_lr)
    one = train(data, tmp_path / "a", TrainConfig(iterations=6, **cfg), SMALL, device="cpu", progress=False, log=None)
    train(data, tmp_path / "b", TrainConfig(iterations=3, **cfg), SMALL, device="cpu", progress=False, log=None)
    two = train(data, tmp_path / "b", TrainConfig(iterations=6, **cfg), SMALL,
                device="cpu", resume=True, progress=False, log=None)
    for k, v in one["model"].state_dict().items():
        assert torch.equal(v, two["model"].state_dict()[k]), k
    plain = train(data, tmp_path / "c", TrainConfig(iterations=6, **(cfg | {"fc_lr": "none"})), SMALL,
                  device="cpu", progress=False, log=None)
    torch.manual_seed(0)
    init = small_model(seq).fc.weight.detach()  # what train() starts from (seed 0)
    moved = (one["model"].fc.weight.detach() - init).abs().mean()
    if fc_lr == "encoder":  # one rate: Adam's steps as large, in another direction than the plain gradient's
        diff = (one["model"].fc.weight - plain["model"].fc.weight).detach().abs().mean()
        assert float(diff) > 0.01 * float(moved)  # 0 if the option did nothing
        assert float(moved / (plain["model"].fc.weight.detach() - init).abs().mean()) == pytest.approx(1, abs=0.2)
        return
    state = json.loads((tmp_path / "a" / "checkpoints" / "00000006" / "state.json").read_text())
    groups = state["optimizer"]["param_groups"]
    assert [g["lr"] for g in groups] == pytest.approx([1e-3, 1e-3 * (fan_in // 4) / fan_in])
    assert groups[1]["params"] == ["fc.weight"]
    assert float(moved / (plain["model"].fc.weight.detach() - init).abs().mean()) < 0.5  # the rate took effect


def test_a_run_stored_before_fc_lr_existed_resumes_with_one_rate(tmp_path):
    import json

    import meshseq
    from meshseq import checkpoint as ckpt

    seq, feats = limb()
    data = training_data(seq, feats)
    cfg = dict(window=6, batch=2, eval_every=0, checkpoint_every=2, log_every=1)
    train(data, tmp_path / "run", TrainConfig(iterations=2, **cfg), SMALL, progress=False, log=None)
    meta_path = tmp_path / "run" / "checkpoints" / "00000002" / "model.json"
    meta = json.loads(meta_path.read_text())
    del meta["train"]["fc_lr"]  # as written before the option existed
    meta_path.write_text(json.dumps(meta))
    assert meshseq.load(tmp_path / "run").iteration == 2
    out = train(data, tmp_path / "run", TrainConfig(iterations=4, **cfg), SMALL, resume=True, progress=False,
                log=None)
    assert out["iteration"] == 4
    assert ckpt.load_folder(tmp_path / "run" / "checkpoints" / "00000004").meta["train"]["fc_lr"] == "none"


def test_motion_loss_measures_the_size_of_each_generated_change_against_the_truth():
    torch.manual_seed(0)
    truth = torch.randn(3, 6, 5, 9)
    true_speed = (truth[:, 1:] - truth[:, :-1]).square().sum((-2, -1)).sqrt()  # (3, 5)
    same = {"forward": truth.clone(), "backward": truth.flip(1).clone()}
    assert motion_loss(same, truth).item() < 1e-10
    # a frozen chain misses every change by its full size; one moving as much in another
    # direction (the negated changes) is not penalised: the term only sees the size
    frozen = {"forward": truth[:, :1].expand_as(truth).clone(), "backward": None}
    assert torch.isclose(motion_loss(frozen, truth), true_speed.square().mean())
    mirrored = {"forward": 2 * truth[:, :1] - truth, "backward": None}
    assert motion_loss(mirrored, truth).item() < 1e-8
    chain = truth.clone().requires_grad_(True)
    half = {"forward": truth[:, :1] + 0.5 * (chain - truth[:, :1]), "backward": None}
    loss = motion_loss(half, truth)
    assert loss.item() > 0
    loss.backward()
    assert torch.isfinite(chain.grad).all() and chain.grad.abs().sum() > 0


def test_w_motion_adds_the_term_off_in_the_paper_recipe_on_in_the_default():
    assert RECIPES["paper"]["w_motion"] == 0.0 and RECIPES["default"]["w_motion"] == 20.0
    assert TrainConfig.from_dict({}).w_motion == 0.0  # runs stored before the term resume without it
    seq, feats = limb()
    model = small_model(seq)
    windows = torch.as_tensor(feats[None, :8] / np.abs(feats).max() * 0.9, dtype=torch.float32)
    cfg = dict(window=8, holdout=0.2)
    torch.manual_seed(1)
    total_off, terms_off = WindowLoss(model, TrainConfig(w_motion=0.0, w_vertex=0.0, **cfg))(windows, sample=False)
    torch.manual_seed(1)
    total_on, terms_on = WindowLoss(model, TrainConfig(w_motion=2.0, w_vertex=0.0, **cfg))(windows, sample=False)
    assert "motion" not in terms_off and terms_on["motion"] > 0
    assert torch.isclose(total_on, total_off + 2.0 * terms_on["motion"])
    with pytest.raises(MeshseqError, match="w_motion"):
        TrainConfig(w_motion=-1.0)


def test_kl_weight_scales_with_the_vertices_in_the_default_recipe_only():
    import meshseq.train as T

    assert T.kl_weight(0.1, T.KL_REFERENCE_VERTICES, "vertices") == pytest.approx(0.1)
    assert T.kl_weight(0.1, 8431, "vertices") == pytest.approx(0.8431)
    assert T.kl_weight(0.1, 8431, "none") == 0.1
    assert RECIPES["paper"]["kl_scale"] == "none" and RECIPES["default"]["kl_scale"] == "vertices"
    assert TrainConfig.from_dict({}).kl_scale == "none"  # runs stored before the option keep one weight
    with pytest.raises(MeshseqError, match="kl_scale"):
        TrainConfig(kl_scale="faces")
    # the objective weighs the KL it logs by the scaled weight
    seq, feats = limb()
    model = small_model(seq)
    windows = torch.as_tensor(feats[None, :8] / np.abs(feats).max() * 0.9, dtype=torch.float32)
    cfg = dict(window=8, w_motion=0.0)
    torch.manual_seed(1)
    base, terms = WindowLoss(model, TrainConfig(kl_scale="none", w_vertex=0.0, **cfg))(windows, sample=False)
    torch.manual_seed(1)
    scaled, _ = WindowLoss(model, TrainConfig(kl_scale="vertices", w_vertex=0.0, **cfg))(windows, sample=False)
    factor = seq.n_vertices / T.KL_REFERENCE_VERTICES
    assert terms["kl"] > 0 and factor != 1.0
    assert torch.isclose(scaled, base + 0.1 * (factor - 1.0) * terms["kl"], rtol=1e-5)


def test_logvar_max_bounds_the_sampling_noise_and_is_stored(tmp_path, capsys):
    import meshseq
    from meshseq.cli import main
    from meshseq.io import save_sequence

    seq, feats = limb()
    bounded, free = twin_models(seq, logvar_max=0.0)
    with torch.no_grad():
        free.fc_logvar.bias.fill_(3.0)  # a head asking for noise of spread e^1.5
        bounded.fc_logvar.bias.fill_(3.0)
    x = torch.as_tensor(feats[:4] / np.abs(feats).max() * 0.9, dtype=torch.float32)
    with torch.no_grad():
        _, lv_free = free.encode(x)
        _, lv_bounded = bounded.encode(x)
    assert float(lv_free.max()) > 1.0 and float(lv_bounded.max()) <= 0.0
    assert torch.equal(lv_bounded, lv_free.clamp(max=0.0))
    # sampled roll-outs draw z = mu + exp(logvar / 2) eps with the bounded spread
    windows = x[None]
    torch.manual_seed(2)
    out = bounded(windows, sample=True)
    assert float(out["logvar"].detach().max()) <= 0.0
    with pytest.raises(MeshseqError, match="logvar_max"):
        ModelConfig(n_vertices=10, logvar_max=float("nan"))
    with pytest.raises(MeshseqError, match="logvar_max"):
        TrainConfig(logvar_max="big")
    assert RECIPES["paper"]["logvar_max"] is None and RECIPES["default"]["logvar_max"] == 0.0
    assert TrainConfig.from_dict({}).logvar_max is None
    # the CLI stores it in both configs; "none" asks for the paper's unbounded head
    data = tmp_path / "limb.npz"
    save_sequence(seq, data)
    common = tiny_cli(tmp_path)

    def stored(run):
        train_opts, model_opts = stored_configs(run)
        return train_opts["logvar_max"], model_opts["logvar_max"]

    assert main(["train", str(data), "--out", str(tmp_path / "d"), *common]) == 0
    assert stored(tmp_path / "d") == (0.0, 0.0)
    assert main(["train", str(data), "--out", str(tmp_path / "n"),
                 *tiny_cli(tmp_path, 'logvar_max = "none"', "n")]) == 0
    assert stored(tmp_path / "n") == (None, None)
    # other options' "none" stays the string "none"
    assert main(["train", str(data), "--out", str(tmp_path / "s"),
                 *tiny_cli(tmp_path, 'kl_scale = "none"\nfc_lr = "none"', "s")]) == 0
    train_opts, _ = stored_configs(tmp_path / "s")
    assert train_opts["kl_scale"] == "none" and train_opts["fc_lr"] == "none" and train_opts["logvar_max"] == 0.0
    assert main(["train", str(data), "--out", str(tmp_path / "p"), "--recipe", "paper",
                 *tiny_cli(tmp_path, "logvar_max = -1", "p")]) == 0
    assert stored(tmp_path / "p") == (-1.0, -1.0)
    assert meshseq.load(tmp_path / "p").net.config.logvar_max == -1.0
    assert main(["train", str(data), "--out", str(tmp_path / "x"), *tiny_cli(tmp_path, 'logvar_max = "big"', "x")]) == 2
    assert f"{tmp_path / 'x.toml'}: logvar_max: expected a number or \"none\", got 'big'" in capsys.readouterr().err


def test_clip_threshold_is_a_multiple_of_the_median_of_recent_norms():
    from meshseq.train import GRAD_CLIP_WARMUP, clip_threshold, scale_gradients

    history = [1.0, 2.0, 3.0, 4.0, 1000.0] * 2  # one exploding roll-out in five
    assert len(history) == GRAD_CLIP_WARMUP
    assert clip_threshold(history, 3.0) == pytest.approx(3.0 * 3.0)  # the median: outliers do not move it
    assert clip_threshold(history[:-1], 3.0) is None  # too few norms known yet
    assert clip_threshold(history, None) is None  # the paper: no clipping
    p = torch.nn.Parameter(torch.ones(3))
    q = torch.nn.Parameter(torch.ones(2))  # no gradient: left alone
    p.grad = torch.tensor([3.0, 0.0, 4.0])
    scale_gradients([p, q], 0.5)
    assert torch.equal(p.grad, torch.tensor([1.5, 0.0, 2.0])) and q.grad is None
    with pytest.raises(MeshseqError, match="grad_clip"):
        TrainConfig(grad_clip=0.0)
    with pytest.raises(MeshseqError, match="grad_clip"):
        TrainConfig(grad_clip=float("inf"))
    assert RECIPES["paper"]["grad_clip"] is None
    assert TrainConfig.from_dict({}).grad_clip is None  # runs stored before the option


def test_training_clips_gradients_and_resumes_the_clip_history_bit_for_bit(tmp_path, monkeypatch):
    import csv

    import meshseq.train as T
    import meshseq.training.loop as loop

    seq, feats = limb()
    data = training_data(seq, feats)
    # a factor below 1 clips every step once GRAD_CLIP_WARMUP norms are known
    cfg = dict(window=6, batch=2, eval_every=0, checkpoint_every=12, log_every=1, grad_clip=0.5)
    after = []
    real_scale = T.scale_gradients

    def spy(parameters, scale):
        real_scale(parameters, scale)
        after.append(float(T.grad_norm(parameters)))

    monkeypatch.setattr(loop, "scale_gradients", spy)
    one = train(data, tmp_path / "a", TrainConfig(iterations=16, **cfg), SMALL, device="cpu", progress=False, log=None)
    with open(tmp_path / "a" / "metrics.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    norms = [float(r["grad_norm"]) for r in rows]
    assert [int(r["clipped"]) for r in rows] == [0] * T.GRAD_CLIP_WARMUP + [1] * (16 - T.GRAD_CLIP_WARMUP)
    # each clipped gradient went to Adam at 0.5 x the median of the norms before it
    expected = [0.5 * float(np.median(norms[:i])) for i in range(T.GRAD_CLIP_WARMUP, 16)]
    assert after == pytest.approx(expected, rel=1e-4)
    # the history of norms travels in the checkpoint: a resumed run clips as the whole one did
    train(data, tmp_path / "b", TrainConfig(iterations=12, **cfg), SMALL, device="cpu", progress=False, log=None)
    two = train(data, tmp_path / "b", TrainConfig(iterations=16, **cfg), SMALL,
                device="cpu", resume=True, progress=False, log=None)
    for k, v in one["model"].state_dict().items():
        assert torch.equal(v, two["model"].state_dict()[k]), k
    # unclipped (the paper's recipe), the same seed ends elsewhere
    free = train(data, tmp_path / "c", TrainConfig(iterations=16, **(cfg | {"grad_clip": None})), SMALL,
                 device="cpu", progress=False, log=None)
    assert not torch.equal(free["model"].fc.weight, one["model"].fc.weight)


def test_cli_grad_clip_option(tmp_path, capsys):
    from meshseq.cli import main
    from meshseq.io import save_sequence

    seq, _ = limb()
    data = tmp_path / "limb.npz"
    save_sequence(seq, data)
    clip = {}
    for name, recipe, option in (("d", "default", "grad_clip = 3"), ("n", "default", 'grad_clip = "none"'),
                                 ("p", "paper", ""), ("q", "paper", "grad_clip = 2")):
        assert main(["train", str(data), "--out", str(tmp_path / name), "--recipe", recipe,
                     *tiny_cli(tmp_path, option, name)]) == 0
        clip[name] = stored_configs(tmp_path / name)[0]["grad_clip"]
    assert clip == {"d": 3.0, "n": None, "p": None, "q": 2.0}
    assert main(["train", str(data), "--out", str(tmp_path / "x"), *tiny_cli(tmp_path, "grad_clip = -1", "x")]) == 2
    assert f"{tmp_path / 'x.toml'}: grad_clip: -1.0: expected a positive number or none" in capsys.readouterr().err


def test_adam_beta2_is_checked_stored_and_used(tmp_path):
    import json

    from meshseq.cli import main
    from meshseq.io import save_sequence

    with pytest.raises(MeshseqError, match="adam_beta2"):
        TrainConfig(adam_beta2=1.0)
    assert TrainConfig.from_dict({}).adam_beta2 == 0.999  # runs stored before the option
    seq, _ = limb()
    data = tmp_path / "limb.npz"
    save_sequence(seq, data)
    assert main(["train", str(data), "--out", str(tmp_path / "r"), *tiny_cli(tmp_path, "adam_beta2 = 0.99")]) == 0
    assert stored_configs(tmp_path / "r")[0]["adam_beta2"] == 0.99
    state = json.loads(next((tmp_path / "r" / "checkpoints").iterdir()).joinpath("state.json").read_text())
    assert {tuple(g["betas"]) for g in state["optimizer"]["param_groups"]} == {(0.9, 0.99)}


def test_average_decay_warms_up_then_holds():
    import meshseq.train as T

    assert T.average_decay(0.99, 1) == pytest.approx(2 / (T.EMA_WARMUP + 1))
    assert T.average_decay(0.99, 10) == pytest.approx(11 / (T.EMA_WARMUP + 10))
    assert T.average_decay(0.99, 5000) == 0.99
    decays = [T.average_decay(0.999, t) for t in range(1, 10000)]  # reaches 0.999 at t = 8991
    assert all(a <= b for a, b in zip(decays, decays[1:])) and decays[-1] == 0.999
    a, p = [torch.zeros(3)], [torch.ones(3)]
    T.update_average(a, p, 0.75)
    assert torch.allclose(a[0], torch.full((3,), 0.25))


def test_ema_checkpoints_deliver_the_average_and_resume_bit_for_bit(tmp_path, monkeypatch):
    """With ema_decay the checkpoint's model is the running average of the weights (recomputed
    here from every iteration's weights), the weights training continues from travel in the
    training state, a resumed run ends exactly where the whole run does, and the average does not
    change training."""
    import meshseq.train as T
    import meshseq.training.loop as loop
    from meshseq import checkpoint as ckpt

    seq, feats = limb()
    data = training_data(seq, feats)
    cfg = dict(window=6, batch=2, eval_every=4, checkpoint_every=6, log_every=1, ema_decay=0.5)
    initial, seen = [], []  # the average before the first update; the weights after every update
    real = T.update_average

    def spy(average, parameters, decay):
        if not initial:
            initial.extend(a.clone() for a in average)
        seen.append(([p.detach().clone() for p in parameters], decay))
        real(average, parameters, decay)

    monkeypatch.setattr(loop, "update_average", spy)
    one = train(data, tmp_path / "a", TrainConfig(iterations=10, **cfg), SMALL, device="cpu", progress=False, log=None)
    monkeypatch.setattr(loop, "update_average", real)
    assert [d for _, d in seen] == [T.average_decay(0.5, t) for t in range(1, 11)]
    expected = initial
    for weights, decay in seen:
        expected = [e.lerp(w, 1.0 - decay) for e, w in zip(expected, weights)]
    names = [n for n, _ in one["model"].named_parameters()]
    final = ckpt.load_latest(tmp_path / "a", with_state=True)
    delivered = dict(final.net.named_parameters())
    raw = {k[len("train."):]: v for k, v in final.state_tensors.items() if k.startswith("train.")}
    assert set(raw) == set(names)
    for n, e, w in zip(names, expected, seen[-1][0]):
        assert torch.equal(delivered[n].detach(), e), n  # the model is the average...
        assert torch.equal(raw[n], w), n  # ... and training continues from the last weights
        assert not torch.equal(e, w), n
    for k, v in final.net.state_dict().items():  # train() returns what the checkpoint delivers
        assert torch.equal(v, one["model"].state_dict()[k]), k
    # resume from iteration 6: the same average and the same training weights as the whole run
    train(data, tmp_path / "b", TrainConfig(iterations=6, **cfg), SMALL, device="cpu", progress=False, log=None)
    two = train(data, tmp_path / "b", TrainConfig(iterations=10, **cfg), SMALL,
                device="cpu", resume=True, progress=False, log=None)
    again = ckpt.load_latest(tmp_path / "b", with_state=True)
    for k, v in one["model"].state_dict().items():
        assert torch.equal(v, two["model"].state_dict()[k]), k
    for n in names:
        assert torch.equal(raw[n], again.state_tensors[f"train.{n}"]), n
    # the average does not change training: a run without it ends at the training weights
    plain = train(data, tmp_path / "c", TrainConfig(iterations=10, **(cfg | {"ema_decay": None})), SMALL,
                  device="cpu", progress=False, log=None)
    for n, p in plain["model"].named_parameters():
        assert torch.equal(p.detach(), raw[n]), n
    assert not any(k.startswith("train.") for k in ckpt.load_latest(tmp_path / "c", with_state=True).state_tensors)


def test_ema_option_is_checked_stored_and_its_training_weights_required(tmp_path):
    from safetensors.torch import load_file, save_file

    from meshseq import checkpoint as ckpt
    from meshseq.cli import main
    from meshseq.io import save_sequence

    for bad in (0.0, 1.0, float("nan")):
        with pytest.raises(MeshseqError, match="ema_decay"):
            TrainConfig(ema_decay=bad)
    assert TrainConfig.from_dict({}).ema_decay is None  # runs stored before the option
    assert RECIPES["paper"]["ema_decay"] is None and RECIPES["default"]["ema_decay"] == 0.99
    seq, _ = limb()
    data = tmp_path / "limb.npz"
    save_sequence(seq, data)
    got = {}
    for name, recipe, option in (("e", "default", "ema_decay = 0.9"), ("n", "default", 'ema_decay = "none"'),
                                 ("p", "paper", "")):
        assert main(["train", str(data), "--out", str(tmp_path / name), "--recipe", recipe,
                     *tiny_cli(tmp_path, option, name)]) == 0
        got[name] = stored_configs(tmp_path / name)[0]["ema_decay"]
    assert got == {"e": 0.9, "n": None, "p": None}
    assert main(["train", str(data), "--out", str(tmp_path / "d"), *tiny_cli(tmp_path)]) == 0
    assert stored_configs(tmp_path / "d")[0]["ema_decay"] == 0.99
    # a training state without its training weights is refused on load, naming the tensor
    folder = ckpt.latest_checkpoint(tmp_path / "e")
    tensors = load_file(folder / "state.safetensors")
    dropped = sorted(k for k in tensors if k.startswith("train."))[0]
    del tensors[dropped]
    save_file(tensors, folder / "state.safetensors")
    import hashlib
    import json

    smeta = json.loads((folder / "state.json").read_text())
    smeta["sha256"] = hashlib.sha256((folder / "state.safetensors").read_bytes()).hexdigest()
    (folder / "state.json").write_text(json.dumps(smeta))
    with pytest.raises(MeshseqError, match=dropped.replace(".", r"\.")):
        ckpt.load_folder(folder, with_state=True)


def test_mu_max_squashes_the_latent_mean_softly_and_is_stored(tmp_path):
    import meshseq
    from meshseq.cli import main
    from meshseq.io import save_sequence

    seq, feats = limb()
    bounded, free = twin_models(seq, mu_max=2.0)
    with torch.no_grad():
        for net in (free, bounded):
            net.fc_mu.bias[:8] = 5.0  # a head throwing half the latent far outside the prior
            net.fc_mu.bias[8:] = 0.0
    x = torch.as_tensor(feats[:4] / np.abs(feats).max() * 0.9, dtype=torch.float32)
    with torch.no_grad():
        mu_free, lv_free = free.encode(x)
        mu_bounded, lv_bounded = bounded.encode(x)
    assert float(mu_free.max()) > 4.0 and float(mu_bounded.abs().max()) < 2.0
    assert torch.allclose(mu_bounded, 2.0 * torch.tanh(mu_free / 2.0))
    assert torch.equal(lv_bounded, lv_free)  # the noise is not touched
    small = mu_free.abs() < 0.2  # near 0 the squashing is (almost) the identity
    assert torch.allclose(mu_bounded[small], mu_free[small], atol=2e-3)
    # roll-outs (the fused training path) see the squashed mean too
    with torch.no_grad():
        out = bounded(x[None], sample=False)
    assert float(out["mu"].abs().max()) < 2.0
    with pytest.raises(MeshseqError, match="mu_max"):
        ModelConfig(n_vertices=10, mu_max=0.0)
    with pytest.raises(MeshseqError, match="mu_max"):
        TrainConfig(mu_max=-1.0)
    assert RECIPES["paper"]["mu_max"] is None and TrainConfig.from_dict({}).mu_max is None
    assert ModelConfig.from_dict({"n_vertices": 10}).mu_max is None  # models stored before the option
    data = tmp_path / "limb.npz"
    save_sequence(seq, data)
    assert main(["train", str(data), "--out", str(tmp_path / "m"), *tiny_cli(tmp_path, "mu_max = 3", "m")]) == 0
    train_opts, model_opts = stored_configs(tmp_path / "m")
    assert train_opts["mu_max"] == 3.0 and model_opts["mu_max"] == 3.0
    assert meshseq.load(tmp_path / "m").net.config.mu_max == 3.0
    assert main(["train", str(data), "--out", str(tmp_path / "n"), *tiny_cli(tmp_path, 'mu_max = "none"', "n")]) == 0
    assert stored_configs(tmp_path / "n")[1]["mu_max"] is None


def test_feedback_grad_option_is_checked_and_stored(tmp_path):
    from meshseq.cli import main
    from meshseq.io import save_sequence

    with pytest.raises(MeshseqError, match="feedback_grad 'none'"):
        TrainConfig(feedback_grad="none")
    assert TrainConfig.from_dict({}).feedback_grad == "full"  # runs stored before the option
    assert RECIPES["paper"]["feedback_grad"] == "full"
    seq, _ = limb()
    data = tmp_path / "limb.npz"
    save_sequence(seq, data)
    got = {}
    for name, recipe, option in (("s", "default", 'feedback_grad = "stop"'), ("d", "default", ""),
                                 ("p", "paper", "")):
        assert main(["train", str(data), "--out", str(tmp_path / name), "--recipe", recipe,
                     *tiny_cli(tmp_path, option, name)]) == 0
        got[name] = stored_configs(tmp_path / name)[0]["feedback_grad"]
    assert got == {"s": "stop", "d": TrainConfig().feedback_grad, "p": "full"}


def test_fc_lr_fan_in_option_is_stored_and_sets_the_fc_rate(tmp_path):
    import json

    from meshseq.cli import main
    from meshseq.io import save_sequence

    seq, _ = limb()
    data = tmp_path / "limb.npz"
    save_sequence(seq, data)
    fan_in = seq.n_vertices * 9
    assert main(["train", str(data), "--out", str(tmp_path / "r"),
                 *tiny_cli(tmp_path, f'fc_lr = "fan-in"\nfc_lr_fan_in = {fan_in // 2}', "r")]) == 0
    assert stored_configs(tmp_path / "r")[0]["fc_lr_fan_in"] == fan_in // 2
    state = json.loads(next((tmp_path / "r" / "checkpoints").glob("*/state.json")).read_text())
    lrs = [g["lr"] for g in state["optimizer"]["param_groups"]]
    assert len(lrs) == 2 and lrs[1] == pytest.approx(lrs[0] / 2)
    assert main(["train", str(data), "--out", str(tmp_path / "p"), "--recipe", "paper", *tiny_cli(tmp_path)]) == 0
    assert stored_configs(tmp_path / "p")[0]["fc_lr_fan_in"] == RECIPES["paper"]["fc_lr_fan_in"]


@pytest.mark.parametrize("given, fast", [(1, True), (3, True), (1, False)])
def test_fc_lr_encoder_scales_only_the_encoders_share_of_the_fc_gradient(given, fast, monkeypatch):
    """``fc_lr="encoder"``: the FC weight's gradient is the decoder's share plus f times the
    encoder's share, f = min(1, fc_lr_fan_in / fan_in); every other gradient and the loss are
    those of the plain objective (banked roll-out, teacher-forced warm-up steps, reference ops)."""
    import meshseq.train as T

    seq, feats = limb()
    net = small_model(seq)
    monkeypatch.setattr(net, "fast_path", fast)
    windows = torch.from_numpy(feats[None, :6].astype(np.float32)).repeat(2, 1, 1, 1) * 0.5
    fan_in = net.fc.weight.shape[1]

    def grads(**option):
        net.zero_grad()
        total, _ = T.WindowLoss(net, TrainConfig(w_vertex=0.0, **option))(windows, sample=False, given=given)
        total.backward()
        return float(total.detach()), {n: p.grad.clone() for n, p in net.named_parameters()}

    plain_loss, plain = grads(fc_lr="none")
    none_loss, decoder_only = grads(fc_lr="encoder", fc_lr_fan_in=1)  # f = 1 / fan_in: the decoder's share, almost
    loss, scaled = grads(fc_lr="encoder", fc_lr_fan_in=fan_in // 4)
    f = (fan_in // 4) / fan_in
    assert T.encoder_grad_scale(fan_in, TrainConfig(fc_lr="encoder", fc_lr_fan_in=fan_in // 4)) == f
    assert T.encoder_grad_scale(fan_in, TrainConfig(fc_lr="fan-in", fc_lr_fan_in=fan_in // 4)) == 1.0
    assert loss == plain_loss == none_loss
    g_min = 1 / fan_in
    decoder = (decoder_only["fc.weight"] - g_min * plain["fc.weight"]) / (1 - g_min)  # exactly the decoder's share
    expect = decoder + f * (plain["fc.weight"] - decoder)
    assert torch.allclose(scaled["fc.weight"], expect, rtol=1e-4, atol=1e-6 * float(expect.abs().max()))
    assert not torch.allclose(scaled["fc.weight"], plain["fc.weight"], rtol=1e-2)
    for n in plain:
        if n != "fc.weight":
            assert torch.allclose(scaled[n], plain[n], rtol=1e-5, atol=1e-7), n
    assert len(T.parameter_groups(net, TrainConfig(fc_lr="encoder", fc_lr_fan_in=fan_in // 4))) == 1
