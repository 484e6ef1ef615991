"""Interchange formats (meshseq.formats): MDD / PC2 point caches with a base mesh, glTF morph
animation in, USD through Pixar's usd-core (checked with UsdGeom itself). Blender as a client:
tests/test_blender.py."""

from __future__ import annotations

import base64
import json
import struct
import warnings
from pathlib import Path

import numpy as np
import pytest
from conftest import shared_file
from pxr import Sdf, Usd, UsdGeom, Vt

from meshseq.cli import main
from meshseq.errors import MeshseqError, MeshseqWarning
from meshseq.export import save_glb
from meshseq.io import MeshSequence, check_output, load_sequence, save_sequence


@pytest.fixture(scope="module")
def horse() -> MeshSequence:
    return load_sequence(shared_file("horse-gallop.npz"))


@pytest.fixture
def cow() -> MeshSequence:
    data = np.load(shared_file("pcow.npz"))
    return MeshSequence(data["vertices"][:10], data["faces"], name="cow", fps=30.0)


def f32(v: np.ndarray) -> np.ndarray:
    return v.astype(np.float32).astype(np.float64)


def one_line_error(capsys, argv: list[str], *words: str) -> str:
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("meshseq: error:") and "\n" not in err and "Traceback" not in err, err
    for w in words:
        assert w in err, err
    return err


# --------------------------------------------------------------------------------------------
# MDD and PC2


def test_mdd_round_trip_is_exact_and_the_file_is_big_endian_mdd(tmp_path, horse, capsys):
    out = tmp_path / "horse.mdd"
    assert main(["export", str(shared_file("horse-gallop.npz")), "-o", str(out), "--fps", "30"]) == 0
    assert "base mesh" in capsys.readouterr().out
    data = out.read_bytes()
    T, V = horse.n_frames, horse.n_vertices
    assert struct.unpack(">2i", data[:8]) == (T, V) and len(data) == 8 + 4 * T + 12 * T * V
    times = np.frombuffer(data, ">f4", T, offset=8)
    np.testing.assert_allclose(times, np.arange(T) / 30, rtol=1e-6)
    last = np.frombuffer(data, ">f4", 3 * V, offset=len(data) - 12 * V).reshape(V, 3)
    np.testing.assert_array_equal(last, horse.vertices[-1].astype(np.float32))
    # read back: the base mesh horse.obj beside it gives the faces
    back = load_sequence(out)
    np.testing.assert_array_equal(back.vertices, f32(horse.vertices))
    np.testing.assert_array_equal(back.faces, horse.faces)
    assert back.fps == 30.0 and back.n_frames == T
    explicit = load_sequence(f"{tmp_path / 'horse.obj'}:{out}")
    np.testing.assert_array_equal(explicit.vertices, back.vertices)


def test_pc2_round_trip_is_exact_and_the_header_is_pointcache2(tmp_path, cow):
    out = save_sequence(cow, tmp_path / "cow.pc2")
    assert (tmp_path / "cow.obj").is_file()
    data = out.read_bytes()
    magic, version, points, start, rate, samples = struct.unpack("<12siiffi", data[:32])
    assert (magic, version, points, start, rate, samples) == (b"POINTCACHE2\0", 1, cow.n_vertices, 0.0, 1.0, 10)
    assert len(data) == 32 + 12 * cow.n_vertices * cow.n_frames
    back = load_sequence(out)
    np.testing.assert_array_equal(back.vertices, f32(cow.vertices))
    np.testing.assert_array_equal(back.faces, cow.faces)
    assert back.fps is None  # PC2 stores frames, not seconds


def test_cache_base_mesh_from_another_file_and_its_errors(tmp_path, cow, capsys):
    save_sequence(cow, tmp_path / "a.mdd")
    (tmp_path / "base").mkdir()
    (tmp_path / "a.obj").rename(tmp_path / "base" / "cow_base.obj")
    err = one_line_error(capsys, ["info", str(tmp_path / "a.mdd")], "a.mdd", "base mesh", "BASE.obj:")
    seq = load_sequence(f"{tmp_path}/base/cow_base.obj:{tmp_path}/a.mdd")
    np.testing.assert_array_equal(seq.faces, cow.faces)
    # a base mesh with another vertex count
    small = MeshSequence(np.random.default_rng(0).random((1, 4, 3)), [[0, 1, 2], [0, 2, 3]])
    save_sequence(small, tmp_path / "small.obj")
    err = one_line_error(capsys, ["info", f"{tmp_path}/small.obj:{tmp_path}/a.mdd"], "a.mdd",
                         f"{cow.n_vertices} points", "4 vertices")
    assert "small.obj" in err


