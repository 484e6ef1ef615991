"""Meshes of several parts: the placement channels put every part where it belongs (acap.parts)."""

import json

import numpy as np
import pytest

from meshseq.acap import Reconstructor, extract
from meshseq.acap.parts import component_offsets
from meshseq.align import per_vertex_error
from meshseq.mesh import Topology, bounding_box_diagonal


def _rel_error(out, v):
    return per_vertex_error(out, v) / bounding_box_diagonal(v)


@pytest.fixture(scope="module")
def multi(tmp_path_factory):
    from meshseq.data.synthetic import multi_part
    from meshseq.io import save_sequence

    seq = multi_part(frames=48)
    path = tmp_path_factory.mktemp("parts") / "multi.npz"
    save_sequence(seq, path)
    return seq, path


@pytest.fixture(scope="module")
def trained(multi, tmp_path_factory):
    """A tiny model trained briefly on the multi-part sequence: its run folder."""
    from meshseq.train import TrainConfig, load_training_data, train

    from conftest import torch_threads

    run = tmp_path_factory.mktemp("parts") / "run"
    with torch_threads(1):
        train(load_training_data([str(multi[1])]), run,
              TrainConfig(iterations=30, window=12, batch=4, eval_every=0, checkpoint_every=0, log_every=0),
              model_options={"latent": 16, "lstm_layers": 2}, device="cpu", progress=False, log=lambda m: None)
    return run


def test_frames_through_a_trained_model_land_at_the_acap_floor(multi, trained):
    from meshseq.api import load

    seq, _ = multi
    v = seq.vertices
    model = load(trained)
    assert model.config.channels == 12
    through = model.vertices(model.features(v))  # no true offsets given
    topo = Topology.from_faces(seq.faces, seq.n_vertices)
    rec = Reconstructor(v[0], seq.faces)
    floor = rec.solve(extract(v, seq.faces)[..., :9], offsets=component_offsets(v, topo))
    centred = v - v.mean(axis=1, keepdims=True)
    err, err_floor = _rel_error(through, centred).mean(), _rel_error(floor, centred).mean()
    assert err <= 2 * err_floor
    rest = _rel_error(rec.solve(extract(v, seq.faces)[..., :9]), centred).mean()  # parts at rest offsets
    assert rest > 20 * err


def test_prediction_and_completion_place_the_parts(multi, trained):
    from meshseq.api import load

    seq, _ = multi
    v = seq.vertices
    model = load(trained)
    pred = model.predict(v[:3], 10)
    assert pred.shape == (13,) + v.shape[1:] and np.isfinite(pred).all()
    assert np.array_equal(pred[:3], v[:3])
    out = model.complete(v[[10, 20]], 9, samples=2)
    assert np.array_equal(out[:, 0], np.repeat(v[None, 10], 2, 0))
    assert np.array_equal(out[:, -1], np.repeat(v[None, 20], 2, 0))
    # every part's centroid stays within the motion's reach of the truth's (the limb moves ~the diagonal)
    topo = Topology.from_faces(seq.faces, seq.n_vertices)
    got = component_offsets(out[0], topo)
    truth = component_offsets(v[10:21], topo)
    assert np.abs(got - truth).max() < 0.25 * bounding_box_diagonal(v)


@pytest.mark.parametrize("given", [1, 3])
def test_prediction_continues_the_given_placement_and_keeps_the_rolled_out_changes(multi, trained, given):
    from meshseq import synthesize
    from meshseq.api import load

    seq, _ = multi
    model = load(trained, backend="numpy")
    g = model.features(seq.vertices[5:5 + given]).astype(np.float32)
    free = synthesize.predict(model, g, 8, continue_placement=False, bound=None)
    cont = synthesize.predict(model, g, 8, continue_placement=True, bound=None)
    assert model.placement == "anchor"  # the default recipe: no continuation unless asked
    assert np.array_equal(synthesize.predict(model, g, 8, bound=None), free)
    model.placement = "centroid"  # a run measured from the centroid (every run before anchors) continues
    assert np.array_equal(synthesize.predict(model, g, 8, bound=None), cont)
    assert np.array_equal(cont[..., :9], free[..., :9])  # the ACAP channels as rolled out
    step = g[-1, :, 9:] - g[-2, :, 9:] if given > 1 else 0.0
    np.testing.assert_allclose(cont[0, :, 9:], g[-1, :, 9:] + step, atol=1e-6)  # no jump at the first frame
    np.testing.assert_allclose(np.diff(cont[..., 9:], axis=0), np.diff(free[..., 9:], axis=0), atol=1e-6)
    assert np.abs(free[0, :, 9:] - cont[0, :, 9:]).max() > 1e-4  # the roll-out alone does jump


