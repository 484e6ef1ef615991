"""Prediction, completion, baselines and evaluation with a small trained model."""

from __future__ import annotations

import json
import time

import numpy as np
import pytest
import torch

from meshseq import baselines
from meshseq.align import per_vertex_error
from meshseq.cli import main
from meshseq.data.synthetic import twisting_limb
from meshseq.errors import MeshseqError
from meshseq.io import MeshSequence, load_sequence, save_sequence


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    """A tiny model trained briefly on a generated limb: (run folder, data path, sequence)."""
    from meshseq.train import TrainConfig, load_training_data, train

    root = tmp_path_factory.mktemp("synth")
    data = root / "limb.npz"
    save_sequence(twisting_limb(frames=72, rings=12, segments=8), data)
    run = root / "run"
    train(load_training_data([str(data)]),
          run, TrainConfig(iterations=40, window=12, batch=4, eval_every=0, checkpoint_every=0, log_every=0),
          model_options={"latent": 16, "lstm_layers": 2}, device="cpu", progress=False, log=lambda m: None)
    return run, data, load_sequence(data)


@pytest.fixture(scope="module")
def model(trained):
    from meshseq.api import load

    return load(trained[0])


def test_long_prediction_stays_finite_and_within_the_data_range(model, trained):
    from meshseq.synthesize import predict

    x = model.features(trained[2].vertices[:3])
    out = predict(model, x, 500)
    assert out.shape == (500,) + x.shape[1:]
    assert np.isfinite(out).all() and np.abs(out).max() <= 1.0
    # without the bound the same roll-out is still finite (the bound only clips)
    free = predict(model, x, 50, bound=None)
    assert np.isfinite(free).all()
    assert np.allclose(np.clip(free[:1], -1, 1), out[:1])


def test_prediction_from_a_pose_held_still_stays_still(model, trained):
    """Three copies of one frame: the default pace keeps the roll-out on that pose; the model's own
    pace (the paper's roll-out) moves away from it, so the test could fail."""
    from meshseq.pace import step_levels
    from meshseq.synthesize import predict

    v = trained[2].vertices
    x = model.features(v[[30, 30, 30]])
    held = predict(model, x, 20)
    free = predict(model, x, 20, pace="model")
    typical = step_levels(v).mean()
    assert step_levels(model.vertices(np.concatenate([x[-1:], held]))).mean() < 1e-3 * typical
    assert step_levels(model.vertices(np.concatenate([x[-1:], free]))).mean() > 0.05 * typical
    moving = model.features(v[30:33])
    assert not np.allclose(predict(model, moving, 5), np.repeat(moving[-1:], 5, 0), atol=1e-4)


def test_novelty_reference_is_the_training_frames_and_the_guard_spares_them(model, trained):
    """The checkpoint holds the delivered model's latents of its training frames (both backends
    read them); prediction from training frames is the roll-out bit for bit."""
    from meshseq import novelty
    from meshseq.api import load
    from meshseq.synthesize import novelty_weights, predict

    v = trained[2].vertices
    split = model.meta["datasets"][0]["split"]["train"]
    whole = model.features(v)  # (features of a part alone may take other rotation branches)
    frames = np.concatenate([whole[a:b] for a, b in split])
    ref = model.novelty
    assert ref is not None and ref.latents.shape == (len(frames), model.config.latent)
    assert np.allclose(ref.latents, model.engine.encode(frames), atol=1e-4)
    assert np.abs(novelty.novelty(model.engine.encode(frames), ref)).max() < 1e-2
    z = model.engine.encode(frames)
    if len(split) == 1:  # each frame's latent step from the one before (the first: to the one after)
        assert np.allclose(ref.steps[1:], np.diff(z, axis=0), atol=1e-4) and np.allclose(ref.steps[0], z[1] - z[0], atol=1e-4)
    cpu = load(trained[0], backend="numpy")
    assert np.array_equal(cpu.novelty.latents, ref.latents) and cpu.novelty.step == ref.step
    assert np.array_equal(cpu.novelty.steps, ref.steps)
    x = model.features(v[20:23])
    assert np.all(novelty_weights(model, x[None]) == 1.0)
    assert np.array_equal(predict(model, x, 8), predict(model, x, 8, guard=False))


def test_prediction_heading_where_training_never_went_falls_back(model, trained):
    """Training frames given in their order, against a reference whose steps all point across the
    given step: every pose is familiar but the direction is not, so 3 given frames get the fallback
    while 1 given frame (no direction) keeps the roll-out."""
    import copy

    from meshseq import novelty
    from meshseq.synthesize import novelty_weights, predict

    x = model.features(trained[2].vertices[20:23])
    z = model.engine.encode(x[-2:]).astype(np.float64)
    given_step = z[1] - z[0]
    across = np.random.default_rng(0).normal(size=given_step.shape)
    across -= (across @ given_step) / (given_step @ given_step) * given_step
    crossing = copy.copy(model)
    ref = model.novelty
    crossing.novelty = novelty.NoveltyReference(ref.latents, ref.step,
                                                np.repeat(across[None], len(ref.latents), 0).astype(np.float32))
    assert novelty_weights(model, x[None])[0] == 1.0 and novelty_weights(crossing, x[None])[0] == 0.0
    out = predict(crossing, x, 6)
    assert np.allclose(out, np.clip(novelty.fallback(x[None], 6)[0], -1, 1), atol=1e-6)
    assert np.array_equal(predict(crossing, x[-1:], 6), predict(model, x[-1:], 6, guard=False))


def test_prediction_from_frames_unlike_the_training_ones_falls_back(model, trained):
    """A pose the model never saw (the limb's features negated): the guard's weight is low and the
    prediction is the roll-out blended by it towards the fallback (the given velocity, damped)."""
    from meshseq import novelty
    from meshseq.synthesize import novelty_weights, predict

    far = -model.features(trained[2].vertices[20:23])
    weight = novelty_weights(model, far[None])
    assert weight[0] < 0.5
    free = predict(model, far, 10, guard=False)
    out = predict(model, far, 10)
    assert np.allclose(out, np.clip(novelty.guarded(free[None], far[None], weight)[0], -1, 1), atol=1e-6)
    base = novelty.fallback(far[None], 10)[0]
    assert np.abs(out - base).max() < 0.5 * np.abs(free - base).max()
    np.testing.assert_array_equal(model.predict(far, 10), out)  # the API: guarded unless asked
    np.testing.assert_array_equal(model.predict(far, 10, guard=False), free)


def test_pace_factor_compares_given_steps_with_the_expected_ones():
    from meshseq.synthesize import pace_factor, predict

    given = np.array([[0.0, 0.0], [0.5, 0.5], [2.0, 2.0], [1.0, 3.0]])
    expected = np.array([[1.0, 1.0], [1.0, 1.0], [1.0, 1.0], [2.0, 2.0]])
    assert np.allclose(pace_factor(given, expected), [0.0, 0.5, 1.0, 1.0])
    with pytest.raises(Exception, match="pace"):
        predict(None, np.zeros((2, 3, 9), np.float32), 2, pace="fast")


