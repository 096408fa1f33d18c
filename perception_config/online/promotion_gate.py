"""Held-out check frames and the statistical gate a policy candidate must pass to serve.

The anchor is safe policy improvement (Thomas et al. 2015, high-confidence off-policy evaluation;
Laroche et al. 2019, SPIBB): a new policy replaces the one serving only when a confidence bound
says it is better, on data it was not trained on.

**Split by frame.** A stored frame (its stamp) is a check frame with probability
`fraction`, decided by a keyed hash of (seed, stamp): the split of a frame never changes as the
store grows, so a candidate never trains on a frame that any later check uses. All the estimates
of one frame (its objects) fall on the same side: they share the image.

**The paired test.** Serving and candidate play the same check episodes (same frame, object,
lambda, stored episode seed and acting seed; cost-table time, so the comparison is deterministic).
The unit is the frame (the episodes of one frame are alike): per check frame, the mean of the
candidate's cost minus the serving cost over its episodes; then the one-sided Student-t upper
bound of the mean of those differences at `confidence` (95 %). The candidate is promoted only when

- there are at least MIN_CHECK_FRAMES check frames and MIN_CHECK_EPISODES check episodes
  (with fewer, a standard error from a handful of frames says little, and t's quantile is
  large: 2.13 at 5 frames, 6.31 at 2);
- the upper bound is below zero (its cost is lower at 95 % confidence);
- its mean cost is below (1 - margin) x the serving one (a minimum effect worth a new version);
- its successes on the check episodes are not fewer than the serving policy's;
- at least one of its successes on them is **confirmed**: judged by the frame's ground truth, or
  within the label tolerance of a pose the robot reported picked (online/pick_labels.py), not
  by the learned pick-success score alone. Without one, a lower cost is only a cheaper failure
  (fewer pick attempts, giving up sooner), or a success the score grants where the robot never
  said yes: a robot program that reports every pick failed leaves no picked pose, so its check
  successes are all the score's, and a candidate that avoids the poses it reported would win
  the comparison without any evidence that it picks.
"""
from __future__ import annotations

import hashlib
import math
from collections import defaultdict
from dataclasses import dataclass
from typing import Sequence

import numpy as np

MIN_CHECK_FRAMES = 5
MIN_CHECK_EPISODES = 15
CONFIDENCE = 0.95
CHECK_FRACTION = 0.3
# The newest this many episodes of the check frames form a check (the learner's default): about
# every check frame of a few hundred stored estimates. The frame is the test's unit, so the bound
# tightens with the frames, not the episodes: a check of the newest 60 (10 frames of a 6-object
# cell) passed a version that was 2.7 points less successful at the same cost on a 220-episode
# hidden evaluation (55 against 55 successes on the check).
CHECK_EPISODES = 200


def is_check_frame(stamp_ns: int, fraction: float = CHECK_FRACTION, seed: int = 0) -> bool:
    """Whether the frame with this stamp is held out for checks (stable for a stamp and seed)."""
    if not 0.0 < fraction < 1.0:
        raise ValueError(f"check fraction must be in (0, 1), got {fraction!r}")
    digest = hashlib.blake2b(f"{int(seed)}:{int(stamp_ns)}".encode(), digest_size=8).digest()
    return int.from_bytes(digest, "little") / 2.0**64 < fraction


@dataclass
class GateDecision:
    """The gate's verdict on a candidate (module docstring); every figure it was decided on."""

    promote: bool
    reason: str
    episodes: int
    frames: int
    cost: float  # the candidate's mean cost over the check episodes (s)
    serving_cost: float
    difference: float  # mean over frames of the per-frame mean cost difference, candidate - serving
    upper: float  # its one-sided upper confidence bound
    confidence: float
    successes: int
    serving_successes: int
    confirmed: int = -1  # of the candidate's successes, those confirmed (module docstring); -1: not given

    def to_json(self) -> dict:
        return dict(self.__dict__)


def per_frame_bound(values: Sequence[float], frames: Sequence[object], confidence: float = CONFIDENCE,
                    side: str = "upper") -> tuple[float, float, int]:
    """(mean, one-sided bound at `confidence`, frames) of per-episode `values` averaged per frame
    first (the frame is the unit: the episodes of one frame are alike): Student-t over the frames'
    means; the bound is +-inf with fewer than 2 frames."""
    from scipy import stats

    by_frame: dict[object, list[float]] = defaultdict(list)
    for f, v in zip(frames, values):
        by_frame[f].append(float(v))
    per_frame = np.array([np.mean(v) for v in by_frame.values()]) if by_frame else np.zeros(0)
    k = len(per_frame)
    mean = float(per_frame.mean()) if k else math.nan
    if k < 2:
        return mean, (math.inf if side == "upper" else -math.inf), k
    half = float(stats.t.ppf(confidence, k - 1)) * float(per_frame.std(ddof=1)) / math.sqrt(k)
    return mean, (mean + half if side == "upper" else mean - half), k


def paired_gate(costs: Sequence[float], serving_costs: Sequence[float], successes: Sequence[bool],
                serving_successes: Sequence[bool], frames: Sequence[int], margin: float = 0.05,
                confidence: float = CONFIDENCE, confirmed: Sequence[bool] | None = None) -> GateDecision:
    """The decision on a candidate from its check episodes, paired with the serving policy's on
    the same ones; `frames`: each episode's frame stamp; `confirmed`: per episode, whether the
    candidate's success there is confirmed by ground truth or a robot's picked pose (None: every
    success is, as with ground truth) (module docstring)."""
    n = len(costs)
    confirmed = successes if confirmed is None else confirmed
    if not (len(serving_costs) == len(successes) == len(serving_successes) == len(frames) == len(confirmed) == n):
        raise ValueError("paired_gate needs one cost, serving cost, success, serving success, confirmation and "
                         "frame per episode")
    cost, serving = np.asarray(costs, float), np.asarray(serving_costs, float)
    difference, upper, k = per_frame_bound(cost - serving, [int(f) for f in frames], confidence, "upper")
    wins, serving_wins = int(np.sum(successes)), int(np.sum(serving_successes))
    sure = int(np.sum(np.asarray(successes, bool) & np.asarray(confirmed, bool)))
    mean_cost = float(cost.mean()) if n else math.nan
    mean_serving = float(serving.mean()) if n else math.nan
    if k < MIN_CHECK_FRAMES or n < MIN_CHECK_EPISODES:
        promote, reason = False, (f"too few checks: {n} episodes on {k} held-out frames (at least "
                                  f"{MIN_CHECK_EPISODES} on {MIN_CHECK_FRAMES})")
    elif not upper < 0.0:
        promote, reason = False, f"not lower at {confidence:.0%} confidence"
    elif not mean_cost < (1.0 - margin) * mean_serving:
        promote, reason = False, f"lower by less than the margin {margin:g}"
    elif wins < serving_wins:
        promote, reason = False, f"fewer successes ({wins} vs {serving_wins})"
    elif wins == 0:
        promote, reason = False, "no success on the check episodes (a cheaper failure is no improvement)"
    elif sure == 0:
        promote, reason = False, (f"none of its {wins} successes is confirmed by ground truth or a pose the robot "
                                  "picked (the score alone granted them)")
    else:
        promote, reason = True, f"lower at {confidence:.0%} confidence, success not lower"
    return GateDecision(promote, reason, n, k, mean_cost, mean_serving, difference, upper, confidence, wins,
                        serving_wins, sure)
