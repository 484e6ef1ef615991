"""The validation block: carved out of the training frames, measured during training, the best
checkpoint kept (``meshseq train --validation``)."""

from __future__ import annotations

import csv
import json

import numpy as np
import pytest

import meshseq
from conftest import training_data
from meshseq import checkpoint as ckpt
from meshseq.cli import main
from meshseq.data.synthetic import twisting_limb
from meshseq.data.windows import Split, WindowSampler, split_frames
from meshseq.errors import MeshseqError
from meshseq.evaluate import validation_error
from meshseq.io import save_sequence
from meshseq.train import TrainConfig, train

SMALL = {"latent": 16, "lstm_layers": 2}

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def test_validation_block_is_cut_from_the_end_of_the_training_frames():
    s = split_frames(100, 0.2, validation=0.25)  # 80 training frames: 20 of them validate
    assert s.train == ((0, 60),) and s.validation == (60, 80) and s.heldout == (80, 100)
    s = split_frames(100, 0.2, at="start", validation=0.25)
    assert s.train == ((20, 80),) and s.validation == (80, 100)
    s = split_frames(100, 0.2, at="0.5", validation=0.25)  # training 0-50 and 70-100; 20 from the last
    assert s.train == ((0, 50), (70, 80)) and s.validation == (80, 100)
    assert split_frames(10, 0.2, validation=0.01).validation == (6, 8)  # at least 2 frames
    assert split_frames(100, 0.2).validation is None
    # training windows never reach into the validation block
    sampler = WindowSampler([split_frames(100, 0.2, validation=0.25)], ["a"], 8)
    assert sampler.rows(np.arange(len(sampler.starts))).max() == 59
    with pytest.raises(MeshseqError, match="--validation 0.999: a validation block of 80 frames"):
        split_frames(100, 0.2, validation=0.999)
    for bad in (1.0, -0.1, True):
        with pytest.raises(MeshseqError, match="--validation"):
            split_frames(100, 0.2, validation=bad)
    with pytest.raises(MeshseqError, match="--validation 1.5"):
        TrainConfig(validation=1.5)


def test_split_round_trips_and_old_splits_have_no_block():
    s = split_frames(50, 0.2, validation=0.2)
    assert Split.from_dict(json.loads(json.dumps(s.to_dict()))) == s
    old = {"n_frames": 50, "train": [[0, 40]], "heldout": [40, 50]}
    assert Split.from_dict(old).validation is None and "validation" not in Split.from_dict(old).to_dict()


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    seq = twisting_limb(frames=40, rings=8, segments=6, seed=0)
    data = training_data(seq)
    run = tmp_path_factory.mktemp("val") / "run"
    cfg = TrainConfig(iterations=40, window=8, batch=2, eval_every=10, checkpoint_every=20, log_every=10,
                      validation=0.25, lr=3e-3)
    result = train(data, run, cfg, SMALL, device="cpu", progress=False, log=None)
    return seq, data, run, result


def read_validation(run):
    with open(run / "metrics.csv", newline="") as fh:
        return {int(r["iteration"]): float(r["validation"]) for r in csv.DictReader(fh) if r["validation"]}


def test_training_keeps_the_checkpoint_with_the_lowest_validation_error(trained):
    _, _, run, result = trained
    errors = read_validation(run)
    assert sorted(errors) == [10, 20, 30, 40] and all(np.isfinite(list(errors.values())))
    best_it = min(errors, key=errors.get)
    assert result["best"]["iteration"] == best_it and result["best"]["error"] == pytest.approx(errors[best_it])
    best = ckpt.best_folder(run)
    meta = json.loads((best / "model.json").read_text())
    assert meta["iteration"] == best_it and meta["validation"]["iteration"] == best_it
    assert meta["datasets"][0]["split"] == {"n_frames": 40, "train": [[0, 24]], "validation": [24, 32],
                                            "heldout": [32, 40]}
    # a checkpoint like the others, loadable by path, but neither listed nor resumed from
    assert meshseq.load(best).iteration == best_it
    assert best not in ckpt.list_checkpoints(run) and meshseq.load(run).iteration == 40
    assert ckpt.best_validation(run) == meta["validation"]


