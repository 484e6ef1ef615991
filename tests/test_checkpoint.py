"""Checkpoints: exact resume, SIGKILL at any moment, connectivity checks, no pickles."""

from __future__ import annotations

import csv
import json
import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
import torch
from safetensors.torch import load_file

import meshseq
from meshseq import acap
from meshseq import checkpoint as ckpt
from meshseq.cli import main
from meshseq.data.synthetic import twisting_limb
from meshseq.errors import MeshseqError
from meshseq.io import save_sequence
from meshseq.train import TrainConfig, TrainingData, train

SMALL = {"latent": 16, "lstm_layers": 2}


pytestmark = pytest.mark.usefixtures("one_torch_thread")


@pytest.fixture(scope="module")
def limb():
    seq = twisting_limb(frames=30, rings=8, segments=6)
    data = TrainingData([seq.name], [seq.source], [acap.extract(seq.vertices, seq.faces)], seq.faces, seq.vertices[0])
    return seq, data


def all_tensors(folder):
    out = {}
    for name in (ckpt.MODEL_TENSORS, ckpt.STATE_TENSORS):
        out.update(load_file(str(folder / name)))
    return out


def test_resume_is_bit_for_bit(tmp_path, limb):
    _, data = limb
    cfg = dict(window=6, batch=3, eval_every=2, checkpoint_every=4, log_every=1)
    one = train(data, tmp_path / "a", TrainConfig(iterations=8, **cfg), SMALL, device="cpu", progress=False, log=None)
    train(data, tmp_path / "b", TrainConfig(iterations=4, **cfg), SMALL, device="cpu", progress=False, log=None)
    # something else uses the global RNGs in between: resume must not depend on it
    torch.randn(100)
    np.random.default_rng().random()
    two = train(data, tmp_path / "b", TrainConfig(iterations=8, **cfg), SMALL, device="cpu", resume=True,
                progress=False, log=None)
    assert two["iteration"] == 8
    sa, sb = one["model"].state_dict(), two["model"].state_dict()
    assert sa.keys() == sb.keys()
    for k in sa:
        assert torch.equal(sa[k], sb[k]), k
    ta = all_tensors(tmp_path / "a" / "checkpoints" / "00000008")
    tb = all_tensors(tmp_path / "b" / "checkpoints" / "00000008")
    assert ta.keys() == tb.keys() and any(k.startswith("optim.") for k in ta)
    for k in ta:
        assert torch.equal(ta[k], tb[k]), k
    sa_meta = json.loads((tmp_path / "a" / "checkpoints" / "00000008" / "state.json").read_text())
    sb_meta = json.loads((tmp_path / "b" / "checkpoints" / "00000008" / "state.json").read_text())
    assert sa_meta["numpy_rng"] == sb_meta["numpy_rng"] and sa_meta["optimizer"] == sb_meta["optimizer"]
    # the metrics of the resumed run continue where the checkpoint was, with the same losses
    def rows(run):
        with open(run / "metrics.csv", newline="") as fh:
            return [(r["iteration"], r["loss"], r["heldout_rec"]) for r in csv.DictReader(fh)]

    assert rows(tmp_path / "a") == rows(tmp_path / "b")


def test_checkpoint_contents_and_no_pickles(tmp_path, limb):
    seq, data = limb
    train(data, tmp_path / "run", TrainConfig(iterations=3, window=6, batch=2, checkpoint_every=1, keep=2),
          SMALL, device="cpu", progress=False, log=None)
    folders = ckpt.list_checkpoints(tmp_path / "run")
    assert [f.name for f in folders] == ["00000002", "00000003"]  # keep=2
    files = sorted(p.name for p in folders[-1].iterdir())
    assert files == ["model.json", "model.safetensors", "state.json", "state.safetensors"]
    meta = json.loads((folders[-1] / "model.json").read_text())
    assert meta["iteration"] == 3 and meta["model"]["variant"] == "bd" and meta["model"]["latent"] == 16
    assert meta["topology"]["n_vertices"] == seq.n_vertices
    assert meta["datasets"][0]["split"] == {"n_frames": 30, "train": [[0, 24]], "heldout": [24, 30]}
    assert set(meta["scaling"]) >= {"minimum", "maximum", "mode"}
    t = load_file(str(folders[-1] / "model.safetensors"))
    assert t["reference.vertices"].dtype == torch.float64
    np.testing.assert_array_equal(t["reference.vertices"].numpy(), seq.vertices[0])
    np.testing.assert_array_equal(t["reference.faces"].numpy(), seq.faces)
    assert "rng.torch" in load_file(str(folders[-1] / "state.safetensors"))
    # nothing in the run is a pickle
    for p in (tmp_path / "run").rglob("*"):
        if p.is_file():
            assert not p.read_bytes()[:2] == b"\x80\x04" and p.suffix in (".json", ".safetensors", ".csv"), p