def test_truncated_and_foreign_caches_are_one_line_errors(tmp_path, cow, capsys):
    save_sequence(cow, tmp_path / "c.mdd")
    save_sequence(cow, tmp_path / "d.pc2")
    for name in ("c.mdd", "d.pc2"):
        data = (tmp_path / name).read_bytes()
        (tmp_path / name).write_bytes(data[:-100])
        one_line_error(capsys, ["info", str(tmp_path / name)], name, "truncated")
        (tmp_path / name).write_bytes(data[:5])
        one_line_error(capsys, ["info", str(tmp_path / name)], name, "header")
    (tmp_path / "d.pc2").write_bytes(b"NOTACACHE!!!" + bytes(100))
    one_line_error(capsys, ["info", str(tmp_path / "d.pc2")], "not a PC2 file")


def test_cache_output_refuses_an_existing_base_mesh(tmp_path, cow, capsys):
    (tmp_path / "cow.obj").write_text("mine\n")
    with pytest.raises(MeshseqError, match="cow.obj"):
        check_output(tmp_path / "cow.mdd")
    one_line_error(capsys, ["export", str(shared_file("pcow.npz")), "-o", str(tmp_path / "cow.mdd")], "cow.obj",
                   "--force")
    with pytest.raises(MeshseqError, match="cow.obj"):
        save_sequence(cow, tmp_path / "cow.pc2")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["cow.obj"]
    assert (tmp_path / "cow.obj").read_text() == "mine\n"
    save_sequence(cow, tmp_path / "cow.pc2", force=True)
    assert load_sequence(tmp_path / "cow.pc2").n_vertices == cow.n_vertices


# --------------------------------------------------------------------------------------------
# glTF in


def test_meshseq_glb_reads_back_its_float32_data(tmp_path, horse, capsys):
    out = tmp_path / "h.glb"
    assert main(["export", str(shared_file("horse-gallop.npz")), "-o", str(out), "--fps", "12.5", "--up", "z"]) == 0
    capsys.readouterr()
    with warnings.catch_warnings():
        warnings.simplefilter("error", MeshseqWarning)  # nothing to merge, nothing to repair
        back = load_sequence(out)
    v = f32(horse.vertices)
    np.testing.assert_array_equal(back.faces, horse.faces)
    assert back.fps == 12.5 and back.n_frames == horse.n_frames and back.name == "horse-gallop"
    np.testing.assert_array_equal(back.vertices[0], v[0])  # the mesh itself
    # later frames are frame 0 + a float32 offset: off by at most the offset's float32 rounding
    bound = 2.0 ** -24 * (np.abs(v[0]) + np.abs(v))
    assert (np.abs(back.vertices - v) <= bound).all()
    assert np.abs(back.vertices - v).max() < 1e-7 and np.abs(np.diff(v, axis=0)).max() > 1e-2
    # the node rotation of --up z is not applied: the data come back in their own axes
    named = load_sequence(f"{out}:horse-gallop")
    np.testing.assert_array_equal(named.vertices, back.vertices)
    one_line_error(capsys, ["info", f"{out}:dog"], "no mesh 'dog'", "horse-gallop")


def test_glb_without_morph_targets_or_animation_is_an_error(tmp_path, cow, capsys):
    save_glb(tmp_path / "still.glb", cow.vertices[:1], cow.faces)
    one_line_error(capsys, ["info", str(tmp_path / "still.glb")], "still.glb", "no mesh with morph targets")
    (tmp_path / "junk.glb").write_bytes(b"glTF" + bytes(40))
    one_line_error(capsys, ["info", str(tmp_path / "junk.glb")], "junk.glb")
    doc = _triangle_gltf(times=[0.0, 0.5], weights=[0.0, 1.0])
    doc["animations"] = []
    (tmp_path / "noanim.gltf").write_text(json.dumps(doc))
    one_line_error(capsys, ["info", str(tmp_path / "noanim.gltf")], "no animation drives")