def test_tiny_and_degenerate_parts_are_placed_and_shaped_exactly():
    from meshseq.data.synthetic import multi_part

    seq = multi_part(frames=16)
    v, f = seq.vertices, seq.faces
    t, n = v.shape[:2]
    angle = np.linspace(0.0, 2.5, t)
    rot = np.zeros((t, 3, 3))
    rot[:, 0, 0], rot[:, 0, 1], rot[:, 1, 0], rot[:, 1, 1] = np.cos(angle), -np.sin(angle), np.sin(angle), np.cos(angle)
    rot[:, 2, 2] = 1.0
    parts = {  # a single triangle, a collinear (zero-area) one, a quad with a zero-area sliver
        "triangle": (np.array([[0, 0, 0], [0.1, 0, 0], [0, 0.1, 0.05]]), np.array([[0, 1, 2]])),
        "collinear": (np.array([[0, 0, 0], [0.1, 0, 0], [0.2, 0, 0]]), np.array([[0, 1, 2]])),
        "sliver": (np.array([[0, 0, 0], [0.1, 0, 0], [0.1, 0.1, 0], [0, 0.1, 0]]), np.array([[0, 1, 2], [0, 2, 3],
                                                                                            [0, 1, 1]])),
    }
    for name, (shape, tri) in parts.items():
        carried = np.einsum("tij,pj->tpi", rot, shape) + v[:, :1] + 0.5  # turns and moves with the limb's tip
        vv, ff = np.concatenate([v, carried], 1), np.concatenate([f, tri + n])
        feats = extract(vv, ff)
        assert np.isfinite(feats).all(), name
        out = Reconstructor(vv[0], ff).solve(feats, target=vv)
        assert np.abs(out[:, n:] - vv[:, n:]).max() < 1e-9, name


def test_a_single_part_mesh_keeps_nine_channels():
    from meshseq.data.synthetic import twisting_limb

    seq = twisting_limb(frames=4)
    assert extract(seq.vertices, seq.faces).shape[-1] == 9
    assert extract(seq.vertices, seq.faces, placement=True).shape[-1] == 12


