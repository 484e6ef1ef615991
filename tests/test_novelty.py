"""The novelty of given frames against the training frames' latents, and prediction's guard."""

import numpy as np
import pytest

from meshseq import novelty
from meshseq.novelty import NoveltyReference


def test_reference_keeps_every_latent_and_the_median_step():
    seq = np.arange(5, dtype=np.float32)[:, None, None] * np.ones((1, 2, 3), np.float32)  # (5, 2, 3)

    def encode(frames):  # (B, 2, 3) -> (B, 2): steps of sqrt(2) * 1 between frames
        return frames[:, :, 0]

    ref = novelty.reference_latents(encode, [seq, seq[:1]])
    assert ref.latents.shape == (6, 2) and ref.latents.dtype == np.float32
    assert ref.step == pytest.approx(np.sqrt(2.0))
    assert np.allclose(ref.steps[:5], 1.0) and np.array_equal(ref.steps[5], [0.0, 0.0])  # one frame: no step
    thinned = novelty.reference_latents(encode, [seq], max_frames=3)
    assert np.array_equal(thinned.latents[:, 0], [0.0, 2.0, 4.0])  # evenly spaced, ends kept
    assert thinned.steps.shape == (3, 2)
    with pytest.raises(ValueError, match="two frames"):
        novelty.reference_latents(encode, [seq[:1]])


def test_novelty_is_the_nearest_distance_in_steps():
    ref = NoveltyReference(np.array([[0.0, 0.0], [10.0, 0.0]], np.float32), step=2.0)
    z = np.array([[[0.0, 0.0], [10.0, 6.0]], [[4.0, 3.0], [5.0, 0.0]]])  # (2, 2, L)
    assert np.allclose(novelty.novelty(z, ref), [[0.0, 3.0], [2.5, 2.5]])


def test_direction_familiarity_compares_with_the_steps_of_the_nearest_training_frames():
    # training: near the origin it moved along +x; near (10, 0) along +y
    lat = np.array([[0.0, 0.0], [1.0, 0.0], [10.0, 0.0], [10.0, 1.0]], np.float32)
    steps = np.array([[1.0, 0.0], [1.0, 0.0], [0.0, 1.0], [0.0, 1.0]], np.float32)
    ref = NoveltyReference(lat, 1.0, steps)
    last = np.array([[0.5, 0.0], [0.5, 0.0], [0.5, 0.0], [10.0, 0.5], [0.5, 0.0]])
    prev = np.array([[0.0, 0.0], [1.0, 0.0], [0.5, -0.5], [9.5, 0.5], [0.5, 0.0]])
    cos = novelty.direction_familiarity(last, prev, ref, neighbours=2)
    assert np.allclose(cos, [1.0, -1.0, 0.0, 0.0, 1.0])  # along, against, across, across; held: 1
    assert np.allclose(novelty.direction_familiarity(last[3:4], prev[3:4], ref, neighbours=4), 1.0)  # +x is near too
    w = novelty.direction_weight(np.array([1.0, novelty.DIRECTION_END, 0.8, novelty.DIRECTION_START, -1.0]))
    assert np.allclose(w, [1.0, 1.0, (0.8 - novelty.DIRECTION_START) / (novelty.DIRECTION_END - novelty.DIRECTION_START),
                           0.0, 0.0])


def test_training_pace_compares_given_steps_with_the_steps_training_took_at_those_poses():
    # training: fast (steps of 2) near the origin, slow (steps of 0.2) near (10, 0), as at a swing's turn
    lat = np.array([[0.0, 0.0], [2.0, 0.0], [10.0, 0.0], [10.2, 0.0]], np.float32)
    steps = np.array([[2.0, 0.0], [2.0, 0.0], [0.2, 0.0], [0.2, 0.0]], np.float32)
    ref = NoveltyReference(lat, 1.0, steps)
    z = np.array([[[0.0, 0.0], [1.0, 0.0], [2.0, 0.0]],  # steps of 1 where training took 2: half its pace
                  [[1.0, 0.0], [1.0, 0.0], [1.0, 0.0]],  # a pose held still
                  [[0.0, 0.0], [3.0, 0.0], [6.0, 0.0]],  # faster than training: never sped up
                  [[9.8, 0.0], [10.0, 0.0], [10.2, 0.0]]])  # slow, at a pose where training is slow too
    assert np.allclose(novelty.training_pace(z, ref, neighbours=2, full=1.0), [0.5, 0.0, 1.0, 1.0])
    assert np.allclose(novelty.training_pace(z[:1, 1:], ref, neighbours=2, full=1.0), 0.5)  # two given frames
    assert np.allclose(novelty.training_pace(z, ref, neighbours=2, full=0.5), [1.0, 0.0, 1.0, 1.0])  # half counts as full