def _triangle_gltf(times: list[float], weights: list[float], interpolation: str = "LINEAR") -> dict:
    """A .gltf (data URI) of one triangle, one morph target moving vertex 2 by +1 in z,
    and a weights animation with the given keys."""
    pos = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], np.float32)
    tgt = np.array([[0, 0, 0], [0, 0, 0], [0, 0, 1]], np.float32)
    idx = np.array([0, 1, 2], np.uint16)
    t = np.array(times, np.float32)
    w = np.array(weights, np.float32)
    parts = [pos.tobytes(), tgt.tobytes(), idx.tobytes() + b"\0\0", t.tobytes(), w.tobytes()]
    views, offset = [], 0
    for p in parts:
        views.append({"buffer": 0, "byteOffset": offset, "byteLength": len(p)})
        offset += len(p)
    blob = b"".join(parts)
    return {
        "asset": {"version": "2.0"},
        "buffers": [{"byteLength": len(blob), "uri": "data:application/octet-stream;base64,"
                     + base64.b64encode(blob).decode()}],
        "bufferViews": views,
        "accessors": [
            {"bufferView": 0, "componentType": 5126, "count": 3, "type": "VEC3", "min": [0, 0, 0], "max": [1, 1, 0]},
            {"bufferView": 1, "componentType": 5126, "count": 3, "type": "VEC3", "min": [0, 0, 0], "max": [0, 0, 1]},
            {"bufferView": 2, "componentType": 5123, "count": 3, "type": "SCALAR"},
            {"bufferView": 3, "componentType": 5126, "count": len(times), "type": "SCALAR",
             "min": [min(times)], "max": [max(times)]},
            {"bufferView": 4, "componentType": 5126, "count": len(weights), "type": "SCALAR"},
        ],
        "meshes": [{"name": "tri", "primitives": [{"attributes": {"POSITION": 0}, "indices": 2,
                                                    "targets": [{"POSITION": 1}]}], "weights": [0]}],
        "nodes": [{"mesh": 0}],
        "scenes": [{"nodes": [0]}],
        "animations": [{"samplers": [{"input": 3, "output": 4, "interpolation": interpolation}],
                        "channels": [{"sampler": 0, "target": {"node": 0, "path": "weights"}}]}],
    }


def test_gltf_thinned_keys_are_resampled_on_the_even_grid(tmp_path):
    # keys at 0, 0.25 and 0.75 s: frames every 0.25 s, the one at 0.5 s interpolated
    path = tmp_path / "tri.gltf"
    path.write_text(json.dumps(_triangle_gltf([0.0, 0.25, 0.75], [0.0, 0.2, 1.0])))
    seq = load_sequence(path)
    assert seq.n_frames == 4 and seq.fps == 4.0
    np.testing.assert_allclose(seq.vertices[:, 2, 2], [0.0, 0.2, 0.6, 1.0], atol=1e-7)
    np.testing.assert_array_equal(seq.vertices[:, :2], np.zeros((4, 2, 3)) + [[0, 0, 0], [1, 0, 0]])
    path.write_text(json.dumps(_triangle_gltf([0.0, 0.25, 0.75], [0.0, 0.2, 1.0], "STEP")))
    np.testing.assert_allclose(load_sequence(path).vertices[:, 2, 2], [0.0, 0.2, 0.2, 1.0], atol=1e-7)
    # uneven keys: the keys themselves are the frames, with a warning
    path.write_text(json.dumps(_triangle_gltf([0.0, 0.3, 0.7], [0.0, 0.5, 1.0])))
    with pytest.warns(MeshseqWarning, match="not evenly spaced"):
        seq = load_sequence(path)
    assert seq.n_frames == 3 and seq.fps is None


# --------------------------------------------------------------------------------------------
# USD


