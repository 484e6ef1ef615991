"""The temporal-resampling augmentation (``meshseq train --speed-augment R``): training windows
played at random speeds, every frame interpolated inside one training segment."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from meshseq import checkpoint as ckpt
from meshseq.cli import main
from meshseq.data.synthetic import twisting_limb
from meshseq.data.windows import WindowSampler, split_frames
from meshseq.errors import MeshseqError
from meshseq.io import save_sequence
from meshseq.train import TrainConfig, training_windows

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def test_windows_at_speeds_stay_inside_their_segment_and_step_evenly():
    # two data sets; the first has training segments 0-40 and 60-100 (held-out block in the middle)
    splits = [split_frames(100, 0.2, at="0.4"), split_frames(50, 0.2, validation=0.25)]
    assert splits[0].train == ((0, 40), (60, 100)) and splits[1].train == ((0, 30),)
    sampler = WindowSampler(splits, ["a", "b"], window=12, stride=2)
    before, after, weight = sampler.sample_at_speeds(np.random.default_rng(0), 4000, 1.5)
    assert before.shape == after.shape == weight.shape == (4000, 12)
    assert ((0 <= weight) & (weight < 1)).all()
    assert ((after == before + 1) | ((after == before) & (weight == 0))).all()
    pos = before + weight
    segments = [(0, 40), (60, 100), (100, 130)]  # rows of the stacked frames (b starts at row 100)
    inside = [((pos >= a) & (pos <= b - 1)).all(1) & (after.max(1) <= b - 1) for a, b in segments]
    assert np.logical_xor.reduce(inside).all()  # every window in exactly one segment
    step = np.diff(pos, axis=1) / 2  # speed, per frame step of the stride
    assert np.allclose(step, step[:, :1])
    assert step.min() >= 1 / 1.5 - 1e-9 and step.max() <= 1.5 + 1e-9
    assert step.max() > 1.4 and step.min() < 0.7  # the range is used
    # a window that cannot play at 1.5 in its segment is slowed to fit: segment b has 30 frames,
    # so at most 29 / 22 = 1.318 for 12 frames at stride 2
    in_b = inside[2]
    assert in_b.any() and step[in_b].max() <= 29 / 22 + 1e-9
    # every segment is drawn (in proportion to its windows)
    assert all(x.mean() > 0.05 for x in inside)


def test_training_windows_interpolate_the_frames_and_are_the_plain_windows_when_off():
    splits = [split_frames(60, 0.2)]
    sampler = WindowSampler(splits, ["a"], window=8)
    t = torch.arange(60, dtype=torch.float32)
    frames = t[:, None, None].expand(60, 3, 9).contiguous() * torch.linspace(1, 2, 9)  # frame t = t * c
    config = TrainConfig(window=8, batch=16, speed_augment=2.0)
    w, w_rows = training_windows(frames, sampler, np.random.default_rng(1), config)
    assert w_rows is None  # interpolated frames: no frame indices
    before, after, weight = sampler.sample_at_speeds(np.random.default_rng(1), 16, 2.0)
    expected = torch.from_numpy(before + weight).float()[..., None, None] * torch.linspace(1, 2, 9)
    assert w.shape == (16, 8, 3, 9)
    assert torch.allclose(w, expected.expand_as(w), atol=1e-4)
    assert not torch.allclose(w[:, 1] - w[:, 0], torch.ones(16, 3, 9) * torch.linspace(1, 2, 9))
    # off (R = 1): exactly the windows (and the random numbers) of WindowSampler.sample
    plain, plain_rows = training_windows(frames, sampler, np.random.default_rng(1), TrainConfig(window=8, batch=16))
    assert torch.equal(plain, frames[torch.from_numpy(sampler.sample(np.random.default_rng(1), 16))])
    assert torch.equal(plain, frames[plain_rows])  # the rows are the windows' frames
    # a process's share (distributed training) is its slice of the same batch
    part, _ = training_windows(frames, sampler, np.random.default_rng(1), config, slice(4, 12))
    assert torch.equal(part, w[4:12])


def test_speed_augment_option_is_checked_and_stored(tmp_path, capsys):
    with pytest.raises(MeshseqError, match="speed_augment 0.5"):
        TrainConfig(speed_augment=0.5)
    with pytest.raises(MeshseqError, match="speed_augment nan"):
        TrainConfig(speed_augment=float("nan"))
    assert TrainConfig.from_dict({"iterations": 5}).speed_augment == 1.0  # older checkpoints: off
    seq = twisting_limb(frames=40, rings=8, segments=6, seed=0)
    save_sequence(seq, tmp_path / "limb.npz")
    argv = ["train", str(tmp_path / "limb.npz"), "--out", str(tmp_path / "run"), "--iterations", "3", "--window",
            "6", "--batch", "2", "--latent", "16", "--no-progress", "--threads", "1"]

    def config(rate: float) -> list[str]:
        (tmp_path / f"{rate}.toml").write_text(f"speed_augment = {rate}\n[model]\nlstm_layers = 1\n")
        return ["--config", str(tmp_path / f"{rate}.toml")]

    assert main(argv + config(0.9)) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and f"{tmp_path / '0.9.toml'}: speed_augment: 0.9: expected a number >= 1" in err
    assert main(argv + config(1.5)) == 0
    meta = json.loads((ckpt.latest_checkpoint(tmp_path / "run") / "model.json").read_text())
    assert meta["iteration"] == 3 and meta["train"]["speed_augment"] == 1.5