def test_info_and_roundtrip_report_the_parts(multi, capsys):
    from meshseq.cli import main

    assert main(["info", str(multi[1]), "--no-jumps"]) == 0
    out = capsys.readouterr().out
    assert "3 separate parts" in out and "three more channels" in out
    assert main(["roundtrip", str(multi[1]), "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["parts"] == 3
    assert report["mean_error_rel_from_features"] <= 1.01 * report["mean_error_rel"] + 1e-7
    assert report["mean_error_rel_rest_placement"] > 20 * report["mean_error_rel"]


def test_checkpoint_schema_takes_twelve_channels_and_refuses_others(trained):
    from meshseq.checkpoint import latest_checkpoint
    from meshseq.checkpoint_schema import CheckpointError, check_model_meta

    file = latest_checkpoint(trained) / "model.json"
    meta = json.loads(file.read_text())
    check_model_meta(meta, file)
    meta["model"]["channels"] = 10
    with pytest.raises(CheckpointError, match="channels"):
        check_model_meta(meta, file)


def test_a_part_collapsed_to_a_point_in_the_reference_is_refused_in_one_line(tmp_path, capsys):
    from meshseq.cli import main
    from meshseq.data.synthetic import multi_part
    from meshseq.io import MeshSequence, save_sequence

    seq = multi_part(frames=6)
    v, n = seq.vertices, seq.n_vertices
    grow = np.linspace(0.0, 1.0, len(v))[:, None, None] * np.array([[0, 0, 0], [0.1, 0, 0], [0, 0.1, 0.05]])
    vv = np.concatenate([v, grow + v[:, :1] + 0.5], 1)  # a triangle that grows from a point at frame 0
    path = tmp_path / "collapsed.npz"
    save_sequence(MeshSequence(vv, np.concatenate([seq.faces, [[n, n + 1, n + 2]]]), name="collapsed"), path)
    for argv in (["roundtrip", str(path)], ["train", str(path), "--out", str(tmp_path / "run"), "--iterations", "1"]):
        assert main(argv) == 2
        errors = [line for line in capsys.readouterr().err.splitlines() if "warning" not in line]
        assert len(errors) == 1 and "frame 0: part 3" in errors[0] and "one point" in errors[0], errors
    assert not (tmp_path / "run").exists()


def _strip(n: int, offset: int) -> np.ndarray:
    """Faces of a 2 x n strip of vertices numbered from ``offset``."""
    i = np.arange(n - 1)
    a, b, c, d = offset + 2 * i, offset + 2 * i + 1, offset + 2 * i + 2, offset + 2 * i + 3
    return np.concatenate([np.stack([a, b, c], 1), np.stack([b, d, c], 1)])


def test_a_part_whose_lowest_vertex_is_an_outlier_keeps_its_logs_off_the_2pi_shell(monkeypatch):
    """A band turning by 0.05 rad whose first vertex (an ill-conditioned end) is turned 2.6 rad:
    rooted there, the BFS put most of the band's logs near 2 pi; rooted at a typical vertex, every
    log stays within pi, and the other part (typical root) keeps its tree."""
    from meshseq.acap.rotations import spatial_bfs, typical_roots

    faces = np.concatenate([_strip(20, 0), _strip(20, 40)])
    topo = Topology.from_faces(faces, 80)
    axis = np.tile([0.0, 0.0, 1.0], (1, 80, 1))
    theta = np.full((1, 80), 0.05)
    axis[0, 40] *= -1  # the second part's lowest vertex: turned 2.6 rad the other way,
    theta[0, 40] = 2.6
    theta[0, [41, 42]] = 1.3  # its neighbours half way
    roots = typical_roots(theta[0], topo)
    assert roots[0] == topo.component_roots[0] and roots[1] != 40
    logs = np.linalg.norm(spatial_bfs(axis, theta, topo)[0], axis=-1)
    assert (logs[:40] <= np.pi).all() and (logs[41:] <= np.pi).all()
    from meshseq.acap import rotations

    monkeypatch.setattr(rotations, "typical_roots", lambda theta, topology: topology.component_roots)
    lowest = np.linalg.norm(spatial_bfs(axis, theta, topo)[0], axis=-1)
    assert (lowest[41:] > np.pi).mean() > 0.9  # what the lowest root did: the band on the 2 pi shell
    assert np.array_equal(lowest[:40], logs[:40])


def test_the_smallest_turn_walk_keeps_a_band_off_the_2pi_shell_past_ill_conditioned_vertices():
    """A band turning by 0.05 rad with two ill-conditioned vertices inside (2.7 rad, and 1.6 rad
    about an axis 120 degrees away: what a thin strap's inverted gradients give): the breadth-first
    walk passes through them and puts the rest of their row on the 2 pi shell (and the unrotated
    end at exactly 2 pi); the smallest-turn walk reaches them last, so every other log stays small
    and unrotated vertices are at 0. Both are logs of the same rotations."""
    from meshseq.acap.rotations import spatial_bfs, smallest_turn_tree

    topo = Topology.from_faces(_strip(20, 0), 40)
    axis = np.tile([0.0, 0.0, 1.0], (1, 40, 1))
    theta = np.full((1, 40), 0.05)
    theta[0, 10] = 2.7
    axis[0, 12], theta[0, 12] = [np.sin(2.1), 0.0, np.cos(2.1)], 1.6
    theta[0, 30:] = 0.0
    bfs = spatial_bfs(axis, theta, topo)[0]
    mst = spatial_bfs(axis, theta, topo, tree="mst")[0]
    others = np.setdiff1d(np.arange(40), [10, 12])
    assert (np.linalg.norm(bfs[others], axis=-1) > np.pi).sum() >= 8  # the check below can fail
    assert np.allclose(np.linalg.norm(bfs[[30, 32]], axis=-1), 2 * np.pi)
    assert (np.linalg.norm(mst[others], axis=-1) <= 0.05 + 1e-12).all()
    assert (mst[30:] == 0.0).all()
    parent, _ = smallest_turn_tree(axis[0], theta[0], topo, topo.component_roots)
    assert not np.isin(parent, [10, 12]).any()  # the outliers are leaves
    angle = np.linalg.norm(mst, axis=-1)
    back = np.where(angle[:, None] > 0, mst / np.maximum(angle, 1e-300)[:, None], axis[0])
    turned = np.mod(angle, 2 * np.pi)
    flip = turned > np.pi  # (2 pi - theta) about -w is the same rotation
    assert np.allclose(np.where(flip, 2 * np.pi - turned, turned), theta[0], atol=1e-12)
    assert np.allclose(np.where(flip[:, None], -back, back)[theta[0] > 0], axis[0][theta[0] > 0], atol=1e-12)


def test_temporal_mst_features_are_the_temporal_ones_where_no_vertex_is_an_outlier():
    """On a smooth rotation field the two walks give the same logs, bit for bit (a twisting limb
    against a reference that is not its first frame)."""
    from meshseq.acap import extract
    from meshseq.data.synthetic import twisting_limb

    seq = twisting_limb(frames=30)
    ref = seq.vertices[0]
    kwargs = dict(reference=ref, threads=1)
    assert np.array_equal(extract(seq.vertices[10:], seq.faces, consistency="temporal", **kwargs),
                          extract(seq.vertices[10:], seq.faces, consistency="temporal-mst", **kwargs))


def test_placement_jitter_shifts_each_part_by_one_offset_per_window_and_is_taken_back():
    import torch

    from meshseq.training.losses import jittered_placement, unjittered

    torch.manual_seed(0)
    labels = torch.tensor([0, 0, 0, 1, 1, 2])
    windows = torch.randn(3, 5, 6, 12)
    shifted, shift = jittered_placement(windows, labels, 0.3)
    assert torch.equal(shifted[..., :9], windows[..., :9])  # the ACAP channels untouched
    d = shifted[..., 9:] - windows[..., 9:]  # (B, n, V, 3)
    assert torch.allclose(d, d[:, :1].expand_as(d), atol=1e-6)  # one offset per window, over all its frames
    for part in range(3):  # ... and over each part's vertices, different between parts and windows
        rows = d[:, 0, labels == part]
        assert torch.allclose(rows, rows[:, :1].expand_as(rows), atol=1e-6)
    assert d[:, 0, 0].sub(d[:, 0, 3]).abs().min() > 0 and d[0, 0, 0].sub(d[1, 0, 0]).abs().min() > 0
    assert 0.05 < float(d[:, 0].std()) < 1.0
    both = torch.cat([shifted[:, [1, 4]], shifted[:, [4, 1]]])  # forward rows, then backward rows
    back = unjittered(both, shift)
    assert torch.allclose(back[:3], windows[:, [1, 4]], atol=1e-6)
    assert torch.allclose(back[3:], windows[:, [4, 1]], atol=1e-6)


def test_placement_jitter_is_checked_and_stored_with_the_run(multi, tmp_path):
    from meshseq.errors import MeshseqError
    from meshseq.train import TrainConfig, load_training_data, train

    from conftest import torch_threads

    with pytest.raises(MeshseqError, match="placement_jitter"):
        TrainConfig(placement_jitter=-0.1)
    with torch_threads(1):
        train(load_training_data([str(multi[1])]), tmp_path / "run",
              TrainConfig(iterations=3, window=12, batch=4, eval_every=0, checkpoint_every=0, log_every=0,
                          placement_jitter=0.3),
              model_options={"latent": 16, "lstm_layers": 2}, device="cpu", progress=False, log=lambda m: None)
    from meshseq.api import load

    assert load(tmp_path / "run").meta["train"]["placement_jitter"] == 0.3


def test_placement_jitter_keeps_l_vertex_against_the_unshifted_truth_with_or_without_cached_targets(multi):
    """L_vertex reads the truth from its cache (rows) or reconstructs it from the windows: both must
    be the unshifted truth, as ours is taken back before it is measured."""
    import torch

    from meshseq import acap
    from meshseq.acap.torch_reconstruct import TorchReconstructor
    from meshseq.model import BDLSTM, ModelConfig
    from meshseq.train import TrainConfig, WindowLoss
    from meshseq.vertex_loss import VertexLoss

    seq, _ = multi
    feats = extract(seq.vertices, seq.faces, placement=True)
    scaling = acap.Scaling.fit(feats)
    frames = torch.as_tensor(scaling.apply(feats), dtype=torch.float32)
    rows = torch.tensor([[2, 3, 4, 5, 6, 7], [20, 21, 22, 23, 24, 25]])
    topo = Topology.from_faces(seq.faces, seq.n_vertices)
    torch.manual_seed(0)
    model = BDLSTM(ModelConfig(n_vertices=seq.n_vertices, channels=12, latent=16, lstm_layers=2), topo)
    vloss = VertexLoss(TorchReconstructor(Reconstructor(seq.vertices[0], seq.faces)), scaling, 1.0, 2)
    assert vloss.cache_targets(frames)
    objective = WindowLoss(model, TrainConfig(window=6, placement_jitter=0.3), vloss, topo.component_labels)

    def vertex_term(**kw):
        torch.manual_seed(1)  # the same shifts
        return objective(frames[rows], sample=False, **kw)[1]["vertex"]

    cached, reconstructed = vertex_term(rows=rows), vertex_term()
    assert torch.isclose(cached, reconstructed, rtol=1e-4)


def test_anchor_placement_measures_each_part_from_its_body_vertex_and_comes_back_exactly(multi):
    """``anchor`` placement: the largest part's channels are zero, a part's channels are its centroid's
    gap to its anchor vertex (minus the reference's), and both reconstructions put the parts back
    as well as the centroid channels do."""
    import torch

    from meshseq.acap.parts import body_part, part_anchors, placement_channels
    from meshseq.acap.torch_reconstruct import TorchReconstructor

    seq, _ = multi
    v = seq.vertices
    topo = Topology.from_faces(seq.faces, seq.n_vertices)
    lab, body = topo.component_labels, body_part(topo)
    ch = placement_channels(v, topo, v[0], "anchor")
    assert np.array_equal(ch[:, lab == body], np.zeros_like(ch[:, lab == body]))
    anchors = part_anchors(v[0], topo)
    assert (lab[anchors] == body).all()
    c = next(k for k in range(topo.n_components) if k != body)
    gap = v[:, lab == c].mean(1) - v[:, anchors[c]]
    np.testing.assert_allclose(ch[:, lab == c][:, 0], gap - gap[0], atol=1e-12)
    centred = v - v.mean(axis=1, keepdims=True)
    errors = {}
    for mode in ("centroid", "anchor"):
        rec = Reconstructor(v[0], seq.faces, placement=mode)
        f = extract(v, seq.faces, placement=True, placement_mode=mode)
        out = rec.solve(f)
        errors[mode] = _rel_error(out, centred).mean()
        back = TorchReconstructor(rec, dtype=torch.float64)(torch.from_numpy(f)).numpy()
        np.testing.assert_allclose(back, out, atol=1e-9)
    assert errors["anchor"] <= 1.5 * errors["centroid"]
    with pytest.raises(ValueError, match="placement mode"):
        Reconstructor(v[0], seq.faces, placement="nearest")


def test_a_model_trained_with_anchor_placement_reads_and_writes_its_own_channels(multi, tmp_path):
    from meshseq.api import load
    from meshseq.errors import MeshseqError
    from meshseq.train import TrainConfig, load_training_data, train

    from conftest import torch_threads

    with pytest.raises(MeshseqError, match="placement"):
        TrainConfig(placement="nearest")
    config = TrainConfig(iterations=3, window=12, batch=4, eval_every=0, checkpoint_every=0, log_every=0)
    with pytest.raises(MeshseqError, match="placement anchor"):  # data extracted the other way
        train(load_training_data([str(multi[1])], placement="centroid"), tmp_path / "mismatch",
              TrainConfig(**(config.to_dict() | {"placement": "anchor"})), device="cpu", progress=False,
              log=lambda m: None)
    with torch_threads(1):
        train(load_training_data([str(multi[1])], placement="anchor"), tmp_path / "run",
              TrainConfig(**(config.to_dict() | {"placement": "anchor"})),
              model_options={"latent": 16, "lstm_layers": 2}, device="cpu", progress=False, log=lambda m: None)
    model = load(tmp_path / "run")
    assert model.placement == "anchor" and model.meta["features"]["placement"] == "anchor"
    v = multi[0].vertices
    f = model.features(v)
    np.testing.assert_allclose(model.scaling.invert(f)[..., 9:],
                               extract(v, multi[0].faces, placement=True, placement_mode="anchor")[..., 9:], atol=1e-5)
    through = model.vertices(f)
    assert _rel_error(through, v - v.mean(axis=1, keepdims=True)).mean() < 0.05
