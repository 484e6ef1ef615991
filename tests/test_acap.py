"""ACAP features and reconstruction (method.md sections 1-2): exactness, real-data accuracy, consistency."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from hypothesis import example, given, settings
from hypothesis import strategies as st

from conftest import shared_file
from meshseq.acap import Reconstructor, Scaling, extract, features_to_gradients
from meshseq.acap.features import IDENTITY_FEATURE
from meshseq.acap.parts import component_offsets
from meshseq.acap.gradients import _svd_rotation, polar_decomposition
from meshseq.acap.rotations import NO_ROTATION, axis_angle
from meshseq.align import per_vertex_error
from meshseq.mesh import Topology, bounding_box_diagonal, cotangent_weights


def _sphere():
    m = trimesh.creation.icosphere(subdivisions=2)
    # squash it so it is not a symmetric sphere (the weights and normals then differ per vertex)
    return np.asarray(m.vertices) * [1.0, 0.6, 0.3], np.asarray(m.faces)


def _rotation(axis, angle):
    axis = np.asarray(axis, dtype=np.float64)
    axis = axis / np.linalg.norm(axis)
    K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(angle) * K + (1 - np.cos(angle)) * K @ K


def _rel_error(recon, truth):
    return per_vertex_error(recon, truth) / bounding_box_diagonal(truth)


def test_reference_frame_gives_identity_feature():
    v, f = _sphere()
    feats = extract(np.stack([v, v]), f)
    assert np.abs(feats - IDENTITY_FEATURE).max() < 1e-12


axes = st.tuples(*[st.floats(-1, 1) for _ in range(3)]).filter(lambda a: np.linalg.norm(a) > 0.1)


@settings(max_examples=25, deadline=None, derandomize=True)
@example(axis=(0.0, 0.0, 1.0), angle=5.960464477539063e-08, shift=(0.0, 0.0, 0.0))  # once drawn at random
@given(axis=axes, angle=st.floats(0.0, 3.1), shift=st.tuples(*[st.floats(-5, 5) for _ in range(3)]))
def test_rigid_motion_gives_rotation_log_and_unit_stretch_and_comes_back_exactly(axis, angle, shift):
    v, f = _sphere()
    R = _rotation(axis, angle)
    moved = v @ R.T + np.asarray(shift)
    seq = np.stack([v, moved])
    feats = extract(seq, f)
    S = feats[1, :, 3:]
    assert np.abs(S - IDENTITY_FEATURE[3:]).max() < 1e-9
    # logR = angle * [w]_x: (logR01, logR02, logR12) = (-angle w_z, angle w_y, -angle w_x)
    w = np.asarray(axis) / np.linalg.norm(axis)
    expected = angle * np.array([-w[2], w[1], -w[0]])
    # angles up to NO_ROTATION (1e-6) are no rotation by design (axis_angle): their log is 0, and
    # the round trip misses them by up to the angle (relative to the diagonal)
    tiny = angle <= 2 * NO_ROTATION
    assert np.abs(feats[1, :, :3] - expected).max() < 1e-8 + (angle if tiny else 0.0)
    recon = Reconstructor(v, f).solve(feats, target=seq)
    assert _rel_error(recon, seq).max() <= 1e-9 + (angle if tiny else 0.0)


def test_polar_decomposition_matches_svd_recipe_including_reflections():
    rng = np.random.default_rng(3)
    M = rng.normal(size=(4000, 3, 3))
    M[:5] = np.diag([1.0, 1.0, 1e-9])  # near-singular: falls back to SVD
    R, S = polar_decomposition(M)
    assert np.abs(R - _svd_rotation(M)).max() < 1e-9
    assert np.abs(np.linalg.det(R) - 1).max() < 1e-12
    assert np.abs(R @ S - M).max() < 1e-12
    assert np.abs(S - np.swapaxes(S, 1, 2)).max() < 1e-12
    neg = np.linalg.det(M) < 0  # reflection fix: S carries the negative singular value
    assert neg.sum() > 1000
    assert (np.linalg.eigvalsh(S[neg]).min(axis=1) < 0).all()


def test_axis_angle_is_accurate_near_zero_and_pi():
    rng = np.random.default_rng(4)
    axes_ = rng.normal(size=(500, 3))
    axes_ /= np.linalg.norm(axes_, axis=1, keepdims=True)
    angles = np.concatenate([rng.uniform(0, np.pi, 300), np.pi - 10.0 ** -rng.uniform(3, 12, 100),
                             10.0 ** -rng.uniform(3, 5.5, 100)])
    R = np.stack([_rotation(a, t) for a, t in zip(axes_, angles)])
    w, theta = axis_angle(R)
    assert np.abs(theta - angles).max() < 1e-7
    # recover R from the axis-angle (the axis sign is irrelevant at pi)
    q = np.concatenate([np.stack([-theta * w[:, 2], theta * w[:, 1], -theta * w[:, 0]], 1),
                        np.tile(IDENTITY_FEATURE[3:], (len(R), 1))], 1)
    assert np.abs(features_to_gradients(q) - R).max() < 1e-7


def test_features_to_gradients_inverts_the_feature_map():
    v, f = _sphere()
    rng = np.random.default_rng(5)
    moved = v + 0.05 * rng.normal(size=v.shape)
    feats = extract(np.stack([v, moved]), f)
    from meshseq.acap.features import extract_gradients

    grads = extract_gradients(np.stack([v, moved]), f)
    assert np.abs(features_to_gradients(feats) - grads).max() < 1e-10


# Mean per-vertex error / bbox diagonal of method.md 2.4 (direct implementation, normal row on).
REFERENCE_ERROR = {"horse-gallop.npz": 1.1e-3, "pcow.npz": 2.6e-4, "crane.npz": 1.0e-4}


@pytest.mark.parametrize("name", sorted(REFERENCE_ERROR))
def test_real_data_roundtrip_default_and_exact(name):
    data = np.load(shared_file(name))
    v, f = data["vertices"].astype(np.float64), data["faces"]
    v = v[:: max(1, len(v) // 40)]  # every k-th frame: keeps the test quick, covers the motion
    rec = Reconstructor(v[0], f)
    feats = extract(v, f)
    err = _rel_error(rec.solve(feats, target=v), v)
    assert err.mean() <= 1.2 * REFERENCE_ERROR[name], err.mean()
    exact = extract(v, f, exact=True)
    assert _rel_error(rec.solve(exact, target=v), v).mean() <= 1e-6
    # float32 storage of the exact features adds at most 1e-5 of the diagonal
    assert _rel_error(rec.solve(exact.astype(np.float32), target=v), v).mean() <= 1e-5


def test_threads_over_frame_chunks_give_the_same_features_bit_for_bit():
    """The frame chunks on a thread pool (default: one thread per CPU) write the same numbers as
    one thread, default and exact (whose sparse solves share one factor under a lock)."""
    data = np.load(shared_file("pcow.npz"))
    v, f = data["vertices"][:60].astype(np.float64), data["faces"]
    for exact in (False, True):
        one = extract(v, f, exact=exact, threads=1)
        assert np.array_equal(extract(v, f, exact=exact, threads=3), one)
    # 60 frames = 8 chunks: more chunks than threads, and a short last chunk
    assert len(v) % 8 and len(v) // 8 > 3


def test_temporal_consistency_removes_two_pi_jumps_of_a_part_spinning_past_two_pi():
    v, f = _sphere()
    angles = np.linspace(0, 3 * np.pi, 40)  # 1.5 turns about a fixed axis
    seq = np.stack([v @ _rotation([0.3, 0.2, 1.0], a).T for a in angles])
    temporal = extract(seq, f, consistency="temporal")
    spatial = extract(seq, f, consistency="spatial")
    step_t = np.linalg.norm(np.diff(temporal[..., :3], axis=0), axis=-1)
    step_s = np.linalg.norm(np.diff(spatial[..., :3], axis=0), axis=-1)
    assert np.linalg.norm(temporal[..., :3], axis=-1).max() == pytest.approx(3 * np.pi, abs=1e-6)
    assert step_t.max() < 0.3  # the true step is 3 pi / 39 = 0.24 rad
    assert step_s.max() > 5.0  # the per-shape method jumps by 2 pi (so the check above can fail)
    # both are logs of the same rotations
    assert np.abs(features_to_gradients(temporal) - features_to_gradients(spatial)).max() < 1e-8


def test_temporal_consistency_has_far_fewer_jumps_on_a_twisting_limb():
    from meshseq.data.synthetic import twisting_limb

    seq = twisting_limb(frames=60)
    temporal = extract(seq.vertices, seq.faces, consistency="temporal")
    spatial = extract(seq.vertices, seq.faces, consistency="spatial")
    jumps_t = (np.linalg.norm(np.diff(temporal[..., :3], axis=0), axis=-1) > np.pi).sum()
    jumps_s = (np.linalg.norm(np.diff(spatial[..., :3], axis=0), axis=-1) > np.pi).sum()
    # Near the 2 pi shell a rotation close to identity has an unstable axis, so some large steps
    # are inherent to any log representation; temporal keeps them rare.
    assert jumps_t <= jumps_s / 3
    assert np.abs(features_to_gradients(temporal) - features_to_gradients(spatial)).max() < 1e-8


def test_multi_component_mesh_roundtrips_like_a_single_component():
    from meshseq.data.synthetic import multi_part, twisting_limb

    multi = multi_part(frames=12)
    topo = Topology.from_faces(multi.faces, multi.n_vertices)
    assert topo.n_components >= 3
    v = multi.vertices
    rec = Reconstructor(v[0], multi.faces)
    feats = extract(v, multi.faces)
    offsets = component_offsets(v, topo)
    err = _rel_error(rec.solve(feats, offsets=offsets, target=v), v)
    single = twisting_limb(frames=12)
    err_single = _rel_error(Reconstructor(single.vertices[0], single.faces).solve(
        extract(single.vertices, single.faces), target=single.vertices), single.vertices)
    assert err.mean() <= max(2 * err_single.mean(), 1e-3)
    # the placement channels (9..11) carry the same offsets: no true offsets needed
    assert feats.shape[-1] == 12 and extract(single.vertices, single.faces).shape[-1] == 9
    assert np.abs(rec.solve(feats, target=v) - rec.solve(feats, offsets=offsets, target=v)).max() < 1e-9
    # without them the parts land in their rest placement: far worse
    err_rest = _rel_error(rec.solve(feats[..., :9], target=v), v)
    assert err_rest.mean() > 3 * err.mean()


def test_placement_channels_are_zero_at_the_reference_and_constant_on_each_part():
    from meshseq.acap.parts import offsets_from_channels, placement_channels
    from meshseq.data.synthetic import multi_part

    multi = multi_part(frames=6)
    topo = Topology.from_faces(multi.faces, multi.n_vertices)
    v = multi.vertices
    ch = placement_channels(v, topo, v[0])  # (T, V, 3)
    assert ch.shape == v.shape and np.abs(ch[0]).max() < 1e-12
    labels = topo.component_labels
    for c in range(topo.n_components):
        part = ch[:, labels == c]
        assert np.abs(part - part[:, :1]).max() < 1e-12
    assert np.abs(offsets_from_channels(ch, topo, v[0]) - component_offsets(v, topo)).max() < 1e-12
    # a translation of the whole mesh leaves the channels unchanged
    assert np.abs(placement_channels(v + np.array([1.0, -2.0, 3.0]), topo, v[0]) - ch).max() < 1e-12


def test_cotangent_weights_stay_finite_on_degenerate_triangles():
    v, f = _sphere()
    v = v.copy()
    v[f[0, 1]] = v[f[0, 0]]  # collapse an edge: two zero-area triangles
    w = cotangent_weights(v, Topology.from_faces(f, len(v)))
    assert np.isfinite(w).all() and (w >= 1e-10).all() and (w <= 1e5).all()
    feats = extract(np.stack([v, v * 1.1]), f)
    assert np.isfinite(feats).all()


def test_scaling_two_group_and_per_channel(tmp_path):
    rng = np.random.default_rng(6)
    x = rng.normal(size=(10, 50, 9)) * np.arange(1, 10)
    for mode in ("two-group", "per-channel"):
        s = Scaling.fit(x, mode)
        y = s.apply(x)
        assert y.min() == pytest.approx(-0.95) and y.max() == pytest.approx(0.95)
        assert np.abs(s.invert(y) - x).max() < 1e-12
        path = tmp_path / f"{mode}.json"
        s.save(path)
        assert np.array_equal(Scaling.load(path).apply(x), y)
    two = Scaling.fit(x, "two-group")
    assert len(set(two.minimum[:3])) == 1 and len(set(two.minimum[3:])) == 1
    per = Scaling.fit(x, "per-channel").apply(x).reshape(-1, 9)
    assert np.allclose(per.min(axis=0), -0.95) and np.allclose(per.max(axis=0), 0.95)


def test_torch_reconstruction_matches_numpy_and_is_differentiable():
    import torch

    from meshseq.acap.torch_reconstruct import TorchReconstructor

    v, f = _sphere()
    rng = np.random.default_rng(7)
    seq = np.stack([v, v + 0.03 * rng.normal(size=v.shape), v @ _rotation([1, 2, 3], 2.0).T])
    feats = extract(seq, f)
    rec = Reconstructor(v, f)
    module = TorchReconstructor(rec, dtype=torch.float64)
    x = torch.tensor(feats, requires_grad=True)
    out = module(x)
    assert np.abs(out.detach().numpy() - rec.solve(feats)).max() < 1e-10
    inp = x.detach()[:1].clone().requires_grad_()
    assert torch.autograd.gradcheck(module, (inp,), eps=1e-6, atol=1e-5, fast_mode=True)


# ---- spurious 2 pi jumps in time (issue 11) ----

RIGID_CASES = ("spin_turns", "precessing_spin", "through_pi", "noise_near_pi", "near_identity", "swing_back")


@pytest.mark.parametrize("name", RIGID_CASES)
def test_temporal_consistency_has_no_spurious_jumps_on_hard_rotation_paths(name):
    from meshseq.acap.diagnostics import feature_jumps
    from meshseq.data import rotation_cases

    seq = getattr(rotation_cases, name)()
    feats = extract(seq.vertices, seq.faces)
    assert feature_jumps(feats)["spurious_jumps"] == 0
    # still logs of the same rotations as the per-frame method
    spatial = extract(seq.vertices, seq.faces, consistency="spatial")
    assert np.abs(features_to_gradients(feats) - features_to_gradients(spatial)).max() < 1e-8


def test_swing_back_breaks_the_greedy_pass_and_not_the_temporal_one():
    """A one-frame swing of 2.4 rad leaves the greedy log on the 2 pi shell; passing near the
    identity then costs it two 2 pi jumps per vertex."""
    from meshseq.acap.diagnostics import feature_jumps
    from meshseq.data.rotation_cases import swing_back

    seq = swing_back()
    greedy = feature_jumps(extract(seq.vertices, seq.faces, consistency="greedy"))
    temporal = feature_jumps(extract(seq.vertices, seq.faces, consistency="temporal"))
    assert greedy["spurious_jumps"] >= seq.n_vertices and greedy["largest_log_norm"] > 6.0
    assert temporal["spurious_jumps"] == 0 and temporal["largest_log_norm"] < 3.0


def test_spin_of_three_turns_accumulates_the_angle():
    from meshseq.data.rotation_cases import spin_turns

    seq = spin_turns(turns=3.0)
    feats = extract(seq.vertices, seq.faces)
    assert np.linalg.norm(feats[-1, :, :3], axis=-1) == pytest.approx(6 * np.pi, abs=1e-6)


def _fewest_jumps_brute_force(logs_principal, m_range=4):
    """Reference: per-vertex DP in plain Python over representatives theta + 2 pi m along the axis,
    lexicographic (spurious jumps, sum of squared steps); frame 0 fixed at its log."""
    from meshseq.acap.rotations import relative_angles

    motion = relative_angles(logs_principal[:, None])[:, 0]
    norms = np.linalg.norm(logs_principal, axis=-1)
    axes = [r / n if n > 1e-6 else None for r, n in zip(logs_principal, norms)]
    last = axes[0] if axes[0] is not None else np.array([1.0, 0.0, 0.0])
    lines = []
    for a, n in zip(axes, norms):
        last = a if a is not None else last
        lines.append((last, n if a is not None else 0.0))
    states = {0: ((0, 0.0), lines[0][1] * lines[0][0])}
    for t in range(1, len(lines)):
        w, th = lines[t]
        new = {}
        for m in range(-m_range, m_range + 1):
            r = (th + 2 * np.pi * m) * w
            best = None
            for (jumps, sq), prev in states.values():
                d = np.linalg.norm(r - prev)
                key = (jumps + int(d > np.pi and motion[t - 1] < np.pi / 2), sq + d * d)
                best = key if best is None or key < best else best
            new[m] = (best, r)
        states = new
    return min(k for k, _ in states.values())[0]


def test_temporal_consistency_reaches_the_fewest_possible_jumps_on_a_fast_twist():
    """Where jumps remain (a tip twisting 3 turns while bending: the rotation passes near the
    identity on the 2 pi shell), no choice of branches does better: a brute-force reference agrees."""
    from meshseq.acap.diagnostics import rotation_logs
    from meshseq.acap.rotations import JUMP_MOTION, JUMP_STEP, relative_angles
    from meshseq.data.synthetic import twisting_limb

    seq = twisting_limb(frames=48, twist_turns=3.0)
    logs = rotation_logs(extract(seq.vertices, seq.faces))
    greedy = rotation_logs(extract(seq.vertices, seq.faces, consistency="greedy"))
    principal = rotation_logs(extract(seq.vertices, seq.faces, consistency="spatial"))

    def per_vertex(r):
        step = np.linalg.norm(np.diff(r, axis=0), axis=-1)
        return ((step > JUMP_STEP) & (relative_angles(r) < JUMP_MOTION)).sum(axis=0)

    ours, before = per_vertex(logs), per_vertex(greedy)
    assert ours.sum() < before.sum()
    # the principal logs' own branch: wrap each to the ball of radius pi
    n = np.linalg.norm(principal, axis=-1, keepdims=True)
    wrapped = np.where(n > np.pi, principal * (1 - 2 * np.pi / np.where(n > 0, n, 1)), principal)
    check = np.concatenate([np.flatnonzero(before > ours)[:6], np.flatnonzero(ours)[:6]])
    for v in check:
        assert ours[v] == _fewest_jumps_brute_force(wrapped[:, v]), v


def test_jump_report_counts_a_planted_jump_and_rejects_bad_shapes():
    from meshseq.acap.diagnostics import branch_jumps, feature_jumps
    from meshseq.errors import MeshseqError

    logs = np.zeros((5, 2, 3))
    logs[:, 0, 2] = [0.1, 0.2, 0.3, 0.4, 0.5]
    logs[:, 1, 2] = [3.0, 3.1, 3.2 - 2 * np.pi, 3.3 - 2 * np.pi, 3.4 - 2 * np.pi]  # same rotations, one jump
    r = branch_jumps(logs)
    assert r["spurious_jumps"] == 1 and r["spurious_jump_vertices"] == 1 and r["vertex_steps"] == 8
    assert r["largest_step"] == pytest.approx(2 * np.pi - 0.1) and r["median_motion_at_jumps"] == pytest.approx(0.1)
    logs[3, 0, 2] = 0.3 + 3.5  # a real 3.5 rad turn in one frame (and back) is motion, not a spurious jump
    r = branch_jumps(logs)
    assert r["spurious_jumps"] == 1 and r["largest_spurious_step"] == pytest.approx(2 * np.pi - 0.1)
    assert r["fast_turns"] == 2 and r["fast_turn_vertices"] == 1  # the turn there and the turn back
    for bad in (np.zeros((5, 3)), np.zeros((5, 2, 4)), np.full((2, 1, 3), np.nan)):
        with pytest.raises(MeshseqError):
            branch_jumps(bad)
    with pytest.raises(MeshseqError):
        feature_jumps(np.zeros((5, 2, 3)))


def test_robust_scaling_ignores_a_few_outliers_and_inverts_exactly(tmp_path):
    """``robust``: the two groups' ranges from the 0.1% / 99.9% quantiles, so 0.05% of outlier
    values (a few bad vertices) leave the bulk's range as it was; they map outside [-0.95, 0.95]."""
    from meshseq.acap.scaling import ROBUST_QUANTILE

    rng = np.random.default_rng(7)
    x = rng.uniform(-1, 1, size=(20, 500, 9))
    bad = x.copy()
    bad[:, :5, 3:] *= 20  # 1% of the vertices, in the S group only: 0.5% of its values
    bad[0, 0, 3] = 400.0
    two, robust = Scaling.fit(bad, "two-group"), Scaling.fit(bad, "robust")
    assert two.maximum[3] == 400.0  # min/max: set by one value
    assert robust.maximum[3] < 30 and robust.minimum[3] > -30
    clean = Scaling.fit(x, "robust")
    assert np.allclose(clean.minimum[:3], np.quantile(x[..., :3], ROBUST_QUANTILE))
    assert np.allclose(clean.maximum[3:], np.quantile(x[..., 3:], 1 - ROBUST_QUANTILE))
    y = robust.apply(bad)
    assert y.max() > 0.95 and np.abs(robust.invert(y) - bad).max() < 1e-9
    inside = np.abs(y[:, 5:, 3:]) <= 0.95  # the bulk of the S group: within the range
    assert inside.mean() > 0.99
    path = tmp_path / "robust.json"
    robust.save(path)
    loaded = Scaling.load(path)
    assert loaded.mode == "robust" and np.array_equal(loaded.apply(bad), y)


