"""L_vertex: generated frames measured on their reconstructed vertices (meshseq.vertex_loss)."""

from __future__ import annotations

import csv

import numpy as np
import pytest
import torch

from conftest import training_data
from meshseq import acap
from meshseq.acap.torch_reconstruct import TorchReconstructor
from meshseq.data.synthetic import twisting_limb
from meshseq.errors import MeshseqError
from meshseq.train import RECIPES, TrainConfig, WindowLoss, train
from meshseq.vertex_loss import VertexLoss, picked_frames, vertex_unit

pytestmark = pytest.mark.usefixtures("one_torch_thread")
SMALL = {"latent": 16, "lstm_layers": 2}


@pytest.fixture(scope="module")
def limb():
    seq = twisting_limb(frames=40, rings=10, segments=8, seed=0)
    feats = acap.extract(seq.vertices, seq.faces)
    return seq, feats


def test_picked_frames_are_evenly_spaced_and_end_at_the_last():
    assert picked_frames(32, 4) == [1, 11, 21, 31]
    assert picked_frames(32, 1) == [31]
    assert picked_frames(6, 9) == [1, 2, 3, 4, 5]
    assert picked_frames(6, 5) == [1, 2, 3, 4, 5]


def test_vertex_unit_converts_squared_vertex_change_into_feature_units():
    rng = np.random.default_rng(0)
    scaled = [rng.normal(size=(10, 5, 9))]
    verts = [rng.normal(size=(10, 5, 3))]
    unit = vertex_unit(scaled, verts, [[(0, 10)]])
    expected = np.square(np.diff(scaled[0], axis=0)).sum() / np.square(np.diff(verts[0], axis=0)).sum()
    assert unit == pytest.approx(expected)
    # twice the size in vertices: a quarter of the unit; frames outside the segments are not read
    verts2 = [2 * verts[0]]
    verts2[0][8:] = 1e6
    assert vertex_unit(scaled, verts2, [[(0, 8)]]) == pytest.approx(
        np.square(np.diff(scaled[0][:8], axis=0)).sum() / np.square(np.diff(2 * verts[0][:8], axis=0)).sum())
    assert vertex_unit(scaled, [np.zeros((10, 5, 3))], [[(0, 10)]]) == 1.0  # no motion: no calibration


def test_vertex_loss_is_the_reconstructed_distance_of_the_picked_frames(limb):
    seq, feats = limb
    scaling = acap.Scaling.fit(feats)
    scaled = torch.as_tensor(scaling.apply(feats[:8]), dtype=torch.float32)[None]  # (1, 8, V, 9)
    rec = acap.Reconstructor(seq.vertices[0], seq.faces)
    loss = VertexLoss(TorchReconstructor(rec), scaling, unit=2.0, frames=3)
    assert loss(scaled.clone(), scaled).item() == pytest.approx(0.0, abs=1e-6)
    # a roll-out frozen at the first frame: the squared distance of the picked frames (1, 4, 7) to
    # the first, by the float64 numpy reconstruction, times the unit
    frozen = scaled[:, :1].expand_as(scaled).clone().requires_grad_(True)
    value = loss(frozen, scaled)
    verts = rec.solve(feats[:8])
    verts = verts - verts.mean(axis=1, keepdims=True)
    expected = 2.0 * np.mean([np.square(verts[i] - verts[0]).sum() for i in (1, 4, 7)])
    assert value.item() == pytest.approx(expected, rel=1e-3)
    value.backward()
    grad = frozen.grad
    assert torch.isfinite(grad).all() and grad[:, [1, 4, 7]].abs().sum() > 0
    assert grad[:, [0, 2, 3, 5, 6]].abs().sum() == 0  # frames that are not picked get no gradient


def test_cached_targets_give_the_same_loss_and_gradient_as_reconstructing_the_truth(limb):
    """``cache_targets``: the truth's vertices of every training frame reconstructed once and
    indexed by the windows' rows give L_vertex and its gradient as reconstructing the picked
    truth frames does; without rows, or with a cache too large for ``CACHE_BYTES``, the truth is
    reconstructed."""
    seq, feats = limb
    scaling = acap.Scaling.fit(feats)
    frames = torch.as_tensor(scaling.apply(feats), dtype=torch.float32)  # (40, V, 9): all frames
    rows = torch.tensor([[3, 4, 5, 6, 7, 8, 9], [30, 29, 28, 27, 26, 25, 24]])  # two windows, one reversed
    truth = frames[rows]
    generated = (truth + 0.05 * torch.randn(truth.shape, generator=torch.Generator().manual_seed(0)))
    rec = acap.Reconstructor(seq.vertices[0], seq.faces)
    loss = VertexLoss(TorchReconstructor(rec), scaling, unit=2.0, frames=3)

    def value_and_grad(**kw):
        g = generated.clone().requires_grad_(True)
        v = loss(g, truth, **kw)
        v.backward()
        return v.detach(), g.grad

    v_ref, g_ref = value_and_grad()
    assert loss.cache_targets(frames, batch=7)  # several batches
    assert loss.targets.shape == (40, frames.shape[1], 3)
    v, g = value_and_grad(rows=rows)
    torch.testing.assert_close(v, v_ref, rtol=1e-6, atol=0)
    torch.testing.assert_close(g, g_ref, rtol=1e-6, atol=1e-9)
    # the cache is really what is read: a wrong row changes the value
    wrong = rows.clone()
    wrong[0, -1] = 0
    assert not torch.allclose(loss(generated, truth, rows=wrong), v_ref)
    assert torch.equal(loss(generated, truth), v_ref)  # no rows: the truth is reconstructed
    loss.CACHE_BYTES = 100
    assert not loss.cache_targets(frames) and loss.targets is None


