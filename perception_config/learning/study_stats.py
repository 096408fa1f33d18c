"""Confidence intervals for agent comparisons: the percentile bootstrap, in plain numpy.

Every figure here is a ratio of sums over episodes, `sum(num) / sum(den)`:
- a mean (success, first-pick success, episode cost): num = the values, den = 1;
- time to success (successful episodes only): num = time x success, den = success;
- a paired difference (a seed's episode cost minus the bar's on the same episode): num = the
  differences, den = 1;
- a time ratio to the oracle on the episodes both picked: num = the agent's time on them, den =
  the oracle's (the mean of the agent's over the mean of the oracle's).
So one resampling scheme serves them all, and resampling the episodes keeps the pairs together
(both arrays are indexed by the same resampled episodes).

Percentile bootstrap (Efron): draw `resamples` (default 2000) samples of the n episodes with
replacement, compute the figure on each, and report the 2.5 and 97.5 percentiles of those
figures (for `level` 0.95) around the figure on the data. A resample whose denominator sums to 0
(no successful episode in it, for time to success) has no figure and is left out; with none left
the interval is None. The generator is seeded (`seed`, default 0), so a report repeats exactly.

Pooled over seeds (`ratio_interval` with 2-D arrays, one row per seed, the same n episodes
each): a two-level bootstrap, the seeds resampled with replacement, then the episodes within each
drawn seed. Its interval covers both the spread between training seeds and the test episodes'
noise: what another seed's policy would be expected to do, not only this one.

Shapes: num, den (n,) for one sample or (S, n) for S seeds of n paired episodes; float64.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

RESAMPLES = 2000  # bootstrap resamples
LEVEL = 0.95  # two-sided confidence level of the intervals
BOOTSTRAP_SEED = 0
METHOD = "percentile bootstrap over the test episodes (pooled: over seeds, then episodes)"


@dataclass(frozen=True)
class Estimate:
    """A figure on the data and its bootstrap interval (None where undefined); n: the episodes
    (or seeds x episodes) it was computed from, n_den: the sum of the denominator (successful
    episodes for time to success)."""

    value: float | None
    lo: float | None
    hi: float | None
    n: int
    n_den: float = 0.0

    def to_json(self) -> dict[str, Any]:
        return {"mean": self.value, "lo": self.lo, "hi": self.hi, "n": self.n, "n_den": self.n_den}

    def format(self, fmt: str = ".3f", scale: float = 1.0) -> str:
        """'0.412 [0.351, 0.480]' ('-' for no value; no interval when undefined)."""
        if self.value is None:
            return "-"
        text = format(self.value * scale, fmt)
        if self.lo is not None and self.hi is not None:
            text += f" [{format(self.lo * scale, fmt)}, {format(self.hi * scale, fmt)}]"
        return text


def _ratio(num: np.ndarray, den: np.ndarray) -> np.ndarray:
    """sum(num) / sum(den) over the last axis; NaN where the denominator sums to 0."""
    d = den.sum(axis=-1)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(d != 0, num.sum(axis=-1) / np.where(d != 0, d, 1.0), np.nan)


def resample_indices(n: int, resamples: int, rng: np.random.Generator) -> np.ndarray:
    """(resamples, n) int: each row n draws of 0..n-1 with replacement."""
    return rng.integers(0, n, size=(resamples, n))


def percentile_interval(figures: np.ndarray, level: float = LEVEL) -> tuple[float | None, float | None]:
    """The (1 - level) / 2 and (1 + level) / 2 percentiles of the finite bootstrap figures."""
    f = np.asarray(figures, np.float64)
    f = f[np.isfinite(f)]
    if f.size == 0:
        return None, None
    lo, hi = np.percentile(f, [50.0 * (1.0 - level), 50.0 * (1.0 + level)])
    return float(lo), float(hi)


def ratio_interval(num: Any, den: Any = None, *, resamples: int = RESAMPLES, level: float = LEVEL,
                   seed: int = BOOTSTRAP_SEED) -> Estimate:
    """sum(num) / sum(den) and its percentile bootstrap interval (module docstring).

    num, den: (n,) paired per episode, or (S, n) for S seeds (two-level bootstrap: seeds, then
    episodes); den None = ones (a plain mean). An empty sample gives Estimate(None, None, None, 0).
    """
    num = np.asarray(num, np.float64)
    den = np.ones_like(num) if den is None else np.asarray(den, np.float64)
    if num.shape != den.shape or num.ndim not in (1, 2):
        raise ValueError(f"num and den must have the same shape (n,) or (seeds, n), got {num.shape} and {den.shape}")
    if not (np.isfinite(num).all() and np.isfinite(den).all()):
        raise ValueError("bootstrap: the values must be finite")
    if resamples < 1 or not 0.0 < level < 1.0:
        raise ValueError(f"need resamples >= 1 and 0 < level < 1, got {resamples} and {level}")
    if num.size == 0:
        return Estimate(None, None, None, 0)
    value = float(_ratio(num.ravel(), den.ravel()))
    value_or_none = value if np.isfinite(value) else None
    rng = np.random.default_rng(seed)
    if num.ndim == 1:
        idx = resample_indices(num.shape[0], resamples, rng)  # (B, n)
        figures = _ratio(num[idx], den[idx])
    else:
        s, n = num.shape
        seeds = resample_indices(s, resamples, rng)  # (B, S): the seeds drawn
        episodes = rng.integers(0, n, size=(resamples, s, n))  # (B, S, n): episodes within each drawn seed
        rows = seeds[:, :, None]
        b = resamples
        figures = _ratio(num[rows, episodes].reshape(b, s * n), den[rows, episodes].reshape(b, s * n))
    lo, hi = percentile_interval(figures, level) if value_or_none is not None else (None, None)
    return Estimate(value_or_none, lo, hi, int(num.size), float(den.sum()))


def mean_interval(values: Any, **kw: Any) -> Estimate:
    """The mean of `values` ((n,), or (S, n) pooled over seeds) with its bootstrap interval."""
    return ratio_interval(values, None, **kw)


def success_time_interval(time: Any, success: Any, **kw: Any) -> Estimate:
    """Mean time over the successful episodes (time, success: per episode, same shape)."""
    s = np.asarray(success, np.float64)
    return ratio_interval(np.asarray(time, np.float64) * s, s, **kw)


def paired_difference_interval(a: Any, b: Any, **kw: Any) -> Estimate:
    """mean(a - b) over paired episodes (a, b: the same episodes in the same order)."""
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    if a.shape != b.shape:
        raise ValueError(f"paired samples must have the same shape, got {a.shape} and {b.shape}")
    return ratio_interval(a - b, None, **kw)


def oracle_ratio_interval(time: Any, success: Any, oracle_time: Any, oracle_success: Any, **kw: Any) -> Estimate:
    """The agent's mean time over the oracle's on the episodes both succeeded on (paired arrays
    per episode; times with the first generator call, as evaluation's oracle_ratio)."""
    both = np.asarray(success, bool) & np.asarray(oracle_success, bool)
    t = np.where(both, np.asarray(time, np.float64), 0.0)
    o = np.where(both, np.asarray(oracle_time, np.float64), 0.0)
    return ratio_interval(t, o, **kw)


def beats(candidate: dict[str, float], bar: dict[str, float]) -> bool:
    """Whether a candidate beats the bar on point estimates: a lower mean episode cost AND a
    success rate not lower. Both dicts: {"cost": mean episode cost, "success": share}."""
    return float(candidate["cost"]) < float(bar["cost"]) and float(candidate["success"]) >= float(bar["success"])


def count_beats(candidates: list[dict[str, float]], bar: dict[str, float]) -> int:
    """How many candidates beat the bar (`beats`)."""
    return sum(1 for c in candidates if beats(c, bar))


__all__ = ["Estimate", "RESAMPLES", "LEVEL", "BOOTSTRAP_SEED", "METHOD", "ratio_interval", "mean_interval",
           "success_time_interval", "paired_difference_interval", "oracle_ratio_interval", "beats", "count_beats",
           "percentile_interval", "resample_indices"]