def test_geodesic_interpolation_turns_each_rotation_the_short_way_and_keeps_the_rest_linear():
    from scipy.spatial.transform import Rotation

    from meshseq.acap.diagnostics import rotation_logs
    from meshseq.acap.interpolation import geodesic_interpolation, log_channels
    from meshseq.baselines import linear_interpolation

    rng = np.random.default_rng(3)
    axis = np.array([0.0, 0.6, 0.8])
    logs_a = np.stack([0.4 * axis, 1.0 * axis, (2.0 + 2 * np.pi) * axis])  # the third on an outer shell
    logs_b = np.stack([0.9 * axis, 2.5 * axis, 2.0 * axis])  # the third: the same rotation, one shell in
    key_a = np.concatenate([log_channels(logs_a), rng.normal(size=(3, 6))], axis=1)
    key_b = np.concatenate([log_channels(logs_b), rng.normal(size=(3, 6))], axis=1)
    out = geodesic_interpolation(key_a, key_b, 4)
    line = linear_interpolation(key_a, key_b, 4)
    np.testing.assert_array_equal(out[[0, -1]], np.stack([key_a, key_b]))
    np.testing.assert_allclose(out[..., 3:], line[..., 3:])
    logs = rotation_logs(out)
    np.testing.assert_allclose(logs[:, :2], rotation_logs(line)[:, :2], atol=1e-12)  # one axis, one branch: the line
    held = Rotation.from_rotvec(logs[:, 2]).as_matrix()  # the line would turn it a full turn
    np.testing.assert_allclose(held, np.broadcast_to(Rotation.from_rotvec(logs_b[2]).as_matrix(), held.shape), atol=1e-9)
    assert (np.linalg.norm(logs - rotation_logs(line), axis=-1) <= np.pi).all()  # each the branch nearest the line
