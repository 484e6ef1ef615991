"""Tests of meshseq.io: loaders, validation, repairs, saving, atomic output."""

from __future__ import annotations

import os
import warnings
from pathlib import Path

import h5py
import numpy as np
import pytest

from conftest import shared_file
from meshseq.errors import MeshseqError, MeshseqWarning
from meshseq.io import MeshSequence, atomic_output, check_output, load_sequence, natural_key, save_sequence

# An octahedron: closed, manifold, 6 vertices, 8 faces.
OCTA_V = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], dtype=np.float64)
OCTA_F = np.array([[0, 2, 4], [2, 1, 4], [1, 3, 4], [3, 0, 4], [2, 0, 5], [1, 2, 5], [3, 1, 5], [0, 3, 5]])


def octa_frames(n_frames: int = 4, seed: int = 0) -> np.ndarray:
    """``(T, 6, 3)`` smoothly varying octahedra with non-round coordinates."""
    rng = np.random.default_rng(seed)
    t = np.arange(n_frames)[:, None, None]
    return OCTA_V[None] * (1.0 + 0.1 * t) + 0.01 * rng.standard_normal((n_frames, 6, 3)) + np.pi / 7


def write_obj(path: Path, vertices: np.ndarray, faces: np.ndarray, *, extra_vertex_lines: str = "") -> Path:
    lines = ["# test", "o thing"]
    lines += [f"v {x!r} {y!r} {z!r}" for x, y, z in vertices.tolist()]
    if extra_vertex_lines:
        lines.append(extra_vertex_lines)
    lines += ["f " + " ".join(str(i + 1) for i in face) for face in np.asarray(faces).tolist()]
    path.write_text("\n".join(lines) + "\n")
    return path


def write_frames(folder: Path, vertices: np.ndarray, faces: np.ndarray, pattern: str = "{:03d}.obj") -> list[Path]:
    folder.mkdir(parents=True, exist_ok=True)
    return [write_obj(folder / pattern.format(t), v, faces) for t, v in enumerate(vertices)]


def listing(folder: Path) -> list[str]:
    return sorted(str(p.relative_to(folder)) for p in folder.rglob("*"))


def expect_error(spec, *fragments: str, root: Path | None = None):
    """load_sequence(spec) raises a one-line MeshseqError containing every fragment; writes nothing."""
    before = listing(root) if root is not None else None
    with pytest.raises(MeshseqError) as info:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", MeshseqWarning)
            load_sequence(spec)
    msg = str(info.value)
    assert "\n" not in msg, msg
    for fragment in fragments:
        assert fragment in msg, f"{fragment!r} not in {msg!r}"
    if root is not None:
        assert listing(root) == before
    return msg


@pytest.fixture
def octa_seq() -> MeshSequence:
    return MeshSequence(octa_frames(5), OCTA_F, name="octa", fps=24.0)


# ------------------------------------------------------------------------------------------
# MeshSequence


def test_meshsequence_coerces_dtypes_and_checks_shapes():
    seq = MeshSequence(octa_frames(2).astype(np.float32), OCTA_F.astype(np.int32), name="x")
    assert seq.vertices.dtype == np.float64 and seq.faces.dtype == np.int64
    assert (seq.n_frames, seq.n_vertices, seq.n_faces) == (2, 6, 8)
    assert "frames=2" in repr(seq)
    with pytest.raises(MeshseqError, match=r"vertices must have shape \(T, V, 3\)"):
        MeshSequence(OCTA_V, OCTA_F)
    with pytest.raises(MeshseqError, match=r"faces must have shape \(F, 3\)"):
        MeshSequence(octa_frames(1), OCTA_F[:, :2])
    with pytest.raises(MeshseqError, match="faces must be integers"):
        MeshSequence(octa_frames(1), OCTA_F.astype(float))


def test_natural_key_orders_numbers_numerically():
    names = ["frame10.obj", "frame2.obj", "frame1.obj", "Frame3.obj"]
    assert sorted(names, key=natural_key) == ["frame1.obj", "frame2.obj", "Frame3.obj", "frame10.obj"]


# ------------------------------------------------------------------------------------------
# Round trips


def test_npz_round_trip_is_exact(tmp_path, octa_seq):
    octa_seq.vertex_map = np.arange(10, 16)
    out = save_sequence(octa_seq, tmp_path / "s.npz")
    back = load_sequence(out)
    np.testing.assert_array_equal(back.vertices, octa_seq.vertices)
    np.testing.assert_array_equal(back.faces, octa_seq.faces)
    assert back.name == "octa" and back.fps == 24.0
    np.testing.assert_array_equal(back.vertex_map, np.arange(10, 16))
    assert listing(tmp_path) == ["s.npz"]  # no temporary left behind


def test_obj_folder_round_trip(tmp_path, octa_seq):
    save_sequence(octa_seq, tmp_path / "frames")
    assert listing(tmp_path / "frames") == [f"frame_{t:04d}.obj" for t in range(5)]
    back = load_sequence(tmp_path / "frames")
    np.testing.assert_array_equal(back.faces, octa_seq.faces)
    np.testing.assert_allclose(back.vertices, octa_seq.vertices, rtol=1e-6, atol=0)
    assert back.name == "frames" and back.n_frames == 5
    exact = load_sequence(save_sequence(octa_seq, tmp_path / "exact", precision=17))
    np.testing.assert_array_equal(exact.vertices, octa_seq.vertices)


