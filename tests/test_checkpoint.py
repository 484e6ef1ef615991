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
from conftest import training_data
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
    return seq, training_data(seq)


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


def test_writing_checkpoints_does_not_change_training(tmp_path, limb):
    """A run that writes (and, to keep the newest, checks) several checkpoints trains exactly as
    one that writes only the last, and a resume from a later checkpoint ends at the same weights.
    (Checking an older checkpoint builds a model; that must not draw from the global generator the
    sampling noise comes from.)"""
    _, data = limb
    cfg = dict(window=6, batch=3, eval_every=0, log_every=1)
    often = train(data, tmp_path / "a", TrainConfig(iterations=12, checkpoint_every=3, keep=2, **cfg), SMALL,
                  device="cpu", progress=False, log=None)
    once = train(data, tmp_path / "b", TrainConfig(iterations=12, checkpoint_every=0, **cfg), SMALL,
                 device="cpu", progress=False, log=None)
    train(data, tmp_path / "c", TrainConfig(iterations=9, checkpoint_every=3, keep=2, **cfg), SMALL,
          device="cpu", progress=False, log=None)
    resumed = train(data, tmp_path / "c", TrainConfig(iterations=12, checkpoint_every=3, keep=2, **cfg), SMALL,
                    device="cpu", resume=True, progress=False, log=None)
    for other in (once, resumed):
        for k, v in often["model"].state_dict().items():
            assert torch.equal(v, other["model"].state_dict()[k]), k


def test_loading_a_checkpoint_leaves_the_global_generator_alone(tmp_path, limb):
    _, data = limb
    train(data, tmp_path / "run", TrainConfig(iterations=1, window=6, batch=2, eval_every=0), SMALL,
          device="cpu", progress=False, log=None)
    before = torch.get_rng_state()
    ckpt.load_latest(tmp_path / "run", with_state=True)
    assert torch.equal(before, torch.get_rng_state())


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
    # nothing in the run is a pickle (TensorBoard's event files, where tensorboard is installed, are
    # protobuf records)
    for p in (tmp_path / "run").rglob("*"):
        if p.is_file():
            assert not p.read_bytes()[:2] == b"\x80\x04", p
            assert p.suffix in (".json", ".safetensors", ".csv") or p.name.startswith("events.out.tfevents."), p


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


def test_latest_meta_reads_the_newest_readable_model_json_without_the_weights(tmp_path, limb):
    _, data = limb
    run = tmp_path / "run"
    with pytest.raises(MeshseqError, match="no checkpoint"):
        ckpt.latest_meta(run)
    train(data, run, TrainConfig(iterations=2, window=6, batch=2, checkpoint_every=1), SMALL, device="cpu",
          progress=False, log=None)
    newest = run / "checkpoints" / "00000002"
    (newest / "model.safetensors").write_bytes(b"not weights")  # weights are not read
    assert ckpt.latest_meta(run)["iteration"] == 2
    (newest / "model.json").write_text("{")  # a model.json that does not read is skipped
    assert ckpt.latest_meta(run)["iteration"] == 1
    (run / "checkpoints" / "00000001" / "model.json").write_text("[]")
    with pytest.raises(MeshseqError, match="every checkpoint is damaged"):
        ckpt.latest_meta(run)


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
    (tmp_path / "run.toml").write_text("checkpoint_every = 1\nlog_every = 1\neval_every = 3\nkeep = 3\n"
                                       "[model]\nlstm_layers = 1\n")
    args = [str(tmp_path / "limb.npz"), "--out", str(run), "--window", "6", "--batch", "2", "--latent", "16",
            "--config", str(tmp_path / "run.toml"), "--no-progress"]
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


# -- the schema of checkpoint files (issue 13.3) -----------------------------------------------


@pytest.fixture(scope="module")
def good_checkpoint(tmp_path_factory, limb):
    """A valid checkpoint folder of a tiny run (copied per test before editing)."""
    _, data = limb
    run = tmp_path_factory.mktemp("schema") / "run"
    train(data, run, TrainConfig(iterations=2, window=6, batch=2, checkpoint_every=0), SMALL, device="cpu",
          progress=False, log=None)
    return ckpt.list_checkpoints(run)[-1]


def _edit_json(name, edit):
    def apply(folder):
        meta = json.loads((folder / name).read_text())
        out = edit(meta)
        (folder / name).write_text(json.dumps(meta if out is None else out))
    return apply


