"""Built-in human motion data (meshseq.data.bodies, meshseq make-bodies).

Needs the ``bodies`` extra (the Anny body model). On a fresh machine the first test pays Anny's
one-off construction (a couple of minutes, ~790 MB in ~/.cache/anny). Without anny the tests
fail (MeshseqError naming the extra), they never skip. Bodies are kept tiny: a few sequences of
16-24 frames at 1,000 vertices.
"""

from __future__ import annotations

import os

import h5py
import numpy as np
import pytest

from meshseq.cli import main
from meshseq.data import bodies
from meshseq.data.motions import MOTIONS, MotionParams, RigAxes, mirror, motion_curves
from meshseq.errors import MeshseqError
from meshseq.io import load_sequence
from meshseq.mesh import Topology, bounding_box_diagonal, degenerate_faces

os.environ.setdefault("HF_HUB_OFFLINE", "1")

FRAMES = 16
VERTICES = 1000


@pytest.fixture(scope="module")
def body():
    return bodies.body_model()


@pytest.fixture(scope="module")
def small_set(tmp_path_factory, body):
    """1 subject x 2 motions x 16 frames at 1,000 vertices, written by the command line."""
    out = tmp_path_factory.mktemp("bodies") / "set.h5"
    status = main(["make-bodies", "--subjects", "1", "--motions", "walk,punch", "--frames", str(FRAMES),
                   "--vertices", str(VERTICES), "--seed", "7", "-o", str(out), "--quiet"])
    assert status == 0
    return out


# ----------------------------------------------------------------------------------------------
# Motion curves (numpy only)


@pytest.mark.parametrize("name", MOTIONS)
def test_motion_rotations_are_rotations_and_periodic(name):
    from meshseq.data.motions import BASE_FREQUENCY

    fps = 30.0
    period = fps / BASE_FREQUENCY[name]  # frames per cycle at speed 1
    n = int(np.ceil(period)) + 3
    m = motion_curves(name, n, fps=fps)
    t = np.arange(n) / fps
    # The same motion started one cycle later (phase + 2 pi) is the same motion.
    shifted = motion_curves(name, n, fps=fps, params=MotionParams(phase=2 * np.pi))
    for bone, R in m.rotations.items():
        assert R.shape == (n, 3, 3)
        assert np.allclose(R @ np.swapaxes(R, -1, -2), np.eye(3), atol=1e-9), bone
        assert np.allclose(np.linalg.det(R), 1.0), bone
        assert np.allclose(R, shifted.rotations[bone], atol=1e-9), bone
    # Something moves: the motion is not the rest pose.
    assert max(np.abs(R - R[:1]).max() for R in m.rotations.values()) > 0.2
    assert t.size == n


def test_motion_parameters_change_the_motion():
    a = motion_curves("punch", 24)
    b = motion_curves("punch", 24, params=MotionParams(speed=1.1, amplitude=0.9, phase=0.5))
    assert any(not np.allclose(a.rotations[k], b.rotations[k]) for k in a.rotations)


def test_jumping_jacks_are_left_right_symmetric():
    m = motion_curves("jumping_jacks", 20)
    for bone, R in m.rotations.items():
        if bone.endswith(".L"):
            assert np.allclose(m.rotations[bone[:-2] + ".R"], mirror(R)), bone


def test_unknown_motion_and_subject_are_one_line_errors():
    with pytest.raises(MeshseqError, match="--motions: unknown motion 'fly'"):
        bodies.resolve_motions("walk,fly")
    with pytest.raises(MeshseqError, match="unknown subject 'bob'"):
        bodies.resolve_subjects("female_fit,bob")
    with pytest.raises(MeshseqError, match="at least 1"):
        bodies.resolve_subjects(0)
    assert bodies.resolve_motions("all") == list(MOTIONS)
    assert bodies.resolve_motions("Punching,jumping-jacks") == ["punch", "jumping_jacks"]


# ----------------------------------------------------------------------------------------------
# Anny bodies


