"""The torch-free CPU inference (``meshseq.numpy_net``) against the torch generator it stands in for.

Fails if the numpy step or roll-out diverges from ``BDLSTM``'s (1e-5) on any variant, with or
without input normalisation; if a seed draws other random initial states than torch's generator;
or if ``meshseq predict`` / ``complete`` on CPU import torch.
"""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest
import torch

from meshseq.data.synthetic import twisting_limb
from meshseq.io import save_sequence
from meshseq.mesh import Topology
from meshseq.model import BDLSTM, ModelConfig
from meshseq.model_config import tensor_shapes
from meshseq.numpy_net import COMPILED_MIN_CHAINS, NumpyNet, ring_matrix

TOL = 1e-5


def _limb():
    seq = twisting_limb(frames=8, rings=6, segments=6)
    return seq, Topology.from_faces(seq.faces, seq.n_vertices)


def _nets(variant: str, input_norm: bool, threads: int = 2, compiled: bool = True):
    """A randomly initialised ``BDLSTM`` (bounded head, step scale) and its ``NumpyNet`` (with the
    compiled mesh convolution, which must build here, or numpy's layers)."""
    seq, topo = _limb()
    torch.manual_seed(3)
    config = ModelConfig(n_vertices=seq.n_vertices, latent=16, lstm_layers=2, variant=variant,
                         input_norm=input_norm, mu_max=2.0, logvar_max=0.0,
                         step_scale=[0.5 + 0.1 * c for c in range(9)])
    net = BDLSTM(config, topo).eval()
    with torch.no_grad():  # biases away from zero, so every term shows
        for p in net.parameters():
            p.add_(0.05 * torch.randn_like(p))
    if input_norm:
        net.set_input_norm(np.random.default_rng(0).uniform(-0.5, 0.5, (6, seq.n_vertices, 9)))
    weights = {k: v.numpy() for k, v in net.state_dict().items()}
    return net, NumpyNet(config, weights, ring_matrix(topo), threads=threads, compiled=compiled)


@pytest.mark.parametrize("variant", ["uni", "bd", "std-bd"])
def test_tensor_shapes_are_the_modules_state_dict(variant):
    seq, topo = _limb()
    for norm in (False, True):
        config = ModelConfig(n_vertices=seq.n_vertices, latent=8, lstm_layers=2, variant=variant, input_norm=norm)
        got = {k: tuple(v.shape) for k, v in BDLSTM(config, topo).state_dict().items()}
        assert got == tensor_shapes(config)


@pytest.mark.parametrize("variant", ["uni", "bd", "std-bd"])
@pytest.mark.parametrize("input_norm", [False, True])
@pytest.mark.parametrize("threads", [1, 2])
@pytest.mark.parametrize("compiled", [True, False])
def test_numpy_step_and_rollout_equal_torch(variant, input_norm, threads, compiled):
    _check_against_torch(variant, input_norm, threads, compiled, chains=8)


@pytest.mark.parametrize("chains", [5, 16, 20])
def test_compiled_layers_take_any_number_of_chains(chains):
    _check_against_torch("std-bd", True, 2, True, chains)


def _check_against_torch(variant: str, input_norm: bool, threads: int, compiled: bool, chains: int) -> None:
    net, npnet = _nets(variant, input_norm, threads, compiled)
    assert npnet.channel_major(chains) is (compiled and chains >= COMPILED_MIN_CHAINS)
    rng = np.random.default_rng(1)
    x = rng.uniform(-0.9, 0.9, (chains, net.config.n_vertices, 9)).astype(np.float32)
    n_forward = chains if variant == "uni" else chains // 2
    h, c = net.initial_state(n_forward, chains - n_forward)
    state = (torch.rand(h.shape) * 0.2 - 0.1, torch.rand(c.shape) * 0.2 - 0.1)
    np_state = tuple(s.numpy().copy() for s in state)
    with torch.no_grad():
        st, nxt, _, _ = net.step(state, torch.from_numpy(x), n_forward=n_forward)
        frames, _, _, fin = net.rollout(torch.from_numpy(x), 5, state, n_forward=n_forward)
    st_np, nxt_np = npnet.step(np_state, x, n_forward)
    assert np.abs(nxt_np - nxt.numpy()).max() < TOL
    for a, b in zip(st_np, st):
        assert np.abs(a - b.numpy()).max() < TOL
    frames_np, fin_np = npnet.rollout(x, 5, np_state, n_forward)
    assert frames_np.shape == tuple(frames.shape)
    assert np.abs(frames_np - frames.numpy()).max() < TOL
    assert np.abs(fin_np[1] - fin[1].numpy()).max() < TOL
    assert np.array_equal(npnet.initial_state(n_forward, chains - n_forward)[0], h.numpy())
    with torch.no_grad():
        mu, _ = net.encode(torch.from_numpy(x))
        d = net.decode(mu)
    assert np.abs(npnet.encode(x) - mu.numpy()).max() < TOL
    assert np.abs(npnet.decode(mu.numpy()) - d.numpy()).max() < TOL