def _edit_tensors(name, edit):
    """Rewrite a safetensors file and record its new SHA-256, so only the contents are wrong."""
    from safetensors.torch import save_file

    def apply(folder):
        tensors = load_file(str(folder / name))
        edit(tensors)
        save_file(tensors, str(folder / name))
        _rehash(folder, name)
    return apply


def _raw_tensors(name, data: bytes):
    def apply(folder):
        (folder / name).write_bytes(data)
        _rehash(folder, name)
    return apply


def _rehash(folder, name):
    meta_name = name.replace(".safetensors", ".json")
    meta = json.loads((folder / meta_name).read_text())
    meta["sha256"] = ckpt._sha256(folder / name)
    (folder / meta_name).write_text(json.dumps(meta))


def _set(path, value):
    def edit(meta):
        *head, last = path
        d = meta
        for k in head:
            d = d[k]
        d[last] = value
    return edit


def _delete(path):
    def edit(meta):
        *head, last = path
        d = meta
        for k in head:
            d = d[k]
        del d[last]
    return edit


M, S, MT, ST = "model.json", "state.json", "model.safetensors", "state.safetensors"
SCHEMA_CASES = {
    # model.json
    "latent is a string": (_edit_json(M, _set(["model", "latent"], "16")), M, "model.latent: expected an integer"),
    "latent missing": (_edit_json(M, _delete(["model", "latent"])), M, "model.latent: missing"),
    "model is a list": (_edit_json(M, _set(["model"], [16, 2])), M, "model: expected an object"),
    "whole file a list": (_edit_json(M, lambda m: [m]), M, "not a meshseq-bdlstm-checkpoint file"),
    "scaling min = max": (_edit_json(M, lambda m: m["scaling"].update(maximum=m["scaling"]["minimum"])), M,
                          "scaling: channel 0: maximum"),
    "scaling with 8 channels": (_edit_json(M, lambda m: m["scaling"].update(minimum=m["scaling"]["minimum"][:8])), M, "scaling: expected 9"),
    "scaling mode": (_edit_json(M, _set(["scaling", "mode"], "log")), M, "scaling.mode"),
    "negative lr in train": (_edit_json(M, _set(["train", "lr"], -1e-3)), M, "train: lr -0.001"),
    "window a float": (_edit_json(M, _set(["train", "window"], 6.5)), M, "train.window: expected an integer"),
    "topology missing": (_edit_json(M, _delete(["topology"])), M, "topology: missing"),
    "vertex count differs": (_edit_json(M, _set(["model", "n_vertices"], 7)), M, "topology"),
    "unknown variant": (_edit_json(M, _set(["model", "variant"], "bi")), M, "stored field model.variant = 'bi': expected one of bd, std-bd, uni"),
    "held-out block outside": (_edit_json(M, _set(["datasets", 0, "split", "heldout"], [24, 99])), M,
                               "datasets[0].split.heldout"),
    "no data sets": (_edit_json(M, _set(["datasets"], [])), M, "datasets: empty"),
    "iteration a string": (_edit_json(M, _set(["iteration"], "two")), M, "iteration: expected an integer"),
    "iteration not the folder's": (_edit_json(M, _set(["iteration"], 7)), M, "iteration: 7 does not match"),
    "newer format": (_edit_json(M, _set(["format_version"], 99)), M, "format_version: 99 is newer"),
    "not JSON": (lambda f: (f / M).write_text('{"format": '), M, "not valid JSON"),
    "NaN in JSON": (_edit_json(M, _set(["model", "init_state"], float("nan"))), M, "model.init_state"),
    # state.json
    "negative lr in state": (_edit_json(S, _set(["optimizer", "param_groups", 0, "lr"], -0.5)), S,
                             "optimizer.param_groups[0].lr: -0.5"),
    "one beta": (_edit_json(S, _set(["optimizer", "param_groups", 0, "betas"], [0.9])), S, "betas"),
    "garbage numpy state": (_edit_json(S, _set(["numpy_rng"], {"bit_generator": "PCG64", "state": "x"})), S,
                            "numpy_rng: not a numpy PCG64 state"),
    "numpy state a list": (_edit_json(S, _set(["numpy_rng"], [1, 2])), S, "numpy_rng: expected an object"),
    "garbage python state": (_edit_json(S, _set(["python_random"], [3, [1, 2], None])), S,
                             "python_random: not a Python random state"),
    "optimizer a list": (_edit_json(S, _set(["optimizer"], [])), S, "optimizer: expected an object"),
    "numpy state missing": (_edit_json(S, _delete(["numpy_rng"])), S, "numpy_rng: missing"),
    "negative step": (_edit_json(S, lambda m: m["optimizer"]["scalars"]["fc.weight"].update(step=-1)), S,
                      "optimizer.scalars.fc.weight"),
    "odd optimizer flag": (_edit_json(S, _set(["optimizer", "param_groups", 0, "fused"], "yes")), S,
                           "param_groups[0].fused"),
    # tensors with the right SHA-256 but wrong contents
    "weight of another shape": (_edit_tensors(MT, lambda t: t.update({"model.fc.weight": t["model.fc.weight"][:3]})),
                                MT, "model.fc.weight: torch.float32 (3, "),
    "weight in float64": (_edit_tensors(MT, lambda t: t.update({"model.fc.bias": t["model.fc.bias"].double()})),
                          MT, "model.fc.bias: torch.float64"),
    "weight missing": (_edit_tensors(MT, lambda t: t.pop("model.fc_mu.bias")), MT, "lacks tensor model.fc_mu.bias"),
    "extra tensor": (_edit_tensors(MT, lambda t: t.update({"model.extra": torch.zeros(2)})), MT, "model.extra"),
    "faces out of range": (_edit_tensors(MT, lambda t: t["reference.faces"].__setitem__((0, 0), 10**6)), MT,
                           "reference.faces: vertex numbers outside"),
    "faces reordered": (_edit_tensors(MT, lambda t: t.update({"reference.faces": t["reference.faces"].flip(0)})),
                        MT, "reference.faces: connectivity hash"),
    "reference in float32": (_edit_tensors(MT, lambda t: t.update(
        {"reference.vertices": t["reference.vertices"].float()})), MT, "reference.vertices: torch.float32"),
    "NaN weight": (_edit_tensors(MT, lambda t: t["model.fc.weight"].__setitem__((0, 0), float("nan"))), MT,
                   "model.fc.weight: non-finite values"),
    "infinite reference": (_edit_tensors(MT, lambda t: t["reference.vertices"].__setitem__((0, 0), float("inf"))),
                           MT, "reference.vertices: non-finite"),
    "novelty latents of another shape": (_edit_tensors(MT, lambda t: t.update(
        {"novelty.latents": t["novelty.latents"][:, :3].contiguous()})), MT, "novelty.latents: torch.float32"),
    "novelty latents missing": (_edit_tensors(MT, lambda t: t.pop("novelty.latents")), MT,
                                "lacks tensor novelty.latents"),
    "NaN novelty latent": (_edit_tensors(MT, lambda t: t["novelty.latents"].__setitem__((0, 0), float("nan"))), MT,
                           "novelty.latents: non-finite"),
    "novelty steps missing": (_edit_tensors(MT, lambda t: t.pop("novelty.steps")), MT, "lacks tensor novelty.steps"),
    "novelty steps of another shape": (_edit_tensors(MT, lambda t: t.update(
        {"novelty.steps": t["novelty.steps"][:2].contiguous()})), MT, "novelty.steps: torch.float32"),
    "novelty without its latents' count": (_edit_json(M, _delete(["novelty", "frames"])), M, "novelty.frames: missing"),
    "novelty step zero": (_edit_json(M, _set(["novelty", "step"], 0.0)), M, "novelty: step 0.0"),
    "vertex share above 1": (_edit_json(M, _set(["completion"], {"vertex_share": 1.5})), M,
                             "completion.vertex_share: 1.5"),
    "vertex share not a number": (_edit_json(M, _set(["completion"], {"vertex_share": "half"})), M,
                                  "completion.vertex_share"),
    "not safetensors": (_raw_tensors(MT, b"\x08\x00\x00\x00\x00\x00\x00\x00{garbage"), MT, "not a safetensors file"),
    "torch RNG garbage": (_edit_tensors(ST, lambda t: t.update({"rng.torch": torch.zeros(7, dtype=torch.uint8)})),
                          ST, "rng.torch: not a torch generator state"),
    "RNG missing": (_edit_tensors(ST, lambda t: t.pop("rng.torch")), ST, "lacks tensor rng.torch"),
    "moment of another shape": (_edit_tensors(ST, lambda t: t.update(
        {"optim.fc.weight.exp_avg": torch.zeros(2, 2)})), ST, "optim.fc.weight.exp_avg: torch.float32 (2, 2)"),
    "moment of no parameter": (_edit_tensors(ST, lambda t: t.update({"optim.nope.exp_avg": torch.zeros(2)})), ST,
                               "optim.nope.exp_avg: moments of an unknown parameter"),
    "NaN moment": (_edit_tensors(ST, lambda t: t["optim.fc.bias.exp_avg_sq"].__setitem__(0, float("nan"))), ST,
                   "optim.fc.bias.exp_avg_sq: non-finite"),
}