def test_guard_weight_falls_from_one_to_zero_between_start_and_end():
    w = novelty.guard_weight(np.array([0.0, novelty.GUARD_START, 3.0, novelty.GUARD_END, 50.0]))
    assert np.allclose(w, [1.0, 1.0, (novelty.GUARD_END - 3.0) / (novelty.GUARD_END - novelty.GUARD_START), 0.0, 0.0])


def test_fallback_holds_one_frame_and_damps_the_velocity_of_two():
    rng = np.random.default_rng(0)
    one = rng.normal(size=(2, 1, 4, 9)).astype(np.float32)
    assert np.array_equal(novelty.fallback(one, 3), np.repeat(one, 3, axis=1))
    two = rng.normal(size=(2, 2, 4, 9))
    out = novelty.fallback(two, 30)
    v = two[:, -1] - two[:, -2]
    assert np.allclose(out[:, 0], two[:, -1] + v)  # the first frame keeps the last velocity
    steps = np.diff(np.concatenate([two[:, -1:], out], axis=1), axis=1)
    assert np.allclose(steps[:, 1:], novelty.FALLBACK_DECAY * steps[:, :-1])
    reach = (out[:, -1] - two[:, -1]) / v
    assert np.all(reach < 1.0 / (1.0 - novelty.FALLBACK_DECAY))  # never past ten velocities
    linear = novelty.fallback(two, 4, decay=1.0)  # no damping: linear extrapolation
    assert np.allclose(linear, two[:, -1:] + np.arange(1, 5)[None, :, None, None] * v[:, None])


def test_guarded_leaves_familiar_frames_alone_and_replaces_novel_ones():
    rng = np.random.default_rng(1)
    given = rng.normal(size=(3, 2, 4, 9)).astype(np.float32)
    frames = rng.normal(size=(3, 5, 4, 9)).astype(np.float32)
    assert novelty.guarded(frames, given, np.ones(3)) is frames
    out = novelty.guarded(frames, given, np.array([1.0, 0.0, 0.5]))
    base = novelty.fallback(given, 5)
    assert np.array_equal(out[0], frames[0]) and np.allclose(out[1], base[1])
    assert np.allclose(out[2], 0.5 * (frames[2] + base[2]), atol=1e-6)


def test_fallback_of_three_or_more_follows_the_given_frames_own_slowing():
    """Steps of the given frames halving: the fallback keeps halving them; speeding up: damped by
    FALLBACK_DECAY at most; turned back: one step, then held; own_pace=False: FALLBACK_DECAY."""
    rng = np.random.default_rng(2)
    base, v = rng.normal(size=(4, 9)), rng.normal(size=(4, 9))
    slowing = np.stack([base, base + v, base + 1.5 * v])  # steps v, v / 2
    faster = np.stack([base, base + v, base + 3 * v])  # steps v, 2 v
    turned = np.stack([base, base + v, base + 0.5 * v])  # steps v, -v / 2
    given = np.stack([slowing, faster, turned])  # (3, 3, 4, 9)
    assert np.allclose(novelty.own_decay(given), [0.5, novelty.FALLBACK_DECAY, 0.0])
    assert np.allclose(novelty.own_decay(given[:, 1:]), novelty.FALLBACK_DECAY)  # two frames: no ratio
    out = novelty.fallback(given, 6)
    steps = np.diff(np.concatenate([given[:, -1:], out], axis=1), axis=1)
    assert np.allclose(steps[0, 1:], 0.5 * steps[0, :-1]) and np.allclose(steps[0, 0], 0.5 * v)
    assert np.allclose(steps[1, 1:], novelty.FALLBACK_DECAY * steps[1, :-1])
    assert np.allclose(steps[2, 0], -0.5 * v) and np.allclose(steps[2, 1:], 0.0)
    fixed = novelty.fallback(given, 6, own_pace=False)
    fixed_steps = np.diff(np.concatenate([given[:, -1:], fixed], axis=1), axis=1)
    assert np.allclose(fixed_steps[:, 1:], novelty.FALLBACK_DECAY * fixed_steps[:, :-1])
