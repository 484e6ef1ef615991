"""glTF 2.0 export: morph-target animation, Khronos validator, ``meshseq export``."""

from __future__ import annotations

import json
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pygltflib
import pytest
from conftest import REPO_ROOT, shared_file

from meshseq.cli import main
from meshseq.errors import MeshseqError
from meshseq.export import glb_bytes, gltf_document, save_glb

VALIDATOR_JS = REPO_ROOT / "tools" / "validate_glb.js"
VALIDATOR_PKG = REPO_ROOT / "tools" / "node_modules" / "gltf-validator" / "package.json"

_DTYPES = {5126: np.float32, 5125: np.uint32, 5123: np.uint16}
_WIDTH = {"SCALAR": 1, "VEC3": 3}


@pytest.fixture(scope="module")
def pcow():
    data = np.load(shared_file("pcow.npz"))
    return data["vertices"][:12].astype(np.float64), data["faces"].astype(np.int64)


def validate(path: Path) -> dict:
    """The Khronos validator's report on ``path``; the test FAILS if the validator is missing."""
    node = shutil.which("node")
    if node is None or not VALIDATOR_PKG.is_file():
        pytest.fail(
            "the Khronos glTF validator is not installed (node + tools/node_modules/gltf-validator); "
            "run tools/install_test_deps.sh",
            pytrace=False,
        )
    proc = subprocess.run([node, str(VALIDATOR_JS), str(path)], capture_output=True, text=True, timeout=120)
    assert proc.returncode in (0, 1), proc.stderr
    return json.loads(proc.stdout)


def read_accessor(doc: pygltflib.GLTF2, index: int) -> np.ndarray:
    acc = doc.accessors[index]
    view = doc.bufferViews[acc.bufferView]
    blob = doc.binary_blob()
    start = view.byteOffset + (acc.byteOffset or 0)
    width = _WIDTH[acc.type]
    data = np.frombuffer(blob, dtype=_DTYPES[acc.componentType], count=acc.count * width, offset=start)
    return data.reshape(acc.count, width) if width > 1 else data


def test_glb_reproduces_every_frame_and_plays_them_in_order(pcow, tmp_path):
    verts, faces = pcow
    path = save_glb(tmp_path / "cow.glb", verts, faces, fps=12.5, name="cow")
    doc = pygltflib.GLTF2().load_binary(str(path))
    assert doc.asset.version == "2.0"
    (prim,) = doc.meshes[0].primitives
    base = read_accessor(doc, prim.attributes.POSITION)
    np.testing.assert_allclose(base, verts[0].astype(np.float32))
    idx = read_accessor(doc, prim.indices).reshape(-1, 3)
    np.testing.assert_array_equal(idx, faces)
    assert len(prim.targets) == len(verts) - 1
    for t, target in enumerate(prim.targets, start=1):
        frame = base + read_accessor(doc, target["POSITION"])
        np.testing.assert_allclose(frame, verts[t], atol=1e-5)
    # Normals: unit length on the base mesh.
    normals = read_accessor(doc, prim.attributes.NORMAL)
    np.testing.assert_allclose(np.linalg.norm(normals, axis=1), 1.0, atol=1e-5)
    # The animation: keyframe t at t / fps holds weight 1 on target t (frame t), 0 elsewhere.
    (anim,) = doc.animations
    (sampler,) = anim.samplers
    assert sampler.interpolation == "LINEAR"
    assert anim.channels[0].target.path == "weights" and anim.channels[0].target.node == 0
    times = read_accessor(doc, sampler.input)
    np.testing.assert_allclose(times, np.arange(len(verts)) / 12.5, rtol=1e-6)
    weights = read_accessor(doc, sampler.output).reshape(len(verts), len(verts) - 1)
    expected = np.zeros_like(weights)
    expected[np.arange(1, len(verts)), np.arange(len(verts) - 1)] = 1
    np.testing.assert_array_equal(weights, expected)
    assert doc.meshes[0].extras["targetNames"][0] == "frame_1"
    assert doc.nodes[0].mesh == 0 and doc.scenes[doc.scene].nodes == [0]