@pytest.mark.parametrize("case", sorted(SCHEMA_CASES))
def test_edited_checkpoint_is_one_line_naming_file_and_field(case, good_checkpoint, tmp_path):
    import shutil

    edit, file_name, fragment = SCHEMA_CASES[case]
    folder = tmp_path / good_checkpoint.name
    shutil.copytree(good_checkpoint, folder)
    ckpt.load_folder(folder, with_state=True)  # the copy is fine before the edit
    edit(folder)
    with pytest.raises(MeshseqError) as info:
        ckpt.load_folder(folder, with_state=True)
    message = str(info.value)
    assert "\n" not in message and str(folder / file_name) in message and fragment in message, message
    assert not ckpt.is_valid(folder)


def test_checkpoint_stored_before_the_novelty_reference_loads_and_predicts_unguarded(good_checkpoint, limb, tmp_path):
    """A run written before checkpoints held the training frames' latents (no ``novelty`` in
    model.json, no ``novelty.latents``): both backends load it, its ``novelty`` is None, and
    prediction is the roll-out alone."""
    import shutil

    from meshseq.api import load
    from meshseq.synthesize import predict

    folder = tmp_path / good_checkpoint.name
    shutil.copytree(good_checkpoint, folder)
    assert load(folder).novelty is not None
    _edit_json(M, _delete(["novelty"]))(folder)
    _edit_tensors(MT, lambda t: (t.pop("novelty.latents"), t.pop("novelty.steps")))(folder)
    for backend in ("torch", "numpy"):
        model = load(folder, backend=backend)
        assert model.novelty is None
        x = model.features(limb[0].vertices[:3])
        np.testing.assert_array_equal(predict(model, x, 4), predict(model, x, 4, guard=False))


