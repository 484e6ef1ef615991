"""The default recipe's window rule (``--window-fit batch``): a window is shortened until the
training frames hold at least a batch of different windows (``fitted_window``)."""

from __future__ import annotations

import json

import pytest

from meshseq import checkpoint as ckpt
from meshseq.cli import main
from meshseq.data.synthetic import twisting_limb
from meshseq.data.windows import fitted_window
from meshseq.errors import MeshseqError
from meshseq.io import save_sequence
from meshseq.train import RECIPES, TrainConfig

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def test_fitted_window_gives_a_batch_of_starts_where_it_can():
    assert fitted_window([29], 32, 8) == 22  # horse-gallop: 29 training frames, starts 0..7
    assert fitted_window([200], 32, 8) == 32  # enough windows already: unchanged
    assert fitted_window([40, 1000], 32, 8) == 32  # counted over all segments
    assert fitted_window([20, 20], 32, 8) == 17  # 4 + 4 starts
    assert fitted_window([20], 32, 8) == 16  # a batch is out of reach: not below 16 frames (5 starts)
    assert fitted_window([10], 32, 8) == 10  # shorter than 16: the longest window that fits
    assert fitted_window([10], 6, 8) == 6  # a window of at most 16 frames is not shortened (5 starts)
    assert fitted_window([1], 32, 8) == 32  # nothing fits: left to the sampler's error
    assert fitted_window([29], 32, 8, stride=2) == 15  # span (15 - 1) * 2 + 1 = 29 frames: one start
    assert fitted_window([100], 32, 8, stride=2) == 32  # span 63: 38 starts


def test_window_fit_is_checked_stored_and_the_paper_recipe_keeps_the_window(tmp_path, capsys):
    with pytest.raises(MeshseqError, match="window_fit 'all'"):
        TrainConfig(window_fit="all")
    assert TrainConfig().window_fit == "batch" and RECIPES["paper"]["window_fit"] == "none"
    assert TrainConfig.from_dict({"iterations": 5}).window_fit == "none"  # older checkpoints: as given
    seq = twisting_limb(frames=40, rings=8, segments=6, seed=0)  # 32 training frames (20% held out)
    save_sequence(seq, tmp_path / "limb.npz")

    def train(name, *extra, config=""):
        (tmp_path / f"{name}.toml").write_text(f"checkpoint_every = 2\n{config}\n[model]\nlstm_layers = 1\n")
        argv = ["train", str(tmp_path / "limb.npz"), "--out", str(tmp_path / name), "--iterations", "2",
                "--window", "32", "--batch", "8", "--latent", "8", "--no-progress",
                "--threads", "1", "--config", str(tmp_path / f"{name}.toml"), *extra]
        code = main(argv)
        out = capsys.readouterr()
        if code:
            return code, out.err.strip()
        meta = json.loads((ckpt.latest_checkpoint(tmp_path / name) / "model.json").read_text())
        return meta["train"], out.out + out.err

    stored, said = train("fit")
    assert stored["window"] == 25 and stored["window_fit"] == "batch"  # 32 - 25 + 1 = 8 starts
    assert "training on windows of 25 frames" in said
    stored, said = train("as-given", config='window_fit = "none"')
    assert stored["window"] == 32 and "training on windows" not in said
    stored, _ = train("paper", "--recipe", "paper")
    assert stored["window"] == 32 and stored["window_fit"] == "none"
    code, err = train("given", config="given = 25")
    assert code == 2 and err.count("\n") == 0 and "given 25" in err and 'window_fit = "none"' in err
    assert not (tmp_path / "given").exists()
