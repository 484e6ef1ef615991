"""Completion's vertex share (``meshseq.inbetween``): fitted on training frames, stored by
training, applied by ``complete_keyframes`` and the evaluation."""

import numpy as np
import pytest

from meshseq.data.synthetic import twisting_limb


def _segments(vertices: np.ndarray, faces: np.ndarray):
    from meshseq import acap

    feats = acap.extract(vertices, faces, reference=vertices[0])
    solver = acap.Reconstructor(vertices[0], faces)
    return [(feats, vertices)], solver.solve


def test_fit_picks_the_vertices_where_the_motion_is_straight_in_vertices_and_the_features_where_it_turns():
    from meshseq.inbetween import VERTEX_SHARES, fit_vertex_share

    from scipy.spatial.transform import Rotation

    limb = twisting_limb(frames=40, rings=8, segments=6, twist_turns=1.0)
    v = limb.vertices.astype(np.float64)
    spin = Rotation.from_rotvec(np.outer(0.15 * np.arange(40), [1.0, 0.0, 0.0])).as_matrix()  # 0.15 rad a frame
    turning = fit_vertex_share(*_segments(np.einsum("tij,vj->tvi", spin, v[10]), limb.faces))
    assert turning["vertex_share"] == 0.0  # one rotation: the features' geodesic line is exact
    assert turning["scores"]["1"] > 1.05 * turning["scores"]["0"]
    s = np.linspace(0.0, 1.0, 40)[:, None, None]
    morph = (1 - s) * v[0] + s * v[20]  # a straight morph in vertex space: the vertices' line is exact
    straight = fit_vertex_share(*_segments(morph, limb.faces))
    assert straight["vertex_share"] == 1.0
    assert set(straight["scores"]) == {f"{x:g}" for x in VERTEX_SHARES}


def test_fit_keeps_the_smaller_share_unless_the_larger_gains_more_than_the_margin(monkeypatch):
    import meshseq.inbetween as inbetween

    scores = {5: [1.0, 0.997, 1.2], 10: [1.0, 0.997, 1.2]}  # errors per share at each gap length

    def errors(features, vertices, reconstruct, gap, shares):
        return np.array([scores[gap]])

    monkeypatch.setattr(inbetween, "blend_errors", errors)
    shares = (0.0, 0.5, 1.0)
    assert inbetween.fit_vertex_share([(None, None)], None, shares)["vertex_share"] == 0.0  # 0.3%: within the margin
    scores[5][1] = scores[10][1] = 0.99
    assert inbetween.fit_vertex_share([(None, None)], None, shares)["vertex_share"] == 0.5
    assert inbetween.fit_vertex_share([], None, shares) == {"vertex_share": 0.0, "scores": {}}


def test_blend_toward_vertices_moves_the_in_between_frames_by_the_share_and_keeps_the_keys():
    from meshseq.synthesize import blend_toward_vertices

    rng = np.random.default_rng(0)
    frames = rng.normal(size=(3, 6, 4, 3))
    lines = frames[:, :1] + np.linspace(0, 1, 6)[None, :, None, None] * (frames[:, -1:] - frames[:, :1])
    out = blend_toward_vertices(frames, np.array([0.0, 0.5, 1.0]))
    np.testing.assert_allclose(out[0], frames[0])
    np.testing.assert_allclose(out[1], 0.5 * (frames[1] + lines[1]))
    np.testing.assert_allclose(out[2], lines[2])
    np.testing.assert_allclose(out[:, [0, -1]], frames[:, [0, -1]])
    assert blend_toward_vertices(frames, np.zeros(3)) is frames


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    from meshseq.io import save_sequence
    from meshseq.train import TrainConfig, load_training_data, train

    root = tmp_path_factory.mktemp("inbetween")
    data = root / "limb.npz"
    save_sequence(twisting_limb(frames=48, rings=8, segments=6), data)
    train(load_training_data([str(data)]), root / "run", TrainConfig(iterations=4, window=12, batch=2, seed=0),
          progress=False)
    return root / "run", data