def test_checkpoint_stored_before_the_training_steps_guards_by_the_pose_alone(good_checkpoint, limb, tmp_path):
    """A run written with the training frames' latents but not their steps (``novelty.steps``
    absent from both files) loads with ``steps`` None and predicts as the pose guard alone says."""
    import shutil

    from meshseq.api import load
    from meshseq.novelty import NoveltyReference
    from meshseq.synthesize import predict

    folder = tmp_path / good_checkpoint.name
    shutil.copytree(good_checkpoint, folder)
    full = load(folder, backend="numpy")
    _edit_json(M, _delete(["novelty", "steps"]))(folder)
    _edit_tensors(MT, lambda t: t.pop("novelty.steps"))(folder)
    model = load(folder, backend="numpy")
    assert model.novelty.steps is None
    np.testing.assert_array_equal(model.novelty.latents, full.novelty.latents)
    x = model.features(limb[0].vertices[:3])
    full.novelty = NoveltyReference(full.novelty.latents, full.novelty.step)  # the same reference, steps dropped
    np.testing.assert_array_equal(predict(model, x, 4), predict(full, x, 4))


def test_edited_checkpoint_through_the_commands(good_checkpoint, limb, tmp_path, capsys):
    """meshseq predict and train --resume: exit 2 and one line, no traceback, nothing written."""
    import shutil

    seq, _ = limb
    save_sequence(seq, tmp_path / "limb.npz")
    run = tmp_path / "run"
    folder = run / "checkpoints" / good_checkpoint.name
    shutil.copytree(good_checkpoint, folder)
    _edit_json(M, _set(["model", "latent"], "16"))(folder)
    out = tmp_path / "out.npz"
    assert main(["predict", str(run), str(tmp_path / "limb.npz"), "-o", str(out), "--frames", "2"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("meshseq: error:") and "model.latent: expected an integer" in err
    assert not out.exists()
    assert main(["train", str(tmp_path / "limb.npz"), "--out", str(run), "--resume", "--iterations", "3",
                 "--no-progress"]) == 2
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if line.startswith("meshseq: error:")]
    assert len(lines) == 1 and "--resume" in lines[0] and "every checkpoint is damaged" in lines[0]
    assert "Traceback" not in err


# -- --resume never starts over; --keep; --force (issue 13.2, 13.3) ----------------------------


def _cli_args(tmp_path, run, *extra, config: str = ""):
    """``meshseq train`` of a tiny model into ``run`` with ``extra`` flags and ``config`` (TOML lines)."""
    (tmp_path / "cli.toml").write_text(f"log_every = 1\n{config}\n[model]\nlstm_layers = 1\n")
    return ["train", str(tmp_path / "limb.npz"), "--out", str(run), "--window", "6", "--batch", "2", "--latent",
            "16", "--no-progress", "--config", str(tmp_path / "cli.toml"), *extra]


def _one_error_line(capsys) -> str:
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if line.startswith("meshseq: error:")]
    assert len(lines) == 1 and "Traceback" not in err, err
    return lines[0]


