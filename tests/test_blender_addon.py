"""The Blender add-on (``meshseq blender-addon``) in the real client: headless Blender 3.4.

Blender installs the zip from the add-on preferences' operator (into temporary user folders, so
the user's own Blender is untouched), enables it, builds an animated icosphere and runs each
operator; tests/blender_addon_client.py is the Blender side. The model is trained once for the
module, by the add-on's Train operator (3 iterations); its completions, predictions and samples
must equal those of the ``meshseq`` commands on the same frames, and pass through the keyframes.
Blender missing -> the tests FAIL (tools/install_test_deps.sh installs it).
"""

from __future__ import annotations

import json
import subprocess
import sys
import zipfile
from pathlib import Path

import numpy as np
import pytest
from conftest import REPO_ROOT, run_blender

from meshseq.cli import main
from meshseq.cli.addon_cmds import ADDON_MODULE, this_meshseq
from meshseq.io import MeshSequence, load_sequence, save_sequence

CLIENT = REPO_ROOT / "tests" / "blender_addon_client.py"
KEYS = (1, 9, 17)  # the client's timeline markers (Blender frames; the animation is frames 1..24)
PRED_AT, PRED_FRAMES, PRED_GIVEN = 10, 6, 3
SAMPLES, SEED = 3, 0
# Blender evaluates a relative shape key as basis - (basis - key): exact up to one float32 rounding
ULP = 2 * np.finfo(np.float32).eps


def blender(folder: Path, *args: str) -> None:
    """Run the client in headless Blender with user folders under ``folder`` (``conftest.run_blender``;
    the add-on runs meshseq by its absolute path)."""
    for name in ("config", "scripts"):
        (folder / name).mkdir(exist_ok=True)
    run_blender(CLIENT, list(args), timeout=900,
                extra_env={"BLENDER_USER_CONFIG": str(folder / "config"), "BLENDER_USER_SCRIPTS": str(folder / "scripts")})


@pytest.fixture(scope="module")
def addon(tmp_path_factory) -> tuple[Path, Path]:
    folder = tmp_path_factory.mktemp("addon")
    zip_path = folder / "meshseq_addon.zip"
    assert main(["blender-addon", "-o", str(zip_path), "--meshseq", this_meshseq()]) == 0
    return folder, zip_path


@pytest.fixture(scope="module")
def trained(addon) -> tuple[Path, dict]:
    folder, zip_path = addon
    out = folder / "train"
    out.mkdir()
    blender(folder, "train", str(out), str(zip_path), this_meshseq(), str(folder / "run"))
    return folder / "run", json.loads((out / "train.json").read_text())


@pytest.fixture(scope="module")
def operated(addon, trained) -> tuple[Path, dict]:
    folder, zip_path = addon
    out = folder / "ops"
    out.mkdir()
    blender(folder, "ops", str(out), str(zip_path), this_meshseq(), str(trained[0]))
    return out, json.loads((out / "ops.json").read_text())


def command_result(folder: Path, name: str, frames: np.ndarray, faces: np.ndarray, args: list[str]) -> np.ndarray:
    """``meshseq COMMAND RUN DATA OPTIONS`` (``args`` without DATA) on ``frames (T, V, 3)`` written as
    NAME.pc2 (float32, as the add-on writes them): the vertices it writes, ``(T', V, 3)``, or
    ``(K, T', V, 3)`` with --samples K."""
    data = folder / f"{name}.pc2"
    save_sequence(MeshSequence(frames.astype(np.float64), faces, name=name), data, force=True)
    out = folder / f"{name}_out"
    assert main([*args[:2], str(data), *args[2:], "-o", str(out) + ("" if "--samples" in args else ".npz")]) == 0
    if "--samples" in args:
        return np.stack([np.load(out / f"sample_{s:02d}.npz")["vertices"] for s in range(SAMPLES)])
    return np.load(str(out) + ".npz")["vertices"]