def test_make_bodies_writes_a_dyna_style_file(small_set, capsys):
    with h5py.File(small_set, "r") as h5:
        names = sorted(k for k in h5 if k != "faces")
        assert names == ["s00_punch", "s00_walk"]
        assert h5["s00_walk"].shape == (VERTICES, 3, FRAMES)
        assert h5["s00_walk"].attrs["motion"] == "walk"
        assert "weight" in h5["s00_walk"].attrs["phenotype"]
        assert int(h5.attrs["seed"]) == 7
    walk = load_sequence(f"{small_set}:s00_walk")
    punch = load_sequence(f"{small_set}:s00_punch")
    assert walk.vertices.shape == (FRAMES, VERTICES, 3)
    assert np.array_equal(walk.faces, punch.faces)  # one connectivity for every sequence
    assert not np.allclose(walk.vertices, punch.vertices)
    # Never overwritten without --force; the file stays as it was.
    before = small_set.read_bytes()
    capsys.readouterr()
    status = main(["make-bodies", "--subjects", "1", "--motions", "walk", "--frames", "4", "-o", str(small_set),
                   "--quiet"])
    assert status == 2
    assert "already exists" in capsys.readouterr().err
    assert small_set.read_bytes() == before


def test_bad_options_are_one_line_errors(tmp_path, capsys):
    for argv, text in ((["--motions", "fly"], "unknown motion"), (["--frames", "1"], "--frames 1"),
                       (["--vertices", "50"], "--vertices 50"), (["--subjects", "nobody"], "unknown subject")):
        status = main(["make-bodies", *argv, "-o", str(tmp_path / "x.h5"), "--quiet"])
        err = capsys.readouterr().err
        assert status == 2, argv
        assert text in err and err.count("\n") == 1, err
        assert not (tmp_path / "x.h5").exists()


def test_same_seed_same_data_other_seed_other_data(tmp_path, body):
    kw = dict(subjects=1, motions=["squat"], frames=8, vertices=VERTICES)
    a = bodies.make_body_set(tmp_path / "a.h5", seed=3, **kw)
    b = bodies.make_body_set(tmp_path / "b.h5", seed=3, **kw)
    c = bodies.make_body_set(tmp_path / "c.h5", seed=4, **kw)
    va, vb, vc = (load_sequence(f"{p}:s00_squat").vertices for p in (a, b, c))
    assert np.array_equal(va, vb)
    assert not np.allclose(va, vc)
    # A subject is the same whatever the number of subjects asked for.
    assert bodies.resolve_subjects(3, seed=3)[0] == bodies.resolve_subjects(1, seed=3)[0]


@pytest.mark.parametrize("name", MOTIONS)
def test_motion_is_smooth_and_on_the_floor(name, body):
    subject = bodies.resolve_subjects("male_heavy")[0]
    seq = bodies.generate(subject, name, 24, vertices=VERTICES,
                          params=MotionParams(speed=1.15, amplitude=1.05, phase=0.3))
    v = seq.vertices
    diag = bounding_box_diagonal(v[0])
    acc = np.linalg.norm(v[2:] - 2 * v[1:-1] + v[:-2], axis=-1).max() / diag
    assert acc < 0.1, f"{name}: per-frame acceleration {acc:.3f} of the diagonal"
    assert np.ptp(v, axis=0).max() > 0.02 * diag  # it does move
    lowest = v[..., 2].min(axis=1)
    assert lowest.min() > -0.003  # never through the floor (3 mm of skinning slack)
    if name != "jumping_jacks":
        assert lowest.max() < 0.003  # always standing on it
    else:
        assert lowest.max() > 0.03  # jumps


@pytest.mark.parametrize("name", [m for m in MOTIONS if m not in ("walk", "jumping_jacks")])
def test_feet_stay_put_in_place(name, body):
    """In-place motions: every sole vertex on the floor keeps its place (no sliding)."""
    subject = bodies.resolve_subjects("female_heavy")[0]
    v = bodies.generate(subject, name, 24, vertices=None).vertices
    for side in "LR":
        sole = v[:, body.soles[side]]
        on = sole[..., 2] < 0.003
        assert on.any()
        drift = np.linalg.norm(sole[..., :2] - sole[:1, :, :2], axis=-1)
        assert drift.max() < 0.003, f"{name}: the {side} foot slides {drift.max() * 1000:.1f} mm"


def test_walk_moves_forward_without_sliding_the_stance_foot(body):
    subject = bodies.resolve_subjects("female_fit")[0]
    m = motion_curves("walk", 40, rig=body.rig_for(subject.phenotype))
    v = bodies.generate(subject, "walk", 40, vertices=None).vertices
    travel = v[-1].mean(axis=0) - v[0].mean(axis=0)
    assert travel[1] < -0.8 and abs(travel[0]) < 0.1  # forward is -y, about 1 m/s
    for side, weight in (("L", m.contact), ("R", 1.0 - m.contact)):
        planted = (weight[1:] > 0.999) & (weight[:-1] > 0.999)
        assert planted.sum() >= 8
        step = np.linalg.norm(np.diff(v[:, body.soles[side], :2].mean(axis=1), axis=0), axis=-1)
        assert step[planted].max() < 0.002, f"{side} stance foot slides {step[planted].max() * 1000:.1f} mm/frame"