def test_resume_never_starts_over(tmp_path, limb, capsys):
    seq, _ = limb
    save_sequence(seq, tmp_path / "limb.npz")
    # nothing to resume: an error, and no folder is created
    missing = tmp_path / "missing"
    assert main(_cli_args(tmp_path, missing, "--iterations", "2", "--resume")) == 2
    assert "leave out --resume" in _one_error_line(capsys) and not missing.exists()
    (tmp_path / "empty").mkdir()
    assert main(_cli_args(tmp_path, tmp_path / "empty", "--iterations", "2", "--resume")) == 2
    assert "no checkpoint" in _one_error_line(capsys) and not any((tmp_path / "empty").iterdir())
    # a run with stored options other than the defaults
    run = tmp_path / "run"
    assert main(_cli_args(tmp_path, run, "--iterations", "4", "--seed", "5",
                          config="checkpoint_every = 2\nlr = 0.002")) == 0
    metrics = (run / "metrics.csv").read_text()
    # resuming with other options on the command line: the stored ones are used
    assert main(_cli_args(tmp_path, run, "--iterations", "6", "--resume", "--window", "5",
                          config='checkpoint_every = 2\nlr = 0.5\nconsistency = "spatial"')) == 0
    meta = json.loads((ckpt.latest_checkpoint(run) / "model.json").read_text())
    assert meta["iteration"] == 6 and meta["train"]["lr"] == 0.002 and meta["train"]["window"] == 6
    assert meta["train"]["seed"] == 5 and meta["train"]["iterations"] == 6
    assert meta["train"]["consistency"] == meta["features"]["consistency"] == "temporal-mst"
    from meshseq.train import load_training_data

    spatial = load_training_data([str(tmp_path / "limb.npz")], consistency="spatial")
    with pytest.raises(MeshseqError, match="trained on temporal-mst features; the data were extracted with spatial"):
        train(spatial, run, TrainConfig(iterations=8), device="cpu", resume=True, progress=False, log=None)
    rows = (run / "metrics.csv").read_text()
    assert rows.startswith(metrics) and len(rows.splitlines()) == 7
    # every checkpoint damaged (state.json garbage): an error; options and metrics untouched
    for folder in ckpt.list_checkpoints(run):
        (folder / "state.json").write_text("[]")
    assert main(_cli_args(tmp_path, run, "--iterations", "8", "--resume")) == 2
    line = _one_error_line(capsys)
    assert "every checkpoint is damaged" in line and "state.json" in line and "--force" in line
    assert (run / "metrics.csv").read_text() == rows
    # --resume with --force is a contradiction
    assert main(_cli_args(tmp_path, run, "--iterations", "8", "--resume", "--force")) == 2
    assert "choose one" in _one_error_line(capsys)


@pytest.mark.parametrize("consistency", acap.CONSISTENCY_MODES)
def test_a_run_of_every_consistency_loads_and_extracts_features_with_it(tmp_path, limb, consistency):
    from meshseq.train import TrainingData

    seq, _ = limb
    ref = seq.vertices[3]  # not the first frame: the modes' first-frame walks could differ
    feats = acap.extract(seq.vertices, seq.faces, reference=ref, consistency=consistency)
    data = TrainingData([seq.name], [seq.source], [feats], seq.faces, ref, consistency)
    run = tmp_path / "run"
    train(data, run, TrainConfig(iterations=2, window=6, batch=2, eval_every=0, consistency=consistency), SMALL,
          device="cpu", progress=False, log=None)
    model = meshseq.load(run)
    assert model.meta["features"]["consistency"] == model.consistency == consistency
    np.testing.assert_array_equal(model.features(seq.vertices), model.scaling.apply(feats).astype(np.float32))