def test_blender_addon_zip_holds_the_addon(addon, tmp_path, capsys):
    _, zip_path = addon
    with zipfile.ZipFile(zip_path) as zf:
        assert sorted(zf.namelist()) == [f"{ADDON_MODULE}/__init__.py", f"{ADDON_MODULE}/cachefiles.py"]
        source = zf.read(f"{ADDON_MODULE}/__init__.py").decode()
    assert f"DEFAULT_MESHSEQ = {this_meshseq()!r}" in source and '"blender": (3, 4, 0)' in source
    compile(source, "__init__.py", "exec")
    assert main(["blender-addon", "-o", str(zip_path)]) == 2
    assert "already exists; use --force" in capsys.readouterr().err
    assert main(["blender-addon", "-o", str(tmp_path / "addon.py")]) == 2
    assert capsys.readouterr().err.strip().endswith("give a path ending in .zip")
    assert not (tmp_path / "addon.py").exists()


def test_meshseq_does_not_import_the_addon():
    code = ("import sys, meshseq, meshseq.cli; meshseq.cli.build_parser(); "
            "assert not any(m.startswith('meshseq.blender_addon') for m in sys.modules) and 'bpy' not in sys.modules")
    subprocess.run([sys.executable, "-c", code], check=True)


def test_train_operator_trains_reports_and_cancels(trained):
    run, result = trained
    meta = json.loads((run / "checkpoints" / "00000003" / "model.json").read_text())
    assert [d["name"] for d in meta["datasets"]] == ["00_Blob", "01_Blob2"]  # the two selected objects
    assert all(d["n_frames"] == 24 for d in meta["datasets"])
    assert (run / "metrics.csv").read_text().splitlines()[-1].startswith("3,")
    # a second Train into the same folder without Replace: a report, the model kept
    assert "is not empty: tick 'Replace model' to train" in result["not_empty_report"]
    # the cancelled training had shown its progress, stopped, and left no temporary files
    assert result["iteration_before_cancel"] >= 1 and "iteration" in result["progress_message"]
    assert result["cancel_state"] == "cancelled" and result["returncode"] not in (0, None)
    assert "cancelled at iteration" in result["cancel_message"]
    assert not result["workdir_left"] and not result["cancel_poll"]


def test_complete_operator_equals_the_command_through_exact_keys(trained, operated, tmp_path):
    out, info = operated
    source, faces = np.load(out / "source.npy"), np.load(out / "faces.npy")  # (24, V, 3) Blender frames 1..24
    shown = np.load(out / "completed.npy")  # the copy's evaluated frames KEYS[0]..KEYS[-1]
    span = source[KEYS[0] - 1: KEYS[-1]]
    assert source.shape[1] == 642 and shown.shape == span.shape
    assert info["completed_name"] == "Blob_completed" and info["completed_keys"] == 1 + len(span)
    np.testing.assert_array_equal(info["completed_world"], np.eye(4))
    keys = [k - KEYS[0] for k in KEYS]
    # the shape keys at the keyframes hold the source's positions bit for bit ...
    np.testing.assert_array_equal(np.load(out / "completed_keys.npy"), span[keys])
    # ... and Blender shows them within one float32 rounding
    np.testing.assert_allclose(shown[keys], span[keys], rtol=0, atol=ULP * np.abs(span).max())
    expected = command_result(tmp_path, "blob", span, faces,
                              ["complete", str(trained[0]), "--keyframes", ",".join(map(str, keys))])
    np.testing.assert_allclose(shown, expected, rtol=0, atol=1e-6)
    between = [t for t in range(len(span)) if t not in keys]
    assert np.abs(np.diff(shown, axis=0)).max() > 1e-3  # it moves between the keys
    assert np.abs(shown[between] - span[between]).max() > 1e-4  # and is meshseq's, not the source's


def test_predict_operator_equals_the_command(trained, operated, tmp_path):
    out, info = operated
    source, faces = np.load(out / "source.npy"), np.load(out / "faces.npy")
    shown = np.load(out / "predicted.npy")  # frames PRED_AT - PRED_GIVEN + 1..PRED_AT + PRED_FRAMES
    assert info["predicted_name"] == "Blob_predicted"
    assert shown.shape == (PRED_GIVEN + PRED_FRAMES, *source.shape[1:])
    given = source[PRED_AT - PRED_GIVEN: PRED_AT]  # the panel's default: 3 frames up to the current one
    np.testing.assert_array_equal(shown[0], given[0])  # the first given frame is the copy's basis: exact
    expected = command_result(tmp_path, "blob", given, faces,
                              ["predict", str(trained[0]), "--given", str(PRED_GIVEN), "--frames", str(PRED_FRAMES)])
    np.testing.assert_allclose(shown, expected, rtol=0, atol=1e-6)
    assert np.abs(shown[1:] - shown[0]).max() > 1e-3
    early = np.load(out / "predicted_early.npy")  # at frame 2 of a scene from frame 1: two frames given
    expected = command_result(tmp_path, "early", source[:2], faces,
                              ["predict", str(trained[0]), "--given", "2", "--frames", str(PRED_FRAMES)])
    np.testing.assert_allclose(early, expected, rtol=0, atol=1e-6)