@pytest.mark.parametrize("suffix", [".usda", ".usdc", ".usd"])
def test_usd_written_by_meshseq_is_read_by_usdgeom_sample_by_sample(tmp_path, cow, suffix, capsys):
    src = tmp_path / "cow.npz"
    save_sequence(cow, src)
    out = tmp_path / f"cow{suffix}"
    assert main(["export", str(src), "-o", str(out), "--up", "z", "--meters-per-unit", "0.01"]) == 0
    assert "30 fps, up axis Z, 0.01 m per unit" in capsys.readouterr().out
    stage = Usd.Stage.Open(str(out))
    assert UsdGeom.GetStageUpAxis(stage) == UsdGeom.Tokens.z
    assert UsdGeom.GetStageMetersPerUnit(stage) == 0.01
    assert stage.GetTimeCodesPerSecond() == 30.0 and stage.GetFramesPerSecond() == 30.0
    assert (stage.GetStartTimeCode(), stage.GetEndTimeCode()) == (0, cow.n_frames - 1)
    mesh = UsdGeom.Mesh(stage.GetDefaultPrim())
    assert mesh and mesh.GetSubdivisionSchemeAttr().Get() == UsdGeom.Tokens.none
    points = mesh.GetPointsAttr()
    assert points.GetTimeSamples() == [float(t) for t in range(cow.n_frames)]
    for t in range(cow.n_frames):
        np.testing.assert_array_equal(np.asarray(points.Get(t)), cow.vertices[t].astype(np.float32))
        ext = np.asarray(mesh.GetExtentAttr().Get(t))
        np.testing.assert_allclose(ext, [cow.vertices[t].min(0), cow.vertices[t].max(0)], rtol=1e-6)
    assert list(mesh.GetFaceVertexCountsAttr().Get()) == [3] * cow.n_faces
    np.testing.assert_array_equal(np.asarray(mesh.GetFaceVertexIndicesAttr().Get()), cow.faces.ravel())
    del stage
    back = load_sequence(out)
    np.testing.assert_array_equal(back.vertices, f32(cow.vertices))
    np.testing.assert_array_equal(back.faces, cow.faces)
    assert back.fps == 30.0


def _author_stage(path: Path) -> np.ndarray:
    """A stage authored with UsdGeom: a static quad floor and an animated quad-and-triangle mesh
    sampled every 2 time codes at 48 codes per second; returns the animated points (T, 5, 3)."""
    stage = Usd.Stage.CreateNew(str(path))
    stage.SetTimeCodesPerSecond(48)
    UsdGeom.Xform.Define(stage, "/World")
    floor = UsdGeom.Mesh.Define(stage, "/World/Floor")
    floor.CreatePointsAttr([(0, 0, 0), (1, 0, 0), (1, 0, 1), (0, 0, 1)])
    floor.CreateFaceVertexCountsAttr([4])
    floor.CreateFaceVertexIndicesAttr([0, 1, 2, 3])
    body = UsdGeom.Mesh.Define(stage, "/World/Body")
    body.CreateFaceVertexCountsAttr([4, 3])
    body.CreateFaceVertexIndicesAttr([0, 1, 2, 3, 1, 4, 2])
    rng = np.random.default_rng(3)
    base = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [2, 0.5, 0]], np.float32)
    frames = base[None] + 0.1 * rng.standard_normal((6, 5, 3)).astype(np.float32)
    points = body.CreatePointsAttr()
    for k, p in enumerate(frames):
        points.Set(Vt.Vec3fArray.FromNumpy(p), 10.0 + 2 * k)
    stage.GetRootLayer().Save()
    return frames.astype(np.float64)


def test_usd_stage_authored_with_usdgeom_is_read(tmp_path, capsys):
    path = tmp_path / "shot.usda"
    frames = _author_stage(path)
    with pytest.warns(MeshseqWarning, match="triangulated 1 non-triangle"):
        seq = load_sequence(path)  # the one animated mesh is chosen
    np.testing.assert_array_equal(seq.vertices, frames)
    np.testing.assert_array_equal(seq.faces, [[0, 1, 2], [0, 2, 3], [1, 4, 2]])
    assert seq.fps == 24.0 and seq.name == "Body"
    with pytest.warns(MeshseqWarning):
        assert np.array_equal(load_sequence(f"{path}:/World/Body").vertices, frames)
    one_line_error(capsys, ["info", f"{path}:/World/Floor"], "/World/Floor", "no time samples")
    one_line_error(capsys, ["info", f"{path}:/World"], "not a Mesh")
    one_line_error(capsys, ["info", f"{path}:/World/Nope"], "no prim /World/Nope", "/World/Body")
    one_line_error(capsys, ["info", f"{path}:World/Body"], "no prim World/Body")


def test_usd_stage_without_a_mesh_or_without_samples_is_an_error(tmp_path, capsys):
    stage = Usd.Stage.CreateNew(str(tmp_path / "empty.usda"))
    UsdGeom.Xform.Define(stage, "/World")
    stage.GetRootLayer().Save()
    one_line_error(capsys, ["info", str(tmp_path / "empty.usda")], "empty.usda", "no Mesh prim")
    stage = Usd.Stage.CreateNew(str(tmp_path / "static.usda"))
    m = UsdGeom.Mesh.Define(stage, "/M")
    m.CreatePointsAttr([(0, 0, 0), (1, 0, 0), (0, 1, 0)])
    m.CreateFaceVertexCountsAttr([3])
    m.CreateFaceVertexIndicesAttr([0, 1, 2])
    stage.GetRootLayer().Save()
    one_line_error(capsys, ["info", str(tmp_path / "static.usda")], "static.usda:/M", "no time samples")
    (tmp_path / "junk.usda").write_text("#usda 1.0\n(\n garbage")
    one_line_error(capsys, ["info", str(tmp_path / "junk.usda")], "junk.usda")
    one_line_error(capsys, ["export", str(tmp_path / "static.usda"), "-o", str(tmp_path / "x.usda"), "--up", "x"],
                   "--up")
    assert not (tmp_path / "x.usda").exists()