def test_a_checkpoint_that_names_no_feature_options_reads_as_stored_before_they_were_named():
    from meshseq.checkpoint_schema import UNNAMED_CONSISTENCY, UNNAMED_PLACEMENT, feature_options

    assert feature_options({}) == (UNNAMED_CONSISTENCY, UNNAMED_PLACEMENT) == ("temporal", "centroid")
    assert feature_options({"features": {"consistency": "greedy"}}) == ("greedy", "centroid")
    assert feature_options({"features": {"consistency": "spatial", "placement": "anchor"}}) == ("spatial", "anchor")


def test_damaged_checkpoint_does_not_count_toward_keep(tmp_path, limb):
    _, data = limb
    cfg = dict(window=6, batch=2, eval_every=0, checkpoint_every=3, keep=2)
    run = tmp_path / "run"
    train(data, run, TrainConfig(iterations=9, **cfg), SMALL, device="cpu", progress=False, log=None)
    assert [f.name for f in ckpt.list_checkpoints(run)] == ["00000006", "00000009"]
    (run / "checkpoints" / "00000009" / "state.json").write_text("{}")
    with pytest.warns(meshseq.MeshseqWarning, match="00000009"):
        train(data, run, TrainConfig(iterations=8, **cfg), SMALL, device="cpu", resume=True, progress=False,
              log=None)
    names = [f.name for f in ckpt.list_checkpoints(run)]
    assert names == ["00000006", "00000008", "00000009"]  # two good ones kept; the damaged one left alone
    assert ckpt.is_valid(run / "checkpoints" / "00000006") and not ckpt.is_valid(run / "checkpoints" / "00000009")


def test_force_removes_only_what_meshseq_wrote(tmp_path, limb, capsys):
    seq, _ = limb
    save_sequence(seq, tmp_path / "limb.npz")
    run = tmp_path / "run"
    assert main(_cli_args(tmp_path, run, "--iterations", "4", config="checkpoint_every = 2")) == 0
    mine = [run / "notes.txt", run / "checkpoints" / "README.txt", run / "tensorboard" / "my-plot.png",
            run / "checkpoints" / "old-runs" / "a.txt"]
    for p in mine:
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_text("the user's")
    (run / "tensorboard" / "events.out.tfevents.1.host").write_text("meshseq's")
    assert main(_cli_args(tmp_path, run, "--iterations", "1", "--force")) == 0
    assert all(p.read_text() == "the user's" for p in mine)
    assert [f.name for f in ckpt.list_checkpoints(run)] == ["00000001"]
    assert not (run / "tensorboard" / "events.out.tfevents.1.host").exists()
    assert len((run / "metrics.csv").read_text().splitlines()) == 2


def test_damaged_vae_baseline_is_one_line(tmp_path, limb):
    from safetensors.torch import save_file

    from meshseq import baselines
    from meshseq.mesh import Topology

    seq, data = limb
    topo = Topology.from_faces(seq.faces, seq.n_vertices)
    vae = baselines.train_vae(np.asarray(data.features[0][:8], dtype=np.float32) * 0.1, topo, latent=8,
                              iterations=2, device="cpu")
    folder = tmp_path / "vae"
    baselines.save_vae(vae, folder, {"data": "x"})
    baselines.load_vae(folder, topo)
    tensors = load_file(str(folder / "vae.safetensors"))
    name = next(k for k, v in tensors.items() if v.is_floating_point() and v.dim() == 2)
    tensors[name][0, 0] = float("nan")
    save_file(tensors, str(folder / "vae.safetensors"))
    with pytest.raises(MeshseqError, match=f"vae.safetensors: {name}: non-finite"):
        baselines.load_vae(folder, topo)
    (folder / "vae.json").write_text('{"config": {"n_vertices": "50"}}')
    with pytest.raises(MeshseqError, match=r"vae.json: config.n_vertices: expected an integer"):
        baselines.load_vae(folder, topo)
    (folder / "vae.safetensors").write_bytes(b"garbage")
    with pytest.raises(MeshseqError, match="damaged VAE baseline"):
        baselines.load_vae(folder, topo)