def test_validation_error_measures_frames_in_the_block_after_given_frames_before_it(trained):
    _, data, run, _ = trained
    model = meshseq.load(run)
    feats = model.scaling.apply(data.features[0]).astype(np.float32)
    verts = model.vertices(feats)
    block = (24, 32)
    base = validation_error(model, [verts], [feats], [block])
    assert np.isfinite(base) and base > 0
    outside = verts.copy()
    outside[:24] += 1.0
    outside[32:] -= 1.0
    assert validation_error(model, [outside], [feats], [block]) == pytest.approx(base)  # truth outside: unused
    inside = verts.copy()
    inside[28, :10] += 0.5  # not a translation (centroids are aligned)
    assert validation_error(model, [inside], [feats], [block]) != pytest.approx(base)  # truth inside: measured
    given = feats.copy()
    given[21:24] = 0.0  # the given frames just before the block are the model's input
    assert validation_error(model, [verts], [given], [block]) != pytest.approx(base)
    with pytest.raises(MeshseqError, match="empty"):
        validation_error(model, [verts], [feats], [(24, 24)])


def test_resume_continues_the_best_and_force_removes_it(trained, tmp_path):
    seq, data, _, _ = trained
    run = tmp_path / "run"
    cfg = TrainConfig(iterations=20, window=8, batch=2, eval_every=10, checkpoint_every=10, log_every=10,
                      validation=0.25, lr=3e-3)
    first = train(data, run, cfg, SMALL, device="cpu", progress=False, log=None)
    cfg.iterations = 40
    second = train(data, run, cfg, SMALL, device="cpu", progress=False, log=None, resume=True)
    errors = read_validation(run)
    assert sorted(errors) == [10, 20, 30, 40]
    assert second["best"]["iteration"] == min(errors, key=errors.get)
    assert second["best"]["error"] <= first["best"]["error"]
    # a best written after the checkpoint a run resumes from is dropped (that future is redone)
    (run / "checkpoints" / "00000040").rename(run / "gone")
    cfg.iterations = 30
    third = train(data, run, cfg, SMALL, device="cpu", progress=False, log=None, resume=True)
    assert third["best"]["iteration"] <= 30
    train(data, run, cfg, SMALL, device="cpu", progress=False, log=None, force=True)
    assert ckpt.best_validation(run)["iteration"] <= 30
    cfg.validation = 0.0
    train(data, run, cfg, SMALL, device="cpu", progress=False, log=None, force=True)
    assert not ckpt.best_folder(run).exists()


def test_cli_validation_option(tmp_path, capsys):
    seq = twisting_limb(frames=40, rings=8, segments=6, seed=0)
    save_sequence(seq, tmp_path / "limb.npz")
    (tmp_path / "run.toml").write_text("eval_every = 2\n[model]\nlstm_layers = 1\n")
    (tmp_path / "as-given.toml").write_text('eval_every = 2\nwindow_fit = "none"\n[model]\nlstm_layers = 1\n')
    argv = ["train", str(tmp_path / "limb.npz"), "--out", str(tmp_path / "run"), "--iterations", "4", "--window",
            "6", "--batch", "2", "--latent", "16", "--no-progress", "--threads", "1"]
    config = ["--config", str(tmp_path / "run.toml")]
    assert main(argv + config + ["--validation", "0.25"]) == 0
    out = capsys.readouterr().out
    assert "best on the validation block: iteration" in out and "checkpoints/best" in out
    assert main(argv + config + ["--validation", "0.999", "--force"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "--validation 0.999" in err
    # the failed --force run removed nothing: the options are checked against the data first
    assert meshseq.load(tmp_path / "run").iteration == 4 and ckpt.best_folder(tmp_path / "run").is_dir()
    assert main(argv + ["--window", "40", "--config", str(tmp_path / "as-given.toml"), "--force"]) == 2
    assert "--window 40" in capsys.readouterr().err
    assert (tmp_path / "run" / "metrics.csv").is_file() and ckpt.best_folder(tmp_path / "run").is_dir()


def test_zero_velocity_validation_error_by_hand(trained):
    _, data, run, _ = trained
    model = meshseq.load(run)
    feats = model.scaling.apply(data.features[0]).astype(np.float32)
    verts = model.vertices(feats)
    # block 24:32 (8 frames, so horizon 8): one start per u, its last given frame 23, predicting 24..31
    expected = []
    for u, starts in ((1, [23]), (3, [21])):
        errs = [np.linalg.norm((verts[s + u - 1] - verts[s + u - 1].mean(0)) - (verts[t] - verts[t].mean(0)), axis=-1).mean()
                for s in starts for t in range(s + u, s + u + 8)]
        expected.append(np.mean(errs) / 1e-4)
    got = validation_error(model, [verts], [feats], [(24, 32)], method="zero_velocity")
    assert got == pytest.approx(np.mean(expected), rel=1e-4)