def test_usd_overwrite_needs_force_and_rereads_the_new_file(tmp_path, cow):
    out = save_sequence(cow, tmp_path / "c.usdc")
    first = load_sequence(out)
    with pytest.raises(MeshseqError, match="already exists"):
        save_sequence(cow, out)
    moved = MeshSequence(cow.vertices[:4] + 1.0, cow.faces, name="cow", fps=10.0)
    save_sequence(moved, out, force=True)
    back = load_sequence(out)  # not a cached copy of the old layer
    assert back.n_frames == 4 and back.fps == 10.0 and first.n_frames == 10
    np.testing.assert_array_equal(back.vertices, f32(moved.vertices))
    assert Sdf.Layer.Find(str(out)) is None or back.n_frames == 4


# --------------------------------------------------------------------------------------------
# every format through one CLI chain


def test_every_format_chains_through_the_cli(tmp_path, cow, capsys):
    src = tmp_path / "cow.npz"
    save_sequence(cow, src)
    chain = ["a.mdd", "b.usda", "c.pc2", "d.glb", "e.usdc", "f.npz"]
    prev = str(src)
    for name in chain:
        assert main(["export", prev, "-o", str(tmp_path / name), "--fps", "30"]) == 0, name
        prev = str(tmp_path / name)
    capsys.readouterr()
    end = load_sequence(prev)
    # pcow has two vertices that coincide in every frame: meshseq's own glb keeps them apart
    flat = cow.vertices.transpose(1, 0, 2).reshape(cow.n_vertices, -1)
    assert len(np.unique(flat, axis=0)) < cow.n_vertices == end.n_vertices
    np.testing.assert_array_equal(end.faces, cow.faces)
    np.testing.assert_allclose(end.vertices, cow.vertices, rtol=0, atol=1e-6)
    assert end.fps == 30.0


def test_predict_and_complete_read_a_cache_and_write_every_format(tmp_path, capsys):
    """DATA as a point cache, -o as .mdd / .pc2 / .usda / .glb: the commands go through
    load_sequence and save_sequence like every other format."""
    from meshseq.data.synthetic import twisting_limb
    from meshseq.train import TrainConfig, load_training_data, train

    limb = twisting_limb(frames=40, rings=8, segments=6)
    limb.fps = 24.0
    data = save_sequence(limb, tmp_path / "limb.pc2")  # + limb.obj
    run = tmp_path / "run"
    train(load_training_data([str(data)]), run,
          TrainConfig(iterations=10, window=8, batch=2, eval_every=0, checkpoint_every=0, log_every=0),
          model_options={"latent": 8, "lstm_layers": 1}, device="cpu", progress=False, log=lambda m: None)
    for suffix in (".mdd", ".usda", ".glb"):
        out = tmp_path / f"pred{suffix}"
        assert main(["predict", str(run), str(data), "--start", "2", "--given", "3", "--frames", "5",
                     "-o", str(out)]) == 0, suffix
        p = load_sequence(out)
        assert p.n_frames == 8 and np.array_equal(p.faces, limb.faces), suffix
        np.testing.assert_allclose(p.vertices[:3], limb.vertices[2:5], rtol=0, atol=1e-6)
    assert (tmp_path / "pred.obj").is_file()  # the MDD's base mesh
    out = tmp_path / "comp.pc2"
    assert main(["complete", str(run), str(data), "--keyframes", "3,9", "--method", "linear", "-o", str(out)]) == 0
    c = load_sequence(out)
    np.testing.assert_allclose(c.vertices[[0, -1]], limb.vertices[[3, 9]], rtol=0, atol=1e-6)
    # a second run to the same cache is refused, also for the base mesh alone
    (tmp_path / "comp.pc2").unlink()
    one_line_error(capsys, ["complete", str(run), str(data), "--keyframes", "3,9", "--method", "linear",
                            "-o", str(out)], "comp.obj", "--force")
    assert not out.exists()
