"""The demo (the README's main job) end to end, with a very short training."""

from __future__ import annotations

import json

import imageio.v3 as iio
import numpy as np
import pytest

from meshseq.demo import run_demo
from meshseq.errors import MeshseqError


def test_demo_writes_pictures_model_and_tables(tmp_path):
    out = tmp_path / "demo"
    result = run_demo(out, iterations=3, data="limb", cache=tmp_path / "cache", device="cpu", log=lambda m: None)
    names = sorted(p.name for p in out.iterdir())
    assert names == ["completion.png", "errors.json", "errors.md", "prediction.gif", "prediction.glb",
                     "prediction.png", "run"]
    table = json.loads((out / "errors.json").read_text())
    assert set(table["errors"]) == {"ours", "zero_velocity", "linear_acap"}
    assert all(v > 0 for per_u in table["errors"].values() for e in per_u.values() for v in e.values())
    assert "| ours |" in (out / "errors.md").read_text()
    strip = iio.imread(out / "prediction.png")
    assert strip.ndim == 3 and strip.shape[1] > strip.shape[0]
    assert (strip[..., :3].std(axis=(0, 1)) > 10).all()  # not blank
    gif = iio.imread(out / "prediction.gif", index=None)
    assert gif.shape[0] > 10
    assert (out / "prediction.glb").read_bytes()[:4] == b"glTF"
    assert result["iterations"] == 3
    # the folder is not replaced without force, and nothing else is written
    with pytest.raises(MeshseqError, match="already exists"):
        run_demo(out, iterations=1, data="limb", cache=tmp_path / "cache", device="cpu", log=lambda m: None)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["cache", "demo"]
    assert np.isfinite(result["train_seconds"])


def test_demo_on_the_body_data_fits_its_horizons(tmp_path, monkeypatch):
    """The default data path: Anny sequences as long as the real default set (64 frames)."""
    from meshseq.data import bodies

    default = dict(bodies.DEFAULT_SET)
    monkeypatch.setattr(bodies, "DEFAULT_SET", dict(default, subjects=default["subjects"][:1],
                                                    motions=default["motions"][:2], vertices=800))
    out = tmp_path / "demo"
    result = run_demo(out, iterations=2, data="bodies", cache=tmp_path / "cache", device="cpu", log=lambda m: None)
    assert result["dataset"].startswith(default["subjects"][0] + "_")
    lo, hi = result["heldout"]
    assert hi - lo >= 18  # 3 given frames + horizon 15
    assert set(result["errors"]["ours"]) == {"u1", "u3"}
    assert (out / "prediction.png").is_file() and (out / "completion.png").is_file()