@pytest.mark.parametrize("seed", [0, 5, 123456789])
@pytest.mark.parametrize("shape", [(2, 2, 16), (3, 16, 128)])
def test_seeded_states_are_torchs_draws(seed, shape):
    from meshseq.synthesize import uniform_states

    gen = torch.Generator().manual_seed(seed)
    want = [torch.rand(shape, generator=gen) * 0.2 - 0.1 for _ in range(2)]
    got = uniform_states(shape, seed)
    for g, w in zip(got, want):
        assert g.dtype == np.float32 and np.array_equal(g, w.numpy())


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    """A tiny trained run and its data: (run folder, data path)."""
    from meshseq.train import TrainConfig, load_training_data, train

    root = tmp_path_factory.mktemp("numpy_net")
    data = root / "limb.npz"
    save_sequence(twisting_limb(frames=40, rings=8, segments=6), data)
    train(load_training_data([str(data)]), root / "run",
          TrainConfig(iterations=3, window=8, batch=2, eval_every=0, checkpoint_every=0, log_every=0),
          model_options={"latent": 16, "lstm_layers": 2}, device="cpu", progress=False, log=lambda m: None)
    return root / "run", data


def test_backends_predict_and_complete_alike(run):
    from meshseq.api import load
    from meshseq.io import load_sequence

    seq = load_sequence(run[1])
    models = {b: load(run[0], backend=b) for b in ("torch", "numpy")}
    assert isinstance(models["numpy"].net, NumpyNet)
    out = {b: (m.predict(seq.vertices[3:6], 12), m.complete(seq.vertices[[5, 17]], 11, samples=3, seed=4))
           for b, m in models.items()}
    scale = np.abs(seq.vertices).max()
    for a, b in zip(out["torch"], out["numpy"]):
        assert a.shape == b.shape and np.abs(a - b).max() < 1e-4 * scale


def test_initial_state_of_a_given_value_on_both_backends(run):
    from meshseq.api import load

    for backend in ("torch", "numpy"):
        h, c = load(run[0], backend=backend).initial_state(2, "backward", value=0.25)
        assert tuple(h.shape) == (2, 2, 16) and (np.asarray(h) == 0.25).all() and (np.asarray(c) == 0.25).all()


#: run in a fresh interpreter: predict and complete on CPU, then whether torch was imported
PROBE = r"""
import json, sys
from meshseq.cli import main
run, data, out = sys.argv[1:4]
codes = [main(["predict", run, data, "--device", "cpu", "--given", "2", "--frames", "5", "-o", out + "/p.npz"]),
         main(["complete", run, data, "--device", "cpu", "--keyframes", "3,12", "--samples", "2", "-o", out + "/c"])]
print(json.dumps({"codes": codes, "torch": "torch" in sys.modules}))
"""


def test_predict_and_complete_on_cpu_import_no_torch(run, tmp_path):
    env = {k: v for k, v in __import__("os").environ.items() if k != "MESHSEQ_INFERENCE"}
    proc = subprocess.run([sys.executable, "-c", PROBE, str(run[0]), str(run[1]), str(tmp_path)],
                          capture_output=True, text=True, timeout=300, env=env)
    assert proc.returncode == 0, proc.stderr
    report = json.loads(proc.stdout.strip().splitlines()[-1])
    assert report == {"codes": [0, 0], "torch": False}, proc.stderr
    assert (tmp_path / "p.npz").is_file() and (tmp_path / "c" / "diversity.json").is_file()


def test_sampling_on_the_numpy_backend_is_one_line_naming_the_torch_model(run):
    from meshseq.api import load
    from meshseq.errors import MeshseqError
    from meshseq.io import load_sequence

    model = load(run[0], backend="numpy")
    frames = load_sequence(run[1]).vertices[3:6]
    for call in (lambda: model.sample(frames, 4), lambda: model.rollout(model.features(frames), 3, sample=True)):
        with pytest.raises(MeshseqError, match="needs the torch model"):
            call()


def test_without_a_compiler_the_numpy_layers_run_after_one_warning(monkeypatch, tmp_path):
    from meshseq import native

    monkeypatch.setenv("CXX", str(tmp_path / "no-such-compiler"))
    monkeypatch.setenv("MESHSEQ_KERNEL_DIR", str(tmp_path / "builds"))
    monkeypatch.setattr(native, "_library", None)  # not tried yet in this process
    with pytest.warns(RuntimeWarning, match="could not be built"):
        assert native.conv_library() is None
    assert not list((tmp_path / "builds").glob("*.so"))  # nothing half-built left under a build's name
    net, npnet = _nets("bd", True, compiled=None)
    assert not npnet.channel_major(16)  # numpy's layers, still equal to torch's step
    x = np.random.default_rng(2).uniform(-0.9, 0.9, (2, net.config.n_vertices, 9)).astype(np.float32)
    with torch.no_grad():
        _, nxt, _, _ = net.step(net.initial_state(1, 1), torch.from_numpy(x), n_forward=1)
    assert np.abs(npnet.step(npnet.initial_state(1, 1), x, 1)[1] - nxt.numpy()).max() < TOL
