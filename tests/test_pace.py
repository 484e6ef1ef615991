"""Pace: motion levels, the tempo augmentation, time-warped body motions."""

import numpy as np
import pytest

from meshseq.data.motions import TEMPO_LEVELS as MOTION_TEMPOS
from meshseq.data.motions import motion_curves, varied_tempo
from meshseq.data.windows import WindowSampler, split_frames
from meshseq.pace import pace_table, step_levels


def test_step_levels_ignore_translation_and_measure_motion():
    rng = np.random.default_rng(0)
    base = rng.normal(size=(50, 3))
    still = np.repeat(base[None], 6, 0) + np.arange(6)[:, None, None] * np.array([1.0, 0, 0])  # only moves
    assert np.allclose(step_levels(still), 0.0)
    moving = base[None] * (1.0 + 0.1 * np.arange(6))[:, None, None]  # grows 10% of base a frame
    lv = step_levels(moving)
    assert lv.shape == (5,) and np.allclose(lv, lv[0]) and lv[0] > 0.05


def test_pace_table_bins_by_given_level():
    levels = {"given": np.array([0.0, 0.05, 0.3, 1.0, 2.0]), "truth": np.array([0.0, 0.1, 0.3, 1.0, 2.0]),
              "ours": np.array([0.5, 0.5, 0.3, 1.0, 1.0])}
    rows = {r["bin"]: r for r in pace_table(levels, 1.0)}
    assert rows["still"]["starts"] == 2 and rows["still"]["ours"] == pytest.approx(0.5)
    assert rows["fast"]["ours_over_truth"] == pytest.approx(0.5)
    assert set(rows) == {"still", "slow", "steady", "fast"}


def test_varied_tempo_holds_slows_and_never_goes_back():
    t = varied_tempo(400, 30.0, np.random.default_rng(3))
    step = np.diff(t) * 30.0
    assert t[0] == 0.0 and (step >= -1e-12).all()
    assert (step < 1e-9).sum() >= 5  # a hold somewhere
    assert step.max() <= max(MOTION_TEMPOS) + 1e-9 and step.max() > 1.0


def test_motion_curves_at_warped_times_match_steady_ones_where_the_times_agree():
    steady = motion_curves("wave", 20, fps=30.0)
    times = np.arange(20) / 30.0
    times[10:] = times[10]  # hold from frame 10
    held = motion_curves("wave", 20, fps=30.0, times=times)
    for bone, r in steady.rotations.items():
        assert np.allclose(held.rotations[bone][:11], r[:11])
        assert np.allclose(held.rotations[bone][11:], r[10])


def test_tempo_windows_stay_in_their_segment_and_keep_exact_ones_exact():
    splits = [split_frames(60, 0.2), split_frames(90, 0.2)]
    sampler = WindowSampler(splits, ["a", "b"], 16, 1)
    rng = np.random.default_rng(0)
    before, after, weight = sampler.sample_at_tempos(rng, 400, 0.5)
    pos = before + weight
    assert (np.diff(pos, axis=1) >= -1e-9).all()  # never backwards
    for row_b, row_a in zip(before, after):
        set_b = 0 if row_b[0] < 60 else 1
        lo = 0 if set_b == 0 else 60
        hi = lo + (48 if set_b == 0 else 72)
        assert (row_b >= lo).all() and (row_a < hi).all()
    steps = np.diff(pos, axis=1)
    exact = np.all(np.abs(steps - 1.0) < 1e-9, axis=1) & np.all(weight < 1e-9, axis=1)
    assert 0.3 < exact.mean() < 0.75  # about half the windows keep their frames
    held = np.all(steps < 1e-9, axis=1)
    assert held.any()  # some windows hold a pose throughout
    assert ((steps.max(1) > 0.2) & (steps.min(1) < 1e-9)).any()  # and some slow to a stop or start from one