def test_training_stores_the_fitted_share_and_completion_blends_the_lines_share_by_it(run):
    import meshseq
    from meshseq.data.windows import Split
    from meshseq.inbetween import VERTEX_SHARES
    from meshseq.io import load_sequence
    from meshseq.synthesize import complete, complete_keyframes, keyframe_features
    from meshseq.training.data import load_training_data
    from meshseq.training.loop import completion_fit

    model = meshseq.load(run[0])
    stored = model.meta["completion"]
    assert stored["vertex_share"] in VERTEX_SHARES and model.vertex_share == stored["vertex_share"]
    splits = [Split.from_dict(d["split"]) for d in model.meta["datasets"]]
    assert completion_fit(load_training_data([str(run[1])]), splits, model.placement) == stored
    v = load_sequence(run[1]).vertices.astype(np.float64)
    keys = v[[4, 15]]
    plain = complete_keyframes(model, keys, [10], vertex_share=0.0)[0]
    lines = complete_keyframes(model, keys, [10], method="linear_vertices")[0]
    f = keyframe_features(model, keys)[0]
    share = complete(model, f[0], f[1], 10).line_share[0]
    for vertex_share in (0.5, 1.0):
        got = complete_keyframes(model, keys, [10], vertex_share=vertex_share)[0]
        np.testing.assert_allclose(got, plain + vertex_share * share * (lines - plain), atol=1e-9)
    model.vertex_share = 0.5  # the model's share is the default
    np.testing.assert_array_equal(complete_keyframes(model, keys, [10])[0],
                                  complete_keyframes(model, keys, [10], vertex_share=0.5)[0])


def test_complete_names_the_share_its_line_leans_by(run, tmp_path, capsys):
    import json
    import shutil

    from meshseq import checkpoint as ckpt
    from meshseq.cli import main

    copy = tmp_path / "run"
    shutil.copytree(run[0], copy)
    for folder in ckpt.list_checkpoints(copy):
        meta = json.loads((folder / "model.json").read_text())
        meta["completion"] = {"vertex_share": 0.25}
        (folder / "model.json").write_text(json.dumps(meta))
    assert main(["complete", str(copy), str(run[1]), "--keyframes", "4,15", "-o", str(tmp_path / "a.npz")]) == 0
    assert "its line 25% of the way to the keys' vertex lines" in capsys.readouterr().out
    assert main(["complete", str(copy), str(run[1]), "--keyframes", "4,15", "--method", "corrected",
                 "-o", str(tmp_path / "b.npz")]) == 0
    assert "vertex lines" not in capsys.readouterr().out
    out = tmp_path / "scores.json"
    assert main(["evaluate", str(copy), str(run[1]), "--range", "20:48", "--methods", "ours", "--given", "3",
                 "--horizons", "4", "--gaps", "5", "--curve-frames", "4", "--json", str(out)]) == 0
    assert any("25% of the way to the keys' vertex lines" in n for n in json.loads(out.read_text())["notes"])


def test_the_benchmark_fits_the_share_of_a_run_stored_without_one_as_training_does(run, tmp_path):
    import json
    import shutil

    import meshseq
    from conftest import benchmark_script
    from meshseq import checkpoint as ckpt

    generalize = benchmark_script("generalize")
    stored = meshseq.load(run[0]).meta["completion"]
    copy = tmp_path / "run"
    shutil.copytree(run[0], copy)
    for folder in ckpt.list_checkpoints(copy):  # as runs were stored before training fitted it
        meta = json.loads((folder / "model.json").read_text())
        del meta["completion"]
        (folder / "model.json").write_text(json.dumps(meta))
    model = meshseq.load(copy)
    model.vertex_share = 0.75  # what the fit must replace
    assert model.meta.get("completion") is None
    got = generalize.ensure_vertex_share(model, *generalize.training_specs(model))
    assert got == {**stored, "source": "fitted when scored"} and model.vertex_share == stored["vertex_share"]
    assert generalize.ensure_vertex_share(meshseq.load(run[0]), [], [])["source"] == "stored"