def test_w_vertex_adds_the_term_to_the_objective(limb):
    seq, feats = limb
    assert RECIPES["paper"]["w_vertex"] == 0.0 and RECIPES["default"]["w_vertex"] == 1.0
    assert TrainConfig.from_dict({}).w_vertex == 0.0  # runs stored before the term resume without it
    from meshseq.mesh import Topology
    from meshseq.model import BDLSTM, ModelConfig

    scaling = acap.Scaling.fit(feats)
    windows = torch.as_tensor(scaling.apply(feats[None, :8]), dtype=torch.float32)
    torch.manual_seed(0)
    model = BDLSTM(ModelConfig(n_vertices=seq.n_vertices, **SMALL), Topology.from_faces(seq.faces, seq.n_vertices))
    vloss = VertexLoss(TorchReconstructor(acap.Reconstructor(seq.vertices[0], seq.faces)), scaling, 1.0, 2)
    cfg = dict(window=8, holdout=0.2)
    off_total, off = WindowLoss(model, TrainConfig(w_vertex=0.0, **cfg), vloss)(windows, sample=False)
    on_total, on = WindowLoss(model, TrainConfig(w_vertex=0.5, **cfg), vloss)(windows, sample=False)
    assert "vertex" not in off and on["vertex"] > 0
    out = model(windows, sample=False)
    both = vloss(out["forward"], windows) + vloss(out["backward"], windows.flip(1))
    assert torch.isclose(on["vertex"], both.detach(), rtol=1e-5)
    assert torch.isclose(on_total, off_total + 0.5 * on["vertex"], rtol=1e-5)
    with pytest.raises(ValueError, match="VertexLoss"):
        WindowLoss(model, TrainConfig(w_vertex=1.0, **cfg))
    with pytest.raises(MeshseqError, match="w_vertex"):
        TrainConfig(w_vertex=-1.0)
    for bad in (0, 4.0, True):  # a float would be stored where checkpoints expect an integer
        with pytest.raises(MeshseqError, match="vertex_frames"):
            TrainConfig(vertex_frames=bad)


def test_training_with_w_vertex_logs_it_and_resumes_bit_for_bit(limb, tmp_path):
    seq, feats = limb
    data = training_data(seq, feats)
    cfg = dict(window=6, batch=2, eval_every=0, checkpoint_every=3, log_every=1, w_vertex=1.0, vertex_frames=2)
    one = train(data, tmp_path / "a", TrainConfig(iterations=6, **cfg), SMALL, device="cpu", progress=False, log=None)
    with open(tmp_path / "a" / "metrics.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert len(rows) == 6 and all(float(r["vertex"]) > 0 for r in rows)
    train(data, tmp_path / "b", TrainConfig(iterations=3, **cfg), SMALL, device="cpu", progress=False, log=None)
    two = train(data, tmp_path / "b", TrainConfig(iterations=6, **cfg), SMALL,
                device="cpu", resume=True, progress=False, log=None)
    for k, v in one["model"].state_dict().items():
        assert torch.equal(v, two["model"].state_dict()[k]), k
    # the term changes training
    plain = train(data, tmp_path / "c", TrainConfig(iterations=6, **(cfg | {"w_vertex": 0.0})), SMALL,
                  device="cpu", progress=False, log=None)
    assert any(not torch.equal(v, plain["model"].state_dict()[k]) for k, v in one["model"].state_dict().items())


def test_cli_stores_the_vertex_options(limb, tmp_path):
    import json

    from meshseq.cli import main
    from meshseq.io import save_sequence

    seq, _ = limb
    data = tmp_path / "limb.npz"
    save_sequence(seq, data)
    (tmp_path / "v.toml").write_text("eval_every = 0\nw_vertex = 0.5\nvertex_frames = 3\n[model]\nlstm_layers = 1\n")
    common = ["--iterations", "1", "--window", "6", "--batch", "2", "--latent", "8", "--no-progress"]
    assert main(["train", str(data), "--out", str(tmp_path / "v"), "--config", str(tmp_path / "v.toml"),
                 *common]) == 0
    meta = json.loads(next((tmp_path / "v" / "checkpoints").iterdir()).joinpath("model.json").read_text())
    assert meta["train"]["w_vertex"] == 0.5 and meta["train"]["vertex_frames"] == 3