def test_the_default_pace_compares_with_the_training_frames_and_warm_up_with_the_model(model, trained):
    """``given`` scales the roll-out by ``novelty.training_pace`` of the given latents, ``warm-up`` by
    ``pace_factor`` of the model's warm-up predictions (also ``given``'s rule for a model stored
    without its training frames' latent steps)."""
    import copy

    from meshseq import novelty
    from meshseq.synthesize import _rms, _warm_up, pace_factor, predict, roll_out_pace

    v = trained[2].vertices
    x = model.features(v[30] + np.array([0.0, 0.2, 0.4])[:, None, None] * (v[31] - v[30]))[None]  # a fifth of the pace
    z = model.engine.encode(x[0])[None]
    _, expected = _warm_up(model.engine, model.engine.initial_state(1, 0), x)
    warm = pace_factor(_rms(x[:, 1:] - x[:, :-1]), expected)
    ours = novelty.training_pace(z, model.novelty)
    assert not np.allclose(ours, warm)  # the two rules differ here, so the test could fail
    assert np.allclose(roll_out_pace(model, x, expected, "given", z)[:, 0, 0], ours)
    assert np.allclose(roll_out_pace(model, x, expected, "warm-up", z)[:, 0, 0], warm)
    assert roll_out_pace(model, x, expected, "model", z) is None and roll_out_pace(model, x[:, :1], expected, "given", z) is None
    stepless = copy.copy(model)
    stepless.novelty = novelty.NoveltyReference(model.novelty.latents, model.novelty.step, None)
    assert np.array_equal(predict(stepless, x[0], 6), predict(stepless, x[0], 6, pace="warm-up"))
    assert not np.array_equal(predict(model, x[0], 6), predict(model, x[0], 6, pace="warm-up"))


def test_carried_steps_start_from_the_given_velocity_and_hand_over_to_the_generated_steps():
    from meshseq.synthesize import carried_steps

    given = np.zeros((1, 3, 2, 1))
    given[0, :, :, 0] = [[0.0, 0.0], [1.0, 1.0], [2.0, 2.0]]  # moving at +1 a frame
    generated = 2.0 - np.arange(1, 31, dtype=float)[None, :, None, None] * np.ones((1, 30, 2, 1))  # -1 a frame
    out = carried_steps(given, generated, carry=0.5)
    steps = np.diff(np.concatenate([given[:, -1:], out], 1), axis=1)[0, :, 0, 0]
    assert np.allclose(steps[:3], [0.0, -0.5, -0.75])  # -1 + 0.5**t (+1 - -1): the difference fades
    assert abs(steps[-1] + 1.0) < 1e-6  # handed over to the generated velocity
    wavy = generated + np.sin(np.arange(30.0))[None, :, None, None]  # a fast rhythm is kept once faded
    assert np.allclose(np.diff(carried_steps(given, wavy, 0.5)[0, 20:], axis=0), np.diff(wavy[0, 20:], axis=0), atol=1e-5)
    assert np.array_equal(carried_steps(given, generated, carry=0.0), generated)
    # a prefix is carried the same whatever follows it
    assert np.allclose(carried_steps(given, generated[:, :7], carry=0.6), carried_steps(given, generated, carry=0.6)[:, :7])
    one = carried_steps(given[:, -1:], generated, carry=0.5)  # one given frame: from the first generated step
    assert np.allclose(one, generated)


def test_prediction_continues_the_given_frames_velocity(model, trained):
    """With 3 given frames of a training sequence, the first generated step is closer to the true
    one with the carried steps than the model's own (carry 0), so the test could fail."""
    from meshseq.synthesize import predict

    x = model.features(trained[2].vertices)
    starts = np.arange(0, len(x) - 4, 3)
    given = np.stack([x[s:s + 3] for s in starts])
    true_step = x[starts + 3] - x[starts + 2]
    miss = {carry: np.linalg.norm(predict(model, given, 3, carry=carry, guard=False)[:, 0] - x[starts + 3])
            for carry in (0.0, 0.6)}
    assert miss[0.6] < miss[0.0]
    assert np.linalg.norm(true_step) > 0  # the sequence moves
    with pytest.raises(MeshseqError, match="carry"):
        predict(model, given, 3, carry=1.0)


def test_warm_up_uses_every_given_frame(model, trained):
    from meshseq.synthesize import predict

    x = model.features(trained[2].vertices[:4])
    one = predict(model, x[3:], 5)
    four = predict(model, x, 5)
    assert not np.allclose(one, four)  # the state took in frames 0..2
    changed = x.copy()
    changed[0] += 0.2
    assert not np.allclose(predict(model, changed, 5), four)


def test_completion_passes_exactly_through_keyframes_and_samples_differ(model, trained):
    from meshseq.synthesize import assemble_vertices, complete

    v = trained[2].vertices
    keys = model.features(v[[10, 24]])
    comp = complete(model, keys[0], keys[1], 13)
    assert comp.frames.shape == (1, 15) + keys.shape[1:]
    assert np.array_equal(comp.frames[0, 0], keys[0]) and np.array_equal(comp.frames[0, -1], keys[1])
    assert 1 <= comp.stitch[0] <= 13
    verts = assemble_vertices(model, comp.frames[0], {0: v[10], 14: v[24]})
    assert np.array_equal(verts[0], v[10]) and np.array_equal(verts[-1], v[24])
    # the frames next to the keys continue smoothly (no jump from exact keys to reconstructions)
    step = np.linalg.norm(np.diff(verts, axis=0), axis=-1).mean(axis=-1)
    assert step.max() < 5 * np.linalg.norm(np.diff(v[10:25], axis=0), axis=-1).mean(axis=-1).max()
    many = complete(model, keys[0], keys[1], 13, samples=3, seed=5)
    assert many.frames.shape[0] == 3
    assert baselines.pairwise_diversity(many.frames[:, 1:-1]) > 1e-4
    assert not np.allclose(many.frames[0], many.frames[1])
    again = complete(model, keys[0], keys[1], 13, samples=3, seed=5)
    assert np.array_equal(again.frames, many.frames)  # a seed reproduces


def test_corrected_join_ends_on_both_keys_and_removes_a_chain_drift():
    from meshseq.synthesize import corrected_crossfade

    rng = np.random.default_rng(0)
    truth = rng.normal(size=(9, 4, 9))  # 9 frames, key a = truth[0], key b = truth[-1]
    # perfect chains give the truth back
    assert np.allclose(corrected_crossfade(truth, truth[::-1]), truth)
    # chains that drift linearly away from the truth (by a constant velocity) are corrected
    drift = rng.normal(size=(4, 9)) * np.arange(9)[:, None, None]
    fwd = truth + drift
    bwd = (truth - drift[::-1])[::-1]  # the backward chain drifts from key b, in its own order
    out = corrected_crossfade(fwd, bwd)
    assert np.allclose(out, truth)
    assert np.array_equal(out[0], truth[0]) and np.allclose(out[-1], truth[-1])
    # the paper's stitch keeps the drift up to the meeting frame
    from meshseq.synthesize import stitch_chains

    assert np.abs(stitch_chains(fwd, bwd)[0] - truth).max() > 0.1


