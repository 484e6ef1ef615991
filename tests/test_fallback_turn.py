"""benchmarks/fallback_turn.py: the turned fallbacks it measures keep a turning shape's shape."""

import numpy as np
from scipy.spatial.transform import Rotation

from conftest import benchmark_script


def _fallback_turn():
    return benchmark_script("fallback_turn")


def _frames(rotations: list[Rotation], stretch: np.ndarray) -> np.ndarray:
    """Unscaled features ``(1, len(rotations), V, 9)``: each frame's rotation logs (in the features'
    channel layout) and one stretch."""
    from meshseq.acap.interpolation import log_channels

    return np.stack([np.concatenate([log_channels(r.as_rotvec()), stretch], axis=1) for r in rotations])[None]


def _rotations(features: np.ndarray) -> Rotation:
    """The rotations that features' ``(..., 9)`` channels hold."""
    from meshseq.acap.diagnostics import rotation_logs

    return Rotation.from_rotvec(rotation_logs(features).reshape(-1, 3))


def test_a_mesh_that_only_turns_is_turned_on_with_its_shape_kept():
    ft = _fallback_turn()
    rng = np.random.default_rng(0)
    own = Rotation.from_rotvec(rng.normal(0, 0.8, (6, 3)))  # each vertex's rotation against the reference
    stretch = rng.normal(0, 0.1, (6, 6))
    q0, step = Rotation.from_rotvec([0.3, -0.2, 0.1]), Rotation.from_rotvec([0.0, 0.15, 0.05])
    raw = _frames([q0 * own, step * q0 * own], stretch)
    turn, own_step, steps = ft.turn_steps(raw)
    assert ft.turn_share(own_step, steps)[0] < 1e-6
    reach = np.array([[1.0, 2.5]])
    out = ft.turned(raw, reach, np.ones(1), turn, own_step)  # with its own steps in full: the same, they are nil
    for k, r in enumerate(reach[0]):
        want = Rotation.from_rotvec(r * step.as_rotvec()) * step * q0 * own
        got = _rotations(out[0, k])
        assert np.allclose((got * want.inv()).magnitude(), 0.0, atol=1e-9)
        np.testing.assert_allclose(out[0, k, :, 3:], stretch, atol=1e-12)


def test_a_mesh_whose_vertices_turn_apart_continues_each_vertex_and_the_rigid_turn_holds_them():
    ft = _fallback_turn()
    rng = np.random.default_rng(1)
    base = Rotation.from_rotvec(rng.normal(0, 0.5, (8, 3)))
    steps = Rotation.from_rotvec(rng.normal(0, 0.1, (8, 3)))
    steps = Rotation.from_rotvec(steps.as_rotvec() - steps.as_rotvec().mean(0))  # no common turn, about
    stretch0, stretch1 = rng.normal(0, 0.1, (8, 6)), rng.normal(0, 0.1, (8, 6))
    raw = np.concatenate([_frames([base], stretch0), _frames([steps * base], stretch1)], axis=1)
    turn, own_step, all_steps = ft.turn_steps(raw)
    assert ft.turn_share(own_step, all_steps)[0] > 0.9
    held = ft.turned(raw, np.array([[1.0, 2.0]]), np.zeros(1), turn, own_step)
    for k in range(2):  # the rigid turn: the last shape's stretch, turned by the (small) mean turn
        np.testing.assert_allclose(held[0, k, :, 3:], stretch1, atol=1e-12)
        got = _rotations(held[0, k]) * (steps * base).inv()
        assert np.allclose(got.as_rotvec(), (k + 1) * turn[0], atol=1e-9)
    moved = ft.turned(raw, np.array([[1.0]]), np.ones(1), turn, own_step)
    np.testing.assert_allclose(moved[0, 0, :, 3:], 2 * stretch1 - stretch0, atol=1e-12)
    want = steps * steps * base
    assert np.allclose((_rotations(moved[0, 0]) * want.inv()).magnitude(), 0.0, atol=1e-9)


def test_a_deformed_mesh_turned_rigidly_is_a_common_turn_in_its_acap_features():
    """On features ``acap.extract`` makes (not rotation vectors laid in the channels by hand): a bent
    limb turned rigidly frame by frame is a common turn (share 0), and the rigid turn continues it to
    the features of the next turned frame."""
    from meshseq import acap
    from meshseq.data.synthetic import twisting_limb

    ft = _fallback_turn()
    seq = twisting_limb(frames=12, rings=8, segments=6)
    bent = seq.vertices[6].astype(np.float64)
    centre, q = bent.mean(0), Rotation.from_rotvec([0.15, 0.05, 0.0])
    frames = np.stack([seq.vertices[0]] + [(q ** k).apply(bent - centre) + centre for k in range(4)])
    feats = acap.extract(frames, seq.faces)
    raw = feats[None, 2:4]
    turn, own_step, steps = ft.turn_steps(raw)
    assert ft.turn_share(own_step, steps)[0] < 1e-9
    np.testing.assert_allclose(ft.turned(raw, np.array([[1.0]]), np.zeros(1), turn, own_step)[0, 0], feats[4],
                               atol=1e-9)
