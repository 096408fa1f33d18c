"""The online learner's held-out split and statistical gate (online/promotion_gate.py): a frame's
side never changes as the store grows; a candidate is promoted only when its per-frame paired
cost difference is below zero at 95 % confidence, with enough frames and episodes, by more than
the margin, and with success not lower."""
from __future__ import annotations

import numpy as np
import pytest

from perception_config.online.promotion_gate import (
    MIN_CHECK_EPISODES,
    MIN_CHECK_FRAMES,
    is_check_frame,
    paired_gate,
)


def test_the_split_is_stable_per_frame_and_near_its_fraction():
    stamps = [1_700_000_000_000_000_000 + i * 33_333_333 for i in range(20_000)]
    held = [is_check_frame(s, 0.3, seed=7) for s in stamps]
    assert abs(np.mean(held) - 0.3) < 0.015
    # a frame's side depends on its stamp and the seed only: not on the other frames
    assert [is_check_frame(s, 0.3, seed=7) for s in stamps[::-1]] == held[::-1]
    assert [is_check_frame(s, 0.3, seed=8) for s in stamps[:200]] != held[:200]
    with pytest.raises(ValueError, match="check fraction"):
        is_check_frame(1, 1.0)


def _episodes(frames: int, per_frame: int, diff: float, noise: float, rng):
    serving = rng.uniform(0.5, 2.0, size=frames * per_frame)
    frame_effect = np.repeat(rng.normal(0.0, noise, size=frames), per_frame)  # frames differ, not episodes
    cost = serving + diff + frame_effect
    stamps = np.repeat(np.arange(frames), per_frame)
    return list(cost), list(serving), stamps


def test_a_clearly_better_candidate_passes_and_its_figures_are_reported():
    rng = np.random.default_rng(0)
    cost, serving, frames = _episodes(8, 3, -0.5, 0.1, rng)
    d = paired_gate(cost, serving, [True] * 24, [True] * 24, frames)
    assert d.promote, d
    assert (d.episodes, d.frames) == (24, 8) and d.upper < 0 and d.difference == pytest.approx(-0.5, abs=0.15)
    assert d.cost < d.serving_cost and d.successes == d.serving_successes == 24


def test_noise_is_not_promoted():
    """A candidate whose mean is a little lower but whose frames disagree: the bound is above zero."""
    rng = np.random.default_rng(1)
    cost, serving, frames = _episodes(8, 3, -0.1, 1.0, rng)
    d = paired_gate(cost, serving, [True] * 24, [True] * 24, frames)
    assert not d.promote and d.upper >= 0 and "confidence" in d.reason, d


def test_frames_not_episodes_are_the_unit():
    """Thirty episodes of two frames: far too few frames, however many episodes."""
    cost, serving, frames = [0.1] * 30, [2.0] * 30, [1] * 15 + [2] * 15
    d = paired_gate(cost, serving, [True] * 30, [True] * 30, frames)
    assert not d.promote and d.frames == 2 and "too few checks" in d.reason, d
    n = MIN_CHECK_EPISODES - 1
    d = paired_gate([0.1] * n, [2.0] * n, [True] * n, [True] * n, list(range(n)))
    assert not d.promote and "too few checks" in d.reason and n >= MIN_CHECK_FRAMES


def test_fewer_successes_or_a_gain_below_the_margin_is_not_promoted():
    rng = np.random.default_rng(2)
    cost, serving, frames = _episodes(8, 3, -0.5, 0.05, rng)
    wins = [True] * 24
    d = paired_gate(cost, serving, [False] + wins[1:], wins, frames)
    assert not d.promote and "fewer successes" in d.reason, d
    cost = list(np.asarray(serving) * 0.98)  # surely lower, by 2 %: under the 5 % margin
    d = paired_gate(cost, serving, wins, wins, frames, margin=0.05)
    assert not d.promote and d.upper < 0 and "margin" in d.reason, d
    with pytest.raises(ValueError, match="one cost"):
        paired_gate(cost, serving[:-1], wins, wins, frames)
    # Surely cheaper, but nothing picked on either side (a robot reporting every pick failed):
    # a cheaper failure, not an improvement. One success makes the same candidate pass.
    cost, serving, frames = _episodes(8, 3, -2.0, 0.05, rng)
    none = [False] * 24
    d = paired_gate(cost, serving, none, none, frames)
    assert not d.promote and d.upper < 0 and "no success" in d.reason, d
    assert paired_gate(cost, serving, [True] + none[1:], none, frames).promote
    # Successes granted by the learned score alone (no ground truth, no pose the robot reported
    # picked: what a robot reporting every pick failed leaves) are no evidence either.
    wins = [True] * 12 + [False] * 12
    d = paired_gate(cost, serving, wins, wins, frames, confirmed=[False] * 24)
    assert not d.promote and "none of its 12 successes is confirmed" in d.reason and d.confirmed == 0, d
    # A confirmed flag on an episode the candidate failed does not count.
    d = paired_gate(cost, serving, wins, wins, frames, confirmed=[False] * 12 + [True] * 12)
    assert not d.promote and d.confirmed == 0, d
    d = paired_gate(cost, serving, wins, wins, frames, confirmed=[True] + [False] * 23)
    assert d.promote and d.confirmed == 1, d
    assert paired_gate(cost, serving, wins, wins, frames).confirmed == 12  # ground truth: every success


def test_the_per_frame_bound_is_students_t_over_the_frames_means():
    """The bound both gates use (the policy's upper bound on the cost difference, the score's lower
    bound on the Brier gain): episodes averaged per frame first, then one-sided Student-t."""
    from scipy import stats

    from perception_config.online.promotion_gate import per_frame_bound

    values = [1.0, 3.0, 2.0, 4.0, 6.0, 5.0, 5.0]
    frames = ["a", "a", "b", "b", "c", "d", "d"]  # frame means 2, 3, 6, 5
    means = np.array([2.0, 3.0, 6.0, 5.0])
    half = stats.t.ppf(0.95, 3) * means.std(ddof=1) / 2.0
    mean, upper, k = per_frame_bound(values, frames)
    assert (mean, k) == (4.0, 4) and upper == pytest.approx(4.0 + half)
    assert per_frame_bound(values, frames, side="lower")[1] == pytest.approx(4.0 - half)
    assert per_frame_bound([1.0, 2.0], ["a", "a"], side="lower") == (1.5, -np.inf, 1)