def test_anchored_join_keeps_chains_that_reach_the_far_key_and_drops_ones_that_miss_it():
    from meshseq.synthesize import join_chains, reach_weights

    t = np.linspace(0.0, 1.0, 9)[:, None, None]
    truth = np.sin(3.0 * t + np.arange(4)[None, :, None] + np.arange(9)[None, None, :])  # (9, 4, 9)
    hit = join_chains(truth[None], truth[::-1][None], "anchored")[0][0]
    assert reach_weights(truth[None], truth[::-1][None])[0] == pytest.approx(1.0)
    np.testing.assert_allclose(hit, truth, atol=1e-12)
    # a pose held still between two equal keys, chains that play a motion: the interpolation
    still = np.repeat(truth[:1], 9, axis=0)
    wander = still + 0.3 * np.sin(6.0 * t)
    out = join_chains(wander[None], wander[None], "anchored")[0][0]
    assert reach_weights(wander[None], wander[None])[0] == 0.0
    np.testing.assert_allclose(out, still, atol=1e-12)


def test_anchor_line_turns_rotations_the_short_way_and_the_anchored_join_falls_back_to_it(model, trained):
    """``anchor_line``: ``straight`` is the keys' linear interpolation; ``geodesic`` is
    ``geodesic_interpolation`` of the unscaled keys, pair by pair as in a batch, and differs from the
    straight line where the rotations turn. Chains that miss their far keys (weight 0) are joined
    onto the line given."""
    from meshseq.acap.interpolation import geodesic_interpolation
    from meshseq.baselines import linear_interpolation
    from meshseq.errors import MeshseqError
    from meshseq.synthesize import anchor_line, join_chains

    f = model.features(trained[2].vertices)
    a, b = f[[2, 10]], f[[30, 50]]  # (2, V, C): two pairs of keys far apart in the twist
    straight = anchor_line(model, a, b, 7, "straight")
    np.testing.assert_allclose(straight[1], linear_interpolation(a[1], b[1], 5), atol=1e-6)
    geo = anchor_line(model, a, b, 7)
    assert geo.shape == (2, 7) + f.shape[1:] and geo.dtype == f.dtype
    one = model.scaling.apply(geodesic_interpolation(*model.scaling.invert(np.stack([a[1], b[1]]).astype(np.float64)), 5))
    np.testing.assert_allclose(geo[1], one, atol=1e-5)
    np.testing.assert_allclose(geo[:, [0, -1]], np.stack([a, b], 1), atol=1e-5)
    assert np.abs(geo - straight).max() > 1e-3
    held_a, held_b = np.repeat(a[:, None], 7, 1), np.repeat(b[:, None], 7, 1)  # each chain stays on its key
    out = join_chains(held_a, held_b, "anchored", line=geo)[0]
    np.testing.assert_allclose(out, geo, atol=1e-5)
    with pytest.raises(MeshseqError, match="unknown line"):
        anchor_line(model, a, b, 7, "curved")


def test_context_fit_trusts_frames_the_model_predicts_and_not_a_pose_held_still(model, trained):
    """``context_fit``: frames that are the model's own roll-out (to the key, each side in its
    chain's direction) are predicted exactly (0); a pose held still is not (standing still is exact)."""
    from meshseq.synthesize import context_fit

    x = model.features(trained[2].vertices[[10, 40]])
    fwd = model.engine.rollout(x[:1], 5, model.engine.initial_state(1, 0))[0][0]
    bwd = model.engine.rollout(x[1:], 5, model.engine.initial_state(0, 1), n_forward=0)[0][0]
    before, key_a = fwd[None, :-1], fwd[None, -1]  # forward: far frame first, the key last
    key_b, after = bwd[None, -1], bwd[None, -2::-1]  # backward, rolled from the far frame: in time order the key first
    assert context_fit(model, before, key_a, after, key_b)[0] < 1e-5
    still = np.repeat(x[:1, None], 4, 1)
    assert context_fit(model, still, x[:1], still, x[:1])[0] > 1.0
    assert np.isinf(context_fit(model, None, x[:1], None, x[:1])[0])


def test_context_trust_needs_familiar_keys_and_frames_at_the_models_pace(model, trained):
    """``context_trust``: training frames around training keys are trusted; the same keys with a
    pose held still before them are not (pace 0), nor are keys the model never saw (negated
    features); a model stored without the training latents falls back to ``context_fit``, one
    stored without their latent steps judges the frames by the warm-up's pace."""
    import copy
    import dataclasses

    from meshseq.synthesize import PACE_TRUST, context_fit, context_pace, context_trust, side_trust

    f = model.features(trained[2].vertices)
    before, key_a, key_b, after = f[None, 3:10], f[None, 10], f[None, 21], f[None, 22:29]
    assert context_pace(model, f[None, 3:11])[0] == pytest.approx(1.0)
    assert context_trust(model, before, key_a, after, key_b)[0]
    still = np.repeat(f[None, 10:11], 7, 1)
    assert context_pace(model, np.concatenate([still, key_a[:, None]], 1))[0] == 0.0
    assert not context_trust(model, still, key_a, after, key_b)[0]
    assert not context_trust(model, -before, -key_a, -after, -key_b)[0]
    assert not context_trust(model, None, key_a, None, key_b)[0]
    old = copy.copy(model)
    old.novelty = None
    np.testing.assert_array_equal(context_trust(old, before, key_a, after, key_b),
                                  context_fit(model, before, key_a, after, key_b) < 1.0)
    paths = np.concatenate([np.concatenate([before, key_a[:, None]], 1),
                            np.concatenate([still, key_a[:, None]], 1)])  # moving, then held still
    np.testing.assert_array_equal(side_trust(model, paths), [True, False])
    no_steps = copy.copy(model)
    no_steps.novelty = dataclasses.replace(model.novelty, steps=None)
    np.testing.assert_array_equal(side_trust(no_steps, paths), context_pace(model, paths) >= PACE_TRUST)