def test_other_connectivity_is_refused(tmp_path, limb):
    seq, data = limb
    train(data, tmp_path / "run", TrainConfig(iterations=1, window=6, batch=2), SMALL, device="cpu",
          progress=False, log=None)
    model = meshseq.load(tmp_path / "run")
    model.check_mesh(seq.faces, seq.n_vertices)  # same mesh: fine
    other = twisting_limb(frames=30, rings=9, segments=6)
    with pytest.raises(MeshseqError, match="another connectivity"):
        model.check_mesh(other.faces, other.n_vertices)
    flipped = seq.faces[:, ::-1]
    with pytest.raises(MeshseqError, match="another connectivity"):
        model.check_mesh(flipped, seq.n_vertices)
    with pytest.raises(MeshseqError, match="another connectivity"):
        model.features(other.vertices[:2], other.faces)
    # resuming on data with another mesh
    odata = TrainingData([other.name], [seq.source], [acap.extract(other.vertices, other.faces)], other.faces,
                         other.vertices[0])
    with pytest.raises(MeshseqError, match="another connectivity"):
        train(odata, tmp_path / "run", TrainConfig(iterations=2, window=6, batch=2), SMALL, device="cpu",
              resume=True, progress=False, log=None)


def test_damaged_checkpoint_is_detected(tmp_path, limb):
    _, data = limb
    train(data, tmp_path / "run", TrainConfig(iterations=2, window=6, batch=2, checkpoint_every=1), SMALL,
          device="cpu", progress=False, log=None)
    newest = tmp_path / "run" / "checkpoints" / "00000002" / "model.safetensors"
    raw = bytearray(newest.read_bytes())
    raw[-1] ^= 0xFF
    newest.write_bytes(bytes(raw))
    with pytest.warns(meshseq.MeshseqWarning, match="damaged"):
        assert ckpt.latest_checkpoint(tmp_path / "run").name == "00000001"
    with pytest.raises(MeshseqError, match="SHA-256"):
        ckpt.load(newest.parent)
    with pytest.raises(MeshseqError, match="no such run"):
        meshseq.load(tmp_path / "nothing")


KILL_SCRIPT = """
import sys, torch
torch.set_num_threads(1)
from meshseq.cli import main
sys.exit(main(sys.argv[1:]))
"""


def test_sigkill_at_any_moment_then_resume(tmp_path):
    seq = twisting_limb(frames=30, rings=8, segments=6)
    save_sequence(seq, tmp_path / "limb.npz")
    run = tmp_path / "run"
    script = tmp_path / "train_script.py"
    script.write_text(KILL_SCRIPT)
    args = [str(tmp_path / "limb.npz"), "--out", str(run), "--window", "6", "--batch", "2", "--latent", "16",
            "--lstm-layers", "1", "--checkpoint-every", "1", "--log-every", "1", "--eval-every", "3",
            "--no-progress", "--keep", "3"]
    env = dict(os.environ, OMP_NUM_THREADS="1")
    for round_ in range(3):  # kill it three times at different moments
        proc = subprocess.Popen([sys.executable, str(script), "train", *args, "--iterations", "100000",
                                 *(["--resume"] if round_ else [])],
                                env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
        before = len(ckpt.list_checkpoints(run)) and int(ckpt.list_checkpoints(run)[-1].name)
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline:
            found = ckpt.list_checkpoints(run)
            if found and int(found[-1].name) >= before + 5 + 3 * round_:
                break
            if proc.poll() is not None:
                pytest.fail(f"training exited early: {proc.stderr.read().decode()}")
            time.sleep(0.01)
        else:
            proc.kill()
            pytest.fail("no checkpoints within 120 s")
        time.sleep(0.013 * (round_ + 1))  # land somewhere inside an iteration or a checkpoint write
        proc.send_signal(signal.SIGKILL)
        proc.wait()
        assert proc.returncode == -signal.SIGKILL
        # every checkpoint folder that exists under its final name is complete and consistent
        for folder in ckpt.list_checkpoints(run):
            assert ckpt.is_valid(folder), folder
    last = int(ckpt.latest_checkpoint(run).name)
    target = last + 4
    assert main(["train", *args, "--iterations", str(target), "--resume"]) == 0
    final = ckpt.latest_checkpoint(run)
    assert final.name == f"{target:08d}" and ckpt.is_valid(final)
    assert not list((run / "checkpoints").glob(".tmp-*"))  # leftovers of killed writes cleaned up
    model = meshseq.load(run)
    assert model.iteration == target
    with open(run / "metrics.csv", newline="") as fh:
        its = [int(r["iteration"]) for r in csv.DictReader(fh)]
    assert its == list(range(1, target + 1))  # nothing lost, nothing twice