def test_float32_data_round_trips_exactly_through_obj(tmp_path):
    v32 = octa_frames(3).astype(np.float32)
    save_sequence(MeshSequence(v32, OCTA_F), tmp_path / "f")
    back = load_sequence(tmp_path / "f").vertices
    np.testing.assert_array_equal(back.astype(np.float32), v32)  # %.9g identifies every float32


def test_ply_folder_round_trip_is_exact(tmp_path, octa_seq):
    save_sequence(octa_seq, str(tmp_path / "plys") + "/", format="ply")
    assert listing(tmp_path / "plys") == [f"frame_{t:04d}.ply" for t in range(5)]
    back = load_sequence(tmp_path / "plys")
    np.testing.assert_array_equal(back.vertices, octa_seq.vertices)
    np.testing.assert_array_equal(back.faces, octa_seq.faces)


def test_single_frame_mesh_file_round_trip(tmp_path):
    one = MeshSequence(octa_frames(1), OCTA_F, name="one")
    for ext in ("obj", "ply"):
        out = save_sequence(one, tmp_path / f"one.{ext}")
        back = load_sequence(out)
        assert back.n_frames == 1 and back.name == "one"
        np.testing.assert_allclose(back.vertices, one.vertices, rtol=1e-6)
        np.testing.assert_array_equal(back.faces, OCTA_F)


def test_many_frames_get_wider_zero_padding(tmp_path):
    seq = MeshSequence(np.repeat(octa_frames(1), 10001, axis=0)[:, :, :], OCTA_F)
    save_sequence(seq, tmp_path / "many", format="ply")
    names = listing(tmp_path / "many")
    assert names[0] == "frame_00000.ply" and names[-1] == "frame_10000.ply"


def test_save_list_and_natural_sort(tmp_path):
    v = octa_frames(12)
    folder = tmp_path / "seq"
    folder.mkdir()
    for t in range(12):
        write_obj(folder / f"pose{t}.obj", v[t], OCTA_F)  # pose0 .. pose11: lexical order would break
    (folder / "notes.txt").write_text("not a mesh")
    (folder / "render.png").write_bytes(b"\x89PNG")
    seq = load_sequence(folder)
    np.testing.assert_array_equal(seq.vertices, v)
    listed = load_sequence([folder / "pose3.obj", folder / "pose1.obj"], name="pair")
    np.testing.assert_array_equal(listed.vertices, v[[3, 1]])
    assert listed.name == "pair"


def test_obj_with_normals_and_uvs_keeps_vertex_order(tmp_path):
    # Face corners reference uv/normal indices that differ from vertex indices; a loader that
    # splits vertices by (v, vt, vn) would reorder or duplicate them.
    text = """mtllib x.mtl
v 0.5 0 0
vt 0 0
vt 1 0
vn 0 0 1
v 0 0.25 0
vt 0 1
v 0 0 0.125
v 1 1 1
vn 1 0 0
usemtl m
s 1
f 4/3/2 2/1/1 3/2/2
f 1/1/1 2/2/2 4/3/1
f 1//2 4//1 3//1
f 1/2 3/1 2/3
"""
    path = tmp_path / "uv.obj"
    path.write_text(text)
    seq = load_sequence(path)
    np.testing.assert_array_equal(seq.vertices[0], [[0.5, 0, 0], [0, 0.25, 0], [0, 0, 0.125], [1, 1, 1]])
    np.testing.assert_array_equal(seq.faces, [[3, 1, 2], [0, 1, 3], [0, 3, 2], [0, 2, 1]])


def test_obj_relative_indices_and_crlf(tmp_path):
    text = "v 0 0 0\r\nv 1 0 0\r\nv 0 1 0\r\nf -3 -2 -1\r\nv 0 0 1\r\nf 1 2 -1\r\nf 2 3 4\r\nf 1 4 3\r\n"
    path = tmp_path / "rel.obj"
    path.write_text(text)
    seq = load_sequence(path)
    np.testing.assert_array_equal(seq.faces, [[0, 1, 2], [0, 1, 3], [1, 2, 3], [0, 3, 2]])
    assert seq.n_vertices == 4


