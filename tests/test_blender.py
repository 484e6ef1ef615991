"""Blender (Debian's ``blender`` 3.4, headless) as the client of meshseq's interchange formats.

Blender makes a deforming mesh and exports it with its own MDD, PC2 and glTF exporters; meshseq
reads each file and matches Blender's evaluated positions. meshseq writes MDD and glb; Blender's
importers read them and show the same positions frame by frame. The Blender-side script is
tests/blender_client.py. Blender missing -> the tests FAIL (tools/install_test_deps.sh installs it).
"""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import pytest
from conftest import REPO_ROOT, run_blender, shared_file
from scipy.spatial import cKDTree

from meshseq.cli import main
from meshseq.errors import MeshseqWarning
from meshseq.io import MeshSequence, load_sequence, save_sequence

CLIENT = REPO_ROOT / "tests" / "blender_client.py"
FRAMES = 25  # Blender frames 1..25; the shape keys are keyed every 3 frames, the last at 25


def blender(*args: str) -> str:
    """Run tests/blender_client.py in headless Blender (``conftest.run_blender``)."""
    return run_blender(CLIENT, list(args), timeout=300)


@pytest.fixture(scope="module")
def made_in_blender(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("blender")
    blender("make", str(out), str(FRAMES))
    return out


def test_blender_mdd_and_pc2_read_as_blenders_evaluated_positions(made_in_blender):
    out = made_in_blender
    positions = np.load(out / "blender_positions.npy")  # (T, V, 3), Blender's evaluated mesh
    faces = np.load(out / "blender_faces.npy")
    assert positions.shape[0] == FRAMES and np.ptp(positions, axis=0).max() > 0.2  # it really deforms
    for spec in (f"{out}/base.obj:{out}/anim.mdd", f"{out}/base.obj:{out}/anim.pc2"):
        seq = load_sequence(spec)
        assert seq.vertices.shape == positions.shape, spec
        np.testing.assert_allclose(seq.vertices, positions, rtol=0, atol=1e-5, err_msg=spec)
        np.testing.assert_array_equal(seq.faces, faces)  # Blender's OBJ keeps vertex and face order
    assert load_sequence(f"{out}/base.obj:{out}/anim.mdd").fps == 24.0  # from the MDD's frame times


def test_blender_glb_reads_as_blenders_evaluated_positions(made_in_blender):
    out = made_in_blender
    positions = np.load(out / "blender_positions.npy")
    yup = positions[..., [0, 2, 1]] * np.array([1.0, 1.0, -1.0])  # Blender z-up -> glTF y-up
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        seq = load_sequence(out / "anim.glb")
    # Blender splits the flat-shaded sphere's vertices per face; meshseq merges them back
    assert any(issubclass(w.category, MeshseqWarning) and "merged" in str(w.message) for w in caught)
    assert seq.vertices.shape == yup.shape and seq.fps == 24.0
    dist, match = cKDTree(seq.vertices[0]).query(yup[0])
    assert dist.max() < 1e-5 and len(set(match.tolist())) == len(match)  # one to one
    np.testing.assert_allclose(seq.vertices[:, match], yup, rtol=0, atol=1e-5)
    faces = np.load(out / "blender_faces.npy")
    assert {tuple(sorted(f)) for f in match[faces].tolist()} == {tuple(sorted(f)) for f in seq.faces.tolist()}


@pytest.fixture(scope="module")
def cow12(tmp_path_factory) -> tuple[Path, MeshSequence]:
    data = np.load(shared_file("pcow.npz"))
    seq = MeshSequence(data["vertices"][:12], data["faces"], name="cow", fps=24.0)
    folder = tmp_path_factory.mktemp("cow")
    save_sequence(seq, folder / "cow.npz")
    return folder, seq


def test_blender_imports_meshseq_mdd_frame_by_frame(cow12):
    folder, seq = cow12
    assert main(["export", str(folder / "cow.npz"), "-o", str(folder / "cow.mdd")]) == 0  # + cow.obj
    blender("import-mdd", str(folder), str(folder / "cow.obj"), str(folder / "cow.mdd"), str(seq.n_frames))
    shown = np.load(folder / "imported_mdd.npy")
    assert shown.shape == seq.vertices.shape
    np.testing.assert_allclose(shown, seq.vertices, rtol=0, atol=1e-5)
    # a real check: consecutive frames differ by much more than the tolerance
    assert np.abs(np.diff(seq.vertices, axis=0)).max() > 1e-3


def test_blender_imports_meshseq_glb_frame_by_frame(cow12):
    folder, seq = cow12
    assert main(["export", str(folder / "cow.npz"), "-o", str(folder / "cow.glb")]) == 0
    blender("import-glb", str(folder), str(folder / "cow.glb"), str(seq.n_frames))
    shown = np.load(folder / "imported_glb.npy")
    np.testing.assert_allclose(np.load(folder / "imported_glb_world.npy"), np.eye(4), atol=1e-6)
    zup = seq.vertices[..., [0, 2, 1]] * np.array([1.0, -1.0, 1.0])  # glTF y-up -> Blender z-up
    assert shown.shape == zup.shape
    np.testing.assert_allclose(shown, zup, rtol=0, atol=1e-5)
