"""Separate parts carried by a body (meshseq.data.accessories, make-bodies --parts).

Needs the ``bodies`` extra (the Anny body model), like test_bodies.py; bodies are tiny (1,000
vertices, a few frames).
"""

from __future__ import annotations

import os

import h5py
import igl
import numpy as np
import pytest

from meshseq.cli import main
from meshseq.data import accessories, bodies
from meshseq.errors import MeshseqError
from meshseq.io import load_sequence
from meshseq.mesh import Topology, face_areas

os.environ.setdefault("HF_HUB_OFFLINE", "1")

VERTICES = 1000
FRAMES = 12
EYE_VERTICES = 2 * 162  # two icospheres of 2 subdivisions


@pytest.fixture(scope="module")
def posed():
    """female_fit doing jumping jacks on the 1,000-vertex template, its rest pose, and the parts."""
    subject = bodies.resolve_subjects("female_fit")[0]
    seq = bodies.generate(subject, "jumping_jacks", FRAMES, vertices=VERTICES)
    rest = bodies.body_template(VERTICES).apply(bodies.body_model().rest_for(subject.phenotype)[None])[0]
    v, f = accessories.attach(seq.vertices, seq.faces, rest, ["eyes", "strap"])
    return seq, rest, v, f


def test_body_is_unchanged_and_parts_are_separate_closed_components(posed):
    seq, _, v, f = posed
    n = seq.vertices.shape[1]
    assert v.shape[:2] == (FRAMES, n + EYE_VERTICES + accessories.STRAP_SAMPLES * accessories.STRAP_SIDES)
    assert np.array_equal(v[:, :n], seq.vertices) and np.array_equal(f[:len(seq.faces)], seq.faces)
    topo = Topology.from_faces(f, v.shape[1])
    assert topo.n_components == 1 + 2 + 1
    assert (topo.boundary_edge_count, topo.nonmanifold_edge_count) == (0, 0)
    assert len(topo.unreferenced_vertices) == 0
    labels = topo.component_labels
    assert len(np.unique(labels[:n])) == 1 and labels[0] not in labels[n:]
    assert len(f) - len(seq.faces) == 2 * 320 + 2 * accessories.STRAP_SAMPLES * accessories.STRAP_SIDES


def test_every_triangle_has_an_area_in_every_frame(posed):
    _, _, v, f = posed
    assert min(face_areas(v[t], f).min() for t in range(FRAMES)) > 1e-7


def test_eyes_move_rigidly_with_their_head_triangle(posed):
    seq, rest, v, f = posed
    n = seq.vertices.shape[1]
    part = accessories.eyes(rest, seq.faces.astype(np.int64))
    assert len(np.unique(part.tri)) in (1, 2)
    centroid = seq.vertices[:, seq.faces[part.tri]].mean(axis=2)  # (T, P, 3)
    eye = v[:, n:n + EYE_VERTICES]
    dist = np.linalg.norm(eye - centroid, axis=-1)
    assert np.abs(dist - dist[0]).max() < 1e-9
    # In front of the face (facing -y) and near the top of the head, one eye on each side.
    top = seq.vertices[:, :, 2].max(axis=1)
    centres = eye.reshape(FRAMES, 2, -1, 3).mean(axis=2)
    assert np.all(top[:, None] - centres[..., 2] < 0.2) and np.all(top[:, None] - centres[..., 2] > 0.05)
    assert np.all(np.abs(np.linalg.norm(centres[:, 0] - centres[:, 1], axis=-1) - 0.063) < 0.02)
    head = seq.vertices[0][np.abs(seq.vertices[0, :, 2] - centres[0, 0, 2]) < 0.05]
    assert np.all(centres[0, :, 1] < head[:, 1].mean() - 0.05)  # at the front of the head


def test_strap_follows_the_skin(posed):
    seq, _, v, f = posed
    start = seq.vertices.shape[1] + EYE_VERTICES
    for t in range(FRAMES):
        d2, _, _ = igl.point_mesh_squared_distance(v[t, start:], seq.vertices[t], seq.faces.astype(np.int64))
        assert np.sqrt(d2).max() < 0.02, t
    # Diagonal: it spans from shoulder height (near the top of the torso) down to the hip, on
    # both sides of the body.
    strap = v[0, start:]
    height = np.ptp(seq.vertices[0, :, 2])
    assert np.ptp(strap[:, 2]) > 0.3 * height and np.ptp(strap[:, 0]) > 0.15


def test_unknown_part_is_a_one_line_error():
    with pytest.raises(MeshseqError, match="--parts: unknown part 'wings'"):
        accessories.resolve_parts("eyes,wings")
    assert accessories.resolve_parts("") == [] and accessories.resolve_parts("strap, eyes") == ["strap", "eyes"]


def test_make_bodies_parts_end_to_end(tmp_path, capsys):
    out = tmp_path / "parts.h5"
    argv = ["make-bodies", "--subjects", "1", "--motions", "walk,punch", "--frames", "4", "--vertices",
            str(VERTICES), "--quiet"]
    assert main([*argv, "--parts", "eyes,strap", "-o", str(out)]) == 0
    walk, punch = load_sequence(f"{out}:s00_walk"), load_sequence(f"{out}:s00_punch")
    n_parts = EYE_VERTICES + accessories.STRAP_SAMPLES * accessories.STRAP_SIDES
    assert walk.vertices.shape == (4, VERTICES + n_parts, 3)
    assert np.array_equal(walk.faces, punch.faces)
    assert Topology.from_faces(walk.faces, walk.vertices.shape[1]).n_components == 4
    with h5py.File(out, "r") as h5:
        assert h5.attrs["parts"] == "eyes,strap" and int(h5.attrs["body_vertices"]) == VERTICES
    # Without --parts: the body alone, identical to the body part of the file with parts.
    plain = tmp_path / "plain.h5"
    assert main([*argv, "-o", str(plain)]) == 0
    body = load_sequence(f"{plain}:s00_walk")
    assert body.vertices.shape == (4, VERTICES, 3)
    assert np.array_equal(body.vertices, walk.vertices[:, :VERTICES])
    with h5py.File(plain, "r") as h5:
        assert "parts" not in h5.attrs
    capsys.readouterr()
    assert main([*argv, "--parts", "wings", "-o", str(tmp_path / "x.h5")]) == 2
    err = capsys.readouterr().err
    assert "unknown part 'wings'" in err and err.count("\n") == 1, err
    assert not (tmp_path / "x.h5").exists()