def test_completion_trust_benchmark_scores_the_default_as_the_benchmark_and_puts_the_rule_back(model, trained):
    """benchmarks/completion_trust.py: its ``default`` is the benchmark's own completion figures; a
    rule holds only inside ``trusting`` (also when scoring fails); ``always`` trusts at least where
    the default does and changes ours where the default does not trust every pair."""
    import meshseq.synthesize as syn
    from conftest import benchmark_script
    from meshseq.evaluate import completion_errors

    ct = benchmark_script("completion_trust")
    v = trained[2].vertices.astype(np.float64)
    f = model.features(v)
    own = completion_errors(model, v, f, 10, 40, [5, 10, 20], ["ours", "linear", "linear_vertices"], samples=1,
                            context=syn.CONTEXT)
    assert ct.block_errors(model, v, f, 10, 40, ct.trust_rule("default")) == own
    never = ct.block_errors(model, v, f, 10, 40, ct.trust_rule("never"))
    always = ct.block_errors(model, v, f, 10, 40, ct.trust_rule("always"))
    assert never != always and syn.context_trust is ct.trust_rule("default")
    before, key_a, key_b, after = f[None, 3:10], f[None, 10], f[None, 21], f[None, 22:29]
    assert ct.trust_rule("pace=0")(model, before, key_a, after, key_b) >= syn.context_trust(model, before, key_a,
                                                                                          after, key_b)
    with pytest.raises(ZeroDivisionError), ct.trusting(ct.trust_rule("never")):
        1 / 0
    assert syn.context_trust is ct.trust_rule("default")
    with pytest.raises(SystemExit, match="'pace=slow'"):
        ct.trust_rule("pace=slow")


def test_pace_levels_are_the_guarded_prediction_unless_the_guard_is_off(model, trained):
    """``pace.pace_levels``: a pose held still has no given motion; on frames far from training the
    guard replaces the roll-out, and ``guard=False`` measures the roll-out, as ``predict`` gives it."""
    from meshseq.pace import pace_levels, step_levels
    from meshseq.synthesize import predict

    v = trained[2].vertices.astype(np.float64)
    f = model.features(v)
    starts = np.array([5, 20, 40])
    assert (pace_levels(model, v, f, starts, 3, 10, hold=True)["given"] == 0).all()
    far = 3.0 * f  # poses the model never saw: the guard acts
    levels = {guard: pace_levels(model, v, far, starts, 3, 10, guard=guard)["ours"] for guard in (True, False)}
    assert not np.allclose(levels[True], levels[False])
    idx = starts[:, None] + np.arange(3)
    frames = np.concatenate([far[idx[:, -1]][:, None], predict(model, far[idx], 10, guard=False)], 1)
    rolled = model.vertices(frames.reshape(-1, *frames.shape[2:])).reshape(*frames.shape[:2], -1, 3)
    np.testing.assert_allclose(levels[False], step_levels(rolled).mean(-1), rtol=1e-6)


def test_context_frames_warm_the_chains_and_trusted_pairs_keep_the_corrected_join(model, trained):
    from meshseq.synthesize import complete, join_chains, warm_chain_states

    v = trained[2].vertices
    f = model.features(v)
    state = model.engine.initial_state(2, 2)
    same = warm_chain_states(model, state, f[None, :0].repeat(2, 0), None)
    assert all(np.array_equal(a, b) for a, b in zip(same, state))
    warm = warm_chain_states(model, state, np.stack([f[3:10]] * 2), np.stack([f[30:37]] * 2))
    assert not np.array_equal(warm[0][:, :2], state[0][:, :2]) and not np.array_equal(warm[0][:, 2:], state[0][:, 2:])
    plain = complete(model, f[10], f[21], 10, join="corrected").frames[0]
    ctx = complete(model, f[10], f[21], 10, join="corrected", before=f[3:10], after=f[22:29]).frames[0]
    assert not np.allclose(plain, ctx)
    np.testing.assert_array_equal(ctx[[0, -1]], f[[10, 21]])
    rng = np.random.default_rng(0)
    fwd, bwd = (rng.normal(size=(3, 8, 5, 9)).astype(np.float32) for _ in range(2))
    trusted = np.array([True, False, True])
    got = join_chains(fwd, bwd, "anchored", trusted=trusted)[0]
    np.testing.assert_allclose(got[trusted], join_chains(fwd, bwd, "corrected")[0][trusted], atol=1e-6)
    np.testing.assert_array_equal(got[~trusted], join_chains(fwd, bwd, "anchored")[0][~trusted])


def test_completion_joins_paper_stitch_and_corrected(model, trained):
    from meshseq.errors import MeshseqError
    from meshseq.synthesize import complete

    keys = model.features(trained[2].vertices[[10, 24]])
    ours = complete(model, keys[0], keys[1], 13)
    paper = complete(model, keys[0], keys[1], 13, join="stitch")
    assert not np.allclose(ours.frames, paper.frames)
    assert np.array_equal(ours.stitch, paper.stitch)  # the raw chains' meeting frame either way
    for comp in (ours, paper):
        assert np.array_equal(comp.frames[0, 0], keys[0]) and np.array_equal(comp.frames[0, -1], keys[1])
    with pytest.raises(MeshseqError, match="join"):
        complete(model, keys[0], keys[1], 13, join="glue")


def test_vertex_space_linear_completion_is_straight_lines_through_the_keys(model, trained):
    from meshseq.synthesize import complete_keyframes

    v = trained[2].vertices.astype(np.float64)
    out = complete_keyframes(model, v[[4, 10, 13]], [5, 2], method="linear_vertices")
    assert out.shape == (1, 10) + v.shape[1:]
    assert np.array_equal(out[0, [0, 6, 9]], v[[4, 10, 13]])
    assert np.allclose(out[0, 3], 0.5 * (v[4] + v[10]))  # halfway between the first two keys
    assert np.allclose(np.diff(out[0, :7], 2, axis=0), 0)  # constant velocity within a gap


