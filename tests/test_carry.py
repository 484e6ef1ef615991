"""Prediction's carried velocity (``meshseq.carry``): fitted on the training frames, stored by
training, read by the model and used by ``predict`` unless asked otherwise."""

import json

import numpy as np
import pytest

from meshseq.data.synthetic import twisting_limb


def test_the_body_sets_share_stays_unless_a_smaller_one_is_clearly_better():
    from meshseq.carry import CARRIES, CARRY, MARGIN, choose_carry

    assert CARRIES[-1] == CARRY and list(CARRIES) == sorted(CARRIES)
    assert choose_carry(np.array([0.50, 0.49, 0.48])) == CARRY
    assert choose_carry(np.array([0.49, 0.49, 0.48 + MARGIN / 2])) == CARRY  # within the margin
    assert choose_carry(np.array([0.64, 0.71, 0.96])) == CARRIES[0]  # a gallop: carrying overshoots
    assert choose_carry(np.array([0.60, 0.50, 0.55])) == CARRIES[1]  # the best of the smaller ones


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    from meshseq.io import save_sequence
    from meshseq.train import TrainConfig, load_training_data, train

    folder = tmp_path_factory.mktemp("carry")
    save_sequence(twisting_limb(frames=40, rings=8, segments=6), folder / "limb.npz")
    config = TrainConfig(iterations=6, window=8, batch=4, checkpoint_every=3, log_every=1)
    train(load_training_data([str(folder / "limb.npz")]), folder / "run", config, {"latent": 16, "lstm_layers": 1},
          device="cpu", progress=False, log=None)
    return folder


def test_training_stores_the_fitted_carry_and_prediction_uses_it(run):
    import meshseq
    from meshseq.carry import CARRIES, choose_carry
    from meshseq.io import load_sequence
    from meshseq.synthesize import predict

    model = meshseq.load(run / "run")
    fitted = model.meta["prediction"]
    scores = np.array([fitted["scores"][f"{c:g}"] for c in CARRIES])
    assert np.isfinite(scores).all() and model.carry == fitted["carry"] == choose_carry(scores)
    earlier = json.loads((run / "run" / "checkpoints" / "00000003" / "model.json").read_text())
    assert "prediction" not in earlier  # fitted on the finished model only
    x = model.features(load_sequence(str(run / "limb.npz")).vertices[10:13].astype(np.float64))
    other = 0.3 if model.carry != 0.3 else 0.0
    model.carry = other
    np.testing.assert_array_equal(predict(model, x, 8), predict(model, x, 8, carry=other))
    assert not np.array_equal(predict(model, x, 8), predict(model, x, 8, carry=0.59))


def _with_carry(run, copy, carry: float):
    """A copy of ``run`` whose finished checkpoint's model.json stores ``carry``."""
    import shutil

    shutil.copytree(run, copy)
    meta_path = copy / "checkpoints" / "00000006" / "model.json"
    meta = json.loads(meta_path.read_text())
    meta["prediction"]["carry"] = carry
    meta_path.write_text(json.dumps(meta))
    return copy


def test_a_stored_carry_outside_zero_to_one_is_refused(run, tmp_path):
    import meshseq
    from meshseq.errors import MeshseqError

    copy = _with_carry(run / "run", tmp_path / "run", 1.0)
    with pytest.raises(MeshseqError, match="prediction.carry"):
        meshseq.load(copy / "checkpoints" / "00000006")


def test_meshseq_predict_uses_the_runs_carry_and_says_so(run, tmp_path, capsys):
    from meshseq.cli import main
    from meshseq.io import load_sequence

    copy = _with_carry(run / "run", tmp_path / "run", 0.0)
    limb = str(run / "limb.npz")
    common = ["predict", str(copy), limb, "--start", "10", "--given", "3", "--frames", "6", "--guard", "off"]
    assert main(common + ["-o", str(tmp_path / "fitted.npz")]) == 0
    assert "carries 0 of the given frames' velocity" in capsys.readouterr().out
    assert main(common + ["--carry", "0", "-o", str(tmp_path / "zero.npz")]) == 0
    assert "carries" not in capsys.readouterr().out
    assert main(common + ["--carry", "0.6", "-o", str(tmp_path / "body.npz")]) == 0
    fitted, zero, body = (load_sequence(str(tmp_path / f"{n}.npz")).vertices for n in ("fitted", "zero", "body"))
    np.testing.assert_array_equal(fitted, zero)
    assert not np.array_equal(fitted, body)