def test_samples_operator_makes_the_commands_samples_side_by_side(trained, operated, tmp_path):
    out, info = operated
    source, faces = np.load(out / "source.npy"), np.load(out / "faces.npy")
    shown = np.load(out / "samples.npy")  # (K, frames, V, 3)
    span = source[KEYS[0] - 1: KEYS[-1]]
    keys = [k - KEYS[0] for k in KEYS]
    assert info["sample_names"] == [f"Blob_sample_{s:02d}" for s in range(SAMPLES)]
    x = np.array(info["sample_x"])
    assert np.all(np.diff(x) > 2.0) and x[0] > 2.0  # side by side, clear of the 2-wide source
    expected = command_result(tmp_path, "blob", span, faces,
                              ["complete", str(trained[0]), "--keyframes", ",".join(map(str, keys)),
                               "--samples", str(SAMPLES), "--seed", str(SEED)])
    np.testing.assert_allclose(shown, expected, rtol=0, atol=1e-6)
    np.testing.assert_allclose(shown[:, keys], np.broadcast_to(span[keys], shown[:, keys].shape),
                               rtol=0, atol=ULP * np.abs(span).max())
    assert np.abs(shown[0] - shown[1]).max() > 1e-5  # different completions


def test_failures_are_one_line_reports(operated):
    _, info = operated
    reports = info["reports"]
    assert "mark at least two keyframes with timeline markers" in reports["one_marker"]
    assert "meshseq: error:" in reports["bad_model"] and "no-such-model" in reports["bad_model"]
    assert "meshseq: error: Small.pc2 has another connectivity" in reports["other_mesh"]
    assert "cannot run the meshseq command '/no/such/meshseq'" in reports["no_meshseq"]
    for text in reports.values():
        assert text.startswith("Error: ") and text.strip().count("\n") == 0 and "Traceback" not in text
    assert info["objects_added_by_failures"] == 0


def test_addon_files_match_meshseqs(tmp_path):
    """The add-on's plain-Python PC2/PLY readers read meshseq's files; meshseq reads its PC2 + OBJ."""
    import array

    from meshseq.blender_addon import cachefiles

    rng = np.random.default_rng(0)
    verts = rng.normal(size=(5, 7, 3))
    faces = np.array([[0, 1, 2], [2, 3, 4], [4, 5, 6], [6, 0, 3]])
    seq = MeshSequence(verts, faces, name="r")
    as_float32 = verts.astype(np.float32).reshape(5, -1)
    save_sequence(seq, tmp_path / "r.pc2")
    np.testing.assert_array_equal(np.array(cachefiles.read_pc2(str(tmp_path / "r.pc2"))), as_float32)
    save_sequence(seq, tmp_path / "ply", format="ply")
    np.testing.assert_array_equal(np.array(cachefiles.read_ply_folder(str(tmp_path / "ply"))), as_float32)
    cachefiles.write_pc2(str(tmp_path / "w.pc2"), [array.array("f", f.tolist()) for f in as_float32], 7)
    cachefiles.write_obj(str(tmp_path / "w.obj"), array.array("f", as_float32[0].tolist()),
                         [tuple(f) for f in faces.tolist()])
    back = load_sequence(str(tmp_path / "w.pc2"))  # w.obj beside it
    np.testing.assert_array_equal(back.vertices, verts.astype(np.float32))
    np.testing.assert_array_equal(back.faces, faces)
    (tmp_path / "bad.pc2").write_bytes(cachefiles.PC2_HEADER.pack(b"POINTCACHE2\0", 1, 7, 0.0, 1.0, 2) + bytes(84))
    with pytest.raises(cachefiles.AddonError, match="does not hold"):
        cachefiles.read_pc2(str(tmp_path / "bad.pc2"))