def test_khronos_validator_reports_no_errors(pcow, tmp_path):
    verts, faces = pcow
    path = save_glb(tmp_path / "cow.glb", verts, faces, fps=24)
    report = validate(path)
    assert report["issues"]["numErrors"] == 0, report["issues"]["messages"][:5]
    assert report["issues"]["numWarnings"] == 0, report["issues"]["messages"][:5]
    assert report["info"]["hasMorphTargets"] and report["info"]["animationCount"] == 1
    # The validator is a real check: a corrupted file is reported.
    doc = pygltflib.GLTF2().load_binary(str(path))
    doc.accessors[doc.meshes[0].primitives[0].attributes.POSITION].max = [0.0, 0.0, 0.0]  # wrong bounds
    bad = tmp_path / "bad.glb"
    bad.write_bytes(b"".join(doc.save_to_bytes()))
    assert validate(bad)["issues"]["numErrors"] > 0


def test_single_frame_and_big_meshes_validate(tmp_path):
    # One frame: no targets, no animation. > 65535 vertices: 32-bit indices. z-up: node rotation.
    n = 300
    u, w = np.meshgrid(np.linspace(0, 1, n), np.linspace(0, 1, n))
    grid = np.stack([u.ravel(), w.ravel(), 0.1 * np.sin(6 * u.ravel())], axis=1)
    i = np.arange(n - 1)
    a = (i[:, None] * n + i[None, :]).ravel()
    faces = np.concatenate([np.stack([a, a + 1, a + n], 1), np.stack([a + 1, a + n + 1, a + n], 1)])
    path = tmp_path / "grid.glb"
    path.write_bytes(glb_bytes(grid[None], faces, up="z"))
    report = validate(path)
    assert report["issues"]["numErrors"] == 0, report["issues"]["messages"][:5]
    doc = pygltflib.GLTF2().load_binary(str(path))
    assert doc.accessors[doc.meshes[0].primitives[0].indices].componentType == 5125
    assert not doc.animations and not doc.meshes[0].primitives[0].targets
    q = np.array(doc.nodes[0].rotation)  # +z must map to +y: rotate (0,0,1) by q
    x, y, z, wq = q
    rot = np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * wq), 2 * (x * z + y * wq)],
        [2 * (x * y + z * wq), 1 - 2 * (x * x + z * z), 2 * (y * z - x * wq)],
        [2 * (x * z - y * wq), 2 * (y * z + x * wq), 1 - 2 * (x * x + y * y)],
    ])
    np.testing.assert_allclose(rot @ [0, 0, 1], [0, 1, 0], atol=1e-12)


def test_bad_input_is_refused(pcow):
    verts, faces = pcow
    bad = verts.copy()
    bad[3, 7, 1] = np.nan
    with pytest.raises(MeshseqError, match="frame 3"):
        gltf_document(bad, faces)
    with pytest.raises(MeshseqError, match="fps"):
        gltf_document(verts, faces, fps=0)
    with pytest.raises(MeshseqError, match="faces"):
        gltf_document(verts, faces + verts.shape[1])
    with pytest.raises(MeshseqError, match="--up"):
        gltf_document(verts, faces, up="q")


def test_cli_export_glb_npz_folder_and_errors(tmp_path, capsys):
    src = str(shared_file("pcow.npz"))
    out = tmp_path / "cow.glb"
    assert main(["export", src, "-o", str(out), "--fps", "30"]) == 0
    assert "wrote" in capsys.readouterr().out
    doc = pygltflib.GLTF2().load_binary(str(out))
    times = read_accessor(doc, doc.animations[0].samplers[0].input)
    assert times[1] == pytest.approx(1 / 30)
    assert validate(out)["issues"]["numErrors"] == 0

    before = out.read_bytes()
    assert main(["export", src, "-o", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert "exists" in err and "\n" not in err
    assert out.read_bytes() == before
    assert main(["export", src, "-o", str(out), "--force", "--no-normals"]) == 0
    assert len(out.read_bytes()) < len(before)

    assert main(["export", src, "-o", str(tmp_path / "cow.fbx")]) == 2
    err = capsys.readouterr().err.strip()
    assert "extension" in err and "\n" not in err

    npz = tmp_path / "cow.npz"
    assert main(["export", src, "-o", str(npz)]) == 0
    from meshseq.io import load_sequence

    back = load_sequence(npz)
    orig = np.load(src)
    np.testing.assert_allclose(back.vertices, orig["vertices"])
    folder = tmp_path / "frames"
    assert main(["export", src, "-o", str(folder) + "/", "--format", "ply"]) == 0
    assert len(list(folder.glob("*.ply"))) == orig["vertices"].shape[0]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["cow.glb", "cow.npz", "frames"]