def test_obj_indented_and_tab_separated_lines_are_not_missed(tmp_path):
    path = tmp_path / "odd.obj"
    path.write_text("v 0 0 0\nv 1 0 0\nvn 0 0 1\n  v 0 1 0\nv\t0 0 1\nf 1 3 2\nf 1 2 4\n\tf 2 3 4\nf\t1 4 3\n")
    seq = load_sequence(path)
    np.testing.assert_array_equal(seq.vertices[0], [[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
    np.testing.assert_array_equal(seq.faces, [[0, 2, 1], [0, 1, 3], [1, 2, 3], [0, 3, 2]])


def test_off_with_quad_is_read_in_order_and_triangulated(tmp_path):
    path = tmp_path / "box.off"
    # A square pyramid: one quad base, four triangles.
    path.write_text("OFF\n# comment\n5 5 0\n0 0 0\n1 0 0\n1 1 0\n0 1 0\n0.5 0.5 1\n"
                    "4 0 3 2 1\n3 0 1 4\n3 1 2 4\n3 2 3 4\n3 3 0 4\n")
    with pytest.warns(MeshseqWarning, match=r"box\.off: triangulated 1 non-triangle faces"):
        seq = load_sequence(path)
    np.testing.assert_array_equal(seq.vertices[0][:, 0], [0, 1, 1, 0, 0.5])
    np.testing.assert_array_equal(seq.faces[:2], [[0, 3, 2], [0, 2, 1]])
    assert seq.n_faces == 6


def test_ply_ascii_with_quad_warns(tmp_path):
    path = tmp_path / "pyr.ply"
    path.write_text("ply\nformat ascii 1.0\nelement vertex 5\nproperty float x\nproperty float y\n"
                    "property float z\nelement face 5\nproperty list uchar int vertex_indices\nend_header\n"
                    "0 0 0\n1 0 0\n1 1 0\n0 1 0\n0.5 0.5 1\n4 0 3 2 1\n3 0 1 4\n3 1 2 4\n3 2 3 4\n3 3 0 4\n")
    with pytest.warns(MeshseqWarning, match="triangulated 1 non-triangle"):
        seq = load_sequence(path)
    np.testing.assert_array_equal(seq.vertices[0][:, 0], [0, 1, 1, 0, 0.5])
    assert seq.n_faces == 6


def test_ply_keeps_duplicate_vertices_and_order(tmp_path):
    # process=False: coincident vertices 1 and 4 stay separate; unused vertex 0 is dropped (with map).
    path = tmp_path / "dup.ply"
    path.write_text("ply\nformat ascii 1.0\nelement vertex 5\nproperty float x\nproperty float y\n"
                    "property float z\nelement face 2\nproperty list uchar int vertex_indices\nend_header\n"
                    "9 9 9\n0 0 0\n1 0 0\n0 1 0\n0 0 0\n3 1 2 3\n3 4 3 2\n")
    with pytest.warns(MeshseqWarning, match="dropped 1 unreferenced"):
        seq = load_sequence(path)
    np.testing.assert_array_equal(seq.vertices[0], [[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 0]])
    np.testing.assert_array_equal(seq.faces, [[0, 1, 2], [3, 2, 1]])
    np.testing.assert_array_equal(seq.vertex_map, [1, 2, 3, 4])


def test_h5_addressing(tmp_path):
    path = tmp_path / "dyna_male.h5"
    verts = octa_frames(7)  # (T, V, 3)
    with h5py.File(path, "w") as f:
        f["50004_jumping_jacks"] = np.transpose(verts, (1, 2, 0)).astype(np.float32)  # (V, 3, T)
        f["50004_punching"] = np.transpose(verts[:3], (1, 2, 0))
        f["faces"] = OCTA_F.astype(np.int32)
        f.attrs["fps"] = 60.0
        f["50004_punching"].attrs["fps"] = 30.0
    seq = load_sequence(f"{path}:50004_jumping_jacks")
    assert seq.name == "50004_jumping_jacks" and seq.n_frames == 7
    assert seq.fps == 60.0 and load_sequence(f"{path}:50004_punching").fps == 30.0  # file, then sequence attrs
    np.testing.assert_allclose(seq.vertices, verts, rtol=1e-6)
    np.testing.assert_array_equal(seq.faces, OCTA_F)
    msg = expect_error(f"{path}:50004_running", "50004_running", "available: 50004_jumping_jacks, 50004_punching",
                       root=tmp_path)
    assert str(path) in msg
    expect_error(path, "name the sequence as", "50004_punching", root=tmp_path)
    expect_error(f"{tmp_path / 'missing.h5'}:x", "missing.h5: path does not exist", root=tmp_path)


# ------------------------------------------------------------------------------------------
# Bad input: one-line errors naming the file/frame; nothing written


def test_missing_path(tmp_path):
    expect_error(tmp_path / "nope", "nope: path does not exist", root=tmp_path)
    expect_error([tmp_path / "nope.obj"], "nope.obj: path does not exist", root=tmp_path)


def test_empty_folder_and_folder_without_meshes(tmp_path):
    (tmp_path / "empty").mkdir()
    expect_error(tmp_path / "empty", "empty: no mesh files", "(it is empty)", root=tmp_path)
    (tmp_path / "other").mkdir()
    (tmp_path / "other" / "readme.txt").write_text("x")
    expect_error(tmp_path / "other", "other: no mesh files", "readme.txt", root=tmp_path)
    expect_error([], "empty list")


def test_unsupported_extension(tmp_path):
    (tmp_path / "mesh.stl").write_bytes(b"solid x\nendsolid x\n")
    expect_error(tmp_path / "mesh.stl", "mesh.stl: unsupported extension '.stl'", root=tmp_path)
    write_obj(tmp_path / "a.obj", OCTA_V, OCTA_F)
    expect_error([tmp_path / "a.obj", tmp_path / "mesh.stl"], "mesh.stl: unsupported extension", root=tmp_path)


def test_mixed_formats_in_one_folder(tmp_path):
    write_obj(tmp_path / "0.obj", OCTA_V, OCTA_F)
    save_sequence(MeshSequence(OCTA_V[None], OCTA_F), tmp_path / "1.ply")
    expect_error(tmp_path, "mixes .obj and .ply")


def test_empty_and_garbage_files(tmp_path):
    (tmp_path / "empty.obj").write_text("")
    expect_error(tmp_path / "empty.obj", "empty.obj: file is empty", root=tmp_path)
    (tmp_path / "nothing.obj").write_text("# only a comment\n")
    expect_error(tmp_path / "nothing.obj", "nothing.obj: no vertices", root=tmp_path)
    (tmp_path / "nofaces.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\n")
    expect_error(tmp_path / "nofaces.obj", "nofaces.obj: no faces", root=tmp_path)
    (tmp_path / "noise.ply").write_bytes(np.random.default_rng(0).bytes(500))
    expect_error(tmp_path / "noise.ply", "noise.ply: not a PLY file", root=tmp_path)
    (tmp_path / "bad.obj").write_text("v 0 0 zero\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    expect_error(tmp_path / "bad.obj", "bad.obj: bad number in vertex coordinates", root=tmp_path)
    (tmp_path / "zero.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 0 1 2\n")
    expect_error(tmp_path / "zero.obj", "zero.obj: face index 0", root=tmp_path)
    (tmp_path / "bad.npz").write_bytes(b"PK\x03\x04 not really a zip")
    expect_error(tmp_path / "bad.npz", "bad.npz: cannot read .npz", root=tmp_path)
    (tmp_path / "bad.h5").write_bytes(b"not hdf5")
    expect_error(f"{tmp_path / 'bad.h5'}:seq", "bad.h5: cannot read HDF5", root=tmp_path)


def test_truncated_files(tmp_path, octa_seq):
    folder = tmp_path / "frames"
    save_sequence(octa_seq, folder)
    full = (folder / "frame_0002.obj").read_bytes()
    # Cut at a line boundary inside the face list: fewer faces than frame 0.
    (folder / "frame_0002.obj").write_bytes(full[: full.rfind(b"\nf ") + 1])
    expect_error(folder, "frame_0002.obj: 7 faces, expected 8 (as in", "frame_0000.obj)", root=tmp_path)
    # Cut inside the last face line.
    (folder / "frame_0002.obj").write_bytes(full[: full.rfind(b"\nf ") + 4])
    expect_error(folder, "frame_0002.obj: face 7 has 1 vertices, need at least 3; truncated file?", root=tmp_path)
    # Cut inside the vertex list: the last line has two coordinates.
    cut = full.index(b"\nv ", full.index(b"\nv ") + 1) + 8
    (folder / "frame_0002.obj").write_bytes(full[:cut])
    expect_error(folder / "frame_0002.obj", "frame_0002.obj: vertex 1 has", "truncated file?", root=tmp_path)
    save_sequence(octa_seq, tmp_path / "plys", format="ply")
    ply = (tmp_path / "plys" / "frame_0001.ply").read_bytes()
    (tmp_path / "plys" / "frame_0001.ply").write_bytes(ply[:-40])
    expect_error(tmp_path / "plys", "frame_0001.ply", "truncated or corrupt", root=tmp_path)
    (tmp_path / "t.off").write_text("OFF\n6 8 0\n0 0 0\n1 0 0\n")
    expect_error(tmp_path / "t.off", "t.off: OFF header promises 6 vertices and 8 faces", root=tmp_path)


def test_vertex_count_mismatch_names_first_offending_frame(tmp_path):
    v = octa_frames(20)
    paths = write_frames(tmp_path / "frames", v, OCTA_F)
    for t in (17, 18):  # two bad frames; the first is named
        write_obj(paths[t], np.concatenate([v[t], v[t][:2]]), OCTA_F)
    msg = expect_error(tmp_path / "frames", root=tmp_path)
    assert msg == f"{paths[17]}: 8 vertices, expected 6 (as in {paths[0]})"


def test_face_mismatch_names_frame_and_face(tmp_path):
    v = octa_frames(5)
    paths = write_frames(tmp_path / "frames", v, OCTA_F)
    other = OCTA_F.copy()
    other[3] = other[3][[1, 0, 2]]
    write_obj(paths[2], v[2], other)
    expect_error(tmp_path / "frames", f"{paths[2]}: faces differ from {paths[0]}",
                 f"face 3 is {other[3].tolist()}, expected {OCTA_F[3].tolist()}", root=tmp_path)
    write_obj(paths[2], v[2], OCTA_F[:6])
    expect_error(tmp_path / "frames", f"{paths[2]}: 6 faces, expected 8", root=tmp_path)


def test_nan_and_inf_name_the_frame(tmp_path):
    v = octa_frames(6)
    paths = write_frames(tmp_path / "frames", v, OCTA_F)
    bad = v[4].copy()
    bad[2, 1] = np.nan
    write_obj(paths[4], bad, OCTA_F)
    expect_error(tmp_path / "frames", f"{paths[4]}: non-finite (NaN/Inf) coordinates at vertex 2", root=tmp_path)
    v_inf = v.copy()
    v_inf[3, 5, 0] = np.inf
    np.savez(tmp_path / "inf.npz", vertices=v_inf, faces=OCTA_F)
    expect_error(tmp_path / "inf.npz", "inf.npz frame 3: non-finite (NaN/Inf) coordinates at vertex 5",
                 root=tmp_path)


def test_faces_indexing_missing_vertices(tmp_path):
    faces = OCTA_F.copy()
    faces[5, 1] = 9
    write_obj(tmp_path / "bad.obj", OCTA_V, faces)
    expect_error(tmp_path / "bad.obj", "face 5 uses vertex [1, 9, 5] but there are only 6 vertices",
                 root=tmp_path)
    np.savez(tmp_path / "neg.npz", vertices=OCTA_V[None], faces=np.where(OCTA_F == 4, -1, OCTA_F))
    expect_error(tmp_path / "neg.npz", "neg.npz: face 0 uses vertex [0, 2, -1]", root=tmp_path)


def test_npz_missing_keys_and_wrong_shapes(tmp_path):
    np.savez(tmp_path / "a.npz", verts=octa_frames(2), faces=OCTA_F)
    expect_error(tmp_path / "a.npz", "a.npz: missing key(s) vertices (found: faces, verts)", root=tmp_path)
    np.savez(tmp_path / "b.npz", vertices=OCTA_V, faces=OCTA_F)
    expect_error(tmp_path / "b.npz", "b.npz: 'vertices' must have shape (T, V, 3), got (6, 3)", root=tmp_path)
    np.savez(tmp_path / "c.npz", vertices=octa_frames(2), faces=OCTA_F.T)
    expect_error(tmp_path / "c.npz", "c.npz: 'faces' must have shape (F, 3), got (3, 8)", root=tmp_path)
    np.savez(tmp_path / "d.npz", vertices=octa_frames(2), faces=OCTA_F.astype(float))
    expect_error(tmp_path / "d.npz", "d.npz: 'faces' must be integers", root=tmp_path)


PLY_HEAD = "ply\nformat ascii 1.0\nelement vertex {n}\n{props}element face 1\nproperty list uchar int vertex_indices\nend_header\n"


def test_extreme_coordinates_and_wrong_dtypes_are_one_line_errors(tmp_path):
    """Issue 13 (5): coordinates near 1e200 (overflow in every product), a mesh 1e-200 across,
    complex and bool vertex arrays are refused by name; nothing is computed on them."""
    v = octa_frames(3)
    np.savez(tmp_path / "huge.npz", vertices=v * 1e200, faces=OCTA_F)
    expect_error(tmp_path / "huge.npz", "huge.npz frame 0: coordinate", "beyond +-1e+30", "rescale", root=tmp_path)
    big = v.copy()
    big[2, 4, 1] = -5e35
    np.savez(tmp_path / "big.npz", vertices=big, faces=OCTA_F)
    expect_error(tmp_path / "big.npz", "big.npz frame 2: coordinate 5e+35 at vertex 4", root=tmp_path)
    np.savez(tmp_path / "tiny.npz", vertices=v * 1e-200, faces=OCTA_F)
    expect_error(tmp_path / "tiny.npz", "tiny.npz frame 0: the mesh is only", "too small", root=tmp_path)
    np.savez(tmp_path / "cplx.npz", vertices=v.astype(complex), faces=OCTA_F)
    expect_error(tmp_path / "cplx.npz", "cplx.npz: vertices must be real numbers", "complex128", root=tmp_path)
    np.savez(tmp_path / "bool.npz", vertices=v > 0, faces=OCTA_F)
    expect_error(tmp_path / "bool.npz", "bool.npz: vertices must be real numbers", "bool", root=tmp_path)
    with pytest.raises(MeshseqError, match="vertices must be real numbers"):
        MeshSequence(np.array([[["1", "2", "3"]]]), [[0, 0, 0]])
    # within the limits: 1e29 and a mesh 1e-29 across load as they are
    for scale in (1e29, 1e-29):
        np.savez(tmp_path / "ok.npz", vertices=v * scale, faces=OCTA_F)
        assert np.array_equal(load_sequence(tmp_path / "ok.npz").vertices, v * scale)


def test_huge_face_indices_are_one_line_errors(tmp_path):
    """Issue 13 (5): an index beyond int64 raised OverflowError."""
    (tmp_path / "a.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 99999999999999999999\n")
    expect_error(tmp_path / "a.obj", "a.obj: face index beyond 64-bit integers (99999999999999999999)",
                 root=tmp_path)
    (tmp_path / "a.off").write_text("OFF\n3 1 0\n0 0 0\n1 0 0\n0 1 0\n3 0 1 99999999999999999999\n")
    expect_error(tmp_path / "a.off", "a.off: face index beyond 64-bit integers", root=tmp_path)
    (tmp_path / "b.off").write_text("OFF\n3 1 0\n0 0 0\n1 0 0\n0 1 0\n99999999999999999999 0 1 2\n")
    expect_error(tmp_path / "b.off", "b.off: face size beyond 64-bit integers", root=tmp_path)


def test_ply_header_problems_name_what_is_missing(tmp_path):
    """Issue 13 (6): a PLY without z said "KeyError: 'z'"; one declaring 100 vertices and
    holding 3 blamed the faces."""
    xy = "property float x\nproperty float y\n"
    (tmp_path / "noz.ply").write_text(PLY_HEAD.format(n=3, props=xy) + "0 0\n1 0\n0 1\n3 0 1 2\n")
    expect_error(tmp_path / "noz.ply", "noz.ply: PLY vertices have no z property (they have x, y)", root=tmp_path)
    xyz = xy + "property float z\n"
    body = "0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n"
    (tmp_path / "short.ply").write_text(PLY_HEAD.format(n=100, props=xyz) + body)
    msg = expect_error(tmp_path / "short.ply", "short.ply: header declares 100 vertices", "truncated",
                       root=tmp_path)
    assert "face" not in msg
    save_sequence(MeshSequence(OCTA_V[None], OCTA_F), tmp_path / "bin.ply")
    data = (tmp_path / "bin.ply").read_bytes()
    (tmp_path / "bin.ply").write_bytes(data.replace(b"element vertex 6", b"element vertex 60"))
    expect_error(tmp_path / "bin.ply", "bin.ply: header declares 60 vertices", root=tmp_path)
    (tmp_path / "ok.ply").write_text(PLY_HEAD.format(n=3, props=xyz) + body)
    assert load_sequence(tmp_path / "ok.ply").n_vertices == 3


def test_h5_group_instead_of_a_sequence(tmp_path):
    """Issue 13 (6): FILE.h5:GROUP gave an h5py TypeError."""
    with h5py.File(tmp_path / "d.h5", "w") as h:
        h.create_group("grp")
        h["faces"] = OCTA_F
        h["walk"] = np.transpose(octa_frames(3), (1, 2, 0))
        h["walk"].attrs["fps"] = "not a number"
    expect_error(f"{tmp_path / 'd.h5'}:grp", "d.h5:grp: 'grp' is an HDF5 group, not a sequence dataset "
                 "(available: walk)", root=tmp_path)
    assert load_sequence(f"{tmp_path / 'd.h5'}:walk").fps is None  # a bad fps attribute is ignored


def test_fifo_and_other_non_regular_files_are_refused(tmp_path):
    """Issue 13 (6): reading a FIFO waited forever (an alarm turns a hang into a failure)."""
    import signal

    def hang(signum, frame):
        raise AssertionError("reading a FIFO hangs")

    old = signal.signal(signal.SIGALRM, hang)
    signal.alarm(20)
    try:
        _check_fifos(tmp_path)
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, old)


def _check_fifos(tmp_path):
    for name in ("f.obj", "f.npz", "f.h5", "f.pc2", "f.glb"):
        os.mkfifo(tmp_path / name)
    for spec in ("f.obj", "f.npz", "f.h5:seq", "f.pc2", "f.glb", "f.glb:Mesh"):
        expect_error(f"{tmp_path}/{spec}", f"{tmp_path / spec.split(':')[0]}: not a regular file")
    write_obj(tmp_path / "base.obj", OCTA_V, OCTA_F)
    expect_error(f"{tmp_path / 'base.obj'}:{tmp_path / 'f.pc2'}", "f.pc2: not a regular file")
    expect_error(f"{tmp_path / 'f.obj'}:{tmp_path / 'x.pc2'}", "does not exist")
    expect_error([tmp_path / "base.obj", tmp_path / "f.obj"], "f.obj: not a regular file")
    expect_error(Path("/dev/null"), "/dev/null: not a regular file")


def test_a_list_of_files_holds_frames_not_sequences(tmp_path, octa_seq):
    """Issue 13 (6): `info a.npz b.npz` said ".npz is unsupported"; a list is frames of one sequence."""
    save_sequence(octa_seq, tmp_path / "a.npz")
    save_sequence(octa_seq, tmp_path / "b.npz")
    expect_error([tmp_path / "a.npz", tmp_path / "b.npz"], "a.npz: several DATA are the frames of one sequence",
                 "give the sequence", root=tmp_path)
    expect_error([tmp_path / "a.obj", tmp_path / "b.h5:x"], "a.obj: path does not exist")


# ------------------------------------------------------------------------------------------
# Repairs and warnings


def test_clean_mesh_loads_without_warnings(tmp_path, octa_seq):
    save_sequence(octa_seq, tmp_path / "s.npz")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        load_sequence(tmp_path / "s.npz")


def test_quads_are_triangulated_with_a_warning(tmp_path):
    v = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [2, 0, 0], [2, 1, 0]], dtype=float)
    folder = tmp_path / "quads"
    folder.mkdir()
    for t in range(3):
        (folder / f"{t}.obj").write_text(
            "".join(f"v {x} {y} {z + t}\n" for x, y, z in v.tolist()) + "f 1 2 3 4\nf 2 5 6 3\n")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        seq = load_sequence(folder)
    messages = [str(w.message) for w in caught if issubclass(w.category, MeshseqWarning)]
    assert messages == [f"{folder / '0.obj'}: triangulated 2 non-triangle faces (fan) into 4 triangles in total"]
    np.testing.assert_array_equal(seq.faces, [[0, 1, 2], [0, 2, 3], [1, 4, 5], [1, 5, 2]])
    # A pentagon fans into three triangles.
    (tmp_path / "penta.obj").write_text("v 0 0 0\nv 1 0 0\nv 2 1 0\nv 1 2 0\nv 0 1 0\nf 1 2 3 4 5\n")
    with pytest.warns(MeshseqWarning, match="triangulated 1 non-triangle"):
        penta = load_sequence(tmp_path / "penta.obj")
    np.testing.assert_array_equal(penta.faces, [[0, 1, 2], [0, 2, 3], [0, 3, 4]])
    (tmp_path / "line.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\nf 1 2\n")
    expect_error(tmp_path / "line.obj", "line.obj: face 1 has 2 vertices, need at least 3")


def test_unreferenced_vertices_are_dropped_with_vertex_map(tmp_path):
    # Two unused vertices, at positions 0 and 4 of the file.
    v = np.concatenate([[[9.0, 9, 9]], OCTA_V[:3], [[7.0, 7, 7]], OCTA_V[3:]])
    faces = np.where(OCTA_F >= 3, OCTA_F + 2, OCTA_F + 1)
    frames = np.stack([v, v * 2])
    np.savez(tmp_path / "u.npz", vertices=frames, faces=faces)
    with pytest.warns(MeshseqWarning, match=r"u\.npz: dropped 2 unreferenced vertices"):
        seq = load_sequence(tmp_path / "u.npz")
    np.testing.assert_array_equal(seq.vertex_map, [1, 2, 3, 5, 6, 7])
    np.testing.assert_array_equal(seq.vertices[1], OCTA_V * 2)
    np.testing.assert_array_equal(seq.faces, OCTA_F)
    np.testing.assert_array_equal(frames[:, seq.vertex_map], seq.vertices)
    # Saved and reloaded, the map survives (npz) and composes with a second drop.
    save_sequence(seq, tmp_path / "kept.npz")
    np.testing.assert_array_equal(load_sequence(tmp_path / "kept.npz").vertex_map, [1, 2, 3, 5, 6, 7])
    write_obj(tmp_path / "u.obj", v, faces)
    with pytest.warns(MeshseqWarning, match="first 0"):
        assert load_sequence(tmp_path / "u.obj").n_vertices == 6


def test_degenerate_and_nonmanifold_only_warn(tmp_path):
    v = np.concatenate([OCTA_V, [[0.5, 0.5, 0.0]]])  # vertex 6 lies on the segment 0-2
    faces = np.concatenate([OCTA_F, [[0, 6, 2]]])  # zero area; edge 0-2 now has 3 faces
    np.savez(tmp_path / "d.npz", vertices=v[None], faces=faces)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        seq = load_sequence(tmp_path / "d.npz")
    messages = [str(w.message) for w in caught]
    assert any("1 degenerate (zero-area) triangles of 9" in m for m in messages), messages
    assert any("1 non-manifold edges" in m for m in messages), messages
    assert seq.n_faces == 9


# ------------------------------------------------------------------------------------------
# Saving: overwrite refusal, force, atomicity


def test_save_refuses_existing_output_without_force(tmp_path, octa_seq):
    out = save_sequence(octa_seq, tmp_path / "s.npz")
    before = out.read_bytes()
    other = MeshSequence(octa_frames(2, seed=5), OCTA_F, name="other")
    with pytest.raises(MeshseqError, match=r"s\.npz: output file already exists; use --force"):
        save_sequence(other, out)
    assert out.read_bytes() == before
    save_sequence(other, out, force=True)
    assert load_sequence(out).name == "other"
    assert listing(tmp_path) == ["s.npz"]


def test_force_replaces_a_folder_completely(tmp_path, octa_seq):
    folder = tmp_path / "frames"
    save_sequence(octa_seq, folder)
    with pytest.raises(MeshseqError, match="frames: output folder already exists; use --force"):
        save_sequence(octa_seq, folder)
    shorter = MeshSequence(octa_frames(2, seed=3), OCTA_F)
    save_sequence(shorter, folder, force=True)
    assert listing(folder) == ["frame_0000.obj", "frame_0001.obj"]  # stale frames gone
    assert listing(tmp_path) == ["frames", "frames/frame_0000.obj", "frames/frame_0001.obj"]
    np.testing.assert_allclose(load_sequence(folder).vertices, shorter.vertices, rtol=1e-6)


def test_save_bad_options_write_nothing(tmp_path, octa_seq):
    cases = [
        (tmp_path / "x.obj", {}, "x.obj: a .obj file holds one frame but the sequence has 5"),
        (tmp_path / "x.stl", {}, "unsupported output extension .stl"),
        (tmp_path / "x.npz", {"format": "ply"}, "extension .npz contradicts format='ply'"),
        (tmp_path / "x", {"format": "gltf"}, "format 'gltf' is not one of npz, obj, ply"),
        (tmp_path / "x", {"format": "npz"}, "format 'npz' needs a file path ending in .npz"),
    ]
    for path, kwargs, fragment in cases:
        with pytest.raises(MeshseqError) as info:
            save_sequence(octa_seq, path, **kwargs)
        assert fragment in str(info.value)
    assert listing(tmp_path) == []


def test_failure_mid_write_leaves_original_untouched(tmp_path, octa_seq, monkeypatch):
    folder = tmp_path / "frames"
    save_sequence(octa_seq, folder)
    original = {p: (folder / p).read_bytes() for p in listing(folder)}
    calls = {"n": 0}
    real_write = Path.write_bytes

    def failing_write(self, data):
        calls["n"] += 1
        if calls["n"] == 3:
            raise OSError(28, "No space left on device")
        return real_write(self, data)

    monkeypatch.setattr(Path, "write_bytes", failing_write)
    with pytest.raises(OSError, match="No space left"):
        save_sequence(MeshSequence(octa_frames(5, seed=9), OCTA_F), folder, force=True)
    monkeypatch.undo()
    assert calls["n"] == 3
    assert listing(tmp_path) == ["frames"] + [f"frames/{p}" for p in original]  # no temp left
    assert {p: (folder / p).read_bytes() for p in listing(folder)} == original

    def failing_savez(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(np, "savez", failing_savez)
    with pytest.raises(KeyboardInterrupt):
        save_sequence(octa_seq, tmp_path / "s.npz")
    assert not (tmp_path / "s.npz").exists()
    assert listing(tmp_path) == ["frames"] + [f"frames/{p}" for p in original]


def test_atomic_output_file_and_folder(tmp_path):
    target = tmp_path / "sub" / "out.tar.gz"
    with atomic_output(target) as tmp:
        assert tmp.parent == target.parent and tmp.name.endswith("out.tar.gz") and tmp != target
        assert not tmp.exists() and not target.exists()
        tmp.write_text("one")
    assert target.read_text() == "one"
    with pytest.raises(MeshseqError, match="out.tar.gz: output file already exists; use --force"):
        with atomic_output(target):
            raise AssertionError("body must not run")
    with pytest.raises(ValueError, match="boom"):
        with atomic_output(target, force=True) as tmp:
            tmp.write_text("half")
            raise ValueError("boom")
    assert target.read_text() == "one"
    assert os.listdir(target.parent) == ["out.tar.gz"]
    with atomic_output(target, force=True) as tmp:
        tmp.write_text("two")
    assert target.read_text() == "two"
    # A folder replaced by a file and a file by a folder, with force.
    with atomic_output(target, force=True) as tmp:
        tmp.mkdir()
        (tmp / "inside").write_text("x")
    assert (target / "inside").read_text() == "x"
    with atomic_output(target, force=True) as tmp:
        tmp.write_text("three")
    assert target.read_text() == "three"
    assert os.listdir(target.parent) == ["out.tar.gz"]
    with pytest.raises(RuntimeError, match="nothing was written"):
        with atomic_output(tmp_path / "never"):
            pass
    assert not (tmp_path / "never").exists()


def test_check_output_fails_early(tmp_path):
    assert check_output(tmp_path / "new.npz") == tmp_path / "new.npz"
    (tmp_path / "old.npz").write_bytes(b"x")
    with pytest.raises(MeshseqError, match=r"old\.npz: output file already exists; use --force"):
        check_output(tmp_path / "old.npz")
    assert check_output(tmp_path / "old.npz", force=True) == tmp_path / "old.npz"
    assert (tmp_path / "old.npz").read_bytes() == b"x"


def test_atomic_output_rechecks_existence_at_the_end(tmp_path):
    target = tmp_path / "late.txt"
    with pytest.raises(MeshseqError, match="already exists"):
        with atomic_output(target) as tmp:
            tmp.write_text("mine")
            target.write_text("someone else's")
    assert target.read_text() == "someone else's"
    assert os.listdir(tmp_path) == ["late.txt"]


# ------------------------------------------------------------------------------------------
# Real data and speed


def test_crane_npz_loads():
    path = shared_file("crane.npz")
    seq = load_sequence(path)
    assert (seq.n_frames, seq.n_vertices, seq.n_faces) == (175, 10002, 20000)
    assert seq.vertices.dtype == np.float64 and seq.faces.dtype == np.int64
    assert seq.name == "crane" and seq.vertex_map is None


def test_obj_folder_of_crane_round_trips(tmp_path):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", MeshseqWarning)
        seq = load_sequence(shared_file("crane.npz"))
    save_sequence(seq, tmp_path / "crane")
    back = load_sequence(tmp_path / "crane")
    np.testing.assert_array_equal(back.faces, seq.faces)
    # float32 data: %.9g identifies every float32 exactly
    np.testing.assert_array_equal(back.vertices.astype(np.float32), seq.vertices.astype(np.float32))