def test_cma_baseline_is_bounded_in_evaluations_and_time(model, trained):
    from meshseq.synthesize import complete_cma

    keys = model.features(trained[2].vertices[[10, 20]])
    comp = complete_cma(model, keys[0], keys[1], 9, max_evals=30, max_seconds=60, popsize=8)
    assert 0 < comp.evaluations <= 30 + 8  # CMA-ES checks its budget after each generation of 8
    assert comp.frames.shape == (1, 11) + keys.shape[1:]
    assert np.array_equal(comp.frames[0, -1], keys[1])
    # the time bound stops a run whose evaluation budget is practically unlimited
    t0 = time.monotonic()
    timed = complete_cma(model, keys[0], keys[1], 9, max_evals=10 ** 6, max_seconds=1.0, popsize=8)
    elapsed = time.monotonic() - t0
    per_generation = elapsed / max(1, timed.evaluations // 8)
    assert timed.evaluations < 10 ** 6
    assert elapsed < 1.0 + 3 * per_generation + 2.0  # stops within a generation or two of the limit


def test_baselines():
    given = np.random.default_rng(0).normal(size=(2, 3, 5, 9))
    zv = baselines.zero_velocity(given, 4)
    assert zv.shape == (2, 4, 5, 9) and np.array_equal(zv[:, 3], given[:, -1])
    lin = baselines.linear_acap(given, 4)
    assert np.allclose(lin[:, 1] - lin[:, 0], given[:, -1] - given[:, -2])
    assert np.allclose(lin[:, 0], 2 * given[:, -1] - given[:, -2])
    assert np.array_equal(baselines.linear_acap(given[:, :1], 4), baselines.zero_velocity(given[:, :1], 4))
    li = baselines.linear_interpolation(given[0, 0], given[0, 1], 3)
    assert li.shape == (5, 5, 9) and np.allclose(li[2], (given[0, 0] + given[0, 1]) / 2)


@pytest.mark.parametrize("subdivisions", [2, 4])
def test_vae_fc_learns_at_the_fan_in_rate_on_large_meshes(subdivisions):
    """The VAE baseline's big FC weight learns at lr x min(1, 9000 / (V x 9)) (horse-gallop's ran
    away at one rate for all weights); everything else at lr."""
    from meshseq.data.synthetic import icosphere
    from meshseq.mesh import Topology
    from meshseq.model import ModelConfig

    verts, faces = icosphere(subdivisions)
    vae = baselines.MeshVAE(ModelConfig(n_vertices=len(verts), channels=9, latent=8, lstm_layers=1, variant="uni"),
                            Topology.from_faces(faces, len(verts)))
    groups = baselines.vae_param_groups(vae, 1e-3)
    fc = [g for g in groups if any(p is vae.net.fc.weight for p in g["params"])]
    assert len(fc) == 1 and fc[0]["params"] == [vae.net.fc.weight]
    assert fc[0]["lr"] == pytest.approx(1e-3 * min(1.0, 9000 / (len(verts) * 9)))
    assert (fc[0]["lr"] < 1e-3) == (len(verts) * 9 > 9000)
    rest = [p for g in groups if g is not fc[0] for p in g["params"]]
    assert {id(p) for p in rest} | {id(vae.net.fc.weight)} == {id(p) for p in vae.parameters()}
    assert all(g["lr"] == 1e-3 for g in groups if g is not fc[0])


def test_vae_baseline_cache_is_reused_and_one_from_the_old_fc_rule_retrained(model, trained, tmp_path):
    import shutil

    from meshseq.cli.synth_cmds import _vae

    run = tmp_path / "run"
    shutil.copytree(trained[0], run)
    seq = trained[2]
    feats = model.features(seq.vertices)
    first = _vae(model, str(run), seq, feats, (58, 72), 3)
    meta = json.loads((run / "baselines" / "vae" / "vae.json").read_text())
    assert meta["fc_lr"] == baselines.VAE_FC_LR
    again = _vae(model, str(run), seq, feats, (58, 72), 50)  # cached: not trained another 50 iterations
    assert all(torch.equal(a, b) for a, b in zip(first.state_dict().values(), again.state_dict().values()))
    del meta["fc_lr"]  # a VAE cached before the fan-in rule
    (run / "baselines" / "vae" / "vae.json").write_text(json.dumps(meta))
    retrained = _vae(model, str(run), seq, feats, (58, 72), 50)
    assert not all(torch.equal(a, b) for a, b in zip(first.state_dict().values(), retrained.state_dict().values()))
    assert json.loads((run / "baselines" / "vae" / "vae.json").read_text())["iterations"] == 50


def test_evaluate_command_writes_the_tables_json(trained, tmp_path, capsys):
    run, data, _ = trained
    out = tmp_path / "eval.json"
    plots = tmp_path / "plots"
    assert main(["evaluate", str(run), str(data), "--json", str(out), "--plots", str(plots), "--horizons", "2,5",
                 "--given", "1,2", "--vae-iterations", "20", "--cma-evals", "20", "--cma-seconds", "2",
                 "--gaps", "3", "--samples", "2", "--curve-frames", "10"]) == 0
    r = json.loads(out.read_text())
    assert r["units"] == "x1e-4" and r["range"] == [58, 72]
    for key in ("errors", "errors_aligned"):
        assert set(r[key]) == {"ours", "zero_velocity", "linear_acap", "vae_latent"}
        for per_u in r[key].values():
            assert set(per_u) == {"u1", "u2"} and set(per_u["u1"]) == {"2", "5"}
            assert all(v > 0 for v in per_u["u1"].values())
    # rigid alignment can only lower the error
    assert r["errors_aligned"]["ours"]["u1"]["5"] <= r["errors"]["ours"]["u1"]["5"] + 1e-9
    # scale-free copies: per bounding-box diagonal of the first held-out frame
    seq = load_sequence(data)
    diag = np.linalg.norm(seq.vertices[58].max(0) - seq.vertices[58].min(0))
    assert r["diagonal"] == pytest.approx(diag, rel=1e-6)
    for key, base in (("errors_per_diagonal", "errors"), ("errors_aligned_per_diagonal", "errors_aligned")):
        for m, per_u in r[base].items():
            for u, per_h in per_u.items():
                for h, e in per_h.items():
                    assert r[key][m][u][h] == pytest.approx(e * 1e-4 / diag, rel=1e-9)
    assert len(r["feature_change"]["ours"]) == 10 and r["feature_change"]["ground_truth"] > 0
    assert set(r["completion"]["3"]) >= {"ours", "stitch", "cma", "linear", "linear_vertices", "diversity"}
    assert r["completion"]["3"]["ours"] != r["completion"]["3"]["stitch"]  # two different joins
    # the vertex-space baseline: straight lines between the true keys, measured like the others
    lo, hi = r["range"]
    starts = np.arange(lo, hi - 3 - 1)
    starts = starts[np.linspace(0, len(starts) - 1, min(8, len(starts))).astype(int)]
    v = seq.vertices.astype(np.float64)
    expect = np.mean([per_vertex_error(baselines.linear_interpolation(v[a], v[a + 4], 3)[1:-1], v[a + 1:a + 4]).mean()
                      for a in starts]) * 1e4
    assert r["completion"]["3"]["linear_vertices"] == pytest.approx(expect, rel=1e-9)
    assert any("Tan et al" in n for n in r["notes"])
    assert sorted(p.name for p in plots.iterdir()) == ["error_u1.png", "error_u2.png", "feature_change.png"]


def test_predict_command_guards_against_frames_unlike_the_training_ones(model, trained, tmp_path, capsys):
    """The limb stretched to twice its width: predict blends towards the fallback and says so in a
    note; --guard off writes the roll-out alone, as the API's guard=False."""
    from meshseq.synthesize import assemble_vertices, predict

    run, _, seq = trained
    data = tmp_path / "wide.npz"
    save_sequence(MeshSequence(seq.vertices * np.array([2.0, 1.0, 1.0]), seq.faces, name="wide"), data)
    given = load_sequence(data).vertices[20:23]
    feats = model.features(given)
    outs = {}
    for guard in ("novelty", "off"):
        out = tmp_path / f"{guard}.npz"
        assert main(["predict", str(run), str(data), "--start", "20", "--given", "3", "--frames", "6",
                     "--guard", guard, "-o", str(out)]) == 0
        outs[guard] = load_sequence(out).vertices
        printed = capsys.readouterr().out
        assert ("unlike the training frames" in printed) == (guard == "novelty"), printed
    free = assemble_vertices(model, np.concatenate([feats, predict(model, feats, 6, guard=False)]),
                             {i: given[i] for i in range(3)})
    assert np.allclose(outs["off"], free, atol=1e-5)
    assert not np.allclose(outs["novelty"], outs["off"], atol=1e-4)


def test_evaluate_guard_off_changes_ours_prediction_and_nothing_else(model, trained, tmp_path, capsys):
    """evaluate --guard off scores ours' unguarded roll-out (the limb stretched to twice its width,
    where the guard acts), and its completion is the default one, the keys' trust still measured
    against the training frames' latents (on the limb itself, where that trust differs from the
    rule for runs stored without them)."""
    from meshseq import evaluate
    from meshseq.synthesize import CONTEXT

    run, data, seq = trained
    wide = tmp_path / "wide.npz"
    save_sequence(MeshSequence(seq.vertices * np.array([2.0, 1.0, 1.0]), seq.faces, name="wide"), wide)

    def scored(path, guard: str, gaps: str) -> dict:
        out = tmp_path / f"{path.stem}_{guard}.json"
        assert main(["evaluate", str(run), str(path), "--range", "20:60", "--methods", "ours", "--given", "3",
                     "--horizons", "4", "--gaps", gaps, "--curve-frames", "4", "--guard", guard,
                     "--json", str(out)]) == 0
        return json.loads(out.read_text())

    verts = load_sequence(wide).vertices
    feats = model.features(verts)
    predicted = {}
    for guard in ("novelty", "off"):
        predicted[guard] = scored(wide, guard, "none")["errors"]["ours"]["u3"]["4"]
        expect = evaluate.prediction_errors(model, verts, feats, 20, 60, 3, [4], ["ours"], guard=guard == "novelty")
        assert predicted[guard] == pytest.approx(expect["ours"]["centroid"]["4"], rel=1e-9)
    assert predicted["off"] != predicted["novelty"]
    feats = model.features(seq.vertices)
    expect = evaluate.completion_errors(model, seq.vertices, feats, 20, 60, [6], ["ours"], context=CONTEXT)
    for guard in ("novelty", "off"):
        assert scored(data, guard, "6")["completion"]["6"]["ours"] == pytest.approx(expect["6"]["ours"], rel=1e-9)
    capsys.readouterr()


def test_predict_and_complete_commands(trained, tmp_path, capsys):
    run, data, seq = trained
    out = tmp_path / "pred.npz"
    assert main(["predict", str(run), str(data), "--start", "5", "--given", "3", "--frames", "20", "-o", str(out)]) == 0
    p = load_sequence(out)
    assert p.n_frames == 23 and np.array_equal(p.vertices[:3], seq.vertices[5:8])
    assert np.array_equal(p.faces, seq.faces)
    out = tmp_path / "comp"
    assert main(["complete", str(run), str(data), "--keyframes", "4,15,30", "-o", str(out)]) == 0
    c = load_sequence(out)
    assert c.n_frames == 27
    for i, k in ((0, 4), (11, 15), (26, 30)):
        assert np.allclose(c.vertices[i], seq.vertices[k], atol=1e-6)  # OBJ text: 9 digits
    many = tmp_path / "many"
    assert main(["complete", str(run), str(data), "--keyframes", "4,15", "--samples", "3", "-o", str(many)]) == 0
    assert sorted(p.name for p in many.iterdir()) == ["diversity.json", "sample_00.npz", "sample_01.npz", "sample_02.npz"]
    assert json.loads((many / "diversity.json").read_text())["mean_pairwise_vertex_distance"] > 0
    got = {}
    for method, context in (("ours", "0"), ("ours", None), ("stitch", "0"), ("stitch", None)):
        o = tmp_path / f"{method}{context}.npz"  # the default: 7 frames of DATA around the keys, for ours
        assert main(["complete", str(run), str(data), "--keyframes", "10,21", "--method", method,
                     *(["--context", context] if context else []), "-o", str(o)]) == 0
        got[method, context] = load_sequence(o).vertices
        assert np.array_equal(got[method, context][[0, -1]], seq.vertices[[10, 21]])
    assert not np.allclose(got["ours", "0"], got["ours", None])  # the chains warmed up
    np.testing.assert_array_equal(got["stitch", "0"], got["stitch", None])  # the paper's: the keys alone
    for context in ("0", "7"):  # samples from random states: the keys alone either way
        assert main(["complete", str(run), str(data), "--keyframes", "10,21", "--samples", "2", "--context", context,
                     "-o", str(tmp_path / f"samples{context}")]) == 0
    for name in ("sample_00.npz", "sample_01.npz"):
        np.testing.assert_array_equal(load_sequence(tmp_path / "samples0" / name).vertices,
                                      load_sequence(tmp_path / "samples7" / name).vertices)
    from meshseq.api import load
    from meshseq.synthesize import complete_keyframes
    api = complete_keyframes(load(run), seq.vertices[[10, 21]], [10],
                             before=seq.vertices[3:10], after=seq.vertices[22:29])[0]
    np.testing.assert_allclose(got["ours", None], api, atol=1e-5)  # the command: numpy engine; the API: torch
    method = load(run).complete(seq.vertices[[10, 21]], 10, before=seq.vertices[3:10], after=seq.vertices[22:29])[0]
    np.testing.assert_array_equal(method, api)
    with pytest.raises(MeshseqError, match="before must be"):
        load(run).complete(seq.vertices[[10, 21]], 10, before=seq.vertices[3])
    for method in ("cma", "linear"):
        o = tmp_path / f"{method}.npz"
        assert main(["complete", str(run), str(data), "--keyframes", "4,12", "--method", method,
                     "--cma-evals", "20", "-o", str(o)]) == 0
        assert np.array_equal(load_sequence(o).vertices[[0, -1]], seq.vertices[[4, 12]])


def test_predict_gives_three_frames_by_default_or_as_many_as_the_data_holds(trained, tmp_path, capsys):
    run, data, seq = trained
    outputs = {}
    for name, argv in (("default", ["--start", "5"]), ("three", ["--start", "5", "--given", "3"]),
                       ("one", ["--start", "7", "--given", "1"])):  # the same last given frame
        outputs[name] = tmp_path / f"{name}.npz"
        assert main(["predict", str(run), str(data), "--frames", "8", *argv, "-o", str(outputs[name])]) == 0
    default = load_sequence(outputs["default"]).vertices
    assert len(default) == 3 + 8 and np.array_equal(default[:3], seq.vertices[5:8])
    np.testing.assert_array_equal(default, load_sequence(outputs["three"]).vertices)
    assert not np.allclose(default[3:], load_sequence(outputs["one"]).vertices[1:], atol=1e-4)  # they steer it
    last = seq.n_frames - 1
    near_end = tmp_path / "end.npz"
    assert main(["predict", str(run), str(data), "--start", str(last), "--frames", "4", "-o", str(near_end)]) == 0
    assert load_sequence(near_end).n_frames == 1 + 4  # the one frame the data holds from there
    assert "wrote" in capsys.readouterr().out


@pytest.mark.parametrize("argv, fragment", [
    (["complete", "{run}", "{data}", "--keyframes", "15,4"], "strictly increasing"),
    (["complete", "{run}", "{data}", "--keyframes", "4,99"], "has frames 0..71"),
    (["complete", "{run}", "{data}", "--keyframes", "4"], "at least two keyframes"),
    (["predict", "{run}", "{data}", "--start", "70", "--given", "5"], "--given 5: only 2 frames"),
    (["predict", "{run}", "{data}", "--given", "3", "--carry", "1.5"], "--carry 1.5: expected a share"),
    (["predict", "{run}", "{other}"], "another connectivity"),
    (["evaluate", "{run}", "{data}", "--range", "60:50"], "--range 60:50"),
])
def test_bad_input_is_one_line_and_writes_nothing(argv, fragment, trained, tmp_path, capsys):
    run, data, _ = trained
    other = tmp_path / "other.npz"
    save_sequence(twisting_limb(frames=30, rings=10, segments=8), other)
    out_dir = tmp_path / "outputs"
    out_dir.mkdir()
    argv = [a.format(run=run, data=data, other=other) for a in argv]
    if argv[0] != "evaluate":
        argv += ["-o", str(out_dir / "x.npz")]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.startswith("meshseq: error: ") and err.count("\n") == 1 and fragment in err, err
    assert list(out_dir.iterdir()) == []


def test_python_api_predict_and_complete_on_vertex_arrays(model, trained):
    v = trained[2].vertices
    out = model.predict(v[5:8], 12)
    assert out.shape == (15,) + v.shape[1:] and np.array_equal(out[:3], v[5:8])
    assert np.isfinite(out).all()
    feats = model.predict(model.features(v[5:8]), 12)
    assert feats.shape == (12, v.shape[1], 9)
    comp = model.complete(v[[4, 15, 30]], [10, 14], samples=2, seed=3)
    assert comp.shape == (2, 27) + v.shape[1:]
    for i, k in ((0, 4), (11, 15), (26, 30)):
        assert np.array_equal(comp[:, i], np.broadcast_to(v[k], comp[:, i].shape))
    assert not np.allclose(comp[0], comp[1])
    with pytest.raises(Exception, match="lengths"):
        model.complete(v[[4, 15, 30]], [10])


# --------------------------------------------------------------------------------------------
# batched synthesis equals the one-sample-at-a-time reference


def _assemble_one_frame_at_a_time(model, features, anchors, decay=8):
    """The reference of ``assemble_vertices``: one sample, a Python loop over frames."""
    recon = model.vertices(features)
    keys = sorted(anchors)
    corr = {k: np.asarray(anchors[k], dtype=np.float64) - recon[k] for k in keys}
    centroid = {k: np.asarray(anchors[k], dtype=np.float64).mean(axis=0) for k in keys}
    out = np.empty_like(recon)
    for t in range(len(recon)):
        if t in anchors:
            out[t] = anchors[t]
            continue
        before, after = [k for k in keys if k < t], [k for k in keys if k > t]
        if before and after:
            ka, kb = before[-1], after[0]
            s = (t - ka) / (kb - ka)
            out[t] = recon[t] + (1 - s) * corr[ka] + s * corr[kb]
        else:
            k = before[-1] if before else after[0]
            fade = max(0.0, 1.0 - abs(t - k) / decay) if decay > 0 else 0.0
            out[t] = recon[t] + centroid[k] + fade * (corr[k] - centroid[k])
    return out


@pytest.mark.parametrize("anchor_frames, decay", [((0, 14), 8), ((2, 6, 9), 8), ((0, 1, 2), 4), ((5,), 0)])
def test_batched_assembly_equals_the_frame_by_frame_reference(model, trained, anchor_frames, decay):
    from meshseq.synthesize import assemble_vertices

    v = trained[2].vertices.astype(np.float64)
    feats = model.features(v[20:35])  # (15, V, 9)
    rng = np.random.default_rng(1)
    many = np.stack([feats, np.clip(feats + 0.02 * rng.normal(size=feats.shape), -1, 1)]).astype(np.float32)
    anchors = {k: v[20 + k] + 0.01 * k for k in anchor_frames}
    batched = assemble_vertices(model, many, anchors, decay=decay)
    assert batched.shape == many.shape[:3] + (3,)
    for s in range(2):
        reference = _assemble_one_frame_at_a_time(model, many[s], anchors, decay)
        np.testing.assert_allclose(batched[s], reference, rtol=0, atol=1e-9)
        np.testing.assert_allclose(assemble_vertices(model, many[s], anchors, decay=decay), reference, rtol=0, atol=1e-9)
    for k in anchor_frames:
        assert np.array_equal(batched[:, k], np.broadcast_to(anchors[k], batched[:, k].shape))


def test_batched_samples_equal_one_sample_runs_of_the_same_seeds(model, trained):
    from meshseq.synthesize import complete

    keys = model.features(trained[2].vertices[[10, 24]])
    seeds = [3, 11, 42, 7]
    for join in ("corrected", "stitch"):
        batched = complete(model, keys[0], keys[1], 13, seeds=seeds, join=join)
        assert batched.frames.shape == (4, 15) + keys.shape[1:]
        for s, seed in enumerate(seeds):
            one = complete(model, keys[0], keys[1], 13, samples=1, random_state=True, seed=seed, join=join)
            np.testing.assert_allclose(batched.frames[s], one.frames[0], rtol=0, atol=1e-5)
            assert batched.stitch[s] == one.stitch[0]
            assert batched.gap[s] == pytest.approx(one.gap[0], abs=1e-5)
    assert not np.allclose(batched.frames[0], batched.frames[1])  # the seeds differ, so do the samples


def test_keyframe_completion_samples_equal_sequential_single_sample_completions(model, trained):
    """``complete_keyframes`` (all samples of a gap in one roll-out, one reconstruction) against the
    reference path: each sample completed alone, gap by gap, with the seed it always had, then
    assembled frame by frame. Same seeds give the same samples (to 1e-5)."""
    from meshseq.synthesize import complete, complete_keyframes

    v = trained[2].vertices.astype(np.float64)
    frames, gaps, seed, samples = [4, 15, 30], [10, 14], 2, 3
    batched = complete_keyframes(model, v[frames], gaps, samples=samples, seed=seed)
    assert batched.shape == (samples, 27) + v.shape[1:]
    key_f = model.features(v[frames])
    anchors = {0: v[4], 11: v[15], 26: v[30]}
    for s in range(samples):
        parts = [complete(model, key_f[i], key_f[i + 1], gap, random_state=True,
                          seed=seed * 1000 + s * 97 + i).frames[0][int(i > 0):] for i, gap in enumerate(gaps)]
        reference = _assemble_one_frame_at_a_time(model, np.concatenate(parts), anchors)
        np.testing.assert_allclose(batched[s], reference, rtol=0, atol=1e-5)
    # one sample: the trained initial states, as a one-sample completion always had (without the
    # vertex share's blend, tests/test_inbetween.py)
    one = complete_keyframes(model, v[frames], gaps, samples=1, seed=seed, vertex_share=0.0)
    parts = [complete(model, key_f[i], key_f[i + 1], gap).frames[0][int(i > 0):] for i, gap in enumerate(gaps)]
    np.testing.assert_allclose(one[0], _assemble_one_frame_at_a_time(model, np.concatenate(parts), anchors),
                               rtol=0, atol=1e-5)


@pytest.mark.parametrize("n", [2, 3, 9])
def test_joining_all_pairs_at_once_equals_joining_each_pair(n):
    from meshseq.synthesize import corrected_crossfade, join_chains, reach_weights, stitch_chains

    rng = np.random.default_rng(n)
    forward = rng.normal(size=(3, n, 5, 9)).astype(np.float32)
    backward = rng.normal(size=(3, n, 5, 9)).astype(np.float32)
    for join in ("anchored", "corrected", "stitch"):
        frames, meets, gaps = join_chains(forward, backward, join)
        for p in range(3):
            stitched, meet, gap = stitch_chains(forward[p], backward[p])
            expect = corrected_crossfade(forward[p], backward[p]) if join != "stitch" else stitched
            if join == "anchored":
                line = np.linspace(forward[p, 0], backward[p, 0], n)
                expect = line + reach_weights(forward[p:p + 1], backward[p:p + 1])[0] * (expect - line)
            np.testing.assert_allclose(frames[p], expect, rtol=0, atol=1e-5)
            assert meets[p] == meet and gaps[p] == pytest.approx(gap, rel=1e-5)


def test_batched_completion_errors_equal_the_per_start_reference(model, trained):
    """``evaluate.completion_errors`` runs every start's chains (and every start's samples) as one
    roll-out; the reference completes each start alone with ``complete``, ours given the same
    frames around the keys (the paper's stitch, the keys alone)."""
    from meshseq import evaluate
    from meshseq.synthesize import blend_toward_vertices, complete

    v = trained[2].vertices.astype(np.float64)
    feats = model.features(v)
    lo, hi, gap, samples, seed = 40, 60, 4, 3, 1
    got = evaluate.completion_errors(model, v, feats, lo, hi, [gap], ["ours", "stitch", "linear"],
                                     samples=samples, seed=seed, max_starts=4, context=7,
                                     vertex_share=0.5)[str(gap)]
    starts = np.arange(lo, hi - gap - 1)
    starts = starts[np.linspace(0, len(starts) - 1, 4).astype(int)]
    assert got["starts"] == 4
    for method, join in (("ours", "anchored"), ("stitch", "stitch")):
        errs = []
        for s in starts:
            b = s + gap + 1
            around = {"before": feats[s - 7:s], "after": feats[b + 1:b + 1 + 7]} if method == "ours" else {}
            done = complete(model, feats[s], feats[b], gap, join=join, **around)  # stitch: the keys alone
            verts = _assemble_one_frame_at_a_time(model, done.frames[0], {0: v[s], gap + 1: v[s + gap + 1]})
            if method == "ours":  # the line's share moved on toward the vertices' line (meshseq.inbetween)
                verts = blend_toward_vertices(verts[None], 0.5 * done.line_share[:1])[0]
            errs.append(per_vertex_error(verts[1:-1], v[s + 1:s + gap + 1]).mean() / evaluate.UNITS)
        assert got[method] == pytest.approx(np.mean(errs), rel=1e-6, abs=1e-3)  # abs: 1e-7 data units
    diversity = []
    for s in starts:
        many = complete(model, feats[s], feats[s + gap + 1], gap, samples=samples, seed=seed + int(s))
        anchors = {0: v[s], gap + 1: v[s + gap + 1]}
        verts = np.stack([_assemble_one_frame_at_a_time(model, f, anchors)[1:-1] for f in many.frames])
        diversity.append(baselines.pairwise_diversity(verts) / evaluate.UNITS)
    assert got["diversity"] == pytest.approx(np.mean(diversity), rel=1e-6, abs=1e-3)  # abs: 1e-7 data units


def test_synthesis_commands_list_the_library_methods_without_importing_it():
    from meshseq import synthesize
    from meshseq.cli import synth_cmds

    assert synth_cmds.PREDICTION_METHODS == baselines.PREDICTION_METHODS
    assert synth_cmds.COMPLETION_METHODS == baselines.COMPLETION_METHODS
    assert synth_cmds.PACES == synthesize.PACES
    assert synth_cmds.CONTEXT == synthesize.CONTEXT
    assert synth_cmds.CARRY == synthesize.CARRY
    assert set(synthesize.METHOD_JOINS) <= set(synth_cmds.COMPLETION_METHODS)


def test_vae_baseline_beats_standing_still_on_its_training_frames(trained, model):
    """The VAE baseline sees normalised frames: on the frames it trained on, its latent
    extrapolation 5 frames ahead is closer to the truth than standing still (unnormalised, it
    reconstructed the mean frame)."""
    from meshseq.mesh import Topology

    x = model.features(trained[2].vertices)
    topo = Topology.from_faces(model.faces, model.config.n_vertices)
    torch.manual_seed(0)
    vae = baselines.train_vae(x, topo, latent=16, iterations=1500)
    starts = np.arange(0, len(x) - 8, 2)
    given = np.stack([x[s:s + 3] for s in starts])
    truth = np.stack([x[s + 7] for s in starts])
    ours = baselines.vae_latent(vae, given, 5)[:, -1]
    still = given[:, -1]
    err = lambda p: np.sqrt(np.square(p - truth).sum(-1)).mean()
    assert err(ours) < 0.7 * err(still)  # normalised: 0.54; on raw frames: 0.88


def test_feature_change_curve_is_the_same_a_few_starts_at_a_time(model, trained, monkeypatch):
    from meshseq import evaluate

    feats = model.features(trained[2].vertices)
    starts = np.arange(0, 13)
    monkeypatch.setattr(evaluate, "CURVE_STARTS", 100)
    whole = evaluate.feature_change(model, feats, starts, 2, 6, ["ours", "linear_acap"])
    monkeypatch.setattr(evaluate, "CURVE_STARTS", 3)
    parts = evaluate.feature_change(model, feats, starts, 2, 6, ["ours", "linear_acap"])
    for m in ("ours", "linear_acap"):
        np.testing.assert_allclose(parts[m], whole[m], rtol=1e-6)
    assert parts["ground_truth"] == whole["ground_truth"]
