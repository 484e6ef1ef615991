"""Tests of meshseq.data.synthetic: closed, clean, twisting, bending, deterministic sequences."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from meshseq.data.synthetic import icosphere, multi_part, twisting_limb
from meshseq.errors import MeshseqError
from meshseq.io import load_sequence, save_sequence
from meshseq.mesh import Topology, degenerate_faces, edge_face_counts, face_areas


def assert_closed_oriented(faces: np.ndarray, vertices: np.ndarray) -> None:
    """Every edge in exactly two faces, every directed edge once (consistent orientation),
    outward orientation (positive volume in every frame)."""
    _, counts = edge_face_counts(faces)
    assert (counts == 2).all(), np.unique(counts)
    directed = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    assert len(np.unique(directed, axis=0)) == len(directed)
    v = vertices
    volume = np.einsum("tfi,tfi->t", v[:, faces[:, 0]], np.cross(v[:, faces[:, 1]], v[:, faces[:, 2]])) / 6
    assert (volume > 0).all()


def assert_no_degenerate_triangles(seq) -> None:
    for t, v in enumerate(seq.vertices):
        assert not degenerate_faces(v, seq.faces).any(), f"frame {t}"
    areas = face_areas(seq.vertices, seq.faces)
    assert areas.min() > 0.05 * areas[0].mean()  # no triangle collapses under the deformation


def _kabsch(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    a0, b0 = a - a.mean(0), b - b.mean(0)
    u, _, vt = np.linalg.svd(b0.T @ a0)
    return u @ np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt))]) @ vt


def tip_motion(seq, rings: int, segments: int) -> tuple[float, np.ndarray, np.ndarray, np.ndarray]:
    """Measured from the vertices alone: accumulated twist of the tip ring about the tip axis,
    the tip axis ``(T, 3)``, the base axis ``(T, 3)`` and per-frame tip rotation angles ``(T-1,)``."""
    v = seq.vertices
    tip = v[:, (rings - 1) * segments:rings * segments]
    axis = v[:, rings * segments + 1] - tip.mean(1)  # tip ring centre -> tip apex
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    base = v[:, segments:2 * segments].mean(1) - v[:, :segments].mean(1)
    base /= np.linalg.norm(base, axis=1, keepdims=True)
    twist, steps = 0.0, []
    for t in range(len(v) - 1):
        r = _kabsch(tip[t], tip[t + 1])
        w = np.sqrt(max(0.0, 1.0 + np.trace(r))) / 2
        vec = np.array([r[2, 1] - r[1, 2], r[0, 2] - r[2, 0], r[1, 0] - r[0, 1]]) / (4 * w)
        twist += 2 * np.arctan2(vec @ axis[t], w)  # twist part of the small per-frame rotation
        steps.append(2 * np.arctan2(np.linalg.norm(vec), w))
    return twist, axis, base, np.array(steps)


def test_twisting_limb_shape_and_closed_single_component():
    seq = twisting_limb()
    assert (seq.n_frames, seq.n_vertices, seq.n_faces) == (48, 24 * 16 + 2, 2 * 16 * 24)
    assert 300 <= seq.n_vertices <= 1000
    assert seq.vertices.dtype == np.float64 and seq.faces.dtype == np.int64
    assert seq.name == "twisting_limb" and seq.fps == 24.0
    topo = Topology.from_faces(seq.faces, seq.n_vertices)
    assert topo.n_components == 1
    assert len(topo.unreferenced_vertices) == 0
    assert topo.boundary_edge_count == 0 and topo.nonmanifold_edge_count == 0
    assert seq.n_vertices - len(topo.edges) + seq.n_faces == 2  # a sphere
    assert_closed_oriented(seq.faces, seq.vertices)
    assert_no_degenerate_triangles(seq)


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_twisting_limb_tip_twists_past_two_pi_and_swings_past_right_angle(seed):
    seq = twisting_limb(seed=seed)
    twist, tip_axis, base_axis, steps = tip_motion(seq, 24, 16)
    assert twist > 2 * np.pi
    assert twist == pytest.approx(1.5 * 2 * np.pi, rel=0.02)
    rest_axis = np.array([0.0, 0.0, 1.0])
    assert np.arccos(np.clip(tip_axis @ rest_axis, -1, 1)).max() > np.pi / 2  # swing
    bend = np.arccos(np.clip(np.einsum("ti,ti->t", tip_axis, base_axis), -1, 1))
    assert bend.max() > np.pi / 2  # the limb itself bends past a right angle
    assert steps.max() < 1.0  # smooth: the tip turns less than a radian between frames
    assert_no_degenerate_triangles(seq)


def test_twisting_limb_is_smooth_in_time():
    v = twisting_limb().vertices
    first = np.linalg.norm(np.diff(v, axis=0), axis=2)
    second = np.linalg.norm(np.diff(v, 2, axis=0), axis=2)
    assert second.max() < 0.35 * first.max()
    assert first.max() < 0.3 * 3.0  # per-frame motion well below the limb's length


def test_twist_turns_parameter_is_honoured():
    twist, *_ = tip_motion(twisting_limb(twist_turns=2.0, frames=64), 24, 16)
    assert twist == pytest.approx(2 * 2 * np.pi, rel=0.02)


def test_twisting_limb_is_deterministic_per_seed():
    a, b, c = twisting_limb(seed=3), twisting_limb(seed=3), twisting_limb(seed=4)
    np.testing.assert_array_equal(a.vertices, b.vertices)
    np.testing.assert_array_equal(a.faces, c.faces)
    assert np.abs(a.vertices - c.vertices).max() > 1e-2


@pytest.mark.parametrize("kwargs", [dict(bones=1), dict(bones=5, rings=40), dict(segments=5, rings=3, frames=2)])
def test_twisting_limb_other_sizes_stay_clean(kwargs):
    seq = twisting_limb(**kwargs)
    assert Topology.from_faces(seq.faces, seq.n_vertices).n_components == 1
    assert_closed_oriented(seq.faces, seq.vertices)
    assert_no_degenerate_triangles(seq)


def test_twisting_limb_rejects_bad_sizes():
    with pytest.raises(MeshseqError, match="twisting_limb needs frames >= 2"):
        twisting_limb(frames=1)
    with pytest.raises(MeshseqError, match="segments >= 3"):
        twisting_limb(segments=2)


def test_multi_part_components_and_rigid_eyes():
    seq = multi_part()
    assert (seq.n_frames, seq.n_vertices, seq.n_faces) == (24, 326, 640)
    topo = Topology.from_faces(seq.faces, seq.n_vertices)
    assert topo.n_components == 3
    assert_closed_oriented(seq.faces, seq.vertices)
    assert_no_degenerate_triangles(seq)
    labels = topo.component_labels
    sizes = np.bincount(labels)
    assert sorted(sizes.tolist()) == [42, 42, 242]
    eyes = np.flatnonzero(sizes[labels] == 42)
    assert len(eyes) == 84
    # The two eyes move rigidly, together: all their pairwise distances are constant.
    p = seq.vertices[:, eyes]
    d = np.linalg.norm(p[:, :, None] - p[:, None, :], axis=-1)
    assert np.abs(d - d[0]).max() < 1e-9
    # ... and they ride on the body: their distance to the tip apex is constant too.
    apex = seq.vertices[:, 20 * 12 + 1]
    dist = np.linalg.norm(p - apex[:, None], axis=-1)
    assert np.abs(dist - dist[0]).max() < 1e-3 * dist[0].max()
    # while the body really moves and deforms.
    body = seq.vertices[:, :242]
    assert np.linalg.norm(body - body[0], axis=2).max() > 1.0
    # Eyes stay clear of each other and of the body's axis.
    first, second = p[:, :42], p[:, 42:]
    assert np.linalg.norm(first[:, :, None] - second[:, None], axis=-1).min() > 0.05


def test_multi_part_deterministic():
    np.testing.assert_array_equal(multi_part(seed=2).vertices, multi_part(seed=2).vertices)
    assert np.abs(multi_part(seed=2).vertices - multi_part(seed=5).vertices).max() > 1e-2


def test_icosphere_is_closed_and_unit():
    for k, (n_v, n_f) in enumerate([(12, 20), (42, 80), (162, 320)]):
        v, f = icosphere(k)
        assert v.shape == (n_v, 3) and f.shape == (n_f, 3)
        np.testing.assert_allclose(np.linalg.norm(v, axis=1), 1.0)
        assert_closed_oriented(f, v[None])


def test_synthetic_sequences_pass_io_validation_without_warnings(tmp_path):
    for seq in (twisting_limb(), multi_part()):
        path = save_sequence(seq, tmp_path / f"{seq.name}.npz")
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            back = load_sequence(path)
        np.testing.assert_array_equal(back.vertices, seq.vertices)
        np.testing.assert_array_equal(back.faces, seq.faces)
        assert back.fps == 24.0