def test_template_is_closed_and_manifold_like_the_full_skin(body):
    full = Topology.from_faces(body.faces, body.n_vertices)
    assert (full.n_components, full.boundary_edge_count, full.nonmanifold_edge_count) == (1, 0, 0)
    for n in (VERTICES, 3000):
        tpl = bodies.body_template(n)
        topo = Topology.from_faces(tpl.faces, tpl.n_vertices)
        assert tpl.n_vertices == n
        assert (topo.n_components, topo.boundary_edge_count, topo.nonmanifold_edge_count) == (1, 0, 0)
        assert len(topo.unreferenced_vertices) == 0
        assert n - len(topo.edges) + len(tpl.faces) == 2  # genus 0 like the skin
        assert np.allclose(tpl.bary.sum(axis=1), 1.0) and tpl.bary.min() >= 0.0
    # Posed frames keep every triangle (none collapses when the body moves).
    subject = bodies.resolve_subjects("female_fit")[0]
    seq = bodies.generate(subject, "squat", 24, vertices=VERTICES)
    for t in (0, 12, 23):
        assert not degenerate_faces(seq.vertices[t], seq.faces).any()


def test_template_does_not_turn_on_the_last_bits_of_the_rest_pose(body):
    # Anny's rest pose differs by about 4e-16 with torch's thread count; files made with one
    # count must share the connectivity of files made with another.
    rest = np.asarray(body.rest, dtype=np.float64)
    noise = 1.0 + 1e-15 * np.random.default_rng(0).standard_normal(rest.shape)
    a = bodies.make_template(rest, body.faces, VERTICES)
    b = bodies.make_template(rest * noise, body.faces, VERTICES)
    assert np.array_equal(a.faces, b.faces)
    assert np.abs(a.bary - b.bary).max() < 1e-6


def test_full_resolution_is_the_skin(body):
    subject = bodies.resolve_subjects("female_old")[0]
    seq = bodies.generate(subject, "wave", 3, vertices=None)
    assert seq.vertices.shape == (3, 13348, 3)
    assert np.array_equal(seq.faces, body.faces)


def test_acap_round_trip_meets_foundation_accuracy(small_set):
    from meshseq.acap import Reconstructor, extract
    from meshseq.align import per_vertex_error

    seq = load_sequence(f"{small_set}:s00_punch")
    features = extract(seq.vertices, seq.faces)
    rec = Reconstructor(seq.vertices[0], seq.faces).solve(features, target=seq.vertices)
    err = per_vertex_error(rec, seq.vertices).mean() / bounding_box_diagonal(seq.vertices[0])
    assert err < 1e-3, err


def test_default_body_set_builds_once_and_is_reused(tmp_path, monkeypatch, body):
    monkeypatch.setattr(bodies, "DEFAULT_SET", dict(subjects=("female_fit",), motions=("wave",), frames=4,
                                                    vertices=VERTICES, seed=0))
    seen = []
    path = bodies.default_body_set(tmp_path / "cache", on_sequence=seen.append)
    assert path.is_file() and seen == ["female_fit_wave"]
    stamp = path.stat().st_mtime_ns
    again = bodies.default_body_set(tmp_path / "cache", on_sequence=seen.append)
    assert again == path and path.stat().st_mtime_ns == stamp and seen == ["female_fit_wave"]
    assert load_sequence(f"{path}:female_fit_wave").vertices.shape == (4, VERTICES, 3)


def test_rig_axes_of_the_default_body_match_anny(body):
    default = RigAxes.default()
    assert np.allclose(default.elbow_axis, body.rig.elbow_axis, atol=0.05)
    assert abs(default.elbow_rest - body.rig.elbow_rest) < 5.0


def test_missing_anny_names_the_extra(monkeypatch):
    import sys

    monkeypatch.setitem(sys.modules, "anny", None)  # import anny -> ImportError
    with pytest.raises(MeshseqError, match=r"meshseq\[bodies\]"):
        bodies._import_anny()
