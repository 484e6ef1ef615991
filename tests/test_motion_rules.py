"""benchmarks/motion_rules.py: the roll-out rules it measures do what their names say."""

import numpy as np
from scipy.spatial.transform import Rotation

from conftest import benchmark_script


def _motion_rules():
    return benchmark_script("motion_rules")


def _features(rotations: Rotation, stretch: np.ndarray) -> np.ndarray:
    """Unscaled features ``(V, 9)`` holding ``rotations`` (V of them) and ``stretch`` ``(V, 6)``."""
    from meshseq.acap.interpolation import log_channels

    return np.concatenate([log_channels(rotations.as_rotvec()), stretch], axis=1)


def test_a_part_fixed_to_its_anchor_turns_with_it_and_keeps_its_stretch():
    mr = _motion_rules()
    rng = np.random.default_rng(0)
    own = Rotation.from_rotvec(rng.normal(0, 0.5, (5, 3)))  # vertex 0: the anchor; 3 and 4: the part
    stretch = rng.normal(0, 0.1, (5, 6))
    given = _features(own, stretch)
    turns = [Rotation.from_rotvec(rng.normal(0, 0.6, 3)) for _ in range(4)]
    frames = []
    for turn in turns:  # the anchor turned on; the part's predicted rotations and stretch off the mark
        rotations = Rotation.concatenate([turn * own[0]] + [Rotation.from_rotvec(rng.normal(0, 1, 3)) for _ in range(4)])
        frames.append(_features(rotations, rng.normal(0, 0.3, (5, 6))))
    raw = np.stack(frames)[None]  # (1, 4, 5, 9)
    part = np.zeros(5, bool)
    part[3:] = True
    out = mr.following_parts(raw, given[None], [part], [0])
    from meshseq.acap.diagnostics import rotation_logs

    for t, turn in enumerate(turns):
        got = Rotation.from_rotvec(rotation_logs(out[0, t, 3:]))
        want = turn * own[3:]
        assert (got * want.inv()).magnitude().max() < 1e-9
        np.testing.assert_allclose(out[0, t, 3:, 3:], stretch[3:])
    np.testing.assert_array_equal(out[0, :, :3], raw[0, :, :3])  # the other vertices as predicted
    held = mr.held_parts(raw, given[None], [part])
    np.testing.assert_array_equal(held[0, :, 3:], np.broadcast_to(given[3:], (4, 2, 9)))
    rigid = mr.rigid_parts(raw, [part])
    np.testing.assert_allclose(rigid[0, :, 3], rigid[0, :, 4])


def test_a_roll_out_replayed_at_a_pace_takes_steps_of_that_size():
    mr = _motion_rules()
    n = mr.MAX_TEMPO * mr.N_FRAMES
    direction = np.random.default_rng(1).normal(size=(1, 1, 4, 9))
    direction /= np.linalg.norm(direction)
    x = np.zeros((2, 1, 4, 9))
    path = np.arange(1, n + 1)[None, :, None, None] * direction * np.array([0.01, 0.05])[:, None, None, None]
    out = mr.at_training_pace(x, path, 0.02)  # twice and 0.4 times the roll-outs' own step
    steps = np.linalg.norm(np.diff(np.concatenate([x, out], axis=1), axis=1).reshape(2, mr.N_FRAMES, -1), axis=-1)
    np.testing.assert_allclose(steps, 0.02, rtol=1e-5)
